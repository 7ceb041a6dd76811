"""Synchronization-avoiding explicit solver (paper Algorithm 3), with error control.

Synchronized steps run up to ``n_cri`` (>= n_p n_s). Then, in cycles: (a) one
batched refill prediction per part of its shared-node displacements for the next
n_s n_f steps, from the last n_p n_s steps of its history; (b) n_s n_f solver steps with
no exchange, each followed by overwriting the part's shared dofs with its prediction and
imposing the Dirichlet values. Each part's predictor parameters live on its device (a
stacked pytree sharded on the parts axis); the predicted phase has no cross-device
collective in it.

:func:`simulate_sync_avoiding` checks its inputs, finds the steps where loads jump, and
hands the schedule -- ``Synchronized(n_cri)`` then ``Predicted(n_steps - n_cri)`` -- to an
executor: the host executor (:mod:`jaxsync.solve.host`, where error control re-synchronizes
after a rejected cycle) or the traced executor (:mod:`jaxsync.solve.traced`, inside
``jax.grad`` or ``jit``). Both run the phase functions of :mod:`jaxsync.solve.phases`.

A shared node is held, and predicted, by every part that touches it, so after the
switch the parts' values there differ; the returned global trajectory takes the mean
over the parts, and each part's own predictions are kept in ``trajectory.parts`` for
the error estimates of :mod:`jaxsync.metrics`.
"""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ProblemError, SynchronizedRunWarning
from ..fem.loads import load_jumps as find_load_jumps
from ..fem.stepper import build_system, initial_state
from ..options import LoadJumps, choices
from ..pytree import is_traced
from .phases import Predicted, Synchronized
from .predictors import OraclePredictor, predictor_for
from .strategies import ResyncTolerance, SaveAt, TracedExecutor, choose_executor

__all__ = ["ResyncTolerance", "simulate_sync_avoiding", "step_counts", "describe_run"]


