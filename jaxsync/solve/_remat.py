"""Reverse mode through long explicit runs in bounded memory (recomputation).

The loops of the traced executor (:mod:`jaxsync.solve.executors`): the same steps as the
host's (:func:`jaxsync.fem.advance`), with a reverse pass chosen by the run's
adjoint (:class:`jaxsync.solve.Recompute` or ``StoreAll``).

``jax.grad`` through the one ``lax.scan`` of :func:`jaxsync.fem.advance` keeps
the residuals of every step: two (n_nodes, 3) float64 fields per step (d(n) for the
derivative of K d(n) in the Lame parameters, d(n-1) for the damping term), so memory
grows like n_steps. :func:`advance_recomputing` computes the same values, but splits
the time loop into segments whose bodies are ``jax.checkpoint``-ed: the forward pass
keeps only the states at segment boundaries, and the reverse pass recomputes one
segment at a time from its boundary state (one extra forward run). With segments of
about sqrt(n_steps) steps the reverse pass holds about 2 sqrt(n_steps) states plus the
saved outputs, for one more forward pass of compute.

When ``save_every`` exceeds the segment length (few saves, many steps between them),
the steps of one save are themselves split into recomputed sub-segments of about
sqrt(save_every) steps: memory is then n_saves + 2 sqrt(save_every) states, for two
extra forward passes.

"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ProblemError
from ..fem._stepper import STEP_UNROLL, ExplicitSystem, SolverState, advance, step

__all__ = ["advance_recomputing", "advance_traced", "recomputing_scan", "segment_steps_for_budget",
           "segment_length", "segment_steps", "state_bytes", "step_residual_bytes"]


def state_bytes(n_nodes: int, itemsize: int = 8) -> int:
    """Bytes of one state's two (n_nodes, 3) displacement levels."""
    return 2 * 3 * int(n_nodes) * int(itemsize)


def step_residual_bytes(system: ExplicitSystem, itemsize: int = 8) -> int:
    """Estimated bytes reverse mode stores per step of ``system`` (one part's).

    With the symmetric node-blocked ELL stiffness of :func:`jaxsync.fem.build_system`,
    whose product has its own reverse pass (:class:`jaxsync.fem.BlockEll`,
    ``symmetric=True``: only u is kept): 3 (n_nodes, 3) fields, as measured on the coarse
    cantilever (compiled temp memory of plain reverse mode / n_steps: 3.03-3.12 fields).
    A general BlockEll keeps every gathered neighbour value, 3 width + 2 fields (29 on the
    cantilever, measured before the symmetric product). For the matrix-free stiffness only
    the two displacement levels are counted (a lower bound)."""
    from ..fem._sparse import BlockEll

    n_nodes = int(np.shape(system.mass)[-2])
    fields = 2
    if isinstance(system.stiffness, BlockEll):
        fields = 3 if system.stiffness.symmetric else 2 + 3 * int(np.shape(system.stiffness.columns)[-1])
    return fields * 3 * n_nodes * int(itemsize)


def segment_steps_for_budget(n_steps: int, bytes_per_step: int, budget_bytes: int | None = None) -> int | None:
    """Steps per recomputed segment for a reverse pass through ``n_steps`` steps that
    store ``bytes_per_step`` each (:func:`step_residual_bytes`).

    Returns None (no checkpointing: the plain scan, one forward pass less) when storing
    every step, ``n_steps * bytes_per_step``, fits in ``budget_bytes``; otherwise about
    sqrt(n_steps), the segment length that minimizes the steps held (boundaries plus one
    segment, about 2 sqrt(n_steps)). ``budget_bytes=None``: always checkpoint. A budget
    below that cannot be met by two levels of recomputation; the sqrt split is used
    anyway (the least memory this module offers)."""
    n_steps = int(n_steps)
    if budget_bytes is not None and n_steps * int(bytes_per_step) <= int(budget_bytes):
        return None
    return segment_length(n_steps)


def recomputing_scan(body, carry, n: int, length: int, unroll: int = 1):
    """``lax.scan(body, carry, None, length=n)`` in segments of ``length`` iterations,
    each ``jax.checkpoint``-ed: the reverse pass keeps the carry at segment boundaries and
    recomputes one segment at a time. The n % length iterations left over form one more
    (shorter) recomputed segment. Outputs are stacked (n, ...) as by the plain scan."""
    def segment(count):
        # prevent_cse=False: inside a scan the recomputation cannot be CSE'd away (the
        # JAX docs' advice), and the CSE barrier would only cost time
        @functools.partial(jax.checkpoint, prevent_cse=False)
        def run(c, _):
            return jax.lax.scan(body, c, None, length=count, unroll=unroll)
        return run

    n_full, rest = divmod(int(n), int(length))
    pieces = []
    if n_full:
        carry, ys = jax.lax.scan(segment(length), carry, None, length=n_full)
        pieces.append(jax.tree_util.tree_map(lambda y: y.reshape(n_full * length, *y.shape[2:]), ys))
    if rest:
        carry, ys = segment(rest)(carry, None)
        pieces.append(ys)
    if len(pieces) == 1:
        return carry, pieces[0]
    return carry, jax.tree_util.tree_map(lambda *ys: jnp.concatenate(ys), *pieces)


