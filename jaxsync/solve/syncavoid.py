"""Synchronization-avoiding explicit solver (paper Algorithm 3), with error control.

Synchronized steps run up to ``n_cri`` (>= n_p n_s). Then, in cycles: (a) one
batched refill prediction per part of its shared-node displacements for the next
n_s n_f steps, from the last n_p n_s steps of its history; (b) n_s n_f solver steps with
no psum, each followed by overwriting the part's shared dofs with its prediction and
imposing the Dirichlet values. Each part's predictor parameters live on its device (a
stacked pytree sharded on the parts axis); the whole predicted phase is one compiled
loop per chunk of cycles with no cross-device collective in it.

A shared node is held, and predicted, by every part that touches it, so after the
switch the parts' values there differ; the returned global trajectory takes the mean
over the parts, and each part's own predictions are kept in ``trajectory.parts`` for
the error estimates of :mod:`jaxsync.metrics`.

Predictors are pytrees with a method ``predict(buffer, step) -> (n_s n_f, n_dof)`` for
one part (``buffer`` (n_s n_p, n_dof) of steps step - n_s n_p + 1 .. step, ``step`` the
last known step; the predictions are for steps step + 1 .. step + n_s n_f):
:class:`SurrogatePredictor` (trained LSTM replicas) and :class:`OraclePredictor`
(replays known displacements; pins the coupling independently of network error).

Error control (``resync_tolerance``, see :func:`simulate_sync_avoiding`): each cycle's
predictions are checked (es_hat, paper eq. 26) before the solver uses them; a rejected
cycle sends the run back to its last synchronized state, from which the synchronized
solver recomputes the steps, so a tolerance never leaves the run in a predicted state
that the synchronized solver then amplifies.
"""

from __future__ import annotations

import dataclasses
import functools
import time
import warnings
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .distributed import DistributedRunner
from ..parallel.exchange import PartSystems
from ..parallel.spmd import spmd_program
from ..errors import CheckpointError, ProblemError, StabilityError
from ..pytree import pytree_dataclass, static_field
from ..trajectory import RunStats
from .solver import drive
from ..fem.stepper import STEP_UNROLL, SolverState, build_system, initial_state, step

__all__ = ["SurrogatePredictor", "OraclePredictor", "ResyncTolerance", "simulate_sync_avoiding",
           "simulate_full_system", "shared_dof_layout", "step_counts", "describe_run"]


@pytree_dataclass
class SurrogatePredictor:
    """Trained LSTM replicas as a predictor (stacked on a leading part axis).

    Attributes:
        params: stacked network parameters.
        mean, std: (n_parts, n_dof) normalization [cm].
        dof_mask: (n_parts, n_dof) 1 on real dofs, 0 on padding.
        cond: (n_parts,) load parameter of conditional networks (ignored otherwise).
        arch: the architecture (static).
        n_s: the sampling stride the replicas were trained with (static).
    """

    params: Any
    mean: Any
    std: Any
    dof_mask: Any
    cond: Any
    arch: Any = static_field(default=None)
    n_s: int = static_field(default=1)

    @property
    def n_past(self) -> int:
        return self.arch.n_past

    @property
    def n_future(self) -> int:
        return self.arch.n_future

    def predict(self, buffer, step):
        """(n_s n_f, n_dof) predictions of the steps after ``step`` for one part (the
        network reads only ``buffer``)."""
        from ..surrogate.evaluate import refill_predict

        cond = self.cond if self.arch.conditional else None
        out = refill_predict(self.params, self.arch, self.mean, self.std, buffer, self.n_s,
                             cond, self.dof_mask)
        return out * self.dof_mask

    @classmethod
    def initialized(cls, partition, n_s: int, *, n_hidden: int = 100, n_layers: int = 2,
                    n_past: int = 20, n_future: int = 20, dtype: str = "float32",
                    seed: int = 0) -> "SurrogatePredictor":
        """Untrained (randomly initialized) replicas for ``partition``, unit normalization.

        For timing studies: an untrained network costs exactly what a trained one of the
        same architecture costs, and needs no training run. Its predictions are
        meaningless."""
        from ..surrogate.lstm import LSTMArchitecture
        from ..surrogate.train import init_replicas

        n_dof, counts = shared_dof_layout(partition)
        arch = LSTMArchitecture(n_dof=n_dof, n_hidden=n_hidden, n_layers=n_layers,
                                n_past=n_past, n_future=n_future, dtype=dtype)
        params = init_replicas(jax.random.PRNGKey(seed), arch, tuple(int(c) for c in counts))
        n = partition.n_parts
        # normalization and mask in float64, as a checkpoint stores them
        mask = (np.arange(n_dof)[None, :] < counts[:, None]).astype(np.float64)
        return cls(params=params, mean=np.zeros((n, n_dof)), std=np.ones((n, n_dof)),
                   dof_mask=mask, cond=np.zeros(n, dtype=np.float32), arch=arch, n_s=int(n_s))

    @classmethod
    def from_checkpoint(cls, checkpoint, cond: float | None = None) -> "SurrogatePredictor":
        """Predictor of a :class:`jaxsync.surrogate.SurrogateCheckpoint` (or its path)."""
        from ..surrogate.checkpoint import SurrogateCheckpoint, load_checkpoint

        if not isinstance(checkpoint, SurrogateCheckpoint):
            checkpoint = load_checkpoint(checkpoint)
        n = checkpoint.n_parts
        if checkpoint.arch.conditional and cond is None:
            raise CheckpointError("the surrogates are conditional on a load parameter: pass cond=")
        return cls(params=checkpoint.params, mean=np.asarray(checkpoint.mean),
                   std=np.asarray(checkpoint.std), dof_mask=checkpoint.dof_mask.astype(np.asarray(checkpoint.mean).dtype),
                   cond=np.full(n, 0.0 if cond is None else float(cond), dtype=np.float32),
                   arch=checkpoint.arch, n_s=int(checkpoint.n_s))


