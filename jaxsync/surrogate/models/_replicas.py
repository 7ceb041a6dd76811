"""Replicas: one network per part, padded to the largest part and stacked on a leading
part axis, so that all parts train and predict in one program.

Parts have different shared-dof counts.  A replica of ``n`` dofs is zero-padded to the
common width: the first encoder layer's and the decoder's input columns of the dof block
(before the q load-parameter columns) and the dense layer's output rows.  With zero
inputs on padding and outputs forced to zero there (the dof mask), the padded
parameters get zero gradients and stay zero, so each replica computes what it would
alone.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxsync.errors import ConfigError

Params = Any

# the dof axis of each linear-highway parameter (jaxsync.surrogate.models.param_shapes)
_HIGHWAY_DOF_AXIS = {"w_in": 1, "w_out": 2, "b": 1, "w_load": None}

__all__ = ["pad_params", "unpad_params", "stack_params", "replica_params", "init_replicas", "count_parameters"]


def pad_params(params: Params, arch, n_dof: int) -> Params:
    """Zero-pad one LSTM replica's parameters (``arch`` its
    :class:`~jaxsync.surrogate.models.LSTMArchitecture`) from ``arch.n_dof`` to ``n_dof`` dofs.

    Pads the first encoder layer's input columns, the decoder's input columns (the dof
    block, before the q load-parameter columns), the dense layer's output rows and the
    linear highway's dof axes (a network with one).
    """
    extra = n_dof - arch.n_dof
    if extra < 0:
        raise ConfigError(f"cannot pad {arch.n_dof} dofs down to {n_dof}")

    def pad_cols(w, start):
        return jnp.concatenate([w[:, :start], jnp.zeros((w.shape[0], extra), w.dtype), w[:, start:]], axis=1)

    encoder = [dict(layer) for layer in params["encoder"]]
    encoder[0] = {
        direction: {**cell, "w_d": pad_cols(cell["w_d"], arch.n_dof)} for direction, cell in encoder[0].items()
    }
    decoder = {**params["decoder"], "w_d": pad_cols(params["decoder"]["w_d"], arch.n_dof)}
    dense = {
        "w": jnp.pad(params["dense"]["w"], ((0, extra), (0, 0))),
        "b": jnp.pad(params["dense"]["b"], (0, extra)),
    }
    padded = {"encoder": encoder, "decoder": decoder, "dense": dense}
    if "highway" in params:  # the linear highway's dof axes
        padded["highway"] = {name: jnp.pad(w, [(0, extra if axis == _HIGHWAY_DOF_AXIS[name] else 0)
                                               for axis in range(w.ndim)])
                             for name, w in params["highway"].items()}
    return padded


def unpad_params(params: Params, arch, n_dof: int) -> Params:
    """Inverse of :func:`pad_params`: keep the first ``n_dof`` dofs of a padded replica."""
    q = arch.n_cond_repeat

    def cut_cols(w):
        return jnp.concatenate([w[:, :n_dof], w[:, arch.n_dof:arch.n_dof + q]], axis=1)

    encoder = [dict(layer) for layer in params["encoder"]]
    encoder[0] = {d: {**cell, "w_d": cell["w_d"][:, :n_dof]} for d, cell in encoder[0].items()}
    decoder = {**params["decoder"], "w_d": cut_cols(params["decoder"]["w_d"])}
    dense = {"w": params["dense"]["w"][:n_dof], "b": params["dense"]["b"][:n_dof]}
    cut = {"encoder": encoder, "decoder": decoder, "dense": dense}
    if "highway" in params:
        cut["highway"] = {name: jnp.take(w, jnp.arange(n_dof), axis=_HIGHWAY_DOF_AXIS[name])
                          if _HIGHWAY_DOF_AXIS[name] is not None else w for name, w in params["highway"].items()}
    return cut


def stack_params(replicas: list[Params]) -> Params:
    """Stack equally shaped replicas on a new leading axis."""
    return jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *replicas)


def replica_params(stacked: Params, index: int) -> Params:
    """The ``index``-th replica of stacked parameters (still padded)."""
    return jax.tree_util.tree_map(lambda leaf: leaf[index], stacked)


def init_replicas(key: jax.Array, arch, dof_counts: tuple[int, ...]) -> Params:
    """Initial stacked parameters of one replica per part: the model's own
    ``arch.init_replicas(key, dof_counts)`` (:mod:`jaxsync.surrogate.models`; for the
    LSTM, replica r is ``init_params(fold_in(key, r))`` at its own dof count, so it equals
    a replica initialized alone, zero-padded to ``arch.n_dof``)."""
    return arch.init_replicas(key, tuple(int(c) for c in dof_counts))


def count_parameters(params: Params) -> int:
    """Number of scalar parameters in a pytree."""
    return int(sum(np.size(leaf) for leaf in jax.tree_util.tree_leaves(params)))
