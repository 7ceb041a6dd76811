"""The host executor's runners of the predicted phase (paper Algorithm 3).

:class:`PredictedPhase` compiles the phase's per-part functions
(:mod:`jaxsync.solve.executors`: :func:`~jaxsync.solve.executors.predicted_cycles`, and for
the monitored run its two halves :func:`~jaxsync.solve.executors.predict_cycle` and
:func:`~jaxsync.solve.executors.overwritten_steps`) as SPMD programs on the run's devices;
no collective runs in them. Two runners of the host loop (:mod:`jaxsync.solve.executors`)
drive them: :class:`PredictedRunner` (the fused program, predictions made inside the
loop, several cycles per call) and :class:`MonitoredRunner` (each cycle predicted first,
its es_hat checked, then applied; a rejected cycle raises :class:`CycleRejected`).
"""

from __future__ import annotations

import functools
import time

import jax
import numpy as np

from ._distributed import DistributedRunner, to_host
from ._driver import Chunk, Stopped
from ._phases import overwritten_steps, predict_cycle, predicted_cycles

__all__ = ["PredictedPhase", "PredictedRunner", "MonitoredRunner", "CycleRejected", "DisagreementMonitor"]


def _fused(part, predictor, state, buffer, step0, *, n_cycles: int, steps: int, save_every: int):
    """One part, ``n_cycles`` refill cycles with the predictions made inside the loop:
    (state, buffer, saved (n_cycles, steps // save_every, n_local, 3), predictions at the
    saved steps (n_cycles, steps // save_every, n_dof))."""
    (state, buffer, _), (saved, kept) = predicted_cycles(part, predictor, (state, buffer, step0), n_cycles,
                                                         steps, save_every)
    return state, buffer, saved, kept


class PredictedPhase:
    """Compiles and runs the predicted phase under ``shard_map`` (no collectives): the
    fused program (predict and step, ``n_cycles`` cycles per call) and, for the monitored
    run, the two halves (predict one cycle; step it with the predictions).

    ``runner``: the run's :class:`DistributedRunner` (its placed parts and devices);
    ``predictor``: stacked on the part axis (placed here); ``save_every``: the stride of
    the saved snapshots."""

    def __init__(self, runner: DistributedRunner, predictor, save_every: int):
        self.runner = runner
        self.predictor = runner.put(predictor)
        self.save_every = save_every
        self._compiled = {}
        self.compile_seconds = 0.0

    def _spmd(self, body, n_in: int, n_out: int):
        return self.runner.distributed.spmd(body, n_in=n_in, n_out=n_out)

    def program(self, n_cycles: int, steps: int):
        """The jitted fused program ``(parts, predictor, state, buffer, step0) -> (state,
        buffer, saved, predictions)`` of ``n_cycles`` cycles of ``steps`` steps."""
        key = ("jit", n_cycles, steps)
        if key not in self._compiled:
            body = functools.partial(_fused, n_cycles=n_cycles, steps=steps, save_every=self.save_every)
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
        build = lambda: self._spmd(functools.partial(predict_cycle, steps=steps,  # noqa: E731
                                                     save_every=self.save_every), 3, 3)
        return self._ahead(("rollout", steps), build, lambda: (self.predictor, buffer, self.step_counter(0)))

    def _apply_program(self, state, pred, steps: int, probe: bool = False, modal=None):
        exchange = self.runner.distributed.exchange if probe else None
        n_in = 3 if modal is None else 4
        build = lambda: self._spmd(functools.partial(overwritten_steps, steps=steps,  # noqa: E731
                                                     save_every=self.save_every, probe=exchange), n_in, 2)
        extra = () if modal is None else (modal,)
        return self._ahead(("apply", steps, probe, n_in), build, lambda: (self.runner.parts, state, pred()) + extra)

    def prepare_monitored(self, state, buffer, steps: int, probe: bool = False, modal=None) -> None:
        """Compile both halves of a monitored cycle of ``steps`` ahead (nothing runs);
        ``probe``: the second half probes the force-balance defect at the saved steps
        (``modal``: and drives the modes with every step's defect, :func:`defect_probe`'s
        tables placed on the devices)."""
        def pred():  # the shape of a cycle's predictions, for compiling
            length = self.predictor.n_s * self.predictor.n_future
            return jax.ShapeDtypeStruct(buffer.shape[:1] + (length,) + buffer.shape[2:], buffer.dtype,
                                        sharding=buffer.sharding)

        self._rollout_program(buffer, steps)
        self._apply_program(state, pred, steps, probe, modal)

    def rollout(self, buffer, step0: int, steps: int):
        """One cycle predicted ahead: (predictions, buffer, predictions at saved steps)."""
        return self._rollout_program(buffer, steps)(self.predictor, buffer, self.step_counter(step0))

    def apply(self, state, pred, steps: int, probe: bool = False, modal=None):
        """The steps of one cycle with the predictions of :meth:`rollout`: (state, saved),
        with ``probe`` (state, (saved, defects (P, steps // save_every, n_shared_max, 3))),
        with ``modal`` too (state, (saved, (defects, modal responses (P, steps //
        save_every, n_modes, 2))))."""
        extra = () if modal is None else (modal,)
        return self._apply_program(state, lambda: pred, steps, probe, modal)(self.runner.parts, state, pred, *extra)

    def modal_tables(self, propagator, monitor):
        """:func:`~jaxsync.solve.executors.defect_probe`'s modal tables of ``propagator``,
        placed on the devices like the parts (made once per propagator)."""
        key = ("modal", id(propagator))
        if key not in self._compiled:
            width = int(np.asarray(self.runner.parts.shared_local).shape[-1])
            tables = propagator.device_tables(monitor.columns, monitor.share, self.save_every, width)
            self._compiled = {k: v for k, v in self._compiled.items() if k[0] != "modal"}  # an older propagator's
            self._compiled[key] = self.runner.put(tables)
        return self._compiled[key]

    def lowered_apply_text(self, state, buffer, steps: int, probe: bool = True, modal=None) -> str:
        """The compiled HLO text of a monitored cycle's second half (to count its
        collectives)."""
        self.prepare_monitored(state, buffer, steps, probe, modal)
        return self._compiled[("apply", steps, probe, 3 if modal is None else 4)].as_text()