@pytree_dataclass
class OraclePredictor:
    """Replays known shared displacements: ``future[p, k]`` is part p's shared dofs at
    step ``first_step + k``. With the synchronized run's values the predicted phase must
    reproduce that run to round-off.

    Attributes:
        future: (n_parts, n_known, n_dof) [cm]; steps past the end read the last rows
            (pad to whole cycles).
        first_step: the step of ``future[:, 0]`` (static).
        n_s, n_past, n_future: the refill geometry it stands in for (static).
    """

    future: Any
    first_step: int = static_field()
    n_s: int = static_field(default=1)
    n_past: int = static_field(default=1)
    n_future: int = static_field(default=1)

    def predict(self, buffer, step):
        length = self.n_s * self.n_future
        return jax.lax.dynamic_slice_in_dim(self.future, step + 1 - self.first_step, length, axis=0)


def shared_dof_layout(partition) -> tuple[int, np.ndarray]:
    """(n_dof padded = 3 * max shared nodes, (n_parts,) real shared-dof counts)."""
    counts = np.array([3 * p.n_shared for p in partition.parts])
    return max(int(counts.max()), 3), counts


# --------------------------------------------------------------------------- one part, pure

def _predict_cycle(predictor, buffer, step):
    """One part: the predictions (n_s n_f, n_dof) of the steps after ``step`` (the last
    known one) and the history buffer moved on by them."""
    pred = predictor.predict(buffer, step).astype(buffer.dtype)
    return pred, jnp.concatenate([buffer, pred])[-buffer.shape[0]:]


