"""Ensembles: several runs of one system, batched into one compiled program.

Surrogate training sets are ensembles of runs that differ only in their load magnitudes,
Dirichlet values or initial conditions (say 10 cantilever runs with f_z ~ U(0.3, 0.7)).
:func:`ensemble` advances all of them together: ``jax.vmap`` over a leading runs axis of
the synchronized phase (:func:`jaxsync.solve.phases.synchronized_steps`), compiled once,
driven by the one host loop (:func:`jaxsync.solve.driver.run_chunks`) with progress and
divergence checks -- or, for traced inputs, as one traced program (differentiable).
"""

from __future__ import annotations

import contextlib
import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import PartitionError, ProblemError, StabilityError
from ..fem.stepper import ExplicitSystem, build_system, initial_state
from ..fem.timestep import divergence_advice
from ..pytree import is_traced
from ..trajectory import Result
from .driver import Chunk, Diverged, Progress, chunk_of_saves, divergence_limit, run_chunks
from .phases import synchronized_steps
from .record import synchronized_trajectory
from .strategies import HostExecutor, SaveAt, TracedExecutor, choose_executor

__all__ = ["ensemble"]

# Only the per-run data are batched: the stiffness, mass, damping (alpha, beta), dt, constrained dofs and
# load time functions are one copy for all runs.
_RUN_AXES = ExplicitSystem(stiffness=None, mass=None, damping=None, dt=None, load_vectors=0,
                           load_times=None, fixed=None, fixed_values=0, moving=0, moving_times=None,
                           spring=None, dashpot=None, follower=None, stiffness_damping=None)


def _advance_runs(system: ExplicitSystem, states, n_saves: int, save_every: int, interface, adjoint=None):
    """The synchronized phase of every run: ``system`` with load_vectors (n_runs, n_loads,
    n_nodes, 3) and fixed_values (n_runs, n_nodes, 3), ``states`` with a leading runs axis.
    Returns (states, saved (n_saves, n_runs, n_nodes, 3)), or with ``interface`` (node ids)
    the pair (saved, recorded (n_saves * save_every, n_runs, n_interface, 3)) after every
    step. ``adjoint``: as for :func:`jaxsync.solve.phases.synchronized_steps`."""
    record = None if interface is None else (lambda s: s.displacement[interface])

    def one_run(run_system, state):
        return synchronized_steps(run_system, state, n_saves, save_every, record=record, adjoint=adjoint)

    # runs axis second in the outputs: the host reads each chunk as one field of all runs
    return jax.vmap(one_run, in_axes=(_RUN_AXES, 0), out_axes=(0, 1))(system, states)


_advance_runs_jit = jax.jit(_advance_runs, static_argnums=(2, 3))


