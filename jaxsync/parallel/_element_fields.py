"""Per-element state (a material law's internal variables) on the parts of a partition.

A law's internal variables live at the quadrature points of the elements
(:meth:`jaxsync.fem.materials.MaterialLaw.internal_variables`): a pytree of arrays
(n_elements, n_points, ...). They go with the elements: each part holds those of its own
elements, in the order of ``part.elements`` and padded to the largest part as the part's
force operators are (padding slots repeat the part's first element,
:meth:`jaxsync.fem.forces.TotalLagrangian.part_operators`), and they are never
exchanged between the parts of an element partition: an element belongs to one part. With
deep halos parts share (and recompute) elements: each carries the state of all its
elements, the halo exchange copies that of the shared ones from their owner
(:mod:`jaxsync.parallel.exchange`), and the global state is merged from the owners.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import PartitionError

__all__ = ["element_slots", "split_element_fields", "merge_element_fields"]


def element_slots(parts) -> np.ndarray:
    """(P, m_max) int64 the global element of every slot of every part (padding: the
    part's first element), the layout of the part operators (parts may share elements:
    deep halos)."""
    m = max(len(p.elements) for p in parts)
    slots = np.zeros((len(parts), m), dtype=np.int64)
    for k, part in enumerate(parts):
        slots[k, :len(part.elements)], slots[k, len(part.elements):] = part.elements, part.elements[0]
    return slots


def split_element_fields(parts, fields):
    """A pytree of global (n_elements, ...) arrays -> the parts' (P, m_max, ...) arrays (JAX;
    traced values flow through). An empty pytree (a law without state) stays empty."""
    if not jax.tree_util.tree_leaves(fields):
        return fields
    slots = element_slots(parts)
    return jax.tree_util.tree_map(lambda x: jnp.asarray(x)[slots], fields)


def merge_element_fields(parts, fields, n_elements: int, element_owner=None):
    """The parts' (P, m_max, ...) arrays -> global (n_elements, ...) numpy arrays, each
    element from the part that holds it, or with ``element_owner`` ((n_elements,) part
    index, deep halos) from the part that owns it (host)."""
    if not jax.tree_util.tree_leaves(fields):
        return fields
    part_of = np.concatenate([np.full(len(p.elements), k) for k, p in enumerate(parts)])
    slot_of = np.concatenate([np.arange(len(p.elements)) for p in parts])
    elements = np.concatenate([np.asarray(p.elements) for p in parts])
    if element_owner is not None:
        index = np.asarray([p.index for p in parts])[part_of]
        kept = np.asarray(element_owner)[elements] == index
        part_of, slot_of, elements = part_of[kept], slot_of[kept], elements[kept]
    if len(elements) != n_elements or len(np.unique(elements)) != n_elements:
        raise PartitionError("these parts do not hold every element of the mesh: the elements' state cannot be "
                             "merged from them")

    def merge(x):
        x = np.asarray(x)
        out = np.empty((n_elements,) + x.shape[2:], dtype=x.dtype)
        out[elements] = x[part_of, slot_of]
        return out

    return jax.tree_util.tree_map(merge, fields)
