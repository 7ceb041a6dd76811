"""The traced executor: a run's schedule as one JAX program.

Used when any input is a JAX tracer (inside ``jax.grad``, ``jit`` or ``vmap``), or on
request (:class:`~jaxsync.solve.TracedExecutor`). It composes the same phase
functions as the host executor (:mod:`jaxsync.solve.executors`) into one program: the
synchronized steps (on one device, or every part under ``shard_map`` with its exchange),
then, in a synchronization-avoiding run, the refill cycles, written with the run's
reverse-pass policy (:mod:`jaxsync.solve`: memory about sqrt(n_steps) under
:class:`~jaxsync.solve.Recompute`). The parts' saved fields are merged into
the global one by :meth:`jaxsync.parallel.PartLayout.merge` (from the owner in
synchronized stretches, the mean over the parts after predicted ones). No host decision
runs inside: no progress, divergence check, checkpoint or re-synchronization; the
trajectory's ``result`` says whether every saved value is finite.
"""

from __future__ import annotations

import jax.numpy as jnp

from ...errors import ProblemError
from ...fem._stepper import ExplicitSystem, SolverState
from ...io.trajectory import Result
from ._phases import PredictedSteps, SynchronizedSteps, part_synchronized_steps, predicted_cycles, synchronized_steps

__all__ = ["run_traced", "TracedRun"]


class TracedRun(tuple):
    """What :func:`run_traced` returns: ``(saved, recorded, predictions, result)``.

    Attributes:
        saved: (n_saves, n_nodes, 3) global displacement at steps save_every, 2 save_every,
            ... of the schedule (the start is not included) [cm].
        recorded: per part, (n_steps, n_shared_max, 3) shared-node displacements after every
            step of a synchronized-only schedule when asked for, else None.
        predictions: (n_parts, n_predicted_saves, n_dof) each part's own predictions at the
            saved predicted steps, or None.
        result: int32 :class:`jaxsync.io.trajectory.Result` code.
    """

    saved = property(lambda self: self[0])
    recorded = property(lambda self: self[1])
    predictions = property(lambda self: self[2])
    result = property(lambda self: self[3])


def _result(*fields):
    finite = jnp.all(jnp.asarray([jnp.all(jnp.isfinite(f)) for f in fields if f is not None]))
    return jnp.where(finite, jnp.int32(Result.SUCCESSFUL), jnp.int32(Result.DIVERGED))