class _EnsembleRunner:
    """Advances the stacked states of all runs on one device (a
    :class:`jaxsync.solve.driver.Runner`). Each chunk shows the runs side by side as one
    field (n_saves, n_runs * n_nodes, 3), so the host loop's divergence check covers every
    run; the shared-node record is one array (steps, n_runs, n_interface, 3)."""

    def __init__(self, system: ExplicitSystem, n_runs: int, n_mesh_nodes: int, save_every: int,
                 interface=None):
        self.system, self.save_every = system, save_every
        self.n_runs, self.n_mesh_nodes = n_runs, n_mesh_nodes
        self.n_nodes = n_runs * n_mesh_nodes
        self.interface = None if interface is None else jnp.asarray(interface)
        self.devices = jax.devices()[:1]
        self.last = None  # (step before the latest chunk, its saved (n_saves, n_runs, n_nodes, 3))
        self._step = 0
        self._programs = {}

    def chunk_steps(self, steps_left: int, preferred: int) -> int:
        return chunk_of_saves(steps_left, preferred, self.save_every)

    def compile(self, states, steps: int) -> float:
        n_saves = steps // self.save_every
        if n_saves in self._programs:
            return 0.0
        start = time.perf_counter()
        self._programs[n_saves] = _advance_runs_jit.lower(self.system, states, n_saves, self.save_every,
                                                          self.interface).compile()
        return time.perf_counter() - start

    def advance(self, states, steps: int):
        self.compile(states, steps)
        states, out = self._programs[steps // self.save_every](self.system, states, self.interface)
        saved, recorded = out if self.interface is not None else (out, None)
        saved = np.asarray(saved)
        self.last, self._step = (self._step, saved), self._step + steps
        shared = None if recorded is None else [np.asarray(recorded)]
        return states, Chunk(saved.reshape(len(saved), self.n_nodes, 3), shared)


def ensemble(problems, n_steps: int, *, partitions=None, labels=None, dt=None, save=1, executor=None) -> tuple:
    """Integrate several problems of one system together, batched (``jax.vmap`` over runs).

    The runs share one mesh, material, damping, set of constrained dofs, load time
    functions and density scale; they may differ in their load MAGNITUDES (and spatial
    load vectors), Dirichlet values and initial displacement / velocity. All advance in
    one compiled program on one device (one compilation per chunk length for the whole
    ensemble, not one per run) -- the way to generate surrogate training sets.

    Args:
        problems: sequence of n_runs :class:`jaxsync.Problem` (e.g.
            ``jaxsync.cantilever(mesh, body_force=(0, 0, -fz))`` for several fz).
        n_steps: time steps of every run (a multiple of the save stride).
        partitions: None; or an int n_parts (METIS, seed 0) or a :class:`jaxsync.Partition`:
            each trajectory then has the per-part shared-node histories of a distributed
            run (``parts``), laid out as ``jaxsync.simulate(problem, n_steps,
            partitions=..., save=...)`` gives them. The computation is still the full-mesh
            stepper on one device; it equals the distributed run to round-off.
        labels: optional sequence of n_runs floats (the load magnitude, an
            initial-condition factor...), stored as ``parameters["load_parameter"]`` of
            each trajectory: the conditional surrogates' input
            (:func:`jaxsync.surrogate.histories.read_shared_histories`).
        dt: time step [s]; default the first problem's ``dt``, checked against the exact
            stability bound as in :func:`jaxsync.simulate`.
        save: an int or a :class:`jaxsync.SaveAt` (with ``partitions``, ``shared_every=1``
            keeps the shared-node displacements after every step, for training).
        executor: :class:`jaxsync.HostExecutor` (default for concrete inputs: progress over
            the batched steps, chunks, divergence checks) or :class:`jaxsync.TracedExecutor`
            (default for traced inputs: one differentiable program).

    Returns:
        A tuple of n_runs :class:`jaxsync.Trajectory`, in the order of ``problems``: each
        with ``n_steps // every + 1`` snapshots, displacement (n_saved, n_nodes, 3)
        [cm], times [s], and with ``partitions`` the ``parts`` of a distributed run.
        ``stats.us_per_step`` is the wall time of one BATCHED step, all runs advancing
        together [us] (per run: divide by n_runs), compilation excluded;
        ``stats.compile_seconds`` the compilation of the batched program (the same in
        every trajectory).

    Raises:
        ProblemError: no problems, problems of different systems (the message names the
            first differing problem and what differs), a wrong number of labels, bad
            ``n_steps`` / ``save``.
        StabilityError: dt above the stability bound, or a run diverged (NaN/Inf or
            blow-up): the message names the run; ``error.run`` is its index,
            ``error.trajectories`` the snapshots of every run before divergence and
            ``error.trajectory`` those of the diverged run.
        PartitionError: a partition of another mesh.
    """
    from ..precision import require_float64

    require_float64("ensemble")
    problems = tuple(problems)
    if not problems:
        raise ProblemError("ensemble needs at least one problem, got an empty sequence")
    n_runs = len(problems)
    if labels is not None:
        labels = tuple(labels)
        if len(labels) != n_runs:
            raise ProblemError(f"got {len(labels)} labels for {n_runs} problems; give one label per "
                               "problem (or labels=None)")
        try:
            labels = tuple(float(x) for x in labels)
        except (TypeError, ValueError) as exc:
            raise ProblemError(f"labels must be numbers (one float per problem), got {labels!r}") from exc
    save = SaveAt.of(save)
    n_steps = save.check_steps(n_steps)
    if partitions is None and save.records_every_step:
        raise ProblemError("shared_every needs a distributed run (partitions=...): a single-device "
                           "run has no shared nodes")
    first = problems[0]
    dt = first.dt if dt is None else dt
    traced = any(is_traced(p.material, p.damping, p.stiffness_damping, p.loads, dt, p.initial_displacement,
                           p.initial_velocity)
                 for p in problems)
    executor = choose_executor(executor, traced)
    if isinstance(executor, HostExecutor) and executor.check_stability:
        from ..fem.timestep import check_dt

        check_dt(first, dt)
    if not traced:
        dt = float(dt)
    mesh = first.mesh
    partition = _partition(first, partitions)

    # One system for all runs: check every problem's against the first, keep its per-run data.
    reference = build_system(first, dt)
    load_vectors, fixed_values, moving, states = [], [], [], []
    for index, problem in enumerate(problems):
        system = reference if index == 0 else build_system(problem, dt)
        what = None if traced else _difference(problem, system, first, reference)
        if what is not None:
            raise ProblemError(
                f"problem {index} of the ensemble differs from problem 0 in its {what}: the runs of an "
                "ensemble share one system (mesh, material, damping, supports, density scale, constrained dofs "
                "and time functions) and may differ only in load magnitudes, Dirichlet values and "
                f"initial conditions; run problem {index} separately with jaxsync.simulate")
        load_vectors.append(system.load_vectors)
        fixed_values.append(system.fixed_values)
        moving.append(system.moving)
    for problem, loads, values, history in zip(problems, load_vectors, fixed_values, moving):  # the start, per run
        states.append(initial_state(problem, dataclasses.replace(reference, load_vectors=loads,
                                                                 fixed_values=values, moving=history)))
    batched = dataclasses.replace(reference, load_vectors=jnp.stack(load_vectors),
                                  fixed_values=jnp.stack(fixed_values),
                                  moving=None if reference.moving is None else jnp.stack(moving))
    stacked = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *states)
    record = partition is not None and save.records_every_step
    interface = partition.shared_nodes if record else None
    start_fields = [s.displacement for s in states]

    def trajectories(saved, every_step, stats=None, result=None):
        """The runs' trajectories from step 0: ``saved`` (n_saves, n_runs, n_nodes, 3),
        ``every_step`` (n_steps, n_runs, n_interface, 3) or None."""
        xp = jnp if traced else np
        out = []
        for r, problem in enumerate(problems):
            recorded = None
            if record:
                steps_r = every_step[:, r]
                recorded = [xp.concatenate([start_fields[r][None, part.shared_nodes].reshape(1, -1),
                                            steps_r[:, part.shared_interface].reshape(len(steps_r),
                                                                                     3 * part.n_shared)])
                            for part in partition.parts]
            displacement = xp.concatenate([xp.asarray(start_fields[r])[None], saved[:, r]])
            traj = synchronized_trajectory(problem, displacement, dt, save, partition, recorded, stats=stats,
                                           result=result if result is None or np.ndim(result) == 0 else result[r])
            if labels is not None:
                traj = dataclasses.replace(traj, parameters={**traj.parameters, "load_parameter": labels[r]})
            out.append(traj)
        return out

    if isinstance(executor, TracedExecutor):
        n_saves = n_steps // save.every
        if n_saves == 0:
            return tuple(trajectories(jnp.zeros((0, n_runs, first.n_nodes, 3)), None))
        _, out = _advance_runs(batched, stacked, n_saves, save.every,
                               None if interface is None else jnp.asarray(interface), executor.adjoint)
        saved, every_step = out if record else (out, None)
        finite = jnp.isfinite(saved).all(axis=(0, 2, 3))
        result = jnp.where(finite, jnp.int32(Result.SUCCESSFUL), jnp.int32(Result.DIVERGED))
        return tuple(trajectories(saved, every_step, result=result))

    start_fields = [np.asarray(f) for f in start_fields]
    runner = _EnsembleRunner(batched, n_runs, first.n_nodes, save.every, interface)

    def from_segment(segment, result):
        saved = segment.displacement.reshape(len(segment.displacement), n_runs, first.n_nodes, 3)
        every_step = None
        if record:
            every_step = (np.zeros((0, n_runs, partition.n_interface, 3)) if segment.shared is None
                          else segment.shared[0])  # None: no step run
        return trajectories(saved, every_step, result=result)

    limit = divergence_limit(mesh, executor.blowup_factor)
    with (contextlib.nullcontext(executor.progress) if isinstance(executor.progress, Progress)
          else Progress(n_steps, show=executor.progress, label=f"ensemble of {n_runs}")) as bar:
        try:
            segment = run_chunks(runner, stacked, 0, n_steps, kind="synchronized", limit=limit,
                                 progress=bar, chunk_steps=executor.chunk_steps)
        except Diverged as bad:
            raise _diverged(bad, runner, from_segment(bad.segment, Result.DIVERGED), limit, dt, first,
                            labels) from None
    from ..parallel.devices import device_summary
    from ..run_stats import SynchronizedStats

    stats = SynchronizedStats(compile_seconds=segment.compile_seconds,
                              us_per_step=1e6 * segment.seconds / segment.n_steps if segment.n_steps else None,
                              **device_summary(runner.devices))
    return tuple(dataclasses.replace(traj, stats=stats) for traj in from_segment(segment, Result.SUCCESSFUL))


