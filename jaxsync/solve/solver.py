"""Explicit solver driver: single-device and distributed runs in compiled chunks.

The numerics (central differences with lumped mass, paper eq. 7; the paper's start) are
the pure stepper of :mod:`jaxsync.fem.stepper`. Here the driver :func:`simulate` runs it in
compiled ``lax.scan`` chunks (on one device, or over parts through
:mod:`jaxsync.solve.distributed`), saves every ``save_every`` steps, shows progress, checks for
divergence and checkpoints between chunks; :func:`steady_state` solves the static problem.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ProblemError, StabilityError
from ..fem.loads import load_jumps
from ..fem.stepper import ExplicitSystem, SolverState, advance, build_system, initial_state
from ..pytree import is_traced
from .checkpoint import CheckpointSchedule, CheckpointWriter, fingerprint, load_checkpoint, watch_chunks
from .driver import Chunk, Diverged, Progress, chunk_of_saves, divergence_limit, run_chunks

__all__ = ["simulate", "steady_state", "drive", "SingleDeviceRunner"]

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


class SingleDeviceRunner:
    """Advances a global :class:`SolverState` on one device (a :class:`jaxsync.solve.driver.Runner`)."""

    def __init__(self, system: ExplicitSystem, save_every: int):
        self.system, self.save_every = system, save_every
        self.n_nodes = int(np.shape(system.mass)[0])
        self.devices = jax.devices()[:1]
        self._programs = {}

    def chunk_steps(self, steps_left: int, preferred: int) -> int:
        return chunk_of_saves(steps_left, preferred, self.save_every)

    def compile(self, state, steps: int) -> float:
        """Compile the chunk program ahead of time; returns the seconds spent."""
        n_saves = steps // self.save_every
        if n_saves in self._programs:
            return 0.0
        start = time.perf_counter()
        self._programs[n_saves] = _advance_jit.lower(self.system, state, n_saves, self.save_every).compile()
        return time.perf_counter() - start

    def advance(self, state, steps: int):
        self.compile(state, steps)
        state, saved = self._programs[steps // self.save_every](self.system, state)
        return state, Chunk(np.asarray(saved))

    def to_global(self, state) -> SolverState:
        return state

    def from_global(self, state: SolverState):
        return state


def check_steps(n_steps, save_every, shared_every, partitions) -> tuple[int, int, int]:
    """``n_steps``, ``save_every`` and ``shared_every`` (defaulted to ``save_every``) of a
    run, checked: a multiple of saves, shared histories at a divisor of the save stride and
    only with parts (``partitions`` not None). Raises :class:`ProblemError`."""
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
    return n_steps, save_every, shared_every


def simulate(problem, n_steps: int, *, dt=None, save_every: int = 1, partitions=None,
             mode: str = "preassembled", seed: int = 0, devices=None,
             progress: bool | None = None, checkpoint: str | os.PathLike | None = None,
             checkpoint_every: int | None = None, chunk_steps: int = 5000,
             blowup_factor: float = 1e3, check_stability: bool = True, sync: str | None = None,
             shared_every: int | None = None, halo_depth: int = 1,
             gradient_checkpoints: bool | int = True):
    """Integrate ``problem`` for ``n_steps`` explicit steps.

    Args:
        problem: a :class:`jaxsync.Problem`.
        n_steps: number of time steps (a multiple of ``save_every``).
        dt: time step [s]; default ``problem.dt``: the paper's CFL step, or 0.9 times the
            exact bound 2/omega_max where that is smaller (``problem.time_step`` says which).
            A dt above the default is checked against the exact bound and refused above it.
        save_every: keep the displacement every this many steps (and at t = 0).
        partitions: None for the single-device solver; an int n_parts or a
            :class:`jaxsync.Partition` for the distributed solver (paper Algorithm 1,
            ``jax.shard_map`` over ``devices`` with a psum of shared-node forces).
        mode: ``"preassembled"`` (sparse K, stored once) or ``"recompute"`` (element
            quantities formed every step), paper Remark 2.
        seed: METIS seed when ``partitions`` is an int.
        devices: devices for the distributed solver (default: as many of
            ``jax.devices()`` as divide n_parts).
        progress: show a tqdm progress bar (default: when n_steps >= 20000), or a
            :class:`jaxsync.solve.Progress` to report to (shared by several runs).
        checkpoint: HDF5 path for resumable runs: the state is stored there every
            ``checkpoint_every`` steps (rounded up to whole chunks), and a run started
            again with the same problem continues from it, giving the same trajectory.
        chunk_steps: steps per compiled chunk, between progress/divergence checks.
        blowup_factor: a displacement larger than this times the mesh's bounding-box
            diagonal counts as divergence.
        check_stability: set False to force a dt through without the bound check.
        sync: distributed only: ``"psum"``, ``"ppermute"``, ``"mpi"`` or ``"halo"`` (see
            :class:`jaxsync.solve.distributed.DistributedRunner`; default:
            :func:`jaxsync.parallel.multiprocess.default_sync`).
        halo_depth: with ``sync="halo"``, the steps k between two exchanges of the deep
            halos (:mod:`jaxsync.parallel.halo`, exact); ``save_every`` and k must divide
            one another and ``n_steps`` be a multiple of the larger.
        shared_every: distributed only: keep each part's shared-node displacements every
            this many steps (a divisor of ``save_every``; default ``save_every``). The
            surrogates train on every step: ``shared_every=1`` keeps that small history
            while the full field is saved only every ``save_every`` steps.
        gradient_checkpoints: traced runs only (inside ``jax.grad``): ``True`` (default)
            runs the time loop with recomputation (:mod:`jaxsync.solve.gradients`), so the
            reverse pass holds about 2 sqrt(n_steps) states instead of every step's, for
            one more forward pass; ``False``: the plain scan (every step stored, fastest
            for short runs); an int: a memory budget in bytes for the stored states (the
            plain scan when every step fits in it, else recomputation). Ignored by
            untraced runs.

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
    checkpoints, and the trajectory holds JAX arrays. Its reverse pass recomputes segments
    of the run (``gradient_checkpoints``) so that memory grows like sqrt(n_steps). With
    ``partitions`` the parts run under ``shard_map`` with ``sync="psum"`` (default) or
    ``"ppermute"`` (``mode``, ``seed`` and ``devices`` as for untraced runs; no
    ``shared_every``, deep halos or MPI), and the trajectory holds the merged global field.
    """
    from ..precision import require_float64
    from ..trajectory import Trajectory

    require_float64("simulate")
    n_steps, save_every, shared_every = check_steps(n_steps, save_every, shared_every, partitions)
    if partitions is None and (sync == "halo" or halo_depth != 1):
        raise ProblemError("deep halos (sync='halo', halo_depth) need a distributed run: pass "
                           "partitions=n_parts")
    if sync == "halo":
        from ..parallel.halo import check_halo_depth, check_save_every

        unit = check_save_every(save_every, check_halo_depth(halo_depth))
        if n_steps % unit:
            raise ProblemError(f"with halo_depth={halo_depth} and save_every={save_every}, n_steps "
                               f"must be a multiple of {unit}; use n_steps={n_steps - n_steps % unit + unit}")
    dt = problem.dt if dt is None else dt
    traced = is_traced(problem.material, problem.damping, problem.loads, dt,
                       problem.initial_displacement, problem.initial_velocity)
    if not traced and check_stability:
        from ..fem.timestep import check_dt

        check_dt(problem, dt)
    system = build_system(problem, dt, mode)
    state = initial_state(problem, system)
    if traced:
        from .gradients import advance_for_gradients, partitioned_trajectory

        n_saves = n_steps // save_every
        if n_saves == 0:
            saved = jnp.zeros((0,) + state.displacement.shape, state.displacement.dtype)
        elif partitions is None:
            _, saved = advance_for_gradients(system, state, n_saves, save_every, gradient_checkpoints)
        else:
            if shared_every != save_every or sync in ("mpi", "halo"):
                raise ProblemError("differentiating a distributed run supports sync='psum' or "
                                   "'ppermute' without shared_every")
            saved = partitioned_trajectory(problem, system, state, partitions, n_saves=n_saves,
                                           save_every=save_every, checkpoints=gradient_checkpoints,
                                           mode=mode, seed=seed, devices=devices, sync=sync)
        displacement = jnp.concatenate([state.displacement[None], saved])
        times = jnp.arange(n_saves + 1, dtype=system.dt.dtype) * save_every * system.dt
        return Trajectory(times=times, displacement=displacement, mesh=problem.mesh,
                          dt=dt, save_every=save_every, parameters=_parameters(problem))
    part_info = None
    if partitions is None:
        runner = SingleDeviceRunner(system, save_every)
    else:
        from .distributed import DistributedRunner

        runner = DistributedRunner(problem, system, partitions, save_every=save_every,
                                   mode=mode, seed=seed, devices=devices, sync=sync,
                                   record_shared=shared_every != save_every, halo_depth=halo_depth)
        part_info = runner.partition
    return drive(problem, runner, state, n_steps, float(dt), save_every, partition=part_info,
                 progress=progress, checkpoint=checkpoint, checkpoint_every=checkpoint_every,
                 chunk_steps=chunk_steps, blowup_factor=blowup_factor, shared_every=shared_every)


def drive(problem, runner, state: SolverState, n_steps: int, dt: float, save_every: int, *,
          partition=None, progress=None, checkpoint=None, checkpoint_every=None,
          chunk_steps=5000, blowup_factor=1e3, label="simulate", shared_every=None,
          return_state=False):
    """A synchronized run from ``state`` to step ``n_steps`` through the host loop
    (:func:`jaxsync.solve.driver.run_chunks`), with resumable checkpoints.

    ``runner``: a :class:`SingleDeviceRunner` or a
    :class:`jaxsync.solve.distributed.DistributedRunner`; ``progress``: a bool (a bar of
    its own; None: for long runs) or a :class:`jaxsync.solve.driver.Progress` to share.
    ``shared_every``: stride of the parts' shared histories when the runner records them
    every step. Returns the :class:`jaxsync.Trajectory` (from step 0, or from the
    checkpoint's start), and with ``return_state`` also the final global
    :class:`SolverState` (both displacement levels, to continue the run)."""
    shared_every = save_every if shared_every is None else shared_every
    snapshots = [np.asarray(state.displacement)[None]]
    recorded = None
    if getattr(runner, "record_shared", False):  # shared-node values at every step, from step 0
        recorded = [[np.asarray(state.displacement)[None, part.shared_nodes].reshape(1, -1)]
                    for part in partition.parts]
    problem_key = fingerprint(problem, dt, save_every)
    if checkpoint is not None and os.path.exists(checkpoint):
        state, snapshots, recorded = load_checkpoint(checkpoint, problem_key, n_steps,
                                                      0 if recorded is None else len(recorded))
    step_now = int(state.step)
    saves_per_chunk = max(1, int(chunk_steps) // save_every)
    stepped = runner
    if checkpoint is not None:
        # every checkpoint_every steps (whole chunks), or by default at most one per
        # CHECKPOINT_SECONDS of wall time; always at the end
        schedule = CheckpointSchedule(
            math.ceil(checkpoint_every / (saves_per_chunk * save_every)) if checkpoint_every else None)
        # each checkpoint appends the chunks since the last one (never all the run so far)
        writer = CheckpointWriter(checkpoint, problem_key, snapshots, recorded, n_steps=n_steps,
                                  save_every=save_every) if jax.process_index() == 0 else None  # one writer
        stepped = watch_chunks(runner)
        pending = []

    def after_chunk(step: int, so_far) -> None:
        new_state, chunk = stepped.last
        pending.append(chunk)
        if schedule.due(step == n_steps):
            global_state = runner.to_global(new_state)  # collective in multi-process runs
            if writer is not None:
                writer.commit(global_state, [c.displacement for c in pending],
                              None if recorded is None else [list(rows) for rows in
                                                             zip(*(c.shared for c in pending))])
            pending.clear()
            schedule.written()

    bar = progress if isinstance(progress, Progress) else None
    limit = divergence_limit(problem.mesh, blowup_factor)
    with (contextlib.nullcontext(bar) if bar is not None
          else Progress(n_steps, show=progress, label=label, initial=step_now)) as bar:
        try:
            segment = run_chunks(stepped, runner.from_global(state), step_now, n_steps, kind="synchronized",
                                 limit=limit, progress=bar, chunk_steps=chunk_steps,
                                 after_chunk=None if checkpoint is None else after_chunk)
        except Diverged as bad:
            from ..fem.timestep import divergence_advice

            partial = _trajectory(problem, snapshots + [bad.segment.displacement], dt, save_every, partition,
                                  _joined(recorded, bad.segment.shared), shared_every)
            err = StabilityError(
                f"the run diverged by step {bad.step} (t = {bad.step * dt:.6g} s): displacement "
                f"is NaN/Inf or above {limit:.3g} cm. {divergence_advice(problem, dt)}. "
                f"The {partial.n_saved} snapshots saved before are kept "
                "(error.trajectory)")
            err.trajectory = partial
            raise err from None
    traj = _trajectory(problem, snapshots + [segment.displacement], dt, save_every, partition,
                       _joined(recorded, segment.shared), shared_every)
    from ..parallel.devices import device_summary
    from ..trajectory import RunStats

    # a runner reaching the other processes through MPI holds one device of each of them
    processes = jax.process_count() if getattr(runner, "transport", None) == "mpi" else None
    stats = RunStats(compile_seconds=segment.compile_seconds,
                     us_per_step=1e6 * segment.seconds / segment.n_steps if segment.n_steps else None,
                     **device_summary(runner.devices, processes=processes))
    traj = dataclasses.replace(traj, stats=stats)
    return (traj, runner.to_global(segment.state)) if return_state else traj


def _joined(recorded, new):
    """Per part, the earlier shared-history chunks followed by ``new`` (None: none)."""
    if recorded is None or new is None:
        return recorded
    return [rec + [values] for rec, values in zip(recorded, new)]


def _trajectory(problem, snapshots, dt, save_every, partition=None, recorded=None, shared_every=None):
    """The trajectory of a run's snapshots; per-part shared histories from ``recorded``
    (every step, thinned to ``shared_every``) or else from the snapshots."""
    from ..trajectory import PartHistory, Trajectory

    displacement = np.concatenate(snapshots, axis=0)
    times = np.arange(len(displacement)) * save_every * dt
    n_steps = (len(displacement) - 1) * save_every  # snapshots from step 0
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
                      save_every=save_every, parameters=_parameters(problem, load_jumps(problem.loads, n_steps, dt)),
                      parts=parts,
                      shared_every=shared_every if partition is not None else None)


def _parameters(problem, jumps=None) -> dict:
    """Problem parameters stored with a trajectory (concrete values only); given the run's
    load jumps (:func:`jaxsync.fem.loads.load_jumps`), also ``last_load_jump``, the last of
    them (absent when there is none), which the offline check of
    :func:`jaxsync.surrogate.train_surrogates` starts after, as an online run does, and
    ``load_jumps``, all of them, across which training takes no window."""
    m = problem.material
    out = {}
    for name, value in (("E", m.E), ("nu", m.nu), ("rho", m.rho), ("damping", problem.damping)):
        if not is_traced(value):
            out[name] = float(value)
    if jumps is not None and len(jumps):
        out["last_load_jump"] = int(jumps[-1])
        out["load_jumps"] = [int(j) for j in jumps]  # training leaves out windows across them
    return out
