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