class CycleRejected(Stopped):
    """A monitored cycle whose es_hat [cm] or estimated error [cm] (``estimate``; NaN when
    es_hat rejected it first) exceeded the tolerance [cm]; the run goes back to its last
    synchronized state."""

    def __init__(self, step: int, es_hat: float, tolerance: float, estimate: float = float("nan")):
        what = f"es_hat {es_hat:.3g} cm" if np.isnan(estimate) else f"estimated error {estimate:.3g} cm"
        super().__init__(f"cycle after step {step} rejected: {what} > {tolerance:.3g} cm")
        self.step, self.es_hat, self.tolerance, self.estimate = step, es_hat, tolerance, estimate


class _PredictedRunnerBase:
    """What both predicted runners share: the compiled phase, the global field of the
    parts' local fields, and the state ``(per-part SolverState, buffer, step)``."""

    def __init__(self, phase: PredictedPhase, cycle_steps: int):
        self.phase = phase
        self.partition = phase.runner.partition
        self.save_every, self.cycle_steps = phase.save_every, cycle_steps
        self.n_nodes = phase.runner.n_nodes

    def _compiled_delta(self, compile_something) -> float:
        before = self.phase.compile_seconds
        compile_something()
        return self.phase.compile_seconds - before

    def _chunk(self, disp, pred) -> Chunk:
        """``disp`` (P, ..., n_local, 3) and ``pred`` (P, ..., n_dof) on the devices -> a
        :class:`Chunk` (global field: mean over the parts that hold each node)."""
        disp, pred = to_host(disp), to_host(pred)
        disp = disp.reshape(disp.shape[0], -1, *disp.shape[-2:])
        pred = pred.reshape(pred.shape[0], -1, pred.shape[-1])
        return Chunk(self.phase.runner.merge(disp, mean=True), None, pred)