def simulate_sync_avoiding(problem, n_steps: int, *, surrogates, partitions, n_cri: int, dt=None, save=1,
                           sync=None, mode="preassembled", resync_tolerance=None, load_jumps: LoadJumps = "synchronize",
                           executor=None):
    """Run paper Algorithm 3: synchronized up to ``n_cri``, then surrogate-predicted.

    Error control (beyond the paper, section 6): with ``resync_tolerance``, every refill
    cycle is predicted BEFORE the solver uses it, and es_hat of its predictions (paper eq.
    26: the mean disagreement of the parts at the shared nodes, which needs no reference
    solution) is checked at the saved steps. Below the tolerance the cycle runs with the
    predictions. Above it the run returns to its last synchronized state and recomputes
    the steps up to the end of the rejected cycle synchronized (:mod:`jaxsync.solve.host`),
    so after every re-synchronization it equals the synchronized solver to round-off.
    Predicted steps that a re-synchronization recomputes are counted as discarded.

    Load jumps (beyond the paper): a load switched off (or on, or any time function that
    changes by more than 5 % of its range in one step, :func:`jaxsync.fem.loads.load_jumps`)
    changes the motion in a way no autonomous surrogate can foresee from past
    displacements; its networks would predict the old motion on (the paper's step-off case,
    figure 14: 5 % errors for about a second after the jump). The solver knows the load
    schedule, so by default (``load_jumps="synchronize"``) it stays synchronized through
    every jump up to the step after which the networks' whole input history (n_p n_s steps)
    follows the last jump: the first synchronized stretch ends at max(n_cri, last jump +
    n_p n_s), rounded up to a saved step. A jump within the last n_p n_s steps keeps the run
    synchronized to the end (a :class:`jaxsync.errors.SynchronizedRunWarning` says so).
    ``load_jumps="predict"`` predicts through them, as the paper did.

    Args:
        problem: the problem.
        n_steps: total steps; steps n_cri + 1 .. n_steps are predicted.
        surrogates: the predictor of every part's shared nodes: a
            :class:`jaxsync.surrogate.Surrogate` (with its load parameter:
            ``Surrogate.with_load_parameter``), an
            :class:`~jaxsync.solve.predictors.OraclePredictor`, or the record of a surrogate
            file (:func:`jaxsync.surrogate.load_surrogate`), whose shared node ids are
            checked against the partition.
        partitions: n_parts or the :class:`jaxsync.Partition` the surrogates were trained on.
        n_cri: last synchronized step; at least n_p n_s (the networks read steps
            n_cri - n_p n_s + 1 .. n_cri).
        dt: time step [s] (default ``problem.dt``; the surrogates were trained at one).
        save: the snapshot stride (an int or a :class:`jaxsync.SaveAt`); must divide n_cri,
            n_steps and n_s n_f.
        sync, mode: as for :func:`jaxsync.simulate` (the synchronized stretches' exchange;
            the internal force).
        resync_tolerance: es_hat above which the run re-synchronizes: a number [cm], a
            string like ``"2%"`` (relative to the largest shared-node displacement seen in
            synchronized steps), or a :class:`jaxsync.ResyncTolerance`; None: never. Its
            ``learning`` lets the surrogates learn from the steps recomputed after every
            rejected cycle (:mod:`jaxsync.surrogate.online`).
        load_jumps: ``"synchronize"`` (default) or ``"predict"``: what the run does at the
            steps where a load's time function jumps (see above).
        executor: as for :func:`jaxsync.simulate`: :class:`jaxsync.HostExecutor` (the
            default for concrete inputs; its ``cycles_per_chunk`` sets the refill cycles per
            compiled call) or :class:`jaxsync.TracedExecutor` (the default inside
            ``jax.grad`` or ``jit``).

    Differentiable: when the material, damping, loads, dt or the surrogate's arrays are JAX
    tracers, the traced executor runs the same phases as one program, differentiable in all
    of them; the trajectory holds JAX arrays (``displacement``, ``times``, ``synchronized``
    flags, each part's predictions; no timings). Give a concrete ``dt``: the default step
    follows a traced E, and the steps where loads jump cannot be found from a traced dt (or
    pass ``load_jumps="predict"``). Error control decides on the host whether to go back to
    a synchronized state, so it is refused there.

    Returns:
        :class:`jaxsync.Trajectory` with ``synchronized`` flags (True at the snapshots of
        synchronized steps, re-synchronized ones included) and, per part,
        ``shared_displacement`` and ``predicted_shared_displacement``
        (n_predicted_saved, 3 n_shared_p): the part's own predictions at the saved
        predicted steps. ``stats`` (:class:`jaxsync.RunStats`): ``n_synchronized_steps``, ``n_predicted_steps``
        (they add up to n_steps), ``n_cri`` (the end of the first synchronized stretch, later
        than the one given when a load jumps), ``load_jumps`` (the steps synchronized
        through), ``n_discarded_steps``, ``n_resynchronizations``,
        ``resynchronized_at`` (the first step of each rejected cycle), ``es_hat_trigger``
        (its es_hat) and ``tolerance_cm`` (the tolerance then) [cm], ``resync_tolerance``,
        ``us_per_step_predicted``, ``us_per_step_synchronized``, ``compile_seconds``; with
        online learning ``surrogate_updated_at`` (the steps after which the surrogates
        learned) and ``seconds_updating``.

    Raises:
        ProblemError: n_cri too small, save_every not dividing n_cri, n_steps and n_s n_f,
            a tolerance that is not > 0 or given with an oracle, learning for a predictor
            without weights (an oracle).
        CheckpointError: surrogates made for another partition.
        StabilityError: without a tolerance, a prediction turned NaN/Inf (the message
            names the step and the part; ``error.trajectory`` keeps the snapshots saved
            before). With a tolerance such a cycle is rejected like any other.
    """
    from ..precision import require_float64
    from .distributed import DistributedParts

    require_float64("simulate_sync_avoiding")
    save = SaveAt.of(save)
    if save.records_every_step:
        raise ProblemError("simulate_sync_avoiding keeps the snapshots every save steps (each part's own "
                           "predictions at them); SaveAt.shared_every is for synchronized runs")
    n_steps, n_cri, save_every = save.check_steps(n_steps), int(n_cri), save.every
    if load_jumps not in choices(LoadJumps):
        raise ProblemError(f"load_jumps={load_jumps!r}: use 'synchronize' (stay synchronized through the steps "
                           "where a load jumps) or 'predict' (predict through them, as the paper did)")
    dt = problem.dt if dt is None else dt
    tolerance = None if resync_tolerance is None else ResyncTolerance.parse(resync_tolerance)
    learning = _online_learning(tolerance, surrogates)
    traced = is_traced(problem.material, problem.damping, problem.stiffness_damping, problem.loads, dt,
                       problem.initial_displacement, problem.initial_velocity, surrogates)
    executor = choose_executor(executor, traced)
    distributed = DistributedParts(problem, partitions, sync, mode=mode)
    predictor = predictor_for(surrogates, distributed.partition, problem, dt)
    history, cycle_steps = predictor.n_s * predictor.n_past, predictor.n_s * predictor.n_future
    if n_cri < history:
        raise ProblemError(f"n_cri={n_cri} is too small: the first refill reads the n_p * n_s = "
                           f"{history} synchronized steps before it (n_p={predictor.n_past}, n_s={predictor.n_s})")
    if n_cri > n_steps:
        raise ProblemError(f"n_cri={n_cri} is beyond n_steps={n_steps}")
    if n_cri % save_every or cycle_steps % save_every or n_steps % save_every:
        raise ProblemError(f"save_every={save_every} must divide n_cri={n_cri}, n_steps={n_steps} "
                           f"and the steps per refill cycle n_s * n_f = {cycle_steps}")
    all_jumps = _find_load_jumps(problem.loads, n_steps, dt, load_jumps)
    jumps, n_cri = _synchronize_through_load_jumps(all_jumps, load_jumps, n_cri, n_steps, dt, history, save_every)
    if tolerance is not None and tolerance.indicator == "es_hat" and isinstance(predictor, OraclePredictor):
        raise ProblemError("resync_tolerance with indicator='es_hat' needs a predictor that works from its input "
                           "history (an OraclePredictor replays fixed values, alike in every part, so its es_hat "
                           "is zero); use the default indicator='estimate'")
    schedule = (Synchronized(n_cri), Predicted(n_steps - n_cri))
    if isinstance(executor, TracedExecutor):
        if tolerance is not None:  # the reason, not a missing feature
            raise ProblemError("resync_tolerance decides on the host, between cycles, whether to go back to a "
                               "synchronized state; a traced run (inside jax.grad or jit) is one program with "
                               "no such point: leave resync_tolerance out of traced runs")
        # one compiled program, also under eager transformations (see solver.simulate)
        return jax.jit(lambda: _traced_run(problem, dt, mode, schedule, save, executor, distributed, predictor,
                                           all_jumps))()
    from .host import OnlineSettings, run_on_host

    if executor.check_stability:
        from ..fem.timestep import check_dt

        check_dt(problem, dt)
    system = build_system(problem, float(dt), mode)
    online = OnlineSettings(predictor, tolerance, None if jumps is None else tuple(int(j) for j in jumps),
                            tuple(int(j) for j in all_jumps), learning)
    return run_on_host(problem, system, initial_state(problem, system), schedule, save=save, executor=executor,
                       distributed=distributed, online=online)