def _partition(problem, partitions):
    """None, or the :class:`jaxsync.Partition` of ``partitions`` (an int or a Partition) on
    the problem's nodes."""
    from ..parallel.partitioning import Partition, partition, partition_from_elements

    if partitions is None:
        return None
    if not isinstance(partitions, Partition):
        return partition(problem, partitions)
    mesh = problem.mesh
    if partitions.mesh is not mesh and not (partitions.mesh.n_nodes == mesh.n_nodes
                                            and np.array_equal(partitions.mesh.tets, mesh.tets)):
        raise PartitionError("the partition was made for another mesh: partition the problems' mesh")
    if partitions.space is not problem.space:
        return partition_from_elements(problem.space, partitions.element_part, seed=partitions.seed)
    return partitions


def _difference(problem, system: ExplicitSystem, reference_problem, reference: ExplicitSystem) -> str | None:
    """What makes ``problem``'s system differ from the reference's, or None."""
    mesh, ref_mesh = problem.mesh, reference_problem.mesh
    if mesh is not ref_mesh and not (np.array_equal(mesh.points, ref_mesh.points)
                                     and np.array_equal(mesh.tets, ref_mesh.tets)):
        return "mesh (points or tetrahedra)"
    if problem.element != reference_problem.element:
        return "element (P1 or P2)"
    checks = (
        ("number of loads", lambda: len(system.load_times) == len(reference.load_times)),
        ("stiffness (material E, nu)", lambda: _same(system.stiffness, reference.stiffness)),
        ("lumped mass (density rho or density_scale)", lambda: _same(system.mass, reference.mass)),
        ("damping (alpha)", lambda: _same(system.damping, reference.damping)),
        ("stiffness-proportional damping (beta)",
         lambda: _same(system.stiffness_damping, reference.stiffness_damping)),
        ("time step", lambda: _same(system.dt, reference.dt)),
        ("constrained dofs (which dofs are fixed)", lambda: _same(system.fixed, reference.fixed)),
        ("prescribed-displacement time functions", lambda: _same(system.moving_times, reference.moving_times)
         and (system.moving is None) == (reference.moving is None)),
        ("elastic supports", lambda: _same(system.spring, reference.spring) and _same(system.dashpot,
                                                                                     reference.dashpot)),
        ("load time functions (ramp, switch-off time, waveform)",
         lambda: _same(system.load_times, reference.load_times)),
        ("follower pressures (surfaces, magnitudes, time functions: one copy for all runs)",
         lambda: _same(system.follower, reference.follower)),
    )
    for what, same in checks:
        if not same():
            return what
    return None


