"""The host-side policy of a synchronization-avoiding run (:class:`jaxsync.SyncAvoiding`):
its predicted phase after the first synchronized one, with error control.

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

The steps run through the host executor's loop (:func:`jaxsync.solve.executors.run_chunks`)
with the runners of :mod:`jaxsync.solve.executors`; the statistics are a
:class:`jaxsync.SyncAvoidingStats`.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from ...errors import StabilityError, SynchronizedRunWarning
from ...fem._timestep import divergence_advice
from ...io.trajectory import Result
from ...run_stats import SyncAvoidingStats
from ..executors._distributed import DistributedRunner
from ..executors._driver import Diverged, Progress, Segment, run_chunks
from ..executors._host import FirstPhase, run_summary
from ..executors._predicted import CycleRejected, DisagreementMonitor, MonitoredRunner, PredictedPhase, PredictedRunner
from ..executors._record import online_trajectory, run_parameters

__all__ = ["OnlineSettings", "OnlineRun"]


@dataclasses.dataclass(frozen=True)
class OnlineSettings:
    """What the predicted phase of a host run needs beyond the schedule.

    Attributes:
        predictor: the surrogates, stacked on the part axis.
        tolerance: a :class:`~jaxsync.solve.ResyncTolerance`, or None.
        load_jumps: the steps where a load jumps that the run stays synchronized through
            (None: predicted through), for the statistics.
        all_load_jumps: every load jump of the run, for the trajectory's parameters.
        learning: a :class:`~jaxsync.surrogate.training.OnlineLearning`: after every
            rejected cycle, the surrogates learn from the steps recomputed synchronized
            (None: they stay as given).
    """

    predictor: object
    tolerance: object = None
    load_jumps: tuple | None = None
    all_load_jumps: tuple = ()
    learning: object = None




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


class OnlineRun:
    """The predicted phase of a host run, after its first synchronized phase, with error
    control (see the module docstring)."""

    def __init__(self, problem, runner: DistributedRunner, first: FirstPhase, online: OnlineSettings,
                 dt: float, save_every: int, executor, limit: float):
        from ...surrogate.training._histories import shared_dof_layout

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
            from ._error_estimate import ErrorPropagator

            self.propagator = ErrorPropagator.build(problem, self.partition, dt, tolerance.modes)
        self._linearised_at = 0  # the step of the state the propagator is linearised at (0: at rest)
        self.dt = dt
        self.learner = None
        if online.learning is not None and tolerance is not None:
            from ...surrogate.training._online import OnlineLearner

            self.learner = OnlineLearner(online.learning, predictor, first.shared,
                                         shared_nodes=[part.shared_nodes for part in self.partition.parts])

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
            np.any(self.learner.reports[-1].kept))
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
            from ._error_estimate import ErrorPropagator

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
            before = SyncAvoidingStats(**run_summary(first.segment, runner))
            partial = self._trajectory(timeline + [bad.segment], before, Result.DIVERGED, estimates)
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
        jumps = None if self.online.load_jumps is None else tuple(int(j) for j in self.online.load_jumps)
        fields = dict(run_summary(first.segment, runner), n_steps=n_steps, n_cri=n_cri,
                      n_synchronized_steps=n_sync, n_predicted_steps=n_pred, n_discarded_steps=n_discarded,
                      load_jumps=jumps, compile_seconds=compile_seconds,
                      us_per_step_synchronized=1e6 * seconds["synchronized"] / max(n_sync, 1),
                      us_per_step_predicted=1e6 * seconds["predicted"] / n_pred if n_pred else None,
                      seconds_discarded=seconds["discarded"])
        if tolerance is not None:
            fields.update(resync_tolerance=str(tolerance), n_resynchronizations=len(resyncs["resynchronized_at"]),
                          **{k: tuple(v) for k, v in resyncs.items()})
            if self.learner is not None:
                reports = self.learner.reports
                fields.update(surrogate_updated_at=tuple(r.step for r in reports),
                              seconds_updating=float(sum(r.seconds for r in reports)))
        stats = SyncAvoidingStats(**fields)
        if tolerance is not None:
            if resyncs["resynchronized_at"] and n_pred < 0.5 * (n_steps - n_cri):
                held = ("es_hat" if tolerance.indicator == "es_hat"
                        else "es_hat and the estimated error")
                warnings.warn(
                    f"the surrogates kept {held} within the tolerance {tolerance} for only {n_pred} of the "
                    f"{n_steps - n_cri} steps after n_cri ({len(resyncs['resynchronized_at'])} "
                    f"re-synchronizations, {n_discarded} predicted steps recomputed): the run was mostly "
                    "synchronized; retrain the surrogates or loosen the tolerance", SynchronizedRunWarning,
                    stacklevel=5)  # the caller of simulate
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

