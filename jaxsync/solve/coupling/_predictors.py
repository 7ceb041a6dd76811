"""Predictors of the partition-shared displacements for the synchronization-avoiding
solver.

A predictor is a pytree whose arrays are stacked on a leading part axis, with a method
``predict(buffer, step) -> (n_s n_f, n_dof)`` for ONE part: ``buffer`` (n_s n_p, n_dof)
holds the part's shared dofs at steps step - n_s n_p + 1 .. step (``step`` the last known
one), and the predictions are for steps step + 1 .. step + n_s n_f. Static sizes
``n_s``, ``n_past``, ``n_future``.

:class:`jaxsync.surrogate.Surrogate` (trained replicas of any surrogate model: the LSTM, the
linear one or a registered model, :mod:`jaxsync.surrogate.models`) and :class:`OraclePredictor`
(replays known displacements; pins the coupling independently of network error).
"""

from __future__ import annotations

from typing import Any

import jax

from ...errors import CheckpointError, ProblemError
from ...pytree import pytree_dataclass, static_field

__all__ = ["OraclePredictor", "predictor_for"]


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


def predictor_for(surrogates, partition, problem=None, dt=None):
    """The predictor of ``surrogates`` for ``partition``, checked to fit it, and bound to
    the load signals of ``problem`` at time step ``dt`` (default ``problem.dt``) when it
    reads them (:meth:`jaxsync.surrogate.Surrogate.for_problem`: refused for other loads).

    ``surrogates``: a :class:`jaxsync.surrogate.Surrogate` or :class:`OraclePredictor`
    (anything with ``predict``, ``n_s``, ``n_past``, ``n_future``), or the record of a
    surrogate file (its shared node ids checked against the partition's). Raises
    :class:`~jaxsync.errors.ProblemError` for anything else (a path: with the fix) and
    :class:`~jaxsync.errors.CheckpointError` for surrogates of another partition."""
    from ...io.surrogate_file import SavedSurrogate, check_compatible
    from ...surrogate._model import Surrogate
    from ...surrogate.training._histories import shared_dof_layout

    if isinstance(surrogates, (str, bytes)) or hasattr(surrogates, "__fspath__"):
        raise ProblemError(f"surrogates={surrogates!r} is a path: load the surrogate file first, "
                           "jaxsync.surrogate.load_surrogate(path) (its shared nodes are checked against the "
                           "partition), or jaxsync.surrogate.Surrogate.load(path)")
    n_dof, _ = shared_dof_layout(partition)
    if isinstance(surrogates, SavedSurrogate):
        check_compatible(surrogates, [p.shared_nodes for p in partition.parts])
        surrogates = Surrogate.from_saved(surrogates)
    if not all(hasattr(surrogates, a) for a in ("predict", "n_s", "n_past", "n_future")):
        raise ProblemError(f"surrogates must be a jaxsync.surrogate.Surrogate, an OraclePredictor or a loaded "
                           f"surrogate file, got {type(surrogates).__name__}")
    made_for = (getattr(surrogates, "n_parts", partition.n_parts), getattr(surrogates, "n_dof", n_dof))
    if made_for != (partition.n_parts, n_dof):
        raise CheckpointError(f"the surrogates were made for {made_for[0]} parts of {made_for[1]} shared dofs "
                              f"but this partition has {partition.n_parts} parts of up to {n_dof}: pass the "
                              "partition they were trained on, or retrain on this one")
    if problem is not None and hasattr(surrogates, "for_problem"):
        surrogates = surrogates.for_problem(problem, dt)
    return surrogates
