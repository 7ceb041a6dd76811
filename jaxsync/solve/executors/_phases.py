"""The phases of a run and what one part computes in each: the pure functions that both
executors run.

A run is a schedule of phases: :class:`SynchronizedSteps` (paper Algorithm 1: every step
completes the parts' shared-node forces, or with deep halos their displacements every k
steps) and :class:`PredictedSteps` (paper Algorithm 3: refill cycles of the surrogates,
no exchange). The host executor (:mod:`jaxsync.solve.executors`) compiles these functions into
chunks it drives from Python; the traced executor (:mod:`jaxsync.solve.executors`) composes
them into one JAX program. Both call the functions below, so the numerics of a phase are
written once:

* :func:`synchronized_steps` -- one part (or the whole mesh on one device) through
  synchronized steps, saving every ``save_every`` steps and optionally recording the
  shared-node displacements after every step;
* :func:`predict_cycle` -- one refill: the part's shared-node displacements for the next
  n_s n_f steps from the last n_s n_p (:func:`jaxsync.surrogate.refill_cycle`);
* :func:`overwritten_steps` -- steps without exchange, each followed by writing the
  predictions into the part's shared nodes;
* :func:`refill_steps` -- one refill cycle, the two above in sequence, and
  :func:`predicted_cycles` -- a loop of them.

``adjoint`` (None: the plain loops of the host's compiled chunks; a
:class:`~jaxsync.solve.Recompute` or ``StoreAll``: the traced executor's
reverse-pass policy) only chooses how the same loop is written (:mod:`jaxsync.solve`).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from ...errors import ConfigError, ProblemError
from ...fem._stepper import ExplicitSystem, Probe, SolverState, advance, central_difference
from ...parallel._layout import PartSystems
from ...parallel.exchange._halo import advance_halo
from ...parallel.exchange._index_maps import Exchange
from ...surrogate._refill import refill_cycle
from .._remat import advance_traced, recomputing_scan, segment_steps, state_bytes

__all__ = ["SynchronizedSteps", "PredictedSteps", "synchronized_steps", "part_synchronized_steps", "check_recordable",
           "predict_cycle",
           "overwritten_steps", "defect_probe", "refill_steps", "predicted_cycles"]


@dataclasses.dataclass(frozen=True)
class SynchronizedSteps:
    """``n_steps`` synchronized steps (paper Algorithm 1)."""

    n_steps: int

    def __post_init__(self):
        if isinstance(self.n_steps, bool) or not int(self.n_steps) == self.n_steps or self.n_steps < 0:
            raise ProblemError(f"a phase needs a whole number of steps >= 0, got {self.n_steps!r}")
        object.__setattr__(self, "n_steps", int(self.n_steps))


@dataclasses.dataclass(frozen=True)
class PredictedSteps(SynchronizedSteps):
    """``n_steps`` predicted steps (paper Algorithm 3): refill cycles of n_s n_f steps, the
    last one partial when n_steps is not a whole number of cycles."""


# --------------------------------------------------------------------------- synchronized


def synchronized_steps(system: ExplicitSystem, state: SolverState, n_saves: int, save_every: int, *,
                       synchronize=None, record=None, adjoint=None):
    """``n_saves * save_every`` steps of ``system`` (the whole mesh, or one part whose
    forces ``synchronize`` completes): :func:`jaxsync.fem.advance`'s outputs,
    written as a plain loop (``adjoint`` None) or with ``adjoint``'s reverse pass
    (:func:`jaxsync.solve._remat.advance_traced`)."""
    if adjoint is None:
        return advance(system, state, n_saves, save_every, synchronize=synchronize, record=record)
    return advance_traced(system, state, n_saves, save_every, adjoint, synchronize=synchronize, record=record)


def check_recordable(exchange: Exchange) -> None:
    """Refuse to record every step's shared-node displacements where they are not known:
    with deep halos, inside an exchange cycle only the nodes a part owns are right, and
    another part's shared nodes are not (a :class:`~jaxsync.errors.ConfigError` naming the
    fix)."""
    if exchange.halo_depth is not None:
        raise ConfigError(
            "sync='halo' cannot record the shared-node displacements after every step (the surrogates' "
            "training data, the synchronization-avoiding solver's synchronized phases): inside an exchange "
            "cycle only the nodes a part owns are right, not the nodes it shares; use sync='psum' or "
            "'ppermute' there")


def part_synchronized_steps(part: PartSystems, state: SolverState, n_saves: int, save_every: int,
                            exchange: Exchange, *, record: bool = False, adjoint=None):
    """One part's synchronized steps: its forces completed every step by ``exchange``, or
    with deep halos (``exchange.halo_depth``) its halo refreshed every k steps. Returns
    (state, saved (n_saves, n_local, 3)), with ``record`` the pair (saved, the shared-node
    displacements after every step (n_saves * save_every, n_shared_max, 3))."""
    if exchange.halo_depth is None:
        return synchronized_steps(part.system, state, n_saves, save_every, synchronize=exchange.force_sum(part),
                                  record=part.shared_displacement if record else None, adjoint=adjoint)
    if record:
        check_recordable(exchange)
    loop = None
    if adjoint is not None:
        unit = max(save_every, exchange.halo_depth)  # the steps of one iteration of the outer loop
        segment = segment_steps(adjoint, n_saves * save_every // unit, unit * state_bytes(state.displacement.shape[-2]))
        if segment is not None:
            def loop(body, carry, n):
                return recomputing_scan(body, carry, n, segment)
    return advance_halo(part, state, n_saves, save_every, exchange, loop=loop)


# --------------------------------------------------------------------------- predicted


def predict_cycle(predictor, buffer, last, steps: int, save_every: int):
    """One part's refill, predicted ahead of the solver: (predictions (n_s n_f, n_dof) of
    steps last + 1 ..., the buffer moved on by them, the predictions at the saved steps
    among the first ``steps`` (steps // save_every, n_dof))."""
    pred, buffer = refill_cycle(predictor, buffer, last)
    return pred, buffer, pred[save_every - 1:steps:save_every]


def overwritten_steps(part: PartSystems, state: SolverState, pred, modal=None, *, steps: int, save_every: int,
                      probe: Exchange | None = None):
    """One part: ``steps`` solver steps without synchronization, each followed by writing
    the predicted shared-node displacements ``pred[j]`` into the part's state (the
    stepper's loop, :func:`jaxsync.fem.advance`, with an overwrite).

    ``probe``: None, or the run's exchange: then each part also measures its
    force-balance defect at its shared nodes, summed over each ``save_every`` steps, with
    one exchange of partial forces at every saved step (:func:`defect_probe`;
    :mod:`jaxsync.solve.coupling`), and, with ``modal`` (its tables, see
    :func:`defect_probe`), its share of the modal error's response to every step's defect.

    Returns (state, saved displacement (steps // save_every, n_local, 3)), with ``probe``
    (state, (saved, defect sums (steps // save_every, n_shared_max, 3) [cm])), with
    ``modal`` too (state, (saved, (defect sums, modal responses (steps // save_every,
    n_modes, 2))))."""
    nodes = pred.reshape(pred.shape[0], -1, 3)
    n_shared = nodes.shape[1]
    # each local node's slot among the part's shared nodes (n_shared for the others): the
    # overwrite is then a gather and a select that XLA fuses into the step, where a
    # scatter of the shared nodes cost as much as the rest of the step (the 11-part
    # vessel on 2 CPU devices: 200 us per step against 110 us for the step without it)
    slot = jnp.full(state.displacement.shape[-2], n_shared, jnp.int32).at[part.shared_local].set(
        jnp.arange(n_shared, dtype=jnp.int32), mode="drop")
    held = (slot < n_shared)[:, None]

    def overwrite(j, new):
        return jnp.where(held, jnp.take(nodes[j], slot, axis=0, mode="clip"), new)

    return advance(part.system, state, steps // save_every, save_every, overwrite=overwrite,
                   probe=None if probe is None else defect_probe(part, probe, modal))


def defect_probe(part: PartSystems, exchange: Exchange, modal=None):
    """The force-balance defect of one part, summed over each ``save_every`` steps, as a
    :class:`~jaxsync.fem.Probe`.

    A step's defect at the part's shared dofs is delta = kept - balanced: what the part
    kept there (its prediction, the Dirichlet values) minus the synchronized update of
    the same state. The synchronized update differs from the part's own update ``u``
    (from its partial force f_p) by L(f - f_p), L the linear map from a force change to
    the update's change (dt^2 / (m (1 + alpha dt / 2)) per dof, or the dashpot's 3 x 3
    solve), f the summed force. L is the same every step, so over a block of steps
    sum(delta) = sum(kept - u) + L(sum(f) - sum(f_p)): each part sums kept - u and f_p at
    its shared nodes locally, and one exchange of the summed partial forces at the end of
    the block completes it (exact; every step's defect counted, none sampled). Zero on
    prescribed dofs and in padding slots. Returns the (n_shared_max, 3) block sums [cm].

    ``modal``: None, or ``(injection, share, response)``: the part's rows of the modal
    injection phi^T M at its shared slots, (n_shared_max, 3, n_modes), 1 / c at each slot
    (c the parts that hold its node; 0 in padding), (n_shared_max,), and the response of every
    mode's (q(n), q(n-1)) a block's end to a unit injection ``save_every - 1 - j`` steps
    before it, (save_every, n_modes, 2) (:meth:`~jaxsync.solve.coupling.ErrorPropagator.device_tables`).
    Then the probe also returns, per block, this part's share of the modal error's
    response to each of its steps' defects, at the step it happened: the mean defect over
    the parts that hold a shared node is a sum over the parts of (kept - u) / c - (1 -
    1 / c) L f_p (c the parts that hold it), each term the part's own, so every part
    drives the modes with its share every step and no exchange is needed; the host adds
    the parts' shares (:meth:`~jaxsync.solve.coupling.ErrorPropagator.propagate`).
    Returns then (block sums, (n_modes, 2) modal responses)."""
    system, total = part.system, exchange.force_sum(part)
    zero = jnp.zeros_like(system.mass)
    still = SolverState(zero, zero, jnp.asarray(0, dtype=jnp.int32))
    free = ~system.fixed.at[part.shared_local].get(mode="fill", fill_value=True)

    def at_shared(field):
        return field.at[part.shared_local].get(mode="fill", fill_value=0.0)

    def linear_update(field):
        # L(g) = central_difference(g) - central_difference(0) of any state (it is affine in g)
        return central_difference(system, still, field) - central_difference(system, still, zero)

    if modal is not None:
        injection, share, response = modal
        every = response.shape[0]
        # the part's share of a step's mean defect, projected on the modes: (kept - u) . a + f_p . b
        # with a = injection / c and b = -(1 - 1/c) L^T injection (L per node, 3 x 3 with dashpots)
        share = share.astype(zero.dtype)[:, None, None]
        columns = [at_shared(linear_update(zero.at[part.shared_local, c].set(1.0, mode="drop")))
                   for c in range(3)]
        lmat = jnp.stack(columns, axis=-1)  # (n_shared_max, 3, 3): L at each shared node
        mask = free[..., None].astype(zero.dtype)
        injection = injection.astype(zero.dtype)
        kept_gain = mask * injection * share
        force_gain = -(1.0 - share) * jnp.einsum("icd,ick->idk", lmat, mask * injection)
        response = response.astype(zero.dtype)

    def per_step(state, internal, updated, new_state):
        kept, own = at_shared(new_state.displacement - updated), at_shared(internal)
        if modal is None:
            return kept, own
        drive = jnp.einsum("ic,ick->k", kept, kept_gain) + jnp.einsum("ic,ick->k", own, force_gain)
        weight = response[every - 1 - jnp.mod(state.step, every)]  # this step's place in its block
        return kept, own, weight * drive[:, None]

    def initial(state):
        shape = part.shared_local.shape + (3,)
        sums = (jnp.zeros(shape, zero.dtype), jnp.zeros(shape, zero.dtype))
        return sums if modal is None else sums + (jnp.zeros(response.shape[1:], zero.dtype),)

    def finish(sums):
        kept, own = sums[:2]
        own_field = zero.at[part.shared_local].set(own, mode="drop")
        change = linear_update(total(own_field) - own_field)
        defects = jnp.where(free, kept - at_shared(change), 0.0)
        return defects if modal is None else (defects, sums[2])

    return Probe(per_step, initial, finish)


def refill_steps(part: PartSystems, predictor, carry, steps: int, save_every: int):
    """One refill cycle of one part: :func:`predict_cycle`, then :func:`overwritten_steps`
    through ``steps`` (n_s n_f, or fewer for a run's last partial cycle) of them.

    ``carry``: (state, buffer (n_s n_p, n_dof) of the steps up to ``last``, ``last``).
    Returns (carry moved on by ``steps``, (saved displacement (steps // save_every,
    n_local, 3), the predictions at the saved steps (steps // save_every, n_dof)))."""
    state, buffer, last = carry
    pred, buffer, kept = predict_cycle(predictor, buffer, last, steps, save_every)
    state, saved = overwritten_steps(part, state, pred, steps=steps, save_every=save_every)
    return (state, buffer, last + steps), (saved, kept)


def predicted_cycles(part: PartSystems, predictor, carry, n_cycles: int, steps: int, save_every: int, *,
                     adjoint=None):
    """``n_cycles`` refill cycles of ``steps`` steps each (:func:`refill_steps`), as one
    loop: plain (``adjoint`` None or all cycles stored) or in recomputed segments of about
    sqrt(n_cycles) cycles. Returns (carry, (saved (n_cycles, steps // save_every, n_local,
    3), predictions at the saved steps (n_cycles, steps // save_every, n_dof)))."""
    def body(c, _):
        return refill_steps(part, predictor, c, steps, save_every)

    state = carry[0]
    segment = None if adjoint is None else segment_steps(adjoint, n_cycles, steps * state_bytes(
        state.displacement.shape[-2]))
    if segment is None:
        return jax.lax.scan(body, carry, None, length=n_cycles)
    return recomputing_scan(body, carry, n_cycles, segment)