def run_traced(problem, system: ExplicitSystem, state: SolverState, schedule, *, save_every: int, adjoint,
               distributed=None, predictor=None, record: bool = False) -> TracedRun:
    """Run ``schedule`` (phases, :mod:`jaxsync.solve.executors`) from ``state`` as one traced
    program.

    Args:
        problem: the run's problem (traced values allowed).
        system: its global :class:`ExplicitSystem`.
        state: the global state to start from (its step counter carries on, for the loads'
            time functions).
        schedule: ``(SynchronizedSteps(n),)`` or ``(SynchronizedSteps(n_cri), PredictedSteps(n))``.
        save_every: the snapshot stride; divides every phase's steps and a refill cycle.
        adjoint: the reverse-pass policy (:class:`~jaxsync.solve.Recompute`,
            ``StoreAll``).
        distributed: the run's :class:`jaxsync.solve.executors.DistributedParts`, or
            None for one device.
        predictor: the surrogates (stacked on the part axis) of a schedule with a
            predicted phase (``n_s``, ``n_past``, ``n_future``, ``predict``).
        record: keep every part's shared-node displacements after every step (a
            synchronized-only distributed schedule).
    """
    kinds = tuple(type(p) for p in schedule)
    if kinds not in ((SynchronizedSteps,), (SynchronizedSteps, PredictedSteps)):
        raise ProblemError("a traced run takes the phases (SynchronizedSteps,) or (SynchronizedSteps, "
                           f"PredictedSteps), got {[k.__name__ for k in kinds]}")
    n_sync = schedule[0].n_steps
    if distributed is None:
        if len(schedule) > 1:
            raise ProblemError("a predicted phase needs a distributed run (the parts' shared nodes)")
        if n_sync == 0:
            saved = jnp.zeros((0,) + state.displacement.shape, state.displacement.dtype)
        else:
            _, saved = synchronized_steps(system, state, n_sync // save_every, save_every, adjoint=adjoint)
        return TracedRun((saved, None, None, _result(saved)))

    if distributed.transport == "mpi":  # the reason, not a missing feature
        raise ProblemError("sync='mpi' drives each process's parts from that process (the host executor); a "
                           "traced run is one JAX program in one process: trace distributed runs with "
                           "sync='psum', 'ppermute' or 'halo' over the devices of one process")
    layout, exchange = distributed.layout, distributed.exchange
    parts = distributed.systems(problem, system)
    local_state = layout.split_state(state)
    n_predicted = schedule[1].n_steps if len(schedule) > 1 else 0
    history = 0 if predictor is None else predictor.n_s * predictor.n_past
    cycle_steps = 0 if predictor is None else predictor.n_s * predictor.n_future
    n_dof = 0 if predictor is None else predictor.n_dof

    def one_part(part, predict, s: SolverState):
        out = {}
        if not n_predicted:  # synchronized only, every step recorded when asked
            if n_sync:
                s, saved = part_synchronized_steps(part, s, n_sync // save_every, save_every, exchange,
                                                   record=record, adjoint=adjoint)
                out["synchronized"], out["recorded"] = saved if record else (saved, None)
            return out
        # the synchronized steps; the last n_s n_p of them record the networks' first history
        before = n_sync - history
        before_saves, before_rest = divmod(before, save_every)
        first_save = (-before - 1) % save_every  # the history's first step that ends a save
        pieces = []
        if before_saves:
            s, saved = part_synchronized_steps(part, s, before_saves, save_every, exchange, adjoint=adjoint)
            pieces.append(saved)
        if before_rest:
            s, _ = part_synchronized_steps(part, s, 1, before_rest, exchange)
        s, (every_step, rows) = part_synchronized_steps(part, s, history, 1, exchange, record=True)
        pieces.append(every_step[first_save::save_every])
        out["synchronized"] = jnp.concatenate(pieces)
        buffer = rows.reshape(history, -1)
        buffer = jnp.pad(buffer, ((0, 0), (0, n_dof - buffer.shape[1])))
        # the refill cycles, then a last partial one from the first rows of its refill
        n_cycles, rest = divmod(n_predicted, cycle_steps)
        carry = (s, buffer, s.step)  # the last known step
        saved, kept = [], []
        if n_cycles:
            carry, (disp, pred) = predicted_cycles(part, predict, carry, n_cycles, cycle_steps, save_every,
                                                   adjoint=adjoint)
            saved.append(disp.reshape(-1, *disp.shape[2:]))
            kept.append(pred.reshape(-1, pred.shape[-1]))
        if rest:
            _, (disp, pred) = predicted_cycles(part, predict, carry, 1, rest, save_every)
            saved.append(disp[0])
            kept.append(pred[0])
        out["predicted"], out["kept"] = jnp.concatenate(saved), jnp.concatenate(kept)
        return out

    program = distributed.spmd(one_part, n_in=3, n_out=1, jit=False)
    out = program(parts, predictor, local_state)
    pieces = []
    if "synchronized" in out:
        pieces.append(layout.merge(out["synchronized"]))
    if "predicted" in out:
        pieces.append(layout.merge(out["predicted"], mean=True))
    saved = (jnp.concatenate(pieces) if pieces
             else jnp.zeros((0,) + state.displacement.shape, state.displacement.dtype))
    return TracedRun((saved, out.get("recorded"), out.get("kept"), _result(saved, out.get("kept"))))
