"""Ensembles: several runs of one system, batched into one compiled program.

Surrogate training sets are ensembles of runs that differ only in their load magnitudes,
Dirichlet values or initial conditions (say 10 cantilever runs with f_z ~ U(0.3, 0.7)).
:func:`ensemble` advances all of them together: ``jax.vmap`` over a leading runs axis of
the synchronized phase (:func:`jaxsync.solve.executors.synchronized_steps`), compiled once,
driven by the one host loop (:func:`jaxsync.solve.executors.run_chunks`) with progress and
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
from ..fem._stepper import ExplicitSystem
from ..fem._timestep import divergence_advice
from ..io.trajectory import Result
from ..pytree import is_traced
from ._ensemble_members import (
    EnsembleSetup,
    RunData,
    batched_system,
    initial_states,
    member_system,
    setup_of_members,
    setup_of_problems,
)
from ._ensemble_stability import check_members_dt, default_dt
from ._members import Members
from ._strategies import HostExecutor, SaveAt, TracedExecutor, choose_executor
from .executors._driver import Chunk, Diverged, Progress, chunk_of_saves, divergence_limit, run_chunks
from .executors._phases import synchronized_steps
from .executors._record import part_histories, run_parameters, synchronized_trajectory

__all__ = ["ensemble", "Members"]

def _advance_runs(system: ExplicitSystem, runs: RunData, states, n_saves: int, save_every: int, interface,
                  adjoint=None):
    """The synchronized phase of every run: the shared ``system`` with each run's own data
    (``runs``, a :class:`jaxsync.solve._ensemble_members.RunData` whose leaves have a leading
    runs axis), ``states`` with a leading runs axis. Returns (states, saved (n_saves, n_runs,
    n_nodes, 3)), or with ``interface`` (node ids) the pair (saved, recorded (n_saves *
    save_every, n_runs, n_interface, 3)) after every step. ``adjoint``: as for
    :func:`jaxsync.solve.executors.synchronized_steps`."""
    record = None if interface is None else (lambda s: s.displacement[interface])

    def one_run(run, state):
        return synchronized_steps(member_system(system, run), state, n_saves, save_every, record=record,
                                  adjoint=adjoint)

    # runs axis second in the outputs: the host reads each chunk as one field of all runs
    return jax.vmap(one_run, in_axes=(0, 0), out_axes=(0, 1))(runs, states)


_advance_runs_jit = jax.jit(_advance_runs, static_argnums=(3, 4))


class _EnsembleRunner:
    """Advances the stacked states of all runs on one device (a
    :class:`jaxsync.solve.executors.Runner`). Each chunk shows the runs side by side as one
    field (n_saves, n_runs * n_nodes, 3), so the host loop's divergence check covers every
    run; the shared-node record is one array (steps, n_runs, n_interface, 3)."""

    def __init__(self, system: ExplicitSystem, runs: RunData, n_runs: int, n_mesh_nodes: int, save_every: int,
                 interface=None):
        self.system, self.runs, self.save_every = system, runs, save_every
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
        self._programs[n_saves] = _advance_runs_jit.lower(self.system, self.runs, states, n_saves,
                                                          self.save_every, self.interface).compile()
        return time.perf_counter() - start

    def advance(self, states, steps: int):
        self.compile(states, steps)
        states, out = self._programs[steps // self.save_every](self.system, self.runs, states,
                                                                      self.interface)
        saved, recorded = out if self.interface is not None else (out, None)
        saved = np.asarray(saved)
        self.last, self._step = (self._step, saved), self._step + steps
        shared = None if recorded is None else [np.asarray(recorded)]
        return states, Chunk(saved.reshape(len(saved), self.n_nodes, 3), shared)


def ensemble(problems, n_steps: int, *, members: Members | None = None, partitions=None, labels=None, dt=None,
             save=1, executor=None) -> tuple:
    """Integrate several runs of one system together, batched (``jax.vmap`` over runs).

    The runs share one mesh, element, material law, supports, density scaling, set of
    constrained dofs and load / prescribed-displacement time functions; each may have its
    own material parameters (E, nu, rho, or a hyperelastic law's), damping alpha and beta,
    load magnitudes (and spatial load vectors), Dirichlet values and initial displacement /
    velocity. All advance in one compiled program on one device (one compilation per chunk
    length for the whole ensemble, not one per run) -- the way to generate surrogate
    training sets, or to fit many observations at once (``jax.grad`` through it).

    Two ways to give the runs:

    * ``ensemble(problems, n_steps)``: a sequence of n_runs :class:`jaxsync.Problem`
      (e.g. ``jaxsync.cantilever(mesh, body_force=(0, 0, -fz))`` for several fz);
    * ``ensemble(problem, n_steps, members=jaxsync.Members(...))``: one problem and per-run
      arrays (:class:`jaxsync.Members`: ``material={"E": (n_runs,)...}``, ``damping``,
      ``stiffness_damping``, ``load_scale``, ``initial_displacement``,
      ``initial_velocity``, ``dirichlet``), set up in one vectorised pass without a
      Problem per run (the fast way to thousands of runs; differentiable in every array).

    Either way nothing is assembled per run: :func:`jaxsync.solve.batched_system` (the
    stiffness of each run's E and nu from the two unit operators, E alone as one scale per
    run; the lumped mass rho_r M_1; the damping per run).

    Args:
        problems: a sequence of n_runs problems, or with ``members`` the one problem.
        n_steps: time steps of every run (a multiple of the save stride). With the number
            of runs it chooses the stiffness product's form, as for one run of n_runs *
            n_steps steps (:meth:`jaxsync.fem.forces.Preassembled.for_run`).
        members: a :class:`jaxsync.Members`, or None (the runs are ``problems``).
        partitions: None; or an int n_parts (METIS, seed 0) or a :class:`jaxsync.Partition`:
            each trajectory then has the per-part shared-node histories of a distributed
            run (``parts``), laid out as ``jaxsync.simulate(problem, n_steps,
            partitions=..., save=...)`` gives them. The computation is still the full-mesh
            stepper on one device; it equals the distributed run to round-off.
        labels: optional sequence of n_runs floats (the load magnitude, an
            initial-condition factor...), stored as ``parameters["load_parameter"]`` of
            each trajectory: the conditional surrogates' input
            (:func:`jaxsync.surrogate.training.read_shared_histories`).
        dt: time step [s], one for all runs; default the smallest of the runs' default
            steps (runs of one material: run 0's ``dt``;
            :func:`jaxsync.solve.default_dt`). Checked against every run's
            stability bound (:func:`jaxsync.solve._ensemble_stability.check_members_dt`: for
            the linear law a bound computed once for all runs, the exact bound of a run
            above it; for a hyperelastic law the exact bound of each distinct run).
            Needed when the runs' parameters are traced and differ.
        save: an int or a :class:`jaxsync.SaveAt` (with ``partitions``, ``shared_every=1``
            keeps the shared-node displacements after every step, for training).
        executor: :class:`jaxsync.HostExecutor` (default for concrete inputs: progress over
            the batched steps, chunks, divergence checks) or :class:`jaxsync.TracedExecutor`
            (default for traced inputs: one differentiable program).

    Returns:
        A tuple of n_runs :class:`jaxsync.Trajectory`, in the order of the runs: each with
        ``n_steps // every + 1`` snapshots, displacement (n_saved, n_nodes, 3) [cm], times
        [s], its own E, nu, rho, damping in ``parameters``, and with ``partitions`` the
        ``parts`` of a distributed run. ``stats.us_per_step`` is the wall time of one
        BATCHED step, all runs advancing together [us] (per run: divide by n_runs),
        compilation excluded; ``stats.compile_seconds`` the compilation of the batched
        program (the same in every trajectory).

    Raises:
        ProblemError: no runs, problems of different systems (the message names the first
            differing problem and what differs), bad ``members`` (wrong lengths or shapes,
            E or rho <= 0, nu outside (-1, 0.5), a field the law lacks), a wrong number of
            labels, bad ``n_steps`` / ``save``, traced differing parameters without ``dt``.
        StabilityError: dt above a run's stability bound (the message names the run), or a
            run diverged (NaN/Inf or blow-up): the message names the run; ``error.run`` is
            its index, ``error.trajectories`` the snapshots of every run before divergence
            and ``error.trajectory`` those of the diverged run.
        PartitionError: a partition of another mesh.
    """
    from ..precision import require_float64

    require_float64("ensemble")
    if members is not None:
        setup = setup_of_members(problems, members)
    else:
        from ..fem._problem import Problem

        if isinstance(problems, Problem):
            raise ProblemError("ensemble(problem, n_steps) needs the runs: a sequence of problems, or "
                               "members=jaxsync.Members(...) with this one problem")
        problems = tuple(problems)
        if not problems:
            raise ProblemError("ensemble needs at least one problem, got an empty sequence")
        setup = setup_of_problems(problems)
    n_runs = setup.n_runs
    if labels is not None:
        labels = tuple(labels)
        if len(labels) != n_runs:
            raise ProblemError(f"got {len(labels)} labels for {n_runs} {'runs' if members else 'problems'}; give "
                               "one label per run (or labels=None)")
        try:
            labels = tuple(float(x) for x in labels)
        except (TypeError, ValueError) as exc:
            raise ProblemError(f"labels must be numbers (one float per run), got {labels!r}") from exc
    save = SaveAt.of(save)
    n_steps = save.check_steps(n_steps)
    if partitions is None and save.records_every_step:
        raise ProblemError("shared_every needs a distributed run (partitions=...): a single-device "
                           "run has no shared nodes")
    first = setup.base
    dt = default_dt(setup) if dt is None else dt
    traced = is_traced(first.material, first.damping, first.stiffness_damping, first.loads, dt,
                       first.initial_displacement, first.initial_velocity, setup.leaves(),
                       None if setup.problems is None else [(p.material, p.loads) for p in setup.problems])
    executor = choose_executor(executor, traced)
    if isinstance(executor, HostExecutor) and executor.check_stability:
        check_members_dt(setup, dt)
    if not traced:
        dt = float(dt)
    mesh = first.mesh
    partition = _partition(first, partitions)

    # One shared system for all runs, and each run's own data (no assembly per run).
    batched, runs = batched_system(setup, dt, n_steps)  # a short ensemble compiles the compact product
    stacked = initial_states(setup, batched, runs)
    record = partition is not None and save.records_every_step
    interface = partition.shared_nodes if record else None
    start_fields = stacked.displacement  # (n_runs, n_nodes, 3)
    problems = setup.problems or (first,) * n_runs
    own = [setup.run_parameters(r) for r in range(n_runs)] if setup.problems is None else [{}] * n_runs

    def trajectories(saved, every_step, stats=None, result=None):
        """The runs' trajectories from step 0: ``saved`` (n_saves, n_runs, n_nodes, 3),
        ``every_step`` (n_steps, n_runs, n_interface, 3) or None. Run 0's is built in full;
        the others share its times, load signals and load jumps (the runs share their time
        functions) and have their own displacements, shared-node histories and parameters."""
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
            result_r = result if result is None or np.ndim(result) == 0 else result[r]
            if r == 0:
                traj = template = synchronized_trajectory(problem, displacement, dt, save, partition, recorded,
                                                          stats=stats, result=result_r)
            else:
                parts = template.parts
                if partition is not None:
                    shared = ([displacement[:, part.shared_nodes].reshape(len(displacement), -1)
                               for part in partition.parts] if recorded is None
                              else [rows[::save.shared_every] for rows in recorded])
                    parts = part_histories(partition, shared)
                traj = dataclasses.replace(template, displacement=displacement, parts=parts, result=result_r,
                                           parameters={**template.parameters, **run_parameters(problem)})
            parameters = {**traj.parameters, **own[r]}
            if labels is not None:
                parameters["load_parameter"] = labels[r]
            out.append(dataclasses.replace(traj, parameters=parameters))
        return out

    if isinstance(executor, TracedExecutor):
        n_saves = n_steps // save.every
        if n_saves == 0:
            return tuple(trajectories(jnp.zeros((0, n_runs, first.n_nodes, 3)), None))
        _, out = _advance_runs(batched, runs, stacked, n_saves, save.every,
                               None if interface is None else jnp.asarray(interface), executor.adjoint)
        saved, every_step = out if record else (out, None)
        finite = jnp.isfinite(saved).all(axis=(0, 2, 3))
        result = jnp.where(finite, jnp.int32(Result.SUCCESSFUL), jnp.int32(Result.DIVERGED))
        return tuple(trajectories(saved, every_step, result=result))

    start_fields = np.asarray(start_fields)
    runner = _EnsembleRunner(batched, runs, n_runs, first.n_nodes, save.every, interface)

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
            raise _diverged(bad, runner, from_segment(bad.segment, Result.DIVERGED), limit, dt, setup,
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
    from ..parallel._partitioning import Partition, partition, partition_from_elements

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


def _diverged(bad: Diverged, runner: _EnsembleRunner, partial: list, limit: float, dt: float,
              setup: EnsembleSetup, labels) -> StabilityError:
    """The error of a diverged ensemble, naming the run(s) whose field went bad first."""
    first_step, saved = runner.last
    snapshot = saved[(bad.step - first_step) // runner.save_every - 1]  # (n_runs, n_nodes, 3)
    ok = np.isfinite(snapshot).all(axis=(1, 2)) & (np.abs(snapshot).max(axis=(1, 2), initial=0) <= limit)
    runs = [int(r) for r in np.flatnonzero(~ok)]
    run = runs[0]
    named = f"run {run}" + ("" if labels is None else f" (label {labels[run]:g})")
    also = f" (also runs {runs[1:]})" if len(runs) > 1 else ""
    advice = divergence_advice(setup.member(run), dt)
    return StabilityError(
        f"{named} of the ensemble diverged by step {bad.step} (t = {bad.step * dt:.6g} s){also}: displacement "
        f"is NaN/Inf or above {limit:.3g} cm. {advice}; check that "
        f"run's loads and initial conditions. The {partial[run].n_saved} snapshots of each run saved before "
        "are kept (error.trajectories)", trajectory=partial[run], trajectories=tuple(partial), run=run,
        runs=tuple(runs))