def _overwritten_steps(part: PartSystems, state: SolverState, pred, steps: int, save_every: int):
    """One part: ``steps`` solver steps without synchronization, each followed by writing
    the predicted shared-node displacements ``pred[j]`` into the part's state.

    Returns (state, saved displacement (steps // save_every, n_local, 3), the predictions
    at the saved steps (steps // save_every, n_dof))."""
    nodes = pred.reshape(pred.shape[0], -1, 3)

    def one_step(st, j):
        overwrite = lambda new: new.at[part.shared_local].set(nodes[j], mode="drop")  # noqa: E731
        return step(part.system, st, overwrite=overwrite), None

    def saved_block(st, k):
        st, _ = jax.lax.scan(one_step, st, k * save_every + jnp.arange(save_every), unroll=STEP_UNROLL)
        return st, (st.displacement, pred[(k + 1) * save_every - 1])

    def saved_step(st, j):  # save_every = 1: no inner loop (it costs ~50 % per step)
        st, _ = one_step(st, j)
        return st, (st.displacement, pred[j])

    if save_every == 1:
        return _unpack(jax.lax.scan(saved_step, state, jnp.arange(steps), unroll=STEP_UNROLL))
    return _unpack(jax.lax.scan(saved_block, state, jnp.arange(steps // save_every)))


def _unpack(result):
    state, (disp, kept) = result
    return state, disp, kept


def _predicted_cycles(part: PartSystems, predictor, state: SolverState, buffer, step0,
                      n_cycles: int, steps: int, save_every: int):
    """One part: ``n_cycles`` refill cycles of ``steps`` unsynchronized steps each, the
    predictions made inside the loop (the fused program of the unmonitored run).

    Returns (state, buffer, saved displacement (n_cycles, steps // save_every, n_local, 3),
    saved predictions (n_cycles, steps // save_every, n_dof))."""

    def cycle(carry, c):
        state, buffer = carry
        pred, buffer = _predict_cycle(predictor, buffer, step0 + c * steps)
        state, disp, kept = _overwritten_steps(part, state, pred, steps, save_every)
        return (state, buffer), (disp, kept)

    (state, buffer), (disp, kept) = jax.lax.scan(cycle, (state, buffer), jnp.arange(n_cycles))
    return state, buffer, disp, kept


def _rollout(predictor, buffer, step0, steps: int, save_every: int):
    """One part, one refill cycle predicted ahead of the solver (the monitored run checks
    it before using it): (predictions (L, n_dof), moved buffer, the predictions at the
    saved steps (steps // save_every, n_dof))."""
    pred, buffer = _predict_cycle(predictor, buffer, step0)
    return pred, buffer, pred[save_every - 1:steps:save_every]


def _apply(part: PartSystems, state: SolverState, pred, steps: int, save_every: int):
    """One part: the steps of one cycle with already made predictions ``pred``."""
    state, disp, _ = _overwritten_steps(part, state, pred, steps, save_every)
    return state, disp


# --------------------------------------------------------------------------- SPMD programs

class PredictedPhase:
    """Compiles and runs the predicted phase under ``shard_map`` (no collectives): the
    fused program (predict and step, ``n_cycles`` cycles per call) and, for the monitored
    run, the two halves (predict one cycle; step it with the predictions)."""

    def __init__(self, runner: DistributedRunner, predictor, save_every: int):
        self.runner = runner
        self.predictor = runner.put(predictor)
        self.save_every = save_every
        self._compiled = {}
        self.compile_seconds = 0.0

    def _spmd(self, body, n_in: int, n_out: int):
        return spmd_program(body, self.runner.device_mesh, n_in=n_in, n_out=n_out)

    def program(self, n_cycles: int, steps: int):
        key = ("jit", n_cycles, steps)
        if key not in self._compiled:
            body = functools.partial(_predicted_cycles, n_cycles=n_cycles, steps=steps,
                                     save_every=self.save_every)
            # step0 is a per-part copy of the step counter (sharded like the rest)
            self._compiled[key] = self._spmd(body, 5, 4)
        return self._compiled[key]

    def _ahead(self, key, build, example_args):
        """Compile ``build()`` once, ahead of its first timed call, for the arguments
        ``example_args()`` returns (called only then: it may place arrays on devices)."""
        if key not in self._compiled:
            start = time.perf_counter()
            self._compiled[key] = build().lower(*example_args()).compile()
            self.compile_seconds += time.perf_counter() - start
        return self._compiled[key]

    def lowered_text(self, state, buffer, n_cycles: int, steps: int) -> str:
        """The compiled fused program's HLO text (to check that it has no collective)."""
        return self.program(n_cycles, steps).lower(self.runner.parts, self.predictor, state,
                                                   buffer, self.step_counter(0)).compile().as_text()

    def step_counter(self, step: int):
        """The step ``step`` as one int32 per part, sharded like the parts (an argument
        of the predicted programs)."""
        return self.runner.put(np.full(self.runner.partition.n_parts, step, dtype=np.int32))

    def prepare(self, state, buffer, n_cycles: int, steps: int):
        """The fused program for ``n_cycles`` cycles of ``steps``, compiled ahead."""
        return self._ahead(("compiled", n_cycles, steps), lambda: self.program(n_cycles, steps),
                           lambda: (self.runner.parts, self.predictor, state, buffer, self.step_counter(0)))

    def run(self, state, buffer, step0: int, n_cycles: int, steps: int):
        return self.prepare(state, buffer, n_cycles, steps)(
            self.runner.parts, self.predictor, state, buffer, self.step_counter(step0))

    def _rollout_program(self, buffer, steps: int):
        build = lambda: self._spmd(functools.partial(_rollout, steps=steps,  # noqa: E731
                                                     save_every=self.save_every), 3, 3)
        return self._ahead(("rollout", steps), build, lambda: (self.predictor, buffer, self.step_counter(0)))

    def _apply_program(self, state, pred, steps: int):
        build = lambda: self._spmd(functools.partial(_apply, steps=steps,  # noqa: E731
                                                     save_every=self.save_every), 3, 2)
        return self._ahead(("apply", steps), build, lambda: (self.runner.parts, state, pred()))

    def prepare_monitored(self, state, buffer, steps: int) -> None:
        """Compile both halves of a monitored cycle of ``steps`` ahead (nothing runs)."""
        def pred():  # the shape of a cycle's predictions, for compiling
            length = self.predictor.n_s * self.predictor.n_future
            return jax.ShapeDtypeStruct(buffer.shape[:1] + (length,) + buffer.shape[2:], buffer.dtype,
                                        sharding=buffer.sharding)

        self._rollout_program(buffer, steps)
        self._apply_program(state, pred, steps)

    def rollout(self, buffer, step0: int, steps: int):
        """One cycle predicted ahead: (predictions, buffer, predictions at saved steps)."""
        return self._rollout_program(buffer, steps)(self.predictor, buffer, self.step_counter(step0))

    def apply(self, state, pred, steps: int):
        """The steps of one cycle with the predictions of :meth:`rollout`."""
        return self._apply_program(state, lambda: pred, steps)(self.runner.parts, state, pred)


# --------------------------------------------------------------------------- error control

@dataclasses.dataclass(frozen=True)
class ResyncTolerance:
    """The es_hat level above which a synchronization-avoiding run re-synchronizes.

    Give it in cm (``ResyncTolerance(absolute=1e-4)``, or just ``1e-4``) or relative to
    the observed amplitude (``ResyncTolerance(relative=0.01)``, or ``"1%"``): a fraction
    of the largest |displacement| at the shared nodes seen in the synchronized steps so
    far (the amplitude that the run itself has measured; no reference needed).
    """

    absolute: float | None = None
    relative: float | None = None

    def __post_init__(self):
        if (self.absolute is None) == (self.relative is None):
            raise ProblemError("resync_tolerance: give exactly one of absolute (cm) or relative")
        value = self.absolute if self.absolute is not None else self.relative
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
                or not value > 0:  # also refuses NaN
            raise ProblemError(f"resync_tolerance must be a tolerance > 0 (cm, or a fraction of the "
                               f"amplitude), got {value!r}")

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
        """The tolerance in cm given the observed amplitude [cm]."""
        return float(self.absolute) if self.absolute is not None else float(self.relative) * amplitude

    def __str__(self) -> str:
        return f"{self.absolute:g} cm" if self.absolute is not None else f"{100 * self.relative:g} %"


class _Segment(NamedTuple):
    """A stretch of the run after n_cri: steps ``first`` + 1 .. ``last``."""

    kind: str  # "predicted" or "synchronized"
    first: int
    last: int
    displacement: np.ndarray  # (saved, n_nodes, 3) global, at the saved steps
    predictions: np.ndarray | None  # (n_parts, saved, n_dof) each part's own; predicted only
    seconds: float  # wall time of the predicted stretch (0 for synchronized ones)


@dataclasses.dataclass
class _Anchor:
    """The last synchronized point of a run: the global state (both displacement levels)
    and each part's last n_p n_s shared-dof values (the networks' input history)."""

    state: SolverState
    history: np.ndarray  # (n_parts, n_s n_p, n_dof)
    segment: int  # number of timeline segments up to this point


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
                           seed: int = 0, devices=None, cond: float | None = None,
                           progress: bool | None = None, cycles_per_chunk: int | None = None,
                           resync_tolerance=None, sync: str | None = None):
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

    Args:
        problem: the problem.
        n_steps: total steps; steps n_cri + 1 .. n_steps are predicted.
        partitions: n_parts or a :class:`jaxsync.Partition` (the surrogates' partition).
        surrogates: a surrogate checkpoint (path or
            :class:`jaxsync.surrogate.SurrogateCheckpoint`), a :class:`SurrogatePredictor`
            or an :class:`OraclePredictor`.
        n_cri: last synchronized step; at least n_p n_s (the networks read steps
            n_cri - n_p n_s + 1 .. n_cri).
        save_every: snapshot stride; must divide n_cri, n_steps and n_s n_f.
        cond: load parameter for conditional surrogates.
        cycles_per_chunk: refill cycles per compiled call of the unmonitored run
            (default: about 20 000 steps).
        resync_tolerance: es_hat above which the run re-synchronizes: a number [cm], a
            string like ``"2%"`` (relative to the largest shared-node displacement seen in
            synchronized steps), or a :class:`ResyncTolerance`; None: never.
        sync: how the synchronized steps sum shared forces (see
            :class:`jaxsync.solve.distributed.DistributedRunner`).

    Returns:
        :class:`jaxsync.Trajectory` with ``synchronized`` flags (True at the snapshots of
        synchronized steps, re-synchronized ones included) and, per part,
        ``shared_displacement`` and ``predicted_shared_displacement``
        (n_predicted_saved, 3 n_shared_p): the part's own predictions at the saved
        predicted steps. ``stats`` (:class:`jaxsync.RunStats`): ``n_synchronized_steps``, ``n_predicted_steps``
        (they add up to n_steps), ``n_discarded_steps``, ``n_resynchronizations``,
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
    dt = problem.dt if dt is None else float(dt)
    if isinstance(surrogates, (str, bytes)) or hasattr(surrogates, "__fspath__"):
        surrogates = load_checkpoint(surrogates)
    tolerance = None if resync_tolerance is None else ResyncTolerance.parse(resync_tolerance)
    system = build_system(problem, dt, mode)
    runner = DistributedRunner(problem, system, partitions, save_every=save_every, mode=mode,
                               seed=seed, devices=devices, sync=sync, record_shared=True)
    partition = runner.partition
    n_dof, counts = shared_dof_layout(partition)
    if isinstance(surrogates, SurrogateCheckpoint):
        check_compatible(surrogates, [p.shared_nodes for p in partition.parts])
        predictor = SurrogatePredictor.from_checkpoint(surrogates, cond)
    else:
        predictor = surrogates
    n_s, n_p, n_f = predictor.n_s, predictor.n_past, predictor.n_future
    if isinstance(predictor, SurrogatePredictor) and predictor.arch.n_dof != n_dof:
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
    monitor = None
    if tolerance is not None:
        if isinstance(predictor, OraclePredictor):
            raise ProblemError("resync_tolerance needs a predictor that works from its input history; "
                               "an OraclePredictor replays fixed values")
        monitor = _DisagreementMonitor(partition)

    # synchronized phase: the full field every save_every steps, shared nodes every step
    synced, anchor_state = drive(problem, runner, initial_state(problem, system), n_cri, dt,
                                 save_every, partition=partition, progress=progress,
                                 label="synchronized", shared_every=1, return_state=True)
    shared_sync = [p.shared_displacement for p in synced.parts]
    amplitude = max(float(np.abs(v).max(initial=0.0)) for v in shared_sync)
    anchor = _Anchor(anchor_state, _histories(partition, shared_sync, history, n_dof), 0)
    state = runner.from_global(anchor_state)
    buffer = runner.put(anchor.history)
    online = PredictedPhase(runner, predictor, save_every)
    timeline: list[_Segment] = []
    stats = {"resynchronized_at": [], "es_hat_trigger": [], "tolerance_cm": []}
    seconds = {"predicted": 0.0, "synchronized": 0.0, "discarded": 0.0}
    sync_seconds = float(synced.stats.us_per_step or 0.0) * 1e-6 * n_cri
    n_discarded = 0
    per_chunk = cycles_per_chunk or max(1, 20000 // cycle_steps)
    from tqdm import tqdm

    n_predicted = n_steps - n_cri
    show = progress if progress is not None else n_predicted >= 20000
    bar = tqdm(total=n_predicted, disable=not show, unit="step", desc="predicted", dynamic_ncols=True)
    step_now, failures = n_cri, 0
    try:
        while step_now < n_steps:
            left = n_steps - step_now
            if monitor is None:
                k, steps = (min(per_chunk, left // cycle_steps), cycle_steps) if left >= cycle_steps else (1, left)
                online.prepare(state, buffer, k, steps)  # compilation is not timed
                start = time.perf_counter()
                state, buffer, disp, pred = online.run(state, buffer, step_now, k, steps)
                disp, pred = _host(disp), _host(pred)  # (P, k, steps/save, ...)
                spent = time.perf_counter() - start
                seconds["predicted"] += spent
                bad = ~np.isfinite(pred).all(axis=-1)  # (P, k, n_saved)
                if bad.any():
                    p, c, j = (int(i[0]) for i in np.nonzero(bad))
                    bad_step = step_now + c * steps + (j + 1) * save_every
                    partial = _assemble(problem, partition, synced, timeline, counts, dt, save_every)
                    err = StabilityError(
                        f"the surrogate of part {p} predicted NaN/Inf for step {bad_step} "
                        f"(t = {bad_step * dt:.6g} s): the network diverged; retrain it, raise n_cri "
                        f"or give a resync_tolerance. The {partial.n_saved} snapshots saved before "
                        "are kept (error.trajectory)")
                    err.trajectory = partial
                    raise err
                timeline.append(_predicted_segment(problem, partition, step_now, k * steps, disp, pred, spent))
                step_now += k * steps
                bar.update(k * steps)
                continue

            steps = min(cycle_steps, left)
            online.prepare_monitored(state, buffer, steps)  # compilation is not timed
            start = time.perf_counter()
            pred, next_buffer, kept = online.rollout(buffer, step_now, steps)
            kept = _host(kept)  # (P, steps / save_every, n_dof)
            tol = tolerance.cm(amplitude)
            es_hat = monitor.es_hat(kept, counts) if np.isfinite(kept).all() else np.array([np.inf])
            check = time.perf_counter() - start
            if es_hat.max() <= tol:
                start = time.perf_counter()
                state, disp = online.apply(state, pred, steps)
                disp = _host(disp)
                spent = check + time.perf_counter() - start
                seconds["predicted"] += spent
                timeline.append(_predicted_segment(problem, partition, step_now, steps, disp[:, None],
                                                   kept[:, None], spent))
                buffer = next_buffer
                step_now += steps
                bar.update(steps)
                continue

            # rejected: back to the anchor, synchronized through the end of this cycle
            seconds["discarded"] += check
            stats["resynchronized_at"].append(step_now)
            stats["es_hat_trigger"].append(float(es_hat.max()))
            stats["tolerance_cm"].append(tol)
            start_step = int(anchor.state.step)
            failures = failures + 1 if step_now == start_step else 0
            n_discarded += step_now - start_step
            wasted = sum(seg.seconds for seg in timeline[anchor.segment:])
            seconds["discarded"] += wasted
            seconds["predicted"] -= wasted
            del timeline[anchor.segment:]
            target = min(step_now + cycle_steps * 2 ** failures, n_steps)
            segment, end_state = drive(problem, runner, anchor.state, target, dt, save_every,
                                       partition=partition, progress=False, label="re-synchronized",
                                       shared_every=1, return_state=True)
            seconds["synchronized"] += 1e-6 * segment.stats.us_per_step * (target - start_step)
            shared = [p.shared_displacement[1:] for p in segment.parts]  # steps after the anchor
            amplitude = max([amplitude] + [float(np.abs(v).max(initial=0.0)) for v in shared])
            timeline.append(_Segment("synchronized", start_step, target, segment.displacement[1:], None, 0.0))
            anchor = _Anchor(end_state, _histories(partition, shared, history, n_dof, anchor.history),
                             len(timeline))
            state = runner.from_global(end_state)
            buffer = runner.put(anchor.history)
            step_now = target
            bar.n = step_now - n_cri
            bar.refresh()
    except BaseException:
        bar.leave = False  # an error clears the bar instead of leaving a (blank) line before it
        raise
    finally:
        bar.close()
    traj = _assemble(problem, partition, synced, timeline, counts, dt, save_every)
    n_sync = n_cri + sum(seg.last - seg.first for seg in timeline if seg.kind == "synchronized")
    n_pred = n_steps - n_sync
    sync_seconds += seconds["synchronized"]
    statistics = {
        **synced.stats.to_dict(),
        "n_steps": n_steps, "n_cri": n_cri,
        "n_synchronized_steps": n_sync, "n_predicted_steps": n_pred,
        "n_discarded_steps": n_discarded,
        "compile_seconds": float(synced.stats.compile_seconds or 0.0) + online.compile_seconds,
        "us_per_step_synchronized": 1e6 * sync_seconds / max(n_sync, 1),
        "seconds_discarded": seconds["discarded"],
    }
    if n_pred:
        statistics["us_per_step_predicted"] = 1e6 * seconds["predicted"] / n_pred
    statistics.pop("us_per_step", None)
    if tolerance is not None:
        statistics.update(resync_tolerance=str(tolerance), n_resynchronizations=len(stats["resynchronized_at"]),
                          **stats)
        if stats["resynchronized_at"] and n_pred < 0.5 * (n_steps - n_cri):
            warnings.warn(
                f"the surrogates kept es_hat below the tolerance {tolerance} for only {n_pred} of the "
                f"{n_steps - n_cri} steps after n_cri ({len(stats['resynchronized_at'])} "
                f"re-synchronizations, {n_discarded} predicted steps recomputed): the run was mostly "
                "synchronized; retrain the surrogates or loosen the tolerance", RuntimeWarning,
                stacklevel=2)
    return dataclasses.replace(traj, stats=RunStats(**statistics))


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


def _host(x) -> np.ndarray:
    from .distributed import to_host

    return _to_host(x)


def _predicted_segment(problem, partition, first: int, n: int, disp, pred, seconds: float):
    """A timeline entry of predicted steps first + 1 .. first + n: the global field at the
    saved steps (mean over the parts that hold each node) and each part's predictions
    there; ``disp`` (P, cycles, saved per cycle, n_local, 3), ``pred`` (P, cycles, saved
    per cycle, n_dof); ``seconds`` it took."""
    disp = disp.reshape(disp.shape[0], -1, *disp.shape[3:])
    pred = pred.reshape(pred.shape[0], -1, pred.shape[-1])
    return _Segment("predicted", first, first + n, _mean_over_parts(problem, partition, disp), pred, seconds)


def _mean_over_parts(problem, partition, local) -> np.ndarray:
    """(n_nodes, 3) global field from per-part local fields (P, ..., n_local_max, 3): the
    mean over the parts that hold each node (they differ at shared nodes after prediction)."""
    local = np.asarray(local)
    total = np.zeros(local.shape[1:-2] + (problem.mesh.n_nodes, 3))
    count = np.zeros(problem.mesh.n_nodes)
    for p, part in enumerate(partition.parts):
        total[..., part.nodes, :] += local[p, ..., :part.n_local, :]
        count[part.nodes] += 1
    return total / count[:, None]


class _DisagreementMonitor:
    """es_hat (paper eq. 26) of the parts' own predictions, for the live error control."""

    def __init__(self, partition):
        from ..metrics import shared_node_errors

        self._errors = shared_node_errors
        index = {int(node): k for k, node in enumerate(partition.shared_nodes)}
        self.columns = [np.array([index[int(n)] for n in part.shared_nodes], dtype=int)
                        for part in partition.parts]
        self.holds = np.zeros((partition.n_parts, len(partition.shared_nodes)), bool)
        for p, cols in enumerate(self.columns):
            self.holds[p, cols] = True

    def es_hat(self, pred, counts) -> np.ndarray:
        """(T,) es_hat of predictions (P, T, n_dof) [cm]."""
        n_parts, T = pred.shape[:2]
        by_node = np.zeros((n_parts, T, self.holds.shape[1], 3))
        for p, cols in enumerate(self.columns):
            by_node[p][:, cols] = pred[p, :, :counts[p]].reshape(T, -1, 3)
        return self._errors(np.zeros(by_node.shape[1:]), by_node, self.holds).es_hat


def _assemble(problem, partition, synced, timeline, counts, dt, save_every):
    """The global trajectory: synchronized snapshots up to n_cri, then the segments of
    ``timeline`` in order -- predicted ones (mean over the parts that hold each node, with
    per-part predictions) and re-synchronized ones -- with per-snapshot flags."""
    from ..trajectory import PartHistory, RunStats, Trajectory

    pieces = [np.asarray(synced.displacement)]
    flags = [np.ones(len(pieces[0]), bool)]
    preds = []
    for seg in timeline:
        pieces.append(seg.displacement)
        if seg.kind == "predicted":
            preds.append(seg.predictions)
        flags.append(np.full(len(seg.displacement), seg.kind == "synchronized"))
    pred = (np.concatenate(preds, axis=1) if preds
            else np.zeros((partition.n_parts, 0, max(counts.max(), 3))))
    displacement = np.concatenate(pieces)
    n_saved = len(displacement)
    synchronized = np.concatenate(flags)
    parts = []
    for p, part in enumerate(partition.parts):
        shared = displacement[:, part.shared_nodes].reshape(n_saved, -1)
        parts.append(PartHistory(part.shared_nodes, part.elements, shared, pred[p, :, :counts[p]]))
    return Trajectory(times=np.arange(n_saved) * save_every * dt, displacement=displacement,
                      mesh=problem.mesh, dt=dt, save_every=save_every,
                      parameters=dict(synced.parameters), parts=tuple(parts),
                      synchronized=synchronized, stats=synced.stats)


def simulate_full_system(problem, reference, surrogates, *, n_cri: int, n_steps: int | None = None,
                         cond: float | None = None):
    """Full-system modeling (paper "Full system modeling"): one surrogate predicts every dof.

    The synchronized ``reference`` (saved at every step) supplies the first ``n_cri``
    steps; after that no solver step runs: refill cycles of the single surrogate,
    each consuming earlier predictions, produce all displacements. The network does not
    know the Dirichlet conditions; their predicted values are reported, not enforced.

    Args:
        problem: the problem (for its Dirichlet dofs).
        reference: :class:`jaxsync.Trajectory` saved at every step, at least n_cri + 1 long.
        surrogates: a one-replica checkpoint (path or object) over all 3 n_nodes dofs, a
            :class:`SurrogatePredictor` or an :class:`OraclePredictor` (one part).
        n_cri: last step taken from the reference (>= n_p n_s + 1).
        n_steps: total steps (default: the reference's length).

    Returns:
        :class:`jaxsync.Trajectory` (saved every step) with ``synchronized`` flags and
        ``stats.dirichlet_max_abs_predicted``, the largest |predicted value| on the
        Dirichlet dofs, whose prescribed values the network does not enforce.
    """
    from ..precision import require_float64
    from ..surrogate.checkpoint import SurrogateCheckpoint, load_checkpoint
    from ..trajectory import PartHistory, RunStats, Trajectory

    require_float64("simulate_full_system")
    if reference.save_every != 1:
        raise ProblemError("full-system modeling needs the reference saved at every step")
    n_steps = reference.n_saved - 1 if n_steps is None else int(n_steps)
    if isinstance(surrogates, (str, bytes)) or hasattr(surrogates, "__fspath__"):
        surrogates = load_checkpoint(surrogates)
    n_dof = problem.mesh.n_dofs
    if isinstance(surrogates, SurrogateCheckpoint):
        if surrogates.n_parts != 1 or surrogates.dof_counts[0] != n_dof:
            raise CheckpointError(f"full-system modeling needs one surrogate over all {n_dof} dofs; "
                                  f"the checkpoint has {surrogates.n_parts} replicas with "
                                  f"{list(surrogates.dof_counts)} dofs")
        predictor = SurrogatePredictor.from_checkpoint(surrogates, cond)
    else:
        predictor = surrogates
    history, cycle_steps = predictor.n_s * predictor.n_past, predictor.n_s * predictor.n_future
    if n_cri < history:
        raise ProblemError(f"n_cri={n_cri} is too small: the first refill reads the n_p * n_s = "
                           f"{history} known steps before it")
    if reference.n_saved < n_cri + 1:
        raise ProblemError(f"the reference holds {reference.n_saved} snapshots, fewer than n_cri + 1")
    known = np.asarray(reference.displacement[:n_cri + 1]).reshape(n_cri + 1, -1)
    n_cycles = -(-(n_steps - n_cri) // cycle_steps)
    one = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[0], predictor)

    @jax.jit
    def rollout(buffer):
        def cycle(buf, c):
            pred = one.predict(buf, n_cri + c * cycle_steps).astype(buf.dtype)
            return jnp.concatenate([buf, pred])[-history:], pred

        _, blocks = jax.lax.scan(cycle, buffer, jnp.arange(n_cycles))
        return blocks.reshape(-1, buffer.shape[1])

    buffer = jnp.asarray(known[-history:])
    start = time.perf_counter()
    compiled = rollout.lower(buffer).compile()
    compile_seconds = time.perf_counter() - start
    start = time.perf_counter()
    predicted = np.asarray(compiled(buffer))[:n_steps - n_cri]
    seconds = time.perf_counter() - start
    if not np.all(np.isfinite(predicted)):
        bad = n_cri + 1 + int(np.argmin(np.isfinite(predicted).all(axis=1)))
        raise StabilityError(f"the full-system surrogate predicted NaN/Inf for step {bad}; retrain it")
    displacement = np.concatenate([known, predicted]).reshape(n_steps + 1, -1, 3)
    fixed, values = problem.dirichlet_dofs()
    dirichlet_error = float(np.abs(predicted[:, fixed] - values).max()) if len(predicted) else 0.0
    return Trajectory(times=np.arange(n_steps + 1) * reference.dt, displacement=displacement,
                      mesh=problem.mesh, dt=reference.dt, save_every=1,
                      parameters=dict(reference.parameters),
                      stats=RunStats(**{"n_steps": n_steps, "n_cri": n_cri, "n_synchronized_steps": n_cri,
                                  "n_predicted_steps": n_steps - n_cri,
                                  "dirichlet_max_abs_predicted": dirichlet_error,
                                  "compile_seconds": compile_seconds,
                                  "us_per_step_predicted": 1e6 * seconds / max(n_steps - n_cri, 1)}),
                      synchronized=np.arange(n_steps + 1) <= n_cri)