def advance_recomputing(system: ExplicitSystem, state: SolverState, n_saves: int, save_every: int,
                         *, segment_steps: int | None = None, synchronize=None, record=None):
    """:func:`jaxsync.fem.advance` with a bounded-memory reverse pass.

    Args:
        system: the (possibly traced) :class:`ExplicitSystem` (one part's, under
            ``shard_map``).
        state: the :class:`SolverState` to start from, fields (n_nodes, 3) [cm].
        n_saves, save_every: run ``n_saves * save_every`` steps, keeping the displacement
            after every ``save_every`` steps (static ints).
        segment_steps: steps per recomputed segment, the steps whose states the reverse
            pass holds at once (default about sqrt(n_saves * save_every)). Segments are
            whole saves when ``save_every <= segment_steps``; otherwise each save is one
            recomputed unit, split into sub-segments of about sqrt(save_every) steps.
        synchronize, record: see :func:`jaxsync.fem.advance` (the distributed
            exchange; a small array kept after every step).

    Returns:
        (final state, (n_saves, n_nodes, 3) saved displacements [cm]) -- with ``record``
        the pair (saved, recorded (n_saves * save_every, ...)) -- equal in value to
        :func:`~jaxsync.fem.advance` with the same arguments. Reverse-mode
        memory: about n_steps / segment_steps boundary states (:func:`state_bytes`) plus
        segment_steps steps' residuals (:func:`step_residual_bytes`), plus the outputs.
    """
    n_saves, save_every = int(n_saves), int(save_every)
    if n_saves < 1 or save_every < 1:
        raise ProblemError(f"need n_saves >= 1 and save_every >= 1, got {n_saves}, {save_every}")
    n_steps = n_saves * save_every
    length = segment_length(n_steps) if segment_steps is None else max(1, int(segment_steps))

    def one_step(s, _):
        s = step(system, s, synchronize)
        return s, None if record is None else record(s)

    def steps_of_save(s, scan):
        """One save's steps by ``scan``; (state, (displacement, rows or None))."""
        if save_every == 1:
            s, rows = one_step(s, None)
            rows = None if rows is None else rows[None]
        else:
            s, rows = scan(s)
        return s, (s.displacement, rows)

    def outputs(ys):
        saved, rows = ys
        return saved if record is None else (saved, rows.reshape(n_steps, *rows.shape[2:]))

    if save_every <= length:
        # segments of whole saves; a save's steps run in a plain (unrolled) scan
        def one_save(s, _):
            return steps_of_save(s, lambda c: jax.lax.scan(one_step, c, None, length=save_every,
                                                           unroll=STEP_UNROLL))

        s, ys = recomputing_scan(one_save, state, n_saves, max(1, length // save_every))
        return s, outputs(ys)

    # long saves: every save is a recomputed unit (n_saves boundary states), and its
    # steps run in recomputed sub-segments of about sqrt(save_every) steps
    inner = segment_length(save_every)

    def long_save(s, _):
        return steps_of_save(s, lambda c: recomputing_scan(one_step, c, save_every, inner, unroll=STEP_UNROLL))

    if n_saves == 1:
        # one save: its sub-segments alone (a checkpoint around them would only recompute
        # the whole run once more, for the same memory)
        s, (saved, rows) = long_save(state, None)
        return s, outputs((saved[None], None if rows is None else rows[None]))
    s, ys = recomputing_scan(long_save, state, n_saves, 1)
    return s, outputs(ys)


def segment_length(n_steps: int) -> int:
    """About sqrt(n_steps): the segment length that minimizes the states a recomputing
    reverse pass holds (boundaries plus one segment, about 2 sqrt(n_steps))."""
    return max(1, math.isqrt(max(int(n_steps), 1)))


def segment_steps(adjoint, n_steps: int, bytes_per_step: int) -> int | None:
    """Steps per recomputed segment of a traced loop of ``n_steps`` steps under
    ``adjoint`` (:class:`~jaxsync.solve.Recompute`: about sqrt(n_steps), or None
    when all steps fit its budget; :class:`~jaxsync.solve.StoreAll`: None,
    the plain scan)."""
    from ._strategies import Recompute

    if not isinstance(adjoint, Recompute):
        return None
    return segment_steps_for_budget(n_steps, bytes_per_step, adjoint.budget_bytes)


def advance_traced(system: ExplicitSystem, state: SolverState, n_saves: int, save_every: int, adjoint,
                   synchronize=None, record=None):
    """The time loop of a traced run: :func:`jaxsync.fem.advance`'s values, with
    the reverse pass of ``adjoint`` (:func:`segment_steps`: :func:`advance_recomputing`
    in segments, or the plain loop)."""
    segment = segment_steps(adjoint, n_saves * save_every, step_residual_bytes(system))
    if segment is None:
        return advance(system, state, n_saves, save_every, synchronize=synchronize, record=record)
    return advance_recomputing(system, state, n_saves, save_every, segment_steps=segment,
                                synchronize=synchronize, record=record)
