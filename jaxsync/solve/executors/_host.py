"""The host executor: a run's schedule as compiled chunks driven from Python.

Used for concrete inputs (no JAX tracers). It runs the first phase of the schedule
(:mod:`jaxsync.solve.executors`: synchronized steps, on one device with
:class:`SingleDeviceRunner` or over parts with
:class:`jaxsync.solve.executors.DistributedRunner`) through the one host loop
(:func:`jaxsync.solve.executors.run_chunks`), and between chunks shows progress, checks for
divergence and writes solver checkpoints. What follows is the coupling's: its plan
(:meth:`jaxsync.solve.coupling.Coupling.plan`) finishes the run from the first phase
(:meth:`~jaxsync.solve.coupling.RunPlan.finish_on_host`) -- a synchronized run builds its
trajectory; a synchronization-avoiding run runs its predicted phase with its
re-synchronization policy (:mod:`jaxsync.solve.coupling`). The executor itself has no
branch on the kind of run. The trajectory is built once, at the end
(:mod:`jaxsync.solve.executors`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import time

import jax
import numpy as np

from ...errors import StabilityError
from ...fem._stepper import ExplicitSystem, SolverState, advance
from ...fem._timestep import divergence_advice
from ...io.checkpoint import CheckpointSchedule, CheckpointWriter, fingerprint, load_checkpoint, watch_chunks
from ...io.trajectory import Result
from ._distributed import DistributedRunner
from ._driver import Chunk, Diverged, Progress, Segment, chunk_of_saves, divergence_limit, run_chunks
from ._record import synchronized_trajectory

__all__ = ["run_on_host", "SingleDeviceRunner", "FirstPhase", "run_summary", "HostRun"]

_advance_jit = jax.jit(advance, static_argnums=(2, 3))


class SingleDeviceRunner:
    """Advances a global :class:`SolverState` on one device (a :class:`jaxsync.solve.executors.Runner`)."""

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


@dataclasses.dataclass
class FirstPhase:
    """The first synchronized phase of a host run: its snapshots and shared-node rows
    (lists of blocks from step 0) and the segment the host loop returned."""

    snapshots: list
    recorded: list | None
    segment: Segment

    @property
    def shared(self) -> list | None:
        """Per part, (n_steps + 1, 3 n_shared_p) rows from step 0, or None."""
        return None if self.recorded is None else [np.concatenate(rows) for rows in self.recorded]


def run_summary(segment: Segment, runner) -> dict:
    """The statistics every run records (:class:`jaxsync.RunStats`'s fields): the
    compilation time of ``segment`` and ``runner``'s devices."""
    from ...parallel.devices import device_summary

    # a runner reaching the other processes through MPI holds one device of each of them
    processes = jax.process_count() if getattr(runner, "transport", None) == "mpi" else None
    return {"compile_seconds": segment.compile_seconds, **device_summary(runner.devices, processes=processes)}


@dataclasses.dataclass(frozen=True)
class HostRun:
    """What a coupling's plan finishes a host run with (:meth:`RunPlan.finish_on_host
    <jaxsync.solve.coupling.RunPlan.finish_on_host>`).

    Attributes:
        problem: the problem.
        runner: the runner of the first phase (a :class:`SingleDeviceRunner` or a
            :class:`~jaxsync.solve.executors.DistributedRunner`).
        first: the first synchronized phase (:class:`FirstPhase`).
        dt: the time step [s].
        save: :class:`~jaxsync.solve.SaveAt`.
        executor: :class:`~jaxsync.solve.HostExecutor`.
        limit: the displacement above which a run has diverged [cm].
        progress: the run's :class:`~jaxsync.solve.executors.Progress`.
    """

    problem: object
    runner: object
    first: FirstPhase
    dt: float
    save: object
    executor: object
    limit: float
    progress: Progress


def _synchronized_phase(problem, runner, state: SolverState, n_steps: int, save, bar: Progress, *,
                        dt: float, checkpoint, executor, limit: float, check=None) -> FirstPhase:
    """The first synchronized phase, from step 0 (or a checkpoint's step) to ``n_steps``,
    with resumable checkpoints; a divergence raises :class:`StabilityError` with the
    snapshots saved before.

    ``check``: a hyperelastic run's :class:`~jaxsync.fem.RunCheck`, applied
    to the global state after every chunk (before its checkpoint): an inverted element or
    dt above the deformed state's stable step stops the run with :class:`StabilityError`
    (the snapshots saved so far in ``error.trajectory``); a divergence inside a chunk is
    replayed from the chunk's start to name the elements that inverted."""
    save_every = save.every
    partition = getattr(runner, "partition", None)
    snapshots = [np.asarray(state.displacement)[None]]
    recorded = None
    if getattr(runner, "record_shared", False):  # shared-node values at every step, from step 0
        recorded = [[np.asarray(state.displacement)[None, part.shared_nodes].reshape(1, -1)]
                    for part in partition.parts]
    stepped, after_chunk = runner, None
    if checkpoint is not None:
        problem_key = fingerprint(problem, dt, save_every)
        if os.path.exists(checkpoint.path):
            state, snapshots, recorded = load_checkpoint(checkpoint.path, problem_key, n_steps,
                                                          0 if recorded is None else len(recorded))
            bar.set(int(state.step))
        saves_per_chunk = max(1, executor.chunk_steps // save_every)
        # every checkpoint.every steps (whole chunks), or by default at most one per
        # CHECKPOINT_SECONDS of wall time; always at the end
        due = CheckpointSchedule(math.ceil(checkpoint.every / (saves_per_chunk * save_every))
                                 if checkpoint.every else None)
        # each checkpoint appends the chunks since the last one (never all the run so far)
        writer = CheckpointWriter(checkpoint.path, problem_key, snapshots, recorded, n_steps=n_steps,
                                  save_every=save_every) if jax.process_index() == 0 else None  # one writer
        stepped, pending = watch_chunks(runner), []

        def after_chunk(step: int, so_far) -> None:
            new_state, chunk = stepped.last
            pending.append(chunk)
            if due.due(step == n_steps):
                global_state = runner.to_global(new_state)  # collective in multi-process runs
                if writer is not None:
                    writer.commit(global_state, [c.displacement for c in pending],
                                  None if recorded is None else [list(rows) for rows in
                                                                 zip(*(c.shared for c in pending))])
                pending.clear()
                due.written()

    def kept(segment: Segment):
        """The trajectory of the snapshots saved through ``segment`` (a stopped run's)."""
        partial = FirstPhase(snapshots + [segment.displacement], _joined(recorded, segment.shared), segment)
        return synchronized_trajectory(problem, np.concatenate(partial.snapshots), dt, save, partition,
                                       partial.shared, result=Result.DIVERGED)

    if check is not None:  # a hyperelastic run: its state checked after every chunk
        stepped = watch_chunks(runner) if stepped is runner else stepped
        checkpoint_hook = after_chunk

        def after_chunk(step: int, so_far) -> None:
            new_state, _ = stepped.last
            try:
                check.check(runner.to_global(new_state))  # collective in multi-process runs
            except StabilityError as stop:
                traj = kept(so_far())
                raise StabilityError(f"{str(stop).rstrip('.')}. The {traj.n_saved} snapshots saved before are kept "
                                     "(error.trajectory)", trajectory=traj, elements=stop.elements) from None
            if checkpoint_hook is not None:
                checkpoint_hook(step, so_far)

    step_now = int(state.step)
    try:
        segment = run_chunks(stepped, runner.from_global(state), step_now, n_steps, kind="synchronized",
                             limit=limit, progress=bar, chunk_steps=executor.chunk_steps, after_chunk=after_chunk)
    except Diverged as bad:
        traj = kept(bad.segment)
        found = None if check is None else check.diagnose(_advance_jit, runner.to_global(bad.segment.state),
                                                        bad.step)
        advice = divergence_advice(problem, dt) if found is None else str(found)
        raise StabilityError(
            f"the run diverged by step {bad.step} (t = {bad.step * dt:.6g} s): displacement "
            f"is NaN/Inf or above {limit:.3g} cm. {advice.rstrip('.')}. "
            f"The {traj.n_saved} snapshots saved before are kept (error.trajectory)", trajectory=traj,
            elements=None if found is None else found.elements) from None
    return FirstPhase(snapshots + [segment.displacement], _joined(recorded, segment.shared), segment)


def _run_check(problem, system: ExplicitSystem, dt: float, executor):
    """The between-chunks check of a run, as its material law sets it
    (:meth:`jaxsync.fem.materials.MaterialLaw.run_check`: a hyperelastic law's
    :class:`jaxsync.fem.RunCheck`; None for a linear law, or with
    ``HostExecutor(check_stability=False)``)."""
    if not executor.check_stability:
        return None
    return problem.material.run_check(problem, system, dt)


def _joined(recorded, new):
    """Per part, the earlier shared-history chunks followed by ``new`` (None: none)."""
    if recorded is None or new is None:
        return recorded
    return [rec + [values] for rec, values in zip(recorded, new)]


def run_on_host(problem, system: ExplicitSystem, state: SolverState, plan, *, save, executor, checkpoint=None):
    """Run ``plan`` (a coupling's :class:`~jaxsync.solve.coupling.RunPlan`: its schedule,
    its parts, and what follows the first synchronized phase) from ``state`` on the host;
    returns the :class:`jaxsync.Trajectory`.

    Args:
        problem, system, state: the problem, its global system and the start (step 0).
        plan: the run's plan (:meth:`jaxsync.solve.coupling.Coupling.plan`).
        save: :class:`~jaxsync.solve.SaveAt`.
        executor: :class:`~jaxsync.solve.HostExecutor`.
        checkpoint: a :class:`~jaxsync.solve.SolverCheckpoint` of the first
            synchronized phase, or None.

    Raises:
        StabilityError: the run diverged (``error.trajectory`` holds what was saved before).
    """
    schedule, distributed = plan.schedule, plan.distributed
    n_steps = sum(phase.n_steps for phase in schedule)
    if distributed is None:
        runner = SingleDeviceRunner(system, save.every)
    else:
        runner = DistributedRunner(problem, system, distributed, save_every=save.every,
                                   record_shared=save.records_every_step or plan.records_shared)
    limit = divergence_limit(problem.mesh, executor.blowup_factor)
    bar = executor.progress if isinstance(executor.progress, Progress) else None
    with (contextlib.nullcontext(bar) if bar is not None
          else Progress(n_steps, show=executor.progress, label=plan.label)) as bar:
        dt = float(system.dt)
        first = _synchronized_phase(problem, runner, state, schedule[0].n_steps, save, bar, dt=dt,
                                    checkpoint=checkpoint, executor=executor, limit=limit,
                                    check=_run_check(problem, system, dt, executor))
        return plan.finish_on_host(HostRun(problem, runner, first, dt, save, executor, limit, bar))