def _traced_run(problem, dt, mode, schedule, save, executor, distributed, predictor, jumps):
    """The run through the traced executor: a :class:`jaxsync.Trajectory` of JAX arrays."""
    from ..trajectory import Trajectory
    from .record import part_histories, run_parameters
    from .traced import run_traced

    system = build_system(problem, dt, mode)
    state = initial_state(problem, system)
    run = run_traced(problem, system, state, schedule, save_every=save.every, adjoint=executor.adjoint,
                     distributed=distributed, predictor=predictor)
    displacement = jnp.concatenate([state.displacement[None], run.saved])
    n_saved = displacement.shape[0]
    partition = distributed.partition
    shared = [displacement[:, part.shared_nodes].reshape(n_saved, -1) for part in partition.parts]
    predicted = [run.predictions[p, :, :3 * part.n_shared] for p, part in enumerate(partition.parts)]
    synchronized = np.arange(n_saved) * save.every <= schedule[0].n_steps
    return Trajectory(times=jnp.arange(n_saved, dtype=system.dt.dtype) * save.every * system.dt,
                      displacement=displacement, mesh=problem.mesh, element=problem.element, dt=dt,
                      save_every=save.every, parameters=run_parameters(problem, jumps),
                      parts=part_histories(partition, shared, predicted),
                      synchronized=synchronized, result=run.result)


def _online_learning(tolerance, surrogates):
    """The run's :class:`~jaxsync.surrogate.online.OnlineLearning` (``tolerance.learning``), or None."""
    if tolerance is None or tolerance.learning is None or tolerance.learning is False:
        return None
    from ..surrogate.online import OnlineLearning

    if isinstance(surrogates, OraclePredictor):
        raise ProblemError("resync_tolerance: learning updates trained surrogates; an OraclePredictor replays known "
                           "values and has no weights to learn: leave learning out")
    return OnlineLearning.parse(tolerance.learning)


def _find_load_jumps(loads, n_steps: int, dt, policy: str) -> np.ndarray:
    """:func:`jaxsync.fem.loads.load_jumps` of the run; in a traced run whose load time
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
                      SynchronizedRunWarning, stacklevel=3)
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