def _same(a, b) -> bool:
    """Equal pytrees: the same structure (node types included) and equal leaves."""
    leaves_a, tree_a = jax.tree_util.tree_flatten(a)
    leaves_b, tree_b = jax.tree_util.tree_flatten(b)
    if tree_a != tree_b:
        return False
    for x, y in zip(leaves_a, leaves_b):
        if np.shape(x) != np.shape(y):
            return False
        if isinstance(x, jax.Array) and isinstance(y, jax.Array):
            if x.dtype != y.dtype or not bool(jnp.array_equal(x, y)):  # on the device
                return False
        elif not np.array_equal(np.asarray(x), np.asarray(y)):
            return False
    return True


def _diverged(bad: Diverged, runner: _EnsembleRunner, partial: list, limit: float, dt: float, problem,
              labels) -> StabilityError:
    """The error of a diverged ensemble, naming the run(s) whose field went bad first."""
    first_step, saved = runner.last
    snapshot = saved[(bad.step - first_step) // runner.save_every - 1]  # (n_runs, n_nodes, 3)
    ok = np.isfinite(snapshot).all(axis=(1, 2)) & (np.abs(snapshot).max(axis=(1, 2), initial=0) <= limit)
    runs = [int(r) for r in np.flatnonzero(~ok)]
    run = runs[0]
    named = f"run {run}" + ("" if labels is None else f" (label {labels[run]:g})")
    also = f" (also runs {runs[1:]})" if len(runs) > 1 else ""
    advice = divergence_advice(problem, dt)
    return StabilityError(
        f"{named} of the ensemble diverged by step {bad.step} (t = {bad.step * dt:.6g} s){also}: displacement "
        f"is NaN/Inf or above {limit:.3g} cm. {advice}; check that "
        f"run's loads and initial conditions. The {partial[run].n_saved} snapshots of each run saved before "
        "are kept (error.trajectories)", trajectory=partial[run], trajectories=tuple(partial), run=run,
        runs=tuple(runs))
