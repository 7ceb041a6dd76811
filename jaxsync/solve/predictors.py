"""Predictors of the partition-shared displacements for the synchronization-avoiding
solver.

A predictor is a pytree whose arrays are stacked on a leading part axis, with a method
``predict(buffer, step) -> (n_s n_f, n_dof)`` for ONE part: ``buffer`` (n_s n_p, n_dof)
holds the part's shared dofs at steps step - n_s n_p + 1 .. step (``step`` the last known
one), and the predictions are for steps step + 1 .. step + n_s n_f. Static sizes
``n_s``, ``n_past``, ``n_future``.

:class:`jaxsync.surrogate.Surrogate` (trained LSTM replicas) and :class:`OraclePredictor`
(replays known displacements; pins the coupling independently of network error).
"""

from __future__ import annotations

from typing import Any

import jax

from ..pytree import pytree_dataclass, static_field

__all__ = ["OraclePredictor"]


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
