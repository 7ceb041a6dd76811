"""Explicit solver driver: single-device and distributed runs in compiled chunks.

The numerics (central differences with lumped mass, paper eq. 7; the paper's start) are
the pure stepper of :mod:`jaxsync.fem.stepper`. Here the driver :func:`simulate` runs it in
compiled ``lax.scan`` chunks (on one device, or over parts through
:mod:`jaxsync.solve.distributed`), saves every ``save_every`` steps, shows progress, checks for
divergence and checkpoints between chunks; :func:`steady_state` solves the static problem.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import CheckpointError, ProblemError, StabilityError
from ..pytree import is_traced
from ..fem.stepper import (ExplicitSystem, SolverState, advance, apply_dirichlet,  # noqa: F401
                      build_system, central_difference, external_force, initial_state, step)

__all__ = ["ExplicitSystem", "SolverState", "build_system", "initial_state", "step",
           "central_difference", "apply_dirichlet", "external_force", "advance",
           "simulate", "steady_state"]

_advance_jit = jax.jit(advance, static_argnums=(2, 3))


def steady_state(problem) -> np.ndarray:
    """Static solution K u = f with every load at full magnitude (time factor 1) and the
    Dirichlet values imposed; (n_nodes, 3) [cm]. Direct sparse solve (scipy)."""
    import scipy.sparse.linalg as spla

    m = problem.material
    K = problem.operators.stiffness(m.lam, m.mu)
    vectors, _ = problem.load_vectors()
    f = np.zeros(problem.mesh.n_dofs)
    for v in vectors:
        f += np.asarray(v, dtype=float).reshape(-1)
    fixed, values = problem.dirichlet_dofs()
    free = np.setdiff1d(np.arange(K.shape[0]), fixed)
    u = np.zeros(K.shape[0])
    u[fixed] = values
    rhs = f[free] - K[free][:, fixed] @ values
    singular = ProblemError("the static problem is singular: the Dirichlet conditions do not "
                            "prevent rigid-body motion; clamp more nodes")
    K_free = K[free][:, free].tocsc()
    try:
        u[free] = spla.splu(K_free).solve(rhs)
    except RuntimeError as exc:  # SuperLU: "Factor is exactly singular"
        raise singular from exc
    residual = np.linalg.norm(K_free @ u[free] - rhs)
    if not np.all(np.isfinite(u)) or residual > 1e-8 * max(np.linalg.norm(rhs), 1e-300):
        raise singular
    return u.reshape(-1, 3)


def _fingerprint(problem, dt: float, save_every: int) -> str:
    """Hash of everything that determines a trajectory, to refuse foreign checkpoints."""
    h = hashlib.sha256()
    mesh = problem.mesh
    for arr in (mesh.points, mesh.tets):
        h.update(np.ascontiguousarray(arr).tobytes())
    m = problem.material
    dofs, values = problem.dirichlet_dofs()
    h.update(np.asarray([float(m.E), float(m.nu), float(m.rho), float(problem.damping), dt,
                         save_every], dtype=float).tobytes())
    h.update(dofs.tobytes())
    h.update(values.tobytes())
    for v in problem.load_vectors()[0]:
        h.update(np.asarray(v, dtype=float).tobytes())
    for ic in (problem.initial_displacement, problem.initial_velocity, problem.density_scale):
        if ic is not None:
            h.update(np.asarray(ic, dtype=float).tobytes())
    return h.hexdigest()


class SingleDeviceRunner:
    """Advances a global :class:`SolverState` on one device (the driver's interface:
    ``compile(state, n_saves) -> seconds``, ``advance(state, n_saves) -> (state, saved
    (n_saves, n_nodes, 3) numpy, shared histories or None)``, ``to_global(state)`` /
    ``from_global(state)`` for checkpoints)."""

    def __init__(self, system: ExplicitSystem, save_every: int):
        self.system, self.save_every = system, save_every
        self._programs = {}

    def compile(self, state, n_saves: int) -> float:
        """Compile the chunk program ahead of time; returns the seconds spent."""
        if n_saves in self._programs:
            return 0.0
        start = time.perf_counter()
        self._programs[n_saves] = _advance_jit.lower(self.system, state, n_saves, self.save_every).compile()
        return time.perf_counter() - start

    def advance(self, state, n_saves):
        self.compile(state, n_saves)
        state, saved = self._programs[n_saves](self.system, state)
        return state, np.asarray(saved), None

    def to_global(self, state) -> SolverState:
        return state

    def from_global(self, state: SolverState):
        return state


def simulate(problem, n_steps: int, *, dt=None, save_every: int = 1, partitions=None,
             mode: str = "preassembled", seed: int = 0, devices=None,
             progress: bool | None = None, checkpoint: str | os.PathLike | None = None,
             checkpoint_every: int | None = None, chunk_steps: int = 5000,
             blowup_factor: float = 1e3, check_stability: bool = True, sync: str | None = None,
             shared_every: int | None = None):
    """Integrate ``problem`` for ``n_steps`` explicit steps.

    Args:
        problem: a :class:`jaxsync.Problem`.
        n_steps: number of time steps (a multiple of ``save_every``).
        dt: time step [s]; default ``problem.dt`` (the paper's CFL rule). A dt above the
            CFL step is checked against the exact bound 2/omega_max and refused above it.
        save_every: keep the displacement every this many steps (and at t = 0).
        partitions: None for the single-device solver; an int n_parts or a
            :class:`jaxsync.Partition` for the distributed solver (paper Algorithm 1,
            ``jax.shard_map`` over ``devices`` with a psum of shared-node forces).
        mode: ``"preassembled"`` (sparse K, stored once) or ``"recompute"`` (element
            quantities formed every step), paper Remark 2.
        seed: METIS seed when ``partitions`` is an int.
        devices: devices for the distributed solver (default: as many of
            ``jax.devices()`` as divide n_parts).
        progress: show a tqdm progress bar (default: when n_steps >= 20000).
        checkpoint: HDF5 path for resumable runs: the state is stored there every
            ``checkpoint_every`` steps (rounded up to whole chunks), and a run started
            again with the same problem continues from it, giving the same trajectory.
        chunk_steps: steps per compiled chunk, between progress/divergence checks.
        blowup_factor: a displacement larger than this times the mesh's bounding-box
            diagonal counts as divergence.
        check_stability: set False to force a dt through without the bound check.
        sync: distributed only: ``"psum"``, ``"ppermute"`` or ``"mpi"`` (see
            :class:`jaxsync.solve.distributed.DistributedRunner`; default: the faster measured).
        shared_every: distributed only: keep each part's shared-node displacements every
            this many steps (a divisor of ``save_every``; default ``save_every``). The
            surrogates train on every step: ``shared_every=1`` keeps that small history
            while the full field is saved only every ``save_every`` steps.

    Returns:
        :class:`jaxsync.Trajectory` with ``n_steps // save_every + 1`` snapshots (and,
        for distributed runs, the per-part shared-node histories in ``parts``, every
        ``shared_every`` steps). ``stats`` holds ``us_per_step`` (compiled chunks
        only) and ``compile_seconds``.

    Raises:
        StabilityError: dt above the bound, or the run diverged (NaN/Inf or blow-up); the
            error's ``trajectory`` attribute holds the snapshots saved before divergence.
        CheckpointError: the checkpoint file belongs to another problem or is corrupt.
        PartitionError: a partition that cannot be made or does not fit the mesh.

    Differentiable: when the material, damping, loads or dt are JAX tracers (inside
    ``jax.grad``), the whole run is one ``lax.scan`` without progress, divergence checks or
    checkpoints, and the trajectory holds JAX arrays (single-device solver).
    """
    from ..precision import require_float64
    from ..trajectory import Trajectory

    require_float64("simulate")
    n_steps, save_every = int(n_steps), int(save_every)
    if n_steps < 0 or save_every < 1:
        raise ProblemError(f"need n_steps >= 0 and save_every >= 1, got {n_steps}, {save_every}")
    if n_steps % save_every:
        raise ProblemError(f"n_steps={n_steps} is not a multiple of save_every={save_every}; "
                           f"use n_steps={n_steps - n_steps % save_every + save_every}")
    shared_every = save_every if shared_every is None else int(shared_every)
    if shared_every < 1 or save_every % shared_every:
        raise ProblemError(f"shared_every={shared_every} must be a positive divisor of "
                           f"save_every={save_every}")
    if shared_every != save_every and partitions is None:
        raise ProblemError("shared_every needs a distributed run (partitions=...): a single-device "
                           "run has no shared nodes")
    dt = problem.dt if dt is None else dt
    traced = is_traced(problem.material, problem.damping, problem.loads, dt,
                       problem.initial_displacement, problem.initial_velocity)
    if not traced and check_stability:
        from ..fem.timestep import check_dt

        check_dt(problem, dt)
    system = build_system(problem, dt, mode)
    state = initial_state(problem, system)
    if traced:
        if partitions is not None:
            raise ProblemError("differentiating through the distributed solver is not supported; "
                               "use partitions=None (the single-device solver) under jax.grad")
        n_saves = n_steps // save_every
        _, saved = advance(system, state, n_saves, save_every)
        displacement = jnp.concatenate([state.displacement[None], saved])
        times = jnp.arange(n_saves + 1) * save_every * system.dt
        return Trajectory(times=times, displacement=displacement, mesh=problem.mesh,
                          dt=dt, save_every=save_every, parameters=_parameters(problem))
    part_info = None
    if partitions is None:
        runner = SingleDeviceRunner(system, save_every)
    else:
        from .distributed import DistributedRunner

        runner = DistributedRunner(problem, system, partitions, save_every=save_every,
                                   mode=mode, seed=seed, devices=devices, sync=sync,
                                   record_shared=shared_every != save_every)
        part_info = runner.partition
    return drive(problem, runner, state, n_steps, float(dt), save_every, partition=part_info,
                 progress=progress, checkpoint=checkpoint, checkpoint_every=checkpoint_every,
                 chunk_steps=chunk_steps, blowup_factor=blowup_factor, shared_every=shared_every)


def drive(problem, runner, state: SolverState, n_steps: int, dt: float, save_every: int, *,
          partition=None, progress=None, checkpoint=None, checkpoint_every=None,
          chunk_steps=5000, blowup_factor=1e3, label="simulate", shared_every=None,
          return_state=False):
    """The host loop shared by all solvers: compiled chunks of ``runner.advance`` (each
    compiled ahead, so that the time per step excludes compilation), a progress bar,
    divergence checks and checkpoints between chunks. ``shared_every`` (distributed
    runners that record shared nodes every step): stride of the parts' shared histories.
    Returns the :class:`jaxsync.Trajectory`, and with ``return_state`` also the final
    global :class:`SolverState` (both displacement levels, to continue the run)."""
    from tqdm import tqdm

    shared_every = save_every if shared_every is None else shared_every
    saves_per_chunk = max(1, int(chunk_steps) // save_every)
    snapshots = [np.asarray(state.displacement)[None]]
    recorded = None
    if getattr(runner, "record_shared", False):  # shared-node values at every step, from step 0
        recorded = [[np.asarray(state.displacement)[None, part.shared_nodes].reshape(1, -1)]
                    for part in partition.parts]
    fingerprint = _fingerprint(problem, dt, save_every)
    if checkpoint is not None and os.path.exists(checkpoint):
        state, snapshots, recorded = _load_checkpoint(checkpoint, fingerprint, n_steps,
                                                      0 if recorded is None else len(recorded))
    run_state = runner.from_global(state)
    step_now = int(state.step)
    checkpoint_chunks = max(1, math.ceil((checkpoint_every or chunk_steps) / (saves_per_chunk * save_every)))
    limit = blowup_factor * float(np.linalg.norm(np.ptp(problem.mesh.points, axis=0)))
    show = progress if progress is not None else n_steps >= 20000
    bar = tqdm(total=n_steps, initial=step_now, disable=not show, unit="step", desc=label,
               dynamic_ncols=True)
    chunks_done = 0
    timed_steps, timed_seconds = 0, 0.0  # compiled chunks (compilation done ahead, not timed)
    compile_seconds = 0.0
    try:
        while step_now < n_steps:
            k = min(saves_per_chunk, (n_steps - step_now) // save_every)
            compile_seconds += runner.compile(run_state, k)
            start = time.perf_counter()
            new_state, saved, shared = runner.advance(run_state, k)
            timed_seconds += time.perf_counter() - start
            timed_steps += k * save_every
            ok = np.isfinite(saved).all(axis=(1, 2)) & (np.abs(saved).max(axis=(1, 2), initial=0) <= limit)
            if not ok.all():
                first_bad = int(np.argmin(ok))
                snapshots.append(saved[:first_bad])
                if recorded is not None:
                    for rec, values in zip(recorded, shared):
                        rec.append(values[:first_bad * save_every])
                bad_step = step_now + (first_bad + 1) * save_every
                partial = _trajectory(problem, snapshots, dt, save_every, partition, recorded, shared_every)
                err = StabilityError(
                    f"the run diverged by step {bad_step} (t = {bad_step * dt:.6g} s): displacement "
                    f"is NaN/Inf or above {limit:.3g} cm. dt={dt:.4e} s vs CFL {problem.dt:.4e} s; "
                    f"reduce dt. The {partial.n_saved} snapshots saved before are kept "
                    "(error.trajectory)")
                err.trajectory = partial
                raise err
            snapshots.append(saved)
            if recorded is not None:
                for rec, values in zip(recorded, shared):
                    rec.append(values)
            run_state = new_state
            step_now += k * save_every
            chunks_done += 1
            bar.update(k * save_every)
            if checkpoint is not None and (chunks_done % checkpoint_chunks == 0 or step_now == n_steps):
                global_state = runner.to_global(run_state)  # collective in multi-process runs
                if jax.process_index() == 0:  # one writer
                    _save_checkpoint(checkpoint, fingerprint, global_state, snapshots, recorded)
    except BaseException:
        bar.leave = False  # an error clears the bar instead of leaving a (blank) line before it
        raise
    finally:
        bar.close()
    traj = _trajectory(problem, snapshots, dt, save_every, partition, recorded, shared_every)
    from ..parallel.devices import device_summary
    from ..trajectory import RunStats

    stats = RunStats(compile_seconds=compile_seconds,
                     us_per_step=1e6 * timed_seconds / timed_steps if timed_steps else None,
                     **device_summary(getattr(runner, "devices", None) or jax.devices()[:1]))
    traj = dataclasses.replace(traj, stats=stats)
    return (traj, runner.to_global(run_state)) if return_state else traj


def _trajectory(problem, snapshots, dt, save_every, partition=None, recorded=None, shared_every=None):
    """The trajectory of a run's snapshots; per-part shared histories from ``recorded``
    (every step, thinned to ``shared_every``) or else from the snapshots."""
    from ..trajectory import PartHistory, Trajectory

    displacement = np.concatenate(snapshots, axis=0)
    times = np.arange(len(displacement)) * save_every * dt
    parts = ()
    if partition is not None:
        if recorded is None:
            shared = [displacement[:, part.shared_nodes].reshape(len(displacement), -1)
                      for part in partition.parts]
            shared_every = save_every
        else:
            shared = [np.concatenate(rec)[::shared_every] for rec in recorded]
        parts = tuple(PartHistory(part.shared_nodes, part.elements, values)
                      for part, values in zip(partition.parts, shared))
    return Trajectory(times=times, displacement=displacement, mesh=problem.mesh, dt=dt,
                      save_every=save_every, parameters=_parameters(problem), parts=parts,
                      shared_every=shared_every if partition is not None else None)


def _parameters(problem) -> dict:
    """Problem parameters stored with a trajectory (concrete values only)."""
    m = problem.material
    out = {}
    for name, value in (("E", m.E), ("nu", m.nu), ("rho", m.rho), ("damping", problem.damping)):
        if not is_traced(value):
            out[name] = float(value)
    return out


_CHECKPOINT_KIND = "jaxsync-solver-checkpoint"


def _checkpoint_checksum(arrays: dict, fingerprint: str, step: int) -> str:
    """sha256 over the stored state arrays, the problem fingerprint and the step."""
    from ..trajectory import array_checksum

    return array_checksum(arrays, {"kind": _CHECKPOINT_KIND, "fingerprint": str(fingerprint),
                                   "step": int(step)})


def _save_checkpoint(path, fingerprint, state: SolverState, snapshots, recorded=None) -> None:
    """``recorded``: per part, the list of shared-history chunks kept every step."""
    from ..trajectory import atomic_h5

    arrays = {"displacement": np.asarray(state.displacement),
              "previous": np.asarray(state.previous),
              "snapshots": np.concatenate(snapshots, axis=0)}
    for p, chunks in enumerate(recorded or ()):
        arrays[f"shared_{p}"] = np.concatenate(chunks, axis=0)
    step_ = int(state.step)
    with atomic_h5(path) as f:
        f.attrs["kind"] = _CHECKPOINT_KIND
        f.attrs["fingerprint"] = fingerprint
        f.attrs["step"] = step_
        f.attrs["checksum"] = _checkpoint_checksum(arrays, fingerprint, step_)
        for name, array in arrays.items():
            f[name] = array


def _load_checkpoint(path, fingerprint, n_steps, n_recorded: int = 0):
    """(state, snapshot chunks, per-part shared-history chunks or None); ``n_recorded``
    parts' every-step shared histories must be in the file when > 0."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("kind") != _CHECKPOINT_KIND:
                raise CheckpointError(f"{path} is not a jaxsync solver checkpoint; delete it or "
                                      "pass another checkpoint path")
            if f.attrs["fingerprint"] != fingerprint:
                raise CheckpointError(
                    f"checkpoint {path} was written by a different problem, dt or save_every; "
                    "delete it or pass another checkpoint path")
            step_ = int(f.attrs["step"])
            names = ["displacement", "previous", "snapshots"] + sorted(
                (k for k in f if k.startswith("shared_")), key=lambda k: int(k.split("_")[1]))
            arrays = {name: f[name][...] for name in names}
            stored = f.attrs.get("checksum")
    except CheckpointError:
        raise
    except Exception as exc:
        raise CheckpointError(f"cannot read checkpoint {path}: {exc}; delete it to start over") from exc
    if stored is None:
        raise CheckpointError(
            f"checkpoint {path} has no checksum (written by an older jaxsync), so its state "
            "cannot be verified; delete it to start over")
    if str(stored) != _checkpoint_checksum(arrays, fingerprint, step_):
        raise CheckpointError(
            f"checkpoint {path} fails its checksum: the stored state was altered or damaged "
            "after it was written, and resuming from it would give a wrong trajectory; "
            "delete it to start over")
    if step_ > n_steps:
        raise CheckpointError(f"checkpoint {path} is at step {step_}, beyond n_steps={n_steps}")
    recorded = None
    if n_recorded:
        if f"shared_{n_recorded - 1}" not in arrays:
            raise CheckpointError(
                f"checkpoint {path} holds no every-step shared histories (it was written with "
                "shared_every = save_every); delete it, or resume with the same shared_every")
        recorded = [[arrays[f"shared_{p}"]] for p in range(n_recorded)]
    state = SolverState(jnp.asarray(arrays["displacement"]), jnp.asarray(arrays["previous"]),
                        jnp.asarray(step_, dtype=jnp.int32))
    return state, [arrays["snapshots"]], recorded
