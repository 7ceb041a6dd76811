"""Registering frozen dataclasses as JAX pytrees.

``@pytree_dataclass`` makes a frozen dataclass whose fields are pytree children, except
those declared with ``static_field()``, which go to the treedef (they must be hashable).
"""

from __future__ import annotations

import dataclasses

import jax

__all__ = ["pytree_dataclass", "static_field", "is_traced"]


def static_field(**kwargs):
    """A dataclass field that is part of the treedef rather than a traced leaf."""
    return dataclasses.field(metadata={"static": True}, **kwargs)


def pytree_dataclass(cls):
    """Decorator: frozen dataclass registered with ``jax.tree_util`` by field name."""
    cls = dataclasses.dataclass(frozen=True)(cls)
    fields = dataclasses.fields(cls)
    data = [f.name for f in fields if not f.metadata.get("static", False)]
    meta = [f.name for f in fields if f.metadata.get("static", False)]
    jax.tree_util.register_dataclass(cls, data_fields=data, meta_fields=meta)
    return cls


def is_traced(*values) -> bool:
    """True when any leaf of ``values`` is a JAX tracer (inside jit/grad/vmap)."""
    leaves = jax.tree_util.tree_leaves(values)
    return any(isinstance(x, jax.core.Tracer) for x in leaves)


def concrete_scalar(value):
    """``value`` as a Python float when it is a concrete scalar, else None.

    Validation in ``__post_init__`` uses it to check user input while letting JAX
    rebuild pytrees with tracers, stacked arrays or placeholder leaves."""
    import numpy as np

    if isinstance(value, jax.core.Tracer):
        return None
    if isinstance(value, (bool, np.bool_)):
        return None
    if isinstance(value, (int, float, np.integer, np.floating)):
        return float(value)
    if isinstance(value, (np.ndarray, jax.Array)) and value.shape == ():
        return float(value)
    return None
