"""The training loss of the surrogate models: the masked, weighted mean squared error of
a model's ``forward`` over windows (what
:meth:`~jaxsync.surrogate.models.SurrogateArchitecture.loss` returns by default, and
gradient training and online learning minimise)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["masked_mse"]


def masked_mse(params, arch, x, y, load_parameter, weight, dof_mask, signals=None):
    """Weighted mean squared error of one replica over windows, steps and real dofs.

    Args:
        params: one replica's parameters; arch: its model.
        x: (B, n_p, D) inputs; y: (B, n_f, D) targets (normalized).
        load_parameter: (B,) load parameter of each window (read by conditional models).
        weight: (B,) window weights (0 for the filler of a short last batch).
        dof_mask: (D,) 1 on real dofs.
        signals: (B, n_p + n_f, L) load signals of each window (read when L > 0).
    """
    load_axis = 0 if arch.conditional else None
    signal_axis = 0 if arch.n_load else None
    pred = jax.vmap(lambda xs, q, u: arch.forward(params, xs, q, dof_mask, None, u),
                    in_axes=(0, load_axis, signal_axis))(
        x, load_parameter if arch.conditional else None, signals if arch.n_load else None)
    sq = jnp.square(pred - y) * dof_mask[None, None]
    per_window = jnp.sum(sq, axis=(1, 2)) / (arch.n_future * jnp.maximum(jnp.sum(dof_mask), 1.0))
    return jnp.sum(weight * per_window) / jnp.sum(weight)