class PredictedRunner(_PredictedRunnerBase):
    """The unmonitored predicted phase: ``cycles_per_chunk`` refill cycles per compiled
    call (the fused program), the last partial cycle alone."""

    def __init__(self, phase: PredictedPhase, cycle_steps: int, cycles_per_chunk: int):
        super().__init__(phase, cycle_steps)
        self.cycles_per_chunk = cycles_per_chunk

    def _split(self, steps: int) -> tuple[int, int]:
        """(cycles, steps per cycle) of a chunk of ``steps``."""
        return (steps // self.cycle_steps, self.cycle_steps) if steps >= self.cycle_steps else (1, steps)

    def chunk_steps(self, steps_left: int, preferred: int) -> int:
        if steps_left < self.cycle_steps:
            return steps_left
        return min(self.cycles_per_chunk, steps_left // self.cycle_steps) * self.cycle_steps

    def compile(self, state, steps: int) -> float:
        solver_state, buffer, _ = state
        return self._compiled_delta(lambda: self.phase.prepare(solver_state, buffer, *self._split(steps)))

    def advance(self, state, steps: int):
        solver_state, buffer, step0 = state
        solver_state, buffer, disp, pred = self.phase.run(solver_state, buffer, step0, *self._split(steps))
        return (solver_state, buffer, step0 + steps), self._chunk(disp, pred)


class MonitoredRunner(_PredictedRunnerBase):
    """The monitored predicted phase: one refill cycle per call, predicted ahead, its
    es_hat (paper eq. 26) checked at the saved steps against ``tolerance`` [cm] before the
    solver uses it; then, with a ``propagator``
    (:class:`~jaxsync.solve.coupling.ErrorPropagator`), run with the force-balance
    defect probed at the saved steps and the estimated error accumulated since the last
    synchronized state checked against the same tolerance. :class:`CycleRejected` when
    either is above it (or not finite). ``estimates`` holds the accepted cycles'
    estimates, one per saved step [cm]."""

    def __init__(self, phase: PredictedPhase, cycle_steps: int, tolerance: float, monitor, propagator=None):
        super().__init__(phase, cycle_steps)
        self.tolerance, self.monitor, self.propagator = float(tolerance), monitor, propagator
        self.error_state = None if propagator is None else propagator.zero_state()
        self.estimates: list[np.ndarray] = []

    def chunk_steps(self, steps_left: int, preferred: int) -> int:
        return min(self.cycle_steps, steps_left)

    def _modal(self):
        return None if self.propagator is None else self.phase.modal_tables(self.propagator, self.monitor)

    def compile(self, state, steps: int) -> float:
        solver_state, buffer, _ = state
        return self._compiled_delta(lambda: self.phase.prepare_monitored(solver_state, buffer, steps,
                                                                         self.propagator is not None, self._modal()))

    def advance(self, state, steps: int):
        solver_state, buffer, step0 = state
        pred, next_buffer, kept = self.phase.rollout(buffer, step0, steps)
        kept = to_host(kept)  # (P, steps / save_every, n_dof)
        es_hat = self.monitor.es_hat(kept) if np.isfinite(kept).all() else np.array([np.inf])
        if not es_hat.max() <= self.tolerance:
            raise CycleRejected(step0, float(es_hat.max()), self.tolerance)
        if self.propagator is None:
            solver_state, disp = self.phase.apply(solver_state, pred, steps)
        else:
            solver_state, (disp, (defects, modal)) = self.phase.apply(solver_state, pred, steps, probe=True,
                                                                      modal=self._modal())
            error_state, estimates = self.propagator.propagate(
                self.error_state, self.monitor.interface_values(to_host(defects)), self.save_every,
                modal=to_host(modal).sum(axis=0))
            if not estimates.max(initial=0.0) <= self.tolerance:
                raise CycleRejected(step0, float(es_hat.max()), self.tolerance,
                                    float(np.nan_to_num(estimates.max(), nan=np.inf)))
            self.error_state = error_state
            self.estimates.append(estimates)
        return (solver_state, next_buffer, step0 + steps), self._chunk(disp, kept)


class DisagreementMonitor:
    """es_hat (paper eq. 26) of the parts' own predictions, for the live error control."""

    def __init__(self, partition):
        from ...metrics import shared_node_errors

        self._errors = shared_node_errors
        index = {int(node): k for k, node in enumerate(partition.shared_nodes)}
        self.columns = [np.array([index[int(n)] for n in part.shared_nodes], dtype=int)
                        for part in partition.parts]
        self.counts = [3 * len(cols) for cols in self.columns]
        self.holds = np.zeros((partition.n_parts, len(partition.shared_nodes)), bool)
        for p, cols in enumerate(self.columns):
            self.holds[p, cols] = True
        #: (n_interface,) 1 / the number of parts that hold each shared node
        self.share = 1.0 / np.maximum(self.holds.sum(axis=0), 1)

    def interface_values(self, values) -> np.ndarray:
        """(T, n_interface, 3): the mean over the parts that hold each shared node of the
        parts' values ``values`` (P, T, n_shared_max, 3) (their shared-node slots)."""
        n_parts, T = values.shape[:2]
        total = np.zeros((T, self.holds.shape[1], 3))
        for p, cols in enumerate(self.columns):
            total[:, cols] += values[p, :, :len(cols)]
        return total / np.maximum(self.holds.sum(axis=0), 1)[None, :, None]

    def es_hat(self, pred) -> np.ndarray:
        """(T,) es_hat of predictions (P, T, n_dof) [cm]."""
        n_parts, T = pred.shape[:2]
        by_node = np.zeros((n_parts, T, self.holds.shape[1], 3))
        for p, cols in enumerate(self.columns):
            by_node[p][:, cols] = pred[p, :, :self.counts[p]].reshape(T, -1, 3)
        return self._errors(np.zeros(by_node.shape[1:]), by_node, self.holds).es_hat
