"""The surrogate models, one interface: dispatch on the architecture's type.

A surrogate model is a module with an architecture class (a static frozen dataclass with
``kind``, ``n_dof``, ``n_past``, ``n_future``, ``dtype``, ``conditional``,
``to_dict``/``from_dict``), ``init_params(key, arch)`` and
``forward(params, arch, xs, load_parameter, dof_mask, compute_dtype=None)`` mapping a
normalized window (n_p, n_dof) to (n_f, n_dof) (``compute_dtype="bfloat16"``: reduced-
precision inference).  Two exist (:data:`jaxsync.options.SurrogateModel`):

=========  =====================================================  ============================
kind       architecture                                           module
=========  =====================================================  ============================
"lstm"     :class:`~jaxsync.surrogate.lstm.LSTMArchitecture`      :mod:`jaxsync.surrogate.lstm`
"linear"   :class:`~jaxsync.surrogate.linear.LinearArchitecture`  :mod:`jaxsync.surrogate.linear`
=========  =====================================================  ============================

The refill (:mod:`jaxsync.surrogate.refill`) and the checkpoint files
(:mod:`jaxsync.surrogate.checkpoint`) go through :func:`forward`, :func:`init_params`,
:func:`architecture_to_dict` and :func:`architecture_from_dict`, so
:class:`~jaxsync.surrogate.Surrogate` and the solver hold either model alike.
"""

from __future__ import annotations

from types import ModuleType
from typing import Any, Union

import jax

from jaxsync.errors import ConfigError
from jaxsync.options import SurrogateModel, check_option
from jaxsync.surrogate import linear, lstm
from jaxsync.surrogate.linear import LinearArchitecture
from jaxsync.surrogate.lstm import LSTMArchitecture

__all__ = ["Architecture", "MODELS", "model_module", "architecture_to_dict", "architecture_from_dict",
           "init_params", "forward"]

Architecture = Union[LSTMArchitecture, LinearArchitecture]

#: kind -> (architecture class, module)
MODELS: dict[str, tuple[type, ModuleType]] = {
    LSTMArchitecture.kind: (LSTMArchitecture, lstm),
    LinearArchitecture.kind: (LinearArchitecture, linear),
}


def model_module(arch: Architecture) -> ModuleType:
    """The module that runs ``arch`` (:mod:`~jaxsync.surrogate.lstm` or :mod:`~jaxsync.surrogate.linear`)."""
    entry = MODELS.get(getattr(arch, "kind", None))
    if entry is None or not isinstance(arch, entry[0]):
        raise ConfigError(f"{arch!r} is not a surrogate architecture; expected one of "
                          + ", ".join(cls.__name__ for cls, _ in MODELS.values()))
    return entry[1]


def architecture_to_dict(arch: Architecture) -> dict[str, Any]:
    """``{"kind": ..., **arch.to_dict()}`` (JSON-ready): what checkpoints and summaries store."""
    model_module(arch)
    return {"kind": arch.kind, **arch.to_dict()}


def architecture_from_dict(values: dict[str, Any]) -> Architecture:
    """Inverse of :func:`architecture_to_dict`.  A dict without ``kind`` is an LSTM's
    (checkpoints written before the linear surrogate existed).

    Raises:
        ConfigError: an unknown kind or fields of another architecture.
    """
    kind = check_option("architecture kind", values.get("kind", LSTMArchitecture.kind), SurrogateModel)
    return MODELS[kind][0].from_dict(values)


def init_params(key: jax.Array, arch: Architecture):
    """Initial parameters of one replica (the model's own ``init_params``)."""
    return model_module(arch).init_params(key, arch)


def forward(params, arch: Architecture, xs: jax.Array, load_parameter: jax.Array | None = None,
            dof_mask: jax.Array | None = None, compute_dtype: str | None = None) -> jax.Array:
    """Normalized window (n_p, n_dof) -> predictions (n_f, n_dof) of one replica (the
    model's own ``forward``); ``compute_dtype="bfloat16"``: reduced-precision inference
    (bfloat16 operands, float32 accumulation; None: the architecture's dtype)."""
    return model_module(arch).forward(params, arch, xs, load_parameter, dof_mask, compute_dtype=compute_dtype)
