"""The host executor: a run's schedule as compiled chunks driven from Python.

Used for concrete inputs (no JAX tracers). It runs the phases of the schedule
(:mod:`jaxsync.solve.phases`) through the one host loop
(:func:`jaxsync.solve.driver.run_chunks`) with a runner per phase -- synchronized steps
on one device (:class:`SingleDeviceRunner`) or over parts
(:class:`jaxsync.solve.distributed.DistributedRunner`), predicted steps
(:mod:`jaxsync.solve.predicted`) -- and between chunks shows progress, checks for
divergence, writes solver checkpoints (the first synchronized phase) and, with a
tolerance, decides on re-synchronization: a rejected refill cycle inserts a synchronized
stretch from the last synchronized state into the schedule. The trajectory is built once,
at the end (:mod:`jaxsync.solve.record`).

Error control (a tolerance): every refill cycle is predicted BEFORE the solver uses it,
and es_hat of its predictions (paper eq. 26: the mean disagreement of the parts at the
shared nodes, which needs no reference solution) is checked at the saved steps. Below
the tolerance the cycle runs with the predictions. Above it the predictions are dropped
and the run returns to its last synchronized point (the anchor: the parts' state at the
end of the last synchronized stretch, kept on the devices) and recomputes every step from
there up to the end of the rejected cycle with the synchronized solver, which then is
the new anchor (its last n_p n_s steps refill the networks' histories). A restart from
a predicted state is NOT used: each part's interior carries the error of its predicted
boundary values, mostly as high-frequency motion that the clamped shared nodes trap, and
joining the parts releases it into the whole structure (a 1700x larger error in the
demo). So after every re-synchronization the run equals the synchronized solver to
round-off, and between them only predictions whose es_hat stayed below the tolerance were
used. When the cycle right after an anchor is rejected, the synchronized stretch doubles
(1, 2, 4 ... cycles) before the next try.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import time
import warnings

import jax
import numpy as np

from ..errors import StabilityError, SynchronizedRunWarning
from ..fem.stepper import ExplicitSystem, SolverState, advance
from ..fem.timestep import divergence_advice
from ..trajectory import Result, RunStats
from .checkpoint import CheckpointSchedule, CheckpointWriter, fingerprint, load_checkpoint, watch_chunks
from .distributed import DistributedRunner
from .driver import Chunk, Diverged, Progress, Segment, chunk_of_saves, divergence_limit, run_chunks
from .predicted import CycleRejected, DisagreementMonitor, MonitoredRunner, PredictedPhase, PredictedRunner
from .record import online_trajectory, run_parameters, synchronized_trajectory

__all__ = ["run_on_host", "SingleDeviceRunner", "OnlineSettings"]

_advance_jit = jax.jit(advance, static_argnums=(2, 3))


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


@dataclasses.dataclass(frozen=True)
class OnlineSettings:
    """What the predicted phase of a host run needs beyond the schedule.

    Attributes:
        predictor: the surrogates, stacked on the part axis.
        tolerance: a :class:`~jaxsync.solve.strategies.ResyncTolerance`, or None.
        load_jumps: the steps where a load jumps that the run stays synchronized through
            (None: predicted through), for the statistics.
        all_load_jumps: every load jump of the run, for the trajectory's parameters.
        learning: a :class:`~jaxsync.surrogate.online.OnlineLearning`: after every
            rejected cycle, the surrogates learn from the steps recomputed synchronized
            (None: they stay as given).
    """

    predictor: object
    tolerance: object = None
    load_jumps: tuple | None = None
    all_load_jumps: tuple = ()
    learning: object = None


@dataclasses.dataclass
class _Synchronized:
    """The first synchronized phase of a host run: its snapshots and shared-node rows
    (lists of blocks from step 0) and the segment the host loop returned."""

    snapshots: list
    recorded: list | None
    segment: Segment

    @property
    def shared(self) -> list | None:
        """Per part, (n_steps + 1, 3 n_shared_p) rows from step 0, or None."""
        return None if self.recorded is None else [np.concatenate(rows) for rows in self.recorded]


def _run_stats(segment: Segment, runner) -> RunStats:
    from ..parallel.devices import device_summary

    # a runner reaching the other processes through MPI holds one device of each of them
    processes = jax.process_count() if getattr(runner, "transport", None) == "mpi" else None
    return RunStats(compile_seconds=segment.compile_seconds,
                    us_per_step=1e6 * segment.seconds / segment.n_steps if segment.n_steps else None,
                    **device_summary(runner.devices, processes=processes))


def _synchronized_phase(problem, runner, state: SolverState, n_steps: int, save, bar: Progress, *,
                        dt: float, checkpoint, executor, limit: float, check=None) -> _Synchronized:
    """The first synchronized phase, from step 0 (or a checkpoint's step) to ``n_steps``,
    with resumable checkpoints; a divergence raises :class:`StabilityError` with the
    snapshots saved before.

    ``check``: a hyperelastic run's :class:`~jaxsync.fem.run_check.RunCheck`, applied
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
        partial = _Synchronized(snapshots + [segment.displacement], _joined(recorded, segment.shared), segment)
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
    return _Synchronized(snapshots + [segment.displacement], _joined(recorded, segment.shared), segment)


def _run_check(problem, system: ExplicitSystem, dt: float, executor):
    """The between-chunks check of a run, as its material law sets it
    (:meth:`jaxsync.fem.material_law.MaterialLaw.run_check`: a hyperelastic law's
    :class:`jaxsync.fem.run_check.RunCheck`; None for a linear law, or with
    ``HostExecutor(check_stability=False)``)."""
    if not executor.check_stability:
        return None
    return problem.material.run_check(problem, system, dt)


def _joined(recorded, new):
    """Per part, the earlier shared-history chunks followed by ``new`` (None: none)."""
    if recorded is None or new is None:
        return recorded
    return [rec + [values] for rec, values in zip(recorded, new)]


def run_on_host(problem, system: ExplicitSystem, state: SolverState, schedule, *, save, executor,
                distributed=None, checkpoint=None, online: OnlineSettings | None = None):
    """Run ``schedule`` (``(Synchronized(n),)``, or ``(Synchronized(n_cri), Predicted(m))``
    with ``online``) from ``state`` on the host; returns the :class:`jaxsync.Trajectory`.

    Args:
        problem, system, state: the problem, its global system and the start (step 0).
        schedule: the phases.
        save: :class:`~jaxsync.solve.strategies.SaveAt`.
        executor: :class:`~jaxsync.solve.strategies.HostExecutor`.
        distributed: the run's :class:`~jaxsync.solve.distributed.DistributedParts`, or
            None for one device.
        checkpoint: a :class:`~jaxsync.solve.strategies.SolverCheckpoint` of the first
            synchronized phase, or None.
        online: what a predicted phase needs (:class:`OnlineSettings`).

    Raises:
        StabilityError: the run diverged (``error.trajectory`` holds what was saved before).
    """
    n_steps = sum(phase.n_steps for phase in schedule)
    predicted = len(schedule) > 1
    if distributed is None:
        runner = SingleDeviceRunner(system, save.every)
    else:
        runner = DistributedRunner(problem, system, distributed, save_every=save.every,
                                   record_shared=save.records_every_step or predicted)
    limit = divergence_limit(problem.mesh, executor.blowup_factor)
    bar = executor.progress if isinstance(executor.progress, Progress) else None
    label = "synchronized" if predicted else "simulate"
    with (contextlib.nullcontext(bar) if bar is not None
          else Progress(n_steps, show=executor.progress, label=label)) as bar:
        dt = float(system.dt)
        first = _synchronized_phase(problem, runner, state, schedule[0].n_steps, save, bar, dt=dt,
                                    checkpoint=checkpoint, executor=executor, limit=limit,
                                    check=_run_check(problem, system, dt, executor))
        if not predicted:
            stats = _run_stats(first.segment, runner)
            return synchronized_trajectory(problem, np.concatenate(first.snapshots), dt, save,
                                           None if distributed is None else distributed.partition, first.shared,
                                           stats=stats, result=Result.SUCCESSFUL)
        return _OnlineRun(problem, runner, first, online, dt, save.every, executor, limit).run(
            schedule[1].n_steps, bar)


@dataclasses.dataclass
class _Anchor:
    """The last synchronized point of a run: the parts' state on the devices (both
    displacement levels), each part's last n_p n_s shared-dof values (the networks' input
    history) and its step."""

    state: object
    history: np.ndarray  # (n_parts, n_s n_p, n_dof)
    step: int


def _histories(n_parts: int, shared, history: int, n_dof: int, previous=None) -> np.ndarray:
    """(n_parts, history, n_dof) buffer: the last ``history`` rows of each part's shared
    values ``shared[p]`` (n, 3 n_shared_p), after the rows of ``previous``."""
    out = np.zeros((n_parts, history, n_dof))
    for p, values in enumerate(shared):
        rows = values if previous is None else np.concatenate([previous[p, :, :values.shape[1]], values])
        out[p, :, :values.shape[1]] = rows[-history:]
    return out


class _OnlineRun:
    """The predicted phase of a host run, after its first synchronized phase, with error
    control (see the module docstring)."""

    def __init__(self, problem, runner: DistributedRunner, first: _Synchronized, online: OnlineSettings,
                 dt: float, save_every: int, executor, limit: float):
        from ..surrogate.histories import shared_dof_layout

        self.problem, self.runner, self.first, self.online = problem, runner, first, online
        self.save_every, self.executor, self.limit = save_every, executor, limit
        self.partition = runner.partition
        predictor = online.predictor
        self.history, self.cycle_steps = predictor.n_s * predictor.n_past, predictor.n_s * predictor.n_future
        self.n_dof, _ = shared_dof_layout(self.partition)
        self.phase = PredictedPhase(runner, predictor, save_every)
        tolerance = online.tolerance
        self.monitor = None if tolerance is None else DisagreementMonitor(self.partition)
        self.propagator = None
        if tolerance is not None and tolerance.indicator == "estimate":
            from .error_estimate import ErrorPropagator

            self.propagator = ErrorPropagator.build(problem, self.partition, dt, tolerance.modes)
        self._linearised_at = 0  # the step of the state the propagator is linearised at (0: at rest)
        self.dt = dt
        self.learner = None
        if online.learning is not None and tolerance is not None:
            from ..surrogate.online import OnlineLearner

            self.learner = OnlineLearner(online.learning, predictor, first.shared)

    def _kept_rows(self, target: int, anchor_step: int) -> int | None:
        """How many of a re-synchronized stretch's last steps to keep: the networks'
        input history, and with online learning the span its windows come from."""
        if self.learner is None:
            return self.history
        s = self.learner.settings
        span = max(1, self.learner.n_s // s.starts_per_stride) * s.windows
        return self.history + min(target - anchor_step, span + self.cycle_steps)

    def _learn(self, segment: Segment, anchor: "_Anchor", target: int) -> bool:
        """Update the surrogates from a re-synchronized stretch (anchor.step .. target),
        with the input history before it where the stretch was kept whole; True when
        they changed."""
        stretch = target - anchor.step
        rows = []
        for p, values in enumerate(segment.shared):
            values = np.asarray(values)
            if len(values) >= stretch:  # whole: the anchor's history goes before it
                values = np.concatenate([anchor.history[p, :, :values.shape[1]], values[-stretch:]])
            rows.append(values)
        self.learner.add_stretch(rows, target - len(rows[0]) + 1)
        updated = self.learner.update(target)
        changed = bool(self.learner.reports) and self.learner.reports[-1].step == target and bool(
            np.any(self.learner.reports[-1].loss_after < self.learner.reports[-1].loss_before))
        if changed:
            self.phase.predictor = self.runner.put(updated)
        return changed

    def _predicted_runner(self, amplitude: float, anchor: "_Anchor"):
        if self.online.tolerance is None:
            per_chunk = self.executor.cycles_per_chunk or max(1, 20000 // self.cycle_steps)
            return PredictedRunner(self.phase, self.cycle_steps, per_chunk)
        # a new runner starts from a synchronized state: its error estimate from zero
        tolerance = self.online.tolerance
        if (self.propagator is not None and tolerance.linearization == "synchronized"
                and self.problem.material.state_dependent_tangent and anchor.step != self._linearised_at):
            from .error_estimate import ErrorPropagator

            at = self.runner.to_global(anchor.state).displacement
            self.propagator = ErrorPropagator.build(self.problem, self.partition, self.dt, tolerance.modes,
                                                    displacement=at)
            self._linearised_at = anchor.step
        return MonitoredRunner(self.phase, self.cycle_steps, self.online.tolerance.cm(amplitude), self.monitor,
                               self.propagator)

    def run(self, n_predicted: int, bar: Progress):
        first, runner = self.first, self.runner
        n_cri = first.segment.last
        n_steps = n_cri + n_predicted
        tolerance = self.online.tolerance
        timeline: list[Segment] = []
        resyncs = {"resynchronized_at": [], "es_hat_trigger": [], "tolerance_cm": [], "error_estimate_trigger": []}
        estimates = []  # per stretch of the timeline: the error estimate at its snapshots (NaN: none)
        seconds = {"predicted": 0.0, "synchronized": first.segment.seconds, "discarded": 0.0}
        compile_seconds = first.segment.compile_seconds
        n_discarded, failures = 0, 0
        shared = first.shared
        amplitude = max(float(np.abs(v).max(initial=0.0)) for v in shared)
        anchor = _Anchor(first.segment.state, _histories(self.partition.n_parts, shared, self.history, self.n_dof),
                         n_cri)
        step_now = n_cri
        try:
            while step_now < n_steps:
                bar.label("predicted")
                state = (anchor.state, runner.put(anchor.history), step_now)
                predicted_runner = self._predicted_runner(amplitude, anchor)
                try:
                    segment = run_chunks(predicted_runner, state, step_now, n_steps,
                                         kind="predicted", limit=self.limit, progress=bar)
                except CycleRejected as rejected:
                    # back to the anchor, synchronized through the end of the rejected cycle
                    discarded = rejected.segment
                    seconds["discarded"] += discarded.seconds
                    compile_seconds += discarded.compile_seconds
                    resyncs["resynchronized_at"].append(rejected.step)
                    resyncs["es_hat_trigger"].append(rejected.es_hat)
                    resyncs["tolerance_cm"].append(rejected.tolerance)
                    resyncs["error_estimate_trigger"].append(rejected.estimate)
                    failures = failures + 1 if rejected.step == anchor.step else 0
                    n_discarded += rejected.step - anchor.step
                    target = min(rejected.step + self.cycle_steps * 2 ** failures, n_steps)
                    bar.label("re-synchronized")
                    bar.set(anchor.step)
                    # the shared values of the last n_s n_p steps are all the next anchor needs:
                    # a long stretch keeps only those (bounded memory at the paper's size)
                    segment = run_chunks(runner, anchor.state, anchor.step, target, kind="synchronized",
                                         limit=self.limit, progress=bar,
                                         keep_shared=self._kept_rows(target, anchor.step),
                                         chunk_steps=self.executor.chunk_steps)
                    seconds["synchronized"] += segment.seconds
                    compile_seconds += segment.compile_seconds
                    amplitude = max(amplitude, segment.shared_abs_max)
                    timeline.append(segment)
                    estimates.append(np.full(len(segment.displacement), np.nan))
                    if self.learner is not None and not self.learner.exhausted:
                        bar.label("learning")
                        if self._learn(segment, anchor, target):
                            failures = 0  # new surrogates: the next try is one cycle again
                    anchor = _Anchor(segment.state, _histories(self.partition.n_parts, segment.shared, self.history,
                                                               self.n_dof, anchor.history), target)
                    step_now = target
                    continue
                seconds["predicted"] += segment.seconds
                compile_seconds += segment.compile_seconds
                timeline.append(segment)
                found = getattr(predicted_runner, "estimates", None)
                estimates.append(np.concatenate(found) if found else np.full(len(segment.displacement), np.nan))
                step_now = segment.last
        except Diverged as bad:  # predicted, or re-synchronized
            partial = self._trajectory(timeline + [bad.segment], _run_stats(first.segment, runner), Result.DIVERGED,
                                       estimates)
            if bad.part is not None:
                where = (f"the surrogate of part {bad.part} predicted NaN/Inf for step {bad.step}: the network "
                         "diverged; retrain it, raise n_cri or give a resync_tolerance")
            else:
                where = (f"the {bad.segment.kind} run diverged by step {bad.step} (displacement NaN/Inf or "
                         f"above {self.limit:.3g} cm); {divergence_advice(self.problem, self.dt)}")
            raise StabilityError(f"{where} (t = {bad.step * self.dt:.6g} s). The {partial.n_saved} snapshots "
                                 "saved before are kept (error.trajectory)", trajectory=partial) from None
        n_sync = n_cri + sum(seg.n_steps for seg in timeline if seg.kind == "synchronized")
        n_pred = n_steps - n_sync
        jumps = self.online.load_jumps
        stats = dataclasses.replace(
            _run_stats(first.segment, runner), us_per_step=None, n_steps=n_steps, n_cri=n_cri,
            n_synchronized_steps=n_sync, n_predicted_steps=n_pred, n_discarded_steps=n_discarded,
            load_jumps=None if jumps is None else tuple(int(j) for j in jumps),
            compile_seconds=compile_seconds,
            us_per_step_synchronized=1e6 * seconds["synchronized"] / max(n_sync, 1),
            us_per_step_predicted=1e6 * seconds["predicted"] / n_pred if n_pred else None,
            seconds_discarded=seconds["discarded"])
        if tolerance is not None:
            stats = dataclasses.replace(stats, resync_tolerance=str(tolerance),
                                        n_resynchronizations=len(resyncs["resynchronized_at"]),
                                        **{k: tuple(v) for k, v in resyncs.items()})
            if self.learner is not None:
                reports = self.learner.reports
                stats = dataclasses.replace(stats, surrogate_updated_at=tuple(r.step for r in reports),
                                            seconds_updating=float(sum(r.seconds for r in reports)))
            if resyncs["resynchronized_at"] and n_pred < 0.5 * (n_steps - n_cri):
                held = ("es_hat" if tolerance.indicator == "es_hat"
                        else "es_hat and the estimated error")
                warnings.warn(
                    f"the surrogates kept {held} within the tolerance {tolerance} for only {n_pred} of the "
                    f"{n_steps - n_cri} steps after n_cri ({len(resyncs['resynchronized_at'])} "
                    f"re-synchronizations, {n_discarded} predicted steps recomputed): the run was mostly "
                    "synchronized; retrain the surrogates or loosen the tolerance", SynchronizedRunWarning,
                    stacklevel=4)
        return self._trajectory(timeline, stats, Result.SUCCESSFUL, estimates)

    def _trajectory(self, timeline, stats, result, estimates):
        pieces = [("synchronized", np.concatenate(self.first.snapshots), None)]
        pieces += [(seg.kind, seg.displacement, seg.predictions) for seg in timeline]
        # the whole run's load jumps, not only its first synchronized stretch's
        parameters = run_parameters(self.problem, self.online.all_load_jumps)
        error_estimate = None
        if self.propagator is not None:  # NaN at the synchronized snapshots (and a diverged stretch's)
            n_saved = sum(len(d) for _, d, _ in pieces)
            error_estimate = np.full(n_saved, np.nan)
            at = len(pieces[0][1])
            for seg, values in zip(timeline, estimates):
                error_estimate[at:at + len(values)] = values[:len(seg.displacement)]
                at += len(seg.displacement)
        return online_trajectory(self.problem, self.partition, pieces, self.dt, self.save_every,
                                 parameters=parameters, stats=stats, result=result, error_estimate=error_estimate)

