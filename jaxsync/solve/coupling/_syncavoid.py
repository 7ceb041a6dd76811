"""Synchronization-avoiding explicit solver (paper Algorithm 3), with error control: the
coupling :class:`SyncAvoiding` of :func:`jaxsync.simulate`.

Synchronized steps run up to ``n_cri`` (>= n_p n_s). Then, in cycles: (a) one
batched refill prediction per part of its shared-node displacements for the next
n_s n_f steps, from the last n_p n_s steps of its history; (b) n_s n_f solver steps with
no exchange, each followed by overwriting the part's shared dofs with its prediction and
imposing the Dirichlet values. Each part's predictor parameters live on its device (a
stacked pytree sharded on the parts axis); the predicted phase has no cross-device
collective in it.

:meth:`SyncAvoiding.plan` checks the run, finds the steps where loads jump, and gives the
executors the schedule -- ``SynchronizedSteps(n_cri)`` then ``PredictedSteps(n_steps -
n_cri)`` -- with the coupling's host-side policy: on the host, the predicted phase with
error control (:mod:`jaxsync.solve.coupling`, where a rejected cycle re-synchronizes); the
traced executor (:mod:`jaxsync.solve.executors`, inside ``jax.grad`` or ``jit``) runs the
schedule as one program. Both run the phase functions of :mod:`jaxsync.solve.executors`.
:func:`simulate_sync_avoiding` is the same run under its earlier name.

A shared node is held, and predicted, by every part that touches it, so after the
switch the parts' values there differ; the returned global trajectory takes the mean
over the parts, and each part's own predictions are kept in ``trajectory.parts`` for
the error estimates of :mod:`jaxsync.metrics`.
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ...errors import ProblemError, SynchronizedRunWarning
from ...fem._loads import load_jumps as find_load_jumps
from ...options import LoadJumps, choices
from ...pytree import pytree_dataclass, static_field
from .._strategies import ResyncTolerance, TracedExecutor
from ..executors._phases import PredictedSteps, SynchronizedSteps
from ._base import Coupling, RunPlan
from ._predictors import OraclePredictor, predictor_for

__all__ = ["SyncAvoiding", "ResyncTolerance", "simulate_sync_avoiding", "step_counts", "describe_run"]


@pytree_dataclass
class SyncAvoiding(Coupling):
    """Paper Algorithm 3 as a coupling of :func:`jaxsync.simulate`: synchronized up to
    ``n_cri``, then surrogate-predicted (``simulate(problem, n_steps, partitions=...,
    coupling=SyncAvoiding(surrogates, n_cri=...))``).

    Error control (beyond the paper, section 6): with ``tolerance``, every refill cycle is
    predicted BEFORE the solver uses it, and es_hat of its predictions (paper eq. 26: the
    mean disagreement of the parts at the shared nodes, which needs no reference solution)
    is checked at the saved steps. Below the tolerance the cycle runs with the predictions.
    Above it the run returns to its last synchronized state and recomputes the steps up to
    the end of the rejected cycle synchronized (:mod:`jaxsync.solve.coupling`), so after
    every re-synchronization it equals the synchronized solver to round-off. Predicted
    steps that a re-synchronization recomputes are counted as discarded.

    Load jumps (beyond the paper): a load switched off (or on, or any time function that
    changes by more than 5 % of its range in one step, :func:`jaxsync.fem.load_jumps`)
    changes the motion in a way no autonomous surrogate can foresee from past
    displacements; its networks would predict the old motion on (the paper's step-off case,
    figure 14: 5 % errors for about a second after the jump). The solver knows the load
    schedule, so by default (``load_jumps="synchronize"``) it stays synchronized through
    every jump up to the step after which the networks' whole input history (n_p n_s steps)
    follows the last jump: the first synchronized stretch ends at max(n_cri, last jump +
    n_p n_s), rounded up to a saved step. A jump within the last n_p n_s steps keeps the run
    synchronized to the end (a :class:`jaxsync.errors.SynchronizedRunWarning` says so).
    ``load_jumps="predict"`` predicts through them, as the paper did.

    Attributes:
        surrogates: the predictor of every part's shared nodes: a
            :class:`jaxsync.surrogate.Surrogate` (with its load parameter:
            ``Surrogate.with_load_parameter``), an
            :class:`~jaxsync.solve.coupling.OraclePredictor`, or the record of a surrogate
            file (:func:`jaxsync.surrogate.load_surrogate`), whose shared node ids are
            checked against the partition. Its arrays are the coupling's pytree leaves.
        n_cri: last synchronized step; at least n_p n_s (the networks read steps
            n_cri - n_p n_s + 1 .. n_cri). The run's ``save`` stride must divide n_cri,
            n_steps and n_s n_f.
        tolerance: es_hat above which the run re-synchronizes: a number [cm], a string like
            ``"2%"`` (relative to the largest shared-node displacement seen in synchronized
            steps), or a :class:`jaxsync.ResyncTolerance` (stored as one); None: never. Its
            ``learning`` lets the surrogates learn from the steps recomputed after every
            rejected cycle (:mod:`jaxsync.surrogate.training`).
        load_jumps: ``"synchronize"`` (default) or ``"predict"``: what the run does at the
            steps where a load's time function jumps (see above).

    The run (:func:`jaxsync.simulate` with this coupling) returns a
    :class:`jaxsync.Trajectory` with ``synchronized`` flags (True at the snapshots of
    synchronized steps, re-synchronized ones included) and, per part,
    ``shared_displacement`` and ``predicted_shared_displacement`` (n_predicted_saved,
    3 n_shared_p): the part's own predictions at the saved predicted steps. Its ``stats`` is
    a :class:`jaxsync.SyncAvoidingStats`: the step counts, ``n_cri`` (the end of the first
    synchronized stretch, later than the one given when a load jumps), the load jumps
    synchronized through, the re-synchronizations, online learning and the time per step
    of both kinds. The host executor's ``cycles_per_chunk`` sets the refill cycles per
    compiled call.

    Differentiable: when the material, damping, loads, dt or the surrogate's arrays are JAX
    tracers, the traced executor runs the same phases as one program, differentiable in all
    of them; the trajectory holds JAX arrays (``displacement``, ``times``, ``synchronized``
    flags, each part's predictions; no timings). Give a concrete ``dt``: the default step
    follows a traced E, and the steps where loads jump cannot be found from a traced dt (or
    pass ``load_jumps="predict"``). Error control decides on the host whether to go back to
    a synchronized state, so it is refused there.

    The run's inputs are checked when it is planned (by :func:`jaxsync.simulate`).

    Raises:
        ProblemError: no partitions, n_cri too small, save not dividing n_cri, n_steps and
            n_s n_f, ``SaveAt.shared_every``, a tolerance that is not > 0 or given with an
            oracle, learning for a predictor without weights (an oracle), a tolerance in a
            traced run, a checkpoint.
        CheckpointError: surrogates made for another partition.
        StabilityError: without a tolerance, a prediction turned NaN/Inf (the message
            names the step and the part; ``error.trajectory`` keeps the snapshots saved
            before). With a tolerance such a cycle is rejected like any other.
    """

    surrogates: Any
    n_cri: int = static_field()
    tolerance: ResyncTolerance | None = static_field(default=None)
    load_jumps: LoadJumps = static_field(default="synchronize")

    def __post_init__(self):
        if isinstance(self.n_cri, bool) or not isinstance(self.n_cri, (int, np.integer)):
            raise ProblemError(f"SyncAvoiding: n_cri={self.n_cri!r} must be a whole number of steps")
        object.__setattr__(self, "n_cri", int(self.n_cri))
        if self.load_jumps not in choices(LoadJumps):
            raise ProblemError(f"load_jumps={self.load_jumps!r}: use 'synchronize' (stay synchronized through the "
                               "steps where a load jumps) or 'predict' (predict through them, as the paper did)")
        if self.tolerance is not None:
            object.__setattr__(self, "tolerance", ResyncTolerance.parse(self.tolerance))

    def plan(self, problem, n_steps: int, *, dt, save, partitions, exchange, mode: str, executor) -> RunPlan:
        from ..executors._distributed import DistributedParts
        from ._resync import OnlineSettings

        if save.records_every_step:
            raise ProblemError("a synchronization-avoiding run keeps the snapshots every save steps (each part's "
                               "own predictions at them); SaveAt.shared_every is for synchronized runs")
        if partitions is None:
            raise ProblemError("SyncAvoiding needs a distributed run: pass partitions= (n_parts or the "
                               "jaxsync.Partition the surrogates were trained on)")
        n_cri, save_every, tolerance = self.n_cri, save.every, self.tolerance
        learning = _online_learning(tolerance, self.surrogates)
        distributed = DistributedParts(problem, partitions, exchange, mode=mode)
        predictor = predictor_for(self.surrogates, distributed.partition, problem, dt)
        history, cycle_steps = predictor.n_s * predictor.n_past, predictor.n_s * predictor.n_future
        if n_cri < history:
            raise ProblemError(f"n_cri={n_cri} is too small: the first refill reads the n_p * n_s = "
                               f"{history} synchronized steps before it (n_p={predictor.n_past}, n_s={predictor.n_s})")
        if n_cri > n_steps:
            raise ProblemError(f"n_cri={n_cri} is beyond n_steps={n_steps}")
        if n_cri % save_every or cycle_steps % save_every or n_steps % save_every:
            raise ProblemError(f"save_every={save_every} must divide n_cri={n_cri}, n_steps={n_steps} "
                               f"and the steps per refill cycle n_s * n_f = {cycle_steps}")
        all_jumps = _find_load_jumps(problem.loads, n_steps, dt, self.load_jumps)
        jumps, n_cri = _synchronize_through_load_jumps(all_jumps, self.load_jumps, n_cri, n_steps, dt, history,
                                                       save_every)
        if tolerance is not None and tolerance.indicator == "es_hat" and isinstance(predictor, OraclePredictor):
            raise ProblemError("resync_tolerance with indicator='es_hat' needs a predictor that works from its "
                               "input history (an OraclePredictor replays fixed values, alike in every part, so "
                               "its es_hat is zero); use the default indicator='estimate'")
        if isinstance(executor, TracedExecutor) and tolerance is not None:  # the reason, not a missing feature
            raise ProblemError("resync_tolerance decides on the host, between cycles, whether to go back to a "
                               "synchronized state; a traced run (inside jax.grad or jit) is one program with "
                               "no such point: leave resync_tolerance out of traced runs")
        online = OnlineSettings(predictor, tolerance, None if jumps is None else tuple(int(j) for j in jumps),
                                tuple(int(j) for j in all_jumps), learning)
        return _SyncAvoidingPlan((SynchronizedSteps(n_cri), PredictedSteps(n_steps - n_cri)), distributed,
                                 predictor, records_shared=True, label="synchronized", online=online)


@dataclasses.dataclass(frozen=True)
class _SyncAvoidingPlan(RunPlan):
    """The plan of a :class:`SyncAvoiding` run; ``online``: the predicted phase's
    settings (:class:`~jaxsync.solve.coupling._resync.OnlineSettings`)."""

    online: Any = None

    def finish_on_host(self, run):
        from ._resync import OnlineRun

        return OnlineRun(run.problem, run.runner, run.first, self.online, run.dt, run.save.every, run.executor,
                         run.limit).run(self.schedule[1].n_steps, run.progress)

    def traced_trajectory(self, problem, dt, system, state, run, save):
        from ...io.trajectory import Trajectory
        from ..executors._record import part_histories, run_parameters

        displacement = jnp.concatenate([state.displacement[None], run.saved])
        n_saved = displacement.shape[0]
        partition = self.distributed.partition
        shared = [displacement[:, part.shared_nodes].reshape(n_saved, -1) for part in partition.parts]
        predicted = [run.predictions[p, :, :3 * part.n_shared] for p, part in enumerate(partition.parts)]
        synchronized = np.arange(n_saved) * save.every <= self.schedule[0].n_steps
        return Trajectory(times=jnp.arange(n_saved, dtype=system.dt.dtype) * save.every * system.dt,
                          displacement=displacement, mesh=problem.mesh, element=problem.element, dt=dt,
                          save_every=save.every, parameters=run_parameters(problem, self.online.all_load_jumps),
                          parts=part_histories(partition, shared, predicted),
                          synchronized=synchronized, result=run.result)


def simulate_sync_avoiding(problem, n_steps: int, *, surrogates, partitions, n_cri: int, dt=None, save=1,
                           sync=None, mode="preassembled", resync_tolerance=None, load_jumps: LoadJumps = "synchronize",
                           executor=None):
    """Run paper Algorithm 3: synchronized up to ``n_cri``, then surrogate-predicted.

    The same run as ``jaxsync.simulate(problem, n_steps, partitions=partitions,
    coupling=jaxsync.SyncAvoiding(surrogates, n_cri, tolerance=resync_tolerance,
    load_jumps=load_jumps), exchange=sync, dt=dt, save=save, mode=mode,
    executor=executor)``, under its earlier name: :class:`jaxsync.SyncAvoiding` describes
    the run, its error control and load-jump policy, what it returns and raises.

    Args:
        problem: the problem.
        n_steps: total steps; steps n_cri + 1 .. n_steps are predicted.
        surrogates: the predictor of every part's shared nodes (:attr:`SyncAvoiding.surrogates`).
        partitions: n_parts or the :class:`jaxsync.Partition` the surrogates were trained on.
        n_cri: last synchronized step; at least n_p n_s.
        dt: time step [s] (default ``problem.dt``; the surrogates were trained at one).
        save: the snapshot stride (an int or a :class:`jaxsync.SaveAt`); must divide n_cri,
            n_steps and n_s n_f.
        sync, mode: as for :func:`jaxsync.simulate` (the synchronized stretches' exchange;
            the internal force).
        resync_tolerance: :attr:`SyncAvoiding.tolerance`; None: never re-synchronize.
        load_jumps: ``"synchronize"`` (default) or ``"predict"`` (:attr:`SyncAvoiding.load_jumps`).
        executor: as for :func:`jaxsync.simulate` (:class:`jaxsync.HostExecutor`, whose
            ``cycles_per_chunk`` sets the refill cycles per compiled call, or
            :class:`jaxsync.TracedExecutor`).

    Returns:
        :class:`jaxsync.Trajectory`, its ``stats`` a :class:`jaxsync.SyncAvoidingStats`.
    """
    from .._solver import simulate

    coupling = SyncAvoiding(surrogates, n_cri, tolerance=resync_tolerance, load_jumps=load_jumps)
    return simulate(problem, n_steps, dt=dt, save=save, partitions=partitions, coupling=coupling, exchange=sync,
                    mode=mode, executor=executor)


def _online_learning(tolerance, surrogates):
    """The run's :class:`~jaxsync.surrogate.training.OnlineLearning` (``tolerance.learning``), or None."""
    if tolerance is None or tolerance.learning is None or tolerance.learning is False:
        return None
    from ...surrogate.training._online import OnlineLearning

    if isinstance(surrogates, OraclePredictor):
        raise ProblemError("resync_tolerance: learning updates trained surrogates; an OraclePredictor replays known "
                           "values and has no weights to learn: leave learning out")
    return OnlineLearning.parse(tolerance.learning)


def _find_load_jumps(loads, n_steps: int, dt, policy: str) -> np.ndarray:
    """:func:`jaxsync.fem.load_jumps` of the run; in a traced run whose load time
    functions (or dt) are traced, a clear error unless jumps are predicted through."""

    try:
        with jax.ensure_compile_time_eval():
            return find_load_jumps(loads, n_steps, dt)
    except (jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError):
        if policy == "predict":
            return np.zeros(0, dtype=np.int64)
        raise ProblemError("the load time functions or dt are traced (inside jax.grad), so the steps where a "
                           "load jumps cannot be found: pass load_jumps='predict', or keep the time "
                           "functions and dt concrete") from None


def _synchronize_through_load_jumps(jumps, policy: str, n_cri: int, n_steps: int, dt: float,
                                    history: int, save_every: int):
    """(the load jumps synchronized through, or None; the end of the first synchronized
    stretch) given the run's ``jumps``: with ``policy="synchronize"``, n_cri moves to the
    first saved step at which the networks' input history (the ``history`` steps up to
    it) lies after the last jump."""
    if policy == "predict":
        return None, n_cri
    if not len(jumps):
        return jumps, n_cri
    needed = int(jumps[-1]) + history - 1  # the history then reads steps jump .. needed: d(jump + 1) on move
    needed = -(-needed // save_every) * save_every
    if needed > n_cri and needed >= n_steps:
        warnings.warn(f"a load jumps at step {int(jumps[-1])} (t = {jumps[-1] * dt:.6g} s), less than n_p n_s = "
                      f"{history} steps before the end ({n_steps}): no surrogate can foresee the motion after "
                      "it, so the whole run stays synchronized (load_jumps='predict' predicts through it)",
                      SynchronizedRunWarning, stacklevel=4)  # the caller of simulate
    return jumps, min(max(n_cri, needed), n_steps)


def step_counts(online) -> tuple[int, int]:
    """(steps, synchronized steps) of a synchronization-avoiding run: from its statistics,
    or else from its per-snapshot flags (each flag stands for the save_every steps that
    end at it; the snapshot at t = 0 is the initial state)."""
    st = online.stats
    if st.n_synchronized_steps is not None and st.n_steps is not None:
        return int(st.n_steps), int(st.n_synchronized_steps)
    flags = np.asarray(online.synchronized, bool)
    return (len(flags) - 1) * int(online.save_every), int(flags[1:].sum()) * int(online.save_every)


def describe_run(online) -> str:
    """The step counts, re-synchronizations and speeds of a synchronization-avoiding run
    (one text for ``predict``, ``report`` and the demo, from its statistics)."""
    st = online.stats
    n_steps, n_sync = step_counts(online)
    text = f"{n_steps} steps: {n_sync} synchronized, {n_steps - n_sync} predicted"
    if st.n_cri is not None:
        text += f" (n_cri = {st.n_cri})"
    if st.load_jumps:
        jumps = list(st.load_jumps)
        text += (f"; synchronized through the load jump{'s' if len(jumps) > 1 else ''} at step"
                 f"{'s' if len(jumps) > 1 else ''} {jumps if len(jumps) > 1 else jumps[0]}")
    if st.resync_tolerance is not None:
        at = list(st.resynchronized_at or ())
        text += (f"; tolerance {st.resync_tolerance}: {len(at)} re-synchronization"
                 f"{'' if len(at) == 1 else 's'}" + (f" (cycles rejected at steps {at})" if at else "")
                 + f", {st.n_discarded_steps} predicted steps recomputed")
        if st.surrogate_updated_at is not None:
            n = len(st.surrogate_updated_at)
            text += f"; {n} surrogate update{'' if n == 1 else 's'} ({st.seconds_updating or 0.0:.1f} s)"
    if st.us_per_step_predicted is not None:
        text += f"; {st.us_per_step_predicted:.1f} us per predicted step"
    if st.us_per_step_synchronized is not None:
        text += f", {st.us_per_step_synchronized:.1f} us per synchronized step"
    if st.n_devices is not None:
        text += f" ({st.n_devices} {st.device_kind} device{'s' if st.n_devices > 1 else ''})"
    return text
