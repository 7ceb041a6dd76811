"""Synchronization-avoiding explicit solver (paper Algorithm 3), with error control.

Synchronized steps run up to ``n_cri`` (>= n_p n_s). Then, in cycles: (a) one
batched refill prediction per part of its shared-node displacements for the next
n_s n_f steps, from the last n_p n_s steps of its history; (b) n_s n_f solver steps with
no psum, each followed by overwriting the part's shared dofs with its prediction and
imposing the Dirichlet values (:mod:`jaxsync.solve.predicted`). Each part's predictor
parameters live on its device (a stacked pytree sharded on the parts axis); the whole
predicted phase is one compiled loop per chunk of cycles with no cross-device collective
in it.

The run is a sequence of calls of the one host loop (:func:`jaxsync.solve.driver.run_chunks`):
the synchronized runner up to n_cri, the predicted runner after it, and -- with error
control -- a synchronized stretch from the last synchronized state after every rejected
cycle.

A shared node is held, and predicted, by every part that touches it, so after the
switch the parts' values there differ; the returned global trajectory takes the mean
over the parts, and each part's own predictions are kept in ``trajectory.parts`` for
the error estimates of :mod:`jaxsync.metrics`.

Error control (``resync_tolerance``, see :func:`simulate_sync_avoiding`): each cycle's
predictions are checked (es_hat, paper eq. 26) before the solver uses them; a rejected
cycle sends the run back to its last synchronized state, from which the synchronized
solver recomputes the steps, so a tolerance never leaves the run in a predicted state
that the synchronized solver then amplifies.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from ..errors import CheckpointError, ProblemError, StabilityError
from ..fem.loads import load_jumps as find_load_jumps
from ..fem.stepper import SolverState, build_system, initial_state
from ..fem.timestep import divergence_advice
from ..parallel.partitioning import Partition
from ..parallel.partitioning import partition as make_partition
from ..pytree import is_traced
from ..surrogate.data import shared_dof_layout
from ..surrogate.model import Surrogate
from .distributed import DistributedRunner
from .driver import Diverged, Progress, Segment, divergence_limit, run_chunks
from .predicted import CycleRejected, DisagreementMonitor, MonitoredRunner, PredictedPhase, PredictedRunner
from .predictors import OraclePredictor
from .solver import _parameters, drive

__all__ = ["ResyncTolerance", "simulate_sync_avoiding", "step_counts", "describe_run"]


# --------------------------------------------------------------------------- error control

@dataclasses.dataclass(frozen=True)
class ResyncTolerance:
    """The es_hat level above which a synchronization-avoiding run re-synchronizes.

    Give it in cm (``ResyncTolerance(absolute=1e-4)``, or just ``1e-4``) or relative to
    the observed amplitude (``ResyncTolerance(relative=0.01)``, or ``"1%"``): a fraction
    of the largest |displacement| at the shared nodes seen in the synchronized steps so
    far (the amplitude that the run itself has measured; no reference needed). Under a
    load that ramps up, that amplitude is small when the prediction starts; ``amplitude``
    [cm] fixes the one a relative tolerance refers to instead (e.g. the largest shared
    displacement of the run the surrogates were trained on).
    """

    absolute: float | None = None
    relative: float | None = None
    amplitude: float | None = None

    def __post_init__(self):
        if (self.absolute is None) == (self.relative is None):
            raise ProblemError("resync_tolerance: give exactly one of absolute (cm) or relative")
        value = self.absolute if self.absolute is not None else self.relative
        if not _positive(value):
            raise ProblemError(f"resync_tolerance must be a tolerance > 0 (cm, or a fraction of the "
                               f"amplitude), got {value!r}")
        if self.amplitude is not None and (self.relative is None or not _positive(self.amplitude)):
            raise ProblemError(f"resync_tolerance: amplitude={self.amplitude!r} must be a length > 0 [cm] "
                               "and goes with a relative tolerance")

    @classmethod
    def parse(cls, value) -> "ResyncTolerance":
        """A tolerance from a number (cm), a string ``"1e-4"`` (cm) or ``"2%"`` (relative),
        or a :class:`ResyncTolerance`."""
        if isinstance(value, cls):
            return value
        if isinstance(value, str):
            text = value.strip()
            try:
                if text.endswith("%"):
                    return cls(relative=float(text[:-1]) / 100.0)
                return cls(absolute=float(text))
            except ValueError:
                pass
            raise ProblemError(f"resync_tolerance {value!r} is neither a length in cm (e.g. 1e-4) "
                               "nor a percentage of the amplitude (e.g. 2%)")
        return cls(absolute=value)  # checked by __post_init__

    def cm(self, amplitude: float) -> float:
        """The tolerance in cm given the observed amplitude [cm] (not used when the
        tolerance is absolute or has its own ``amplitude``)."""
        if self.absolute is not None:
            return float(self.absolute)
        return float(self.relative) * (amplitude if self.amplitude is None else float(self.amplitude))

    def __str__(self) -> str:
        if self.absolute is not None:
            return f"{self.absolute:g} cm"
        return f"{100 * self.relative:g} %" + ("" if self.amplitude is None else f" of {self.amplitude:.4g} cm")


def _positive(value) -> bool:
    """A real number > 0 (not a bool, not NaN)."""
    return (not isinstance(value, bool) and isinstance(value, (int, float, np.integer, np.floating))
            and value > 0)


@dataclasses.dataclass
class _Anchor:
    """The last synchronized point of a run: the global state (both displacement levels),
    each part's last n_p n_s shared-dof values (the networks' input history) and its step."""

    state: SolverState
    history: np.ndarray  # (n_parts, n_s n_p, n_dof)
    step: int


def _histories(partition, shared, history: int, n_dof: int, previous=None) -> np.ndarray:
    """(n_parts, history, n_dof) buffer: the last ``history`` rows of each part's shared
    values ``shared[p]`` (n, 3 n_shared_p), after the rows of ``previous``."""
    out = np.zeros((partition.n_parts, history, n_dof))
    for p, values in enumerate(shared):
        rows = values if previous is None else np.concatenate([previous[p, :, :values.shape[1]], values])
        out[p, :, :values.shape[1]] = rows[-history:]
    return out


def simulate_sync_avoiding(problem, n_steps: int, *, partitions, surrogates, n_cri: int,
                           dt=None, mode: str = "preassembled", save_every: int = 1,
                           seed: int = 0, devices=None, load_parameter: float | None = None,
                           progress: bool | None = None, cycles_per_chunk: int | None = None,
                           resync_tolerance=None, sync: str | None = None,
                           load_jumps: str = "synchronize", blowup_factor: float = 1e3,
                           gradient_checkpoints: bool | int = True):
    """Run paper Algorithm 3: synchronized up to ``n_cri``, then surrogate-predicted.

    Error control (beyond the paper, section 6): with ``resync_tolerance``, every refill
    cycle is predicted BEFORE the solver uses it, and es_hat of its predictions (paper eq.
    26: the mean disagreement of the parts at the shared nodes, which needs no reference
    solution) is checked at the saved steps. Below the tolerance the cycle runs with the
    predictions. Above it the predictions are dropped and the run re-synchronizes: it
    returns to its last synchronized point (the anchor: the state and both displacement
    levels at the end of the last synchronized stretch) and recomputes every step from
    there up to the end of the rejected cycle with the synchronized solver, which then is
    the new anchor (its last n_p n_s steps refill the networks' histories). A restart from
    a predicted state is NOT used: each part's interior carries the error of its
    predicted boundary values, mostly as high-frequency motion that the clamped shared
    nodes trap, and joining the parts releases it into the whole structure (a 1700x
    larger error in the demo). So after every re-synchronization the run equals the
    synchronized solver to round-off, and between them only predictions whose es_hat
    stayed below the tolerance were used. When the cycle right after an anchor is
    rejected, the synchronized stretch doubles (1, 2, 4 ... cycles) before the next try.
    Predicted steps that a re-synchronization recomputes are counted as discarded.

    Load jumps (beyond the paper): a load switched off (or on, or any time function that
    changes by more than 5 % of its range in one step, :func:`jaxsync.fem.loads.load_jumps`)
    changes the motion in a way no autonomous surrogate can foresee from past
    displacements; its networks would predict the old motion on (the paper's step-off case,
    figure 14: 5 % errors for about a second after the jump). The solver knows the load
    schedule, so by default (``load_jumps="synchronize"``) it stays synchronized through
    every jump up to the step after which the networks' whole input history (n_p n_s steps)
    follows the last jump: the first synchronized stretch ends at max(n_cri, last jump +
    n_p n_s), rounded up to a saved step. A predicted state is never joined back (see above),
    so a jump late in the run keeps the run synchronized until then; one within the last
    n_p n_s steps keeps it synchronized to the end (a RuntimeWarning says so).
    ``load_jumps="predict"`` predicts through them, as the paper did.

    Args:
        problem: the problem.
        n_steps: total steps; steps n_cri + 1 .. n_steps are predicted.
        partitions: n_parts or a :class:`jaxsync.Partition` (the surrogates' partition).
        surrogates: a surrogate checkpoint (path or
            :class:`jaxsync.surrogate.SurrogateCheckpoint`), a :class:`jaxsync.surrogate.Surrogate`
            or an :class:`~jaxsync.solve.predictors.OraclePredictor`.
        n_cri: last synchronized step; at least n_p n_s (the networks read steps
            n_cri - n_p n_s + 1 .. n_cri).
        save_every: snapshot stride; must divide n_cri, n_steps and n_s n_f.
        load_parameter: the load parameter of conditional surrogates, a checkpoint's or a
            :class:`~jaxsync.surrogate.Surrogate`'s (which it replaces); any value, trained
            on or not. Unconditional surrogates refuse one (:class:`CheckpointError`).
        cycles_per_chunk: refill cycles per compiled call of the unmonitored run
            (default: about 20 000 steps).
        resync_tolerance: es_hat above which the run re-synchronizes: a number [cm], a
            string like ``"2%"`` (relative to the largest shared-node displacement seen in
            synchronized steps), or a :class:`ResyncTolerance`; None: never.
        sync: how the synchronized steps sum shared forces (see
            :class:`jaxsync.solve.distributed.DistributedRunner`).
        load_jumps: ``"synchronize"`` (default) or ``"predict"``: what the run does at the
            steps where a load's time function jumps (see above).
        gradient_checkpoints: traced runs only (see below): ``True`` (default) recomputes
            segments in the reverse pass (memory ~ sqrt(n_steps)), ``False`` stores every
            step, an int is a memory budget [bytes] for the synchronized phase.

    Differentiable: when the material, damping, loads, dt or the surrogate's arrays are JAX
    tracers (inside ``jax.grad`` or ``jit``), the run is one traced program
    (:func:`jaxsync.solve.gradients.sync_avoiding_trajectory`) with no progress, divergence
    checks or error control (``resync_tolerance`` is refused), and the trajectory holds JAX
    arrays (``displacement``, ``times``; ``synchronized`` flags; no per-part histories or
    timings). Give a concrete ``dt``: the default CFL step follows a traced E, and the steps
    where loads jump cannot be found from a traced dt (or pass ``load_jumps="predict"``).

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
        ``us_per_step_predicted``, ``us_per_step_synchronized``, ``compile_seconds``.

    Raises:
        ProblemError: n_cri too small, save_every not dividing n_cri, n_steps and n_s n_f,
            a tolerance that is not > 0 or given with an oracle.
        CheckpointError: surrogates made for another partition.
        StabilityError: without a tolerance, a prediction turned NaN/Inf (the message
            names the step and the part; ``error.trajectory`` keeps the snapshots saved
            before). With a tolerance such a cycle is rejected like any other.
    """
    from ..precision import require_float64
    from ..surrogate.checkpoint import SurrogateCheckpoint, check_compatible, load_checkpoint

    require_float64("simulate_sync_avoiding")
    n_steps, n_cri, save_every = int(n_steps), int(n_cri), int(save_every)
    dt = problem.dt if dt is None else dt
    if isinstance(surrogates, (str, bytes)) or hasattr(surrogates, "__fspath__"):
        surrogates = load_checkpoint(surrogates)
    tolerance = None if resync_tolerance is None else ResyncTolerance.parse(resync_tolerance)
    traced = is_traced(problem.material, problem.damping, problem.loads, dt, problem.initial_displacement,
                       problem.initial_velocity, surrogates)
    if traced:  # inside jax.grad / jit: one traced program (jaxsync.solve.gradients)
        runner = None
        partition = (partitions if isinstance(partitions, Partition)
                     else make_partition(problem.mesh, partitions, seed=seed))
    else:
        dt = float(dt)
        system = build_system(problem, dt, mode)
        runner = DistributedRunner(problem, system, partitions, save_every=save_every, mode=mode,
                                   seed=seed, devices=devices, sync=sync, record_shared=True)
        partition = runner.partition
    n_dof, counts = shared_dof_layout(partition)
    if isinstance(surrogates, SurrogateCheckpoint):
        check_compatible(surrogates, [p.shared_nodes for p in partition.parts])
        predictor = Surrogate.from_checkpoint(surrogates, load_parameter)
    elif isinstance(surrogates, Surrogate):
        predictor = surrogates.with_load_parameter(load_parameter)
    else:
        predictor = surrogates
    n_s, n_p, n_f = predictor.n_s, predictor.n_past, predictor.n_future
    if isinstance(predictor, Surrogate) and predictor.arch.n_dof != n_dof:
        raise CheckpointError(f"the surrogates predict {predictor.arch.n_dof} dofs per part but this "
                              f"partition needs {n_dof}: retrain on this partition")
    history, cycle_steps = n_s * n_p, n_s * n_f
    if n_cri < history:
        raise ProblemError(f"n_cri={n_cri} is too small: the first refill reads the n_p * n_s = "
                           f"{history} synchronized steps before it (n_p={n_p}, n_s={n_s})")
    if n_cri > n_steps:
        raise ProblemError(f"n_cri={n_cri} is beyond n_steps={n_steps}")
    if n_cri % save_every or cycle_steps % save_every or n_steps % save_every:
        raise ProblemError(f"save_every={save_every} must divide n_cri={n_cri}, n_steps={n_steps} "
                           f"and the steps per refill cycle n_s * n_f = {cycle_steps}")
    all_jumps = _find_load_jumps(problem.loads, n_steps, dt, load_jumps)
    jumps, n_cri = _synchronize_through_load_jumps(all_jumps, load_jumps, n_cri, n_steps, dt, history, save_every)
    if tolerance is not None and isinstance(predictor, OraclePredictor):
        raise ProblemError("resync_tolerance needs a predictor that works from its input history; "
                           "an OraclePredictor replays fixed values")
    if traced:
        if tolerance is not None:
            raise ProblemError("resync_tolerance cannot be used inside jax.grad or jit (it decides on "
                               "the host whether to re-synchronize): leave it out of differentiated runs")
        return _traced_run(problem, dt, predictor, partition, n_cri=n_cri, n_steps=n_steps,
                           save_every=save_every, mode=mode, devices=devices, sync=sync,
                           checkpoints=gradient_checkpoints, jumps=all_jumps)

    # synchronized phase: the full field every save_every steps, shared nodes every step
    limit = divergence_limit(problem.mesh, blowup_factor)
    phase = PredictedPhase(runner, predictor, save_every)
    if tolerance is None:
        predicted = PredictedRunner(phase, problem, cycle_steps, cycles_per_chunk or max(1, 20000 // cycle_steps))
    else:
        predicted = MonitoredRunner(phase, problem, cycle_steps, tolerance, DisagreementMonitor(partition))
    timeline: list[Segment] = []
    resyncs = {"resynchronized_at": [], "es_hat_trigger": [], "tolerance_cm": []}
    seconds = {"predicted": 0.0, "synchronized": 0.0, "discarded": 0.0}
    compile_seconds = 0.0
    n_discarded, failures = 0, 0
    with Progress(n_steps, show=progress, label="synchronized") as bar:
        synced, anchor_state = drive(problem, runner, initial_state(problem, system), n_cri, dt,
                                     save_every, partition=partition, progress=bar,
                                     shared_every=1, return_state=True)
        seconds["synchronized"] += float(synced.stats.us_per_step or 0.0) * 1e-6 * n_cri
        compile_seconds += float(synced.stats.compile_seconds or 0.0)
        shared_sync = [part.shared_displacement for part in synced.parts]
        predicted.amplitude = max(float(np.abs(v).max(initial=0.0)) for v in shared_sync)
        anchor = _Anchor(anchor_state, _histories(partition, shared_sync, history, n_dof), n_cri)
        step_now = n_cri
        try:
            while step_now < n_steps:
                bar.label("predicted")
                state = (runner.from_global(anchor.state), runner.put(anchor.history), step_now)
                try:
                    segment = run_chunks(predicted, state, step_now, n_steps, kind="predicted", limit=limit,
                                         progress=bar)
                except CycleRejected as rejected:
                    # back to the anchor, synchronized through the end of the rejected cycle
                    discarded = rejected.segment
                    seconds["discarded"] += discarded.seconds
                    compile_seconds += discarded.compile_seconds
                    resyncs["resynchronized_at"].append(rejected.step)
                    resyncs["es_hat_trigger"].append(rejected.es_hat)
                    resyncs["tolerance_cm"].append(rejected.tolerance)
                    failures = failures + 1 if rejected.step == anchor.step else 0
                    n_discarded += rejected.step - anchor.step
                    target = min(rejected.step + cycle_steps * 2 ** failures, n_steps)
                    bar.label("re-synchronized")
                    bar.set(anchor.step)
                    # the shared values of the last n_s n_p steps are all the next anchor needs:
                    # a long stretch keeps only those (bounded memory at the paper's size)
                    segment = run_chunks(runner, runner.from_global(anchor.state), anchor.step, target,
                                         kind="synchronized", limit=limit, progress=bar, keep_shared=history)
                    seconds["synchronized"] += segment.seconds
                    compile_seconds += segment.compile_seconds
                    predicted.amplitude = max(predicted.amplitude, segment.shared_abs_max)
                    timeline.append(segment)
                    end_state = runner.to_global(segment.state)
                    anchor = _Anchor(end_state, _histories(partition, segment.shared, history, n_dof, anchor.history),
                                     target)
                    step_now = target
                    continue
                seconds["predicted"] += segment.seconds
                compile_seconds += segment.compile_seconds
                timeline.append(segment)
                step_now = segment.last
        except Diverged as bad:  # predicted, or re-synchronized
            partial = _assemble(problem, partition, synced, timeline + [bad.segment], dt, save_every)
            if bad.part is not None:
                where = (f"the surrogate of part {bad.part} predicted NaN/Inf for step {bad.step}: the network "
                         "diverged; retrain it, raise n_cri or give a resync_tolerance")
            else:
                where = (f"the {bad.segment.kind} run diverged by step {bad.step} (displacement NaN/Inf or "
                         f"above {limit:.3g} cm); {divergence_advice(problem, dt)}")
            err = StabilityError(f"{where} (t = {bad.step * dt:.6g} s). The {partial.n_saved} snapshots "
                                 "saved before are kept (error.trajectory)")
            err.trajectory = partial
            raise err from None
    traj = _assemble(problem, partition, synced, timeline, dt, save_every)
    n_sync = n_cri + sum(seg.n_steps for seg in timeline if seg.kind == "synchronized")
    n_pred = n_steps - n_sync
    stats = dataclasses.replace(
        synced.stats, us_per_step=None, n_steps=n_steps, n_cri=n_cri,
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
        if resyncs["resynchronized_at"] and n_pred < 0.5 * (n_steps - n_cri):
            warnings.warn(
                f"the surrogates kept es_hat below the tolerance {tolerance} for only {n_pred} of the "
                f"{n_steps - n_cri} steps after n_cri ({len(resyncs['resynchronized_at'])} "
                f"re-synchronizations, {n_discarded} predicted steps recomputed): the run was mostly "
                "synchronized; retrain the surrogates or loosen the tolerance", RuntimeWarning,
                stacklevel=2)
    # the whole run's last load jump, not only its first synchronized stretch's
    return dataclasses.replace(traj, stats=stats, parameters={**traj.parameters, **_parameters(problem, all_jumps)})


def _traced_run(problem, dt, predictor, partition, *, n_cri, n_steps, save_every, mode, devices, sync,
                checkpoints, jumps):
    """The run as one traced JAX computation (inside ``jax.grad``/``jit``): a
    :class:`jaxsync.Trajectory` of JAX arrays (:func:`jaxsync.solve.gradients.sync_avoiding_trajectory`)."""
    import jax.numpy as jnp

    from ..trajectory import Trajectory
    from .gradients import sync_avoiding_trajectory

    system = build_system(problem, dt, mode)
    state = initial_state(problem, system)
    saved = sync_avoiding_trajectory(problem, system, state, predictor, partition, n_cri=n_cri,
                                     n_steps=n_steps, save_every=save_every, checkpoints=checkpoints,
                                     mode=mode, devices=devices, sync=sync)
    n_saves = n_steps // save_every
    synchronized = np.arange(n_saves + 1) * save_every <= n_cri
    return Trajectory(times=jnp.arange(n_saves + 1, dtype=system.dt.dtype) * save_every * system.dt,
                      displacement=jnp.concatenate([state.displacement[None], saved]), mesh=problem.mesh,
                      dt=dt, save_every=save_every, parameters=_parameters(problem, jumps),
                      synchronized=synchronized)


def _find_load_jumps(loads, n_steps: int, dt, policy: str) -> np.ndarray:
    """:func:`jaxsync.fem.loads.load_jumps` of the run; in a traced run whose load time
    functions (or dt) are traced, a clear error unless jumps are predicted through."""
    import jax

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
    if policy not in ("synchronize", "predict"):
        raise ProblemError(f"load_jumps={policy!r}: use 'synchronize' (stay synchronized through the steps "
                           "where a load jumps) or 'predict' (predict through them, as the paper did)")
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
                      RuntimeWarning, stacklevel=3)
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
    if st.us_per_step_predicted is not None:
        text += f"; {st.us_per_step_predicted:.1f} us per predicted step"
    if st.us_per_step_synchronized is not None:
        text += f", {st.us_per_step_synchronized:.1f} us per synchronized step"
    if st.n_devices is not None:
        text += f" ({st.n_devices} {st.device_kind} device{'s' if st.n_devices > 1 else ''})"
    return text


def _assemble(problem, partition, synced, timeline, dt, save_every):
    """The global trajectory: synchronized snapshots up to n_cri, then the segments of
    ``timeline`` in order -- predicted ones (mean over the parts that hold each node, with
    per-part predictions) and re-synchronized ones -- with per-snapshot flags."""
    from ..trajectory import PartHistory, Trajectory

    n_dof, counts = shared_dof_layout(partition)
    pieces = [np.asarray(synced.displacement)]
    flags = [np.ones(len(pieces[0]), bool)]
    preds = []
    for seg in timeline:
        pieces.append(seg.displacement)
        if seg.kind == "predicted":
            preds.append(seg.predictions)
        flags.append(np.full(len(seg.displacement), seg.kind == "synchronized"))
    pred = np.concatenate(preds, axis=1) if preds else np.zeros((partition.n_parts, 0, n_dof))
    displacement = np.concatenate(pieces)
    n_saved = len(displacement)
    parts = tuple(PartHistory(part.shared_nodes, part.elements,
                              displacement[:, part.shared_nodes].reshape(n_saved, -1), pred[p, :, :counts[p]])
                  for p, part in enumerate(partition.parts))
    return Trajectory(times=np.arange(n_saved) * save_every * dt, displacement=displacement,
                      mesh=problem.mesh, dt=dt, save_every=save_every,
                      parameters=dict(synced.parameters), parts=parts,
                      synchronized=np.concatenate(flags), stats=synced.stats)
