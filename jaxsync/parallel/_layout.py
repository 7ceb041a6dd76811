"""The parts as one SPMD program holds them: padded local numbering, the per-part systems,
and the way between per-part fields and the global field.

Parts have different sizes, so every part's local nodes are padded to the largest part
(``n_local``): padding nodes have unit mass, zero stiffness and are fixed at zero, and
they are never read back. A :class:`PartLayout` holds the index maps of a
:class:`~jaxsync.parallel.Partition` (or of the grown parts of a
:class:`~jaxsync.parallel.exchange.HaloPartition`) in that padded form, and moves fields:

* :meth:`PartLayout.split`: a global field (..., n_nodes, c) -> (P, ..., n_local, c),
  each part's local nodes gathered, padding filled;
* :meth:`PartLayout.merge`: back to the global field, either from one part per node (the
  node's *owner*: in a synchronized run every part that holds a node has the same value
  there, bit for bit, so reading one is exact) or as the mean over the parts that hold it
  (after a predicted phase the parts differ at shared nodes).

The local numbering is private to the layout: :meth:`PartLayout.of` puts every part's
local nodes in reverse Cuthill-McKee order (:func:`local_order`), so that the neighbours a
row of the stiffness product gathers sit close together in memory (on the generated
coronary tree a node's neighbours are a mean 6 800 positions apart in the mesh's order,
177 in RCM order); split, merge and the shared-node tables map it, and everything that
leaves the layout (shared-node records, merged fields) is in global numbering and order,
unchanged.

Both are JAX functions: the traced executor calls them inside its program, the host
executor on the fields it gathered from the devices. :func:`part_systems` splits a global
:class:`~jaxsync.fem.ExplicitSystem` into the parts' systems (:class:`PartSystems`):
the internal force through the physics seam (:mod:`jaxsync.fem.forces`), the rest
by gathers, so that traced material, damping, loads and dt flow through (differentiable).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import PartitionError
from ..fem._stepper import ExplicitSystem, SolverState
from ..pytree import pytree_dataclass

__all__ = ["PartLayout", "PartSystems", "part_systems", "local_order", "ordered_parts"]


@pytree_dataclass
class PartSystems:
    """Per-part explicit systems stacked on a leading part axis (all arrays (n_parts, ...)).

    Attributes:
        system: :class:`ExplicitSystem` in local numbering, padded to n_local nodes.
        shared_local: (n_parts, n_shared_max) local index of each shared node (padding:
            n_local, out of range, so that scatters drop it).
        shared_interface: (n_parts, n_shared_max) interface index (padding: n_interface).
        owned: (n_parts, n_local) bool, the nodes each part owns, for deep halos
            (:mod:`jaxsync.parallel.exchange`); None for an element partition.
        element_exchange: deep halos' element tables
            (:meth:`jaxsync.parallel.exchange.HaloPartition.element_tables`: owned element
            slots, element-interface slots and indices), or None.
    """

    system: ExplicitSystem
    shared_local: Any
    shared_interface: Any
    owned: Any = None
    element_exchange: Any = None

    def shared_displacement(self, state):
        """One part's (n_shared_max, 3) displacements at its shared nodes in ``state``
        (padding slots read 0): what the distributed solver records after every step, the
        surrogates' training data and input history."""
        return state.displacement.at[self.shared_local].get(mode="fill", fill_value=0.0)


def _padded(rows, length: int, fill, dtype) -> np.ndarray:
    """(len(rows), length) array of the 1-d ``rows``, each padded with ``fill``."""
    out = np.full((len(rows), length), fill, dtype=dtype)
    for k, row in enumerate(rows):
        out[k, :len(row)] = row
    return out


@dataclasses.dataclass(frozen=True, eq=False)
class PartLayout:
    """Index maps of the parts of ``partition`` in padded local numbering (host, numpy).

    Attributes:
        partition: the :class:`~jaxsync.parallel.Partition` or
            :class:`~jaxsync.parallel.exchange.HaloPartition` laid out (``mesh``, ``parts``,
            ``n_interface``; a halo's ``owned_local``), with each part's local nodes in
            reverse Cuthill-McKee order (:func:`ordered_parts`).
        n_local: local nodes per part after padding (the largest part's).
        nodes: (P, n_local) int32 global node of each local slot (0 on padding).
        valid: (P, n_local) bool, False on padding.
        shared_local, shared_interface: (P, n_shared_max) int32 shared-node tables
            (:class:`PartSystems`).
        owned: (P, n_local) bool of a halo's owned nodes, or None.
        owner_slot: (n_nodes,) flat slot ``p * n_local + k`` of each node's owner (the
            lowest-numbered part that holds it, or with deep halos the part that owns it;
            -1 where no part of the layout holds the node).
        holder_slot, holder_node: (n_held,) every flat slot that holds a node kept by
            :meth:`merge` with ``mean=True`` (all real local slots; with deep halos the
            owned ones) and its global node.
        holders: (n_nodes,) float, how many slots hold each node.
    """

    partition: Any
    n_local: int
    nodes: np.ndarray
    valid: np.ndarray
    shared_local: np.ndarray
    shared_interface: np.ndarray
    owned: np.ndarray | None
    owner_slot: np.ndarray
    holder_slot: np.ndarray
    holder_node: np.ndarray
    holders: np.ndarray

    @classmethod
    def of(cls, partition) -> "PartLayout":
        """The layout of a :class:`Partition` or :class:`HaloPartition`, each part's local
        nodes put in reverse Cuthill-McKee order first (:func:`ordered_parts`)."""
        partition = ordered_parts(partition)
        parts = partition.parts
        n_nodes = partition.n_nodes
        n_local = max(p.n_local for p in parts)
        n_shared = max(max(p.n_shared for p in parts), 1)
        owned_local = getattr(partition, "owned_local", None)
        nodes = _padded([p.nodes for p in parts], n_local, 0, np.int32)
        valid = _padded([np.ones(p.n_local, bool) for p in parts], n_local, False, bool)
        owned = None
        if owned_local is not None:
            owned = np.zeros((len(parts), n_local), dtype=bool)
            for p, local in enumerate(owned_local):
                owned[p, local] = True
        kept = owned if owned is not None else valid  # the slots whose values are right
        slot = np.flatnonzero(kept.ravel())
        node = nodes.ravel()[slot]
        owner_slot = np.full(n_nodes, np.iinfo(np.int64).max, dtype=np.int64)
        np.minimum.at(owner_slot, node, slot)  # slots grow with the part: the lowest part holding it
        owner_slot[owner_slot == np.iinfo(np.int64).max] = -1  # held by no part (a layout of some parts)
        return cls(partition=partition, n_local=n_local, nodes=nodes, valid=valid,
                   shared_local=_padded([p.shared_local for p in parts], n_shared, n_local, np.int32),
                   shared_interface=_padded([p.shared_interface for p in parts], n_shared,
                                            partition.n_interface, np.int32),
                   owned=owned, owner_slot=owner_slot, holder_slot=slot, holder_node=node,
                   holders=np.bincount(node, minlength=n_nodes).astype(float))

    @property
    def parts(self) -> tuple:
        """The parts laid out (those of ``partition``, in the layout's local order)."""
        return self.partition.parts

    @property
    def n_parts(self) -> int:
        return len(self.partition.parts)

    @property
    def n_nodes(self) -> int:
        return self.partition.n_nodes

    def split(self, field, fill=0.0):
        """(..., n_nodes, c) -> (P, ..., n_local, c): every part's local nodes, padding
        slots set to ``fill`` (JAX; traced values flow through)."""
        gathered = jnp.moveaxis(jnp.asarray(field)[..., self.nodes, :], -3, 0)
        mask = self.valid.reshape((self.n_parts,) + (1,) * (gathered.ndim - 3) + (self.n_local, 1))
        return jnp.where(mask, gathered, jnp.asarray(fill, gathered.dtype))

    def split_state(self, state: SolverState) -> SolverState:
        """A global :class:`SolverState` as the parts' states (the step counter per part; the
        material's internal variables with the elements, :mod:`jaxsync.parallel`)."""
        from ._element_fields import split_element_fields

        step = jnp.broadcast_to(jnp.asarray(state.step, dtype=jnp.int32), (self.n_parts,))
        return SolverState(self.split(state.displacement), self.split(state.previous), step,
                           split_element_fields(self.parts, state.internal))

    def merge(self, local, *, mean: bool = False):
        """(P, ..., n_local, c) per-part fields -> (..., n_nodes, c) global field (JAX).

        ``mean=False``: each node from its owner (exact where the parts agree: synchronized
        steps, deep halos' owned nodes). ``mean=True``: the mean over the parts that hold
        the node (they differ at shared nodes after predicted steps)."""
        if np.any(self.owner_slot < 0):
            raise PartitionError("these parts do not hold every node of the mesh: a global field cannot be "
                                 "merged from them")
        local = jnp.asarray(local)
        flat = jnp.moveaxis(local, 0, -3)  # (..., P, n_local, c)
        flat = flat.reshape(*flat.shape[:-3], -1, flat.shape[-1])  # (..., P n_local, c)
        if not mean:
            return flat[..., self.owner_slot, :]
        total = jnp.zeros((*flat.shape[:-2], self.n_nodes, flat.shape[-1]), flat.dtype)
        total = total.at[..., self.holder_node, :].add(flat[..., self.holder_slot, :])
        count = jnp.asarray(self.holders, flat.dtype).reshape((1,) * (total.ndim - 2) + (self.n_nodes, 1))
        return total / count


def local_order(part) -> np.ndarray:
    """(n_local,) the part's local nodes in reverse Cuthill-McKee order
    (``scipy.sparse.csgraph.reverse_cuthill_mckee`` of its node graph: two nodes are
    neighbours when one of its elements holds both): entry k is the current local index of
    the node that goes to slot k. It starts from the nodes sorted by global id, so it does
    not depend on the part's current numbering: ordering an ordered part changes nothing."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    n = part.n_local
    canonical = np.argsort(part.nodes, kind="stable")  # canonical index -> current local index
    position = np.empty(n, dtype=np.int64)
    position[canonical] = np.arange(n)
    tets = position[np.asarray(part.local_tets)]
    k = tets.shape[1]
    graph = sp.csr_matrix((np.ones(tets.size * k, dtype=np.int8),
                           (np.repeat(tets, k, axis=1).ravel(), np.tile(tets, (1, k)).ravel())), shape=(n, n))
    return canonical[reverse_cuthill_mckee(graph, symmetric_mode=True)]


def ordered_parts(partition):
    """``partition`` (a :class:`Partition` or :class:`HaloPartition`) with every part's
    local nodes in :func:`local_order`: ``nodes``, ``local_tets``, ``shared_local`` (same
    shared nodes in the same order, so ``shared_interface`` and the shared-node records
    are unchanged) and a halo's ``owned_local`` renumbered. Returns ``partition`` itself
    when every part is in that order already."""
    parts, owned = [], []
    owned_local = getattr(partition, "owned_local", None)
    for p, part in enumerate(partition.parts):
        order = local_order(part)
        if np.array_equal(order, np.arange(part.n_local)):
            parts.append(part)
            owned.append(None if owned_local is None else owned_local[p])
            continue
        new_of_old = np.empty(part.n_local, dtype=np.int64)
        new_of_old[order] = np.arange(part.n_local)
        parts.append(dataclasses.replace(part, nodes=np.asarray(part.nodes)[order],
                                         local_tets=new_of_old[np.asarray(part.local_tets)],
                                         shared_local=new_of_old[np.asarray(part.shared_local)]))
        owned.append(None if owned_local is None else np.sort(new_of_old[np.asarray(owned_local[p])]))
    if all(a is b for a, b in zip(parts, partition.parts)):
        return partition
    if owned_local is None:
        return dataclasses.replace(partition, parts=tuple(parts))
    return dataclasses.replace(partition, parts=tuple(parts), owned_local=tuple(owned))


def part_systems(problem, system: ExplicitSystem, layout: PartLayout, mode="preassembled") -> PartSystems:
    """The parts' systems of the global ``system`` of ``problem`` (JAX arrays, not placed).

    The internal force comes from the force model (``mode``,
    :func:`jaxsync.fem.forces.force_model`) and the supports' springs on each
    part's own elements and facets; the mass, the dashpots, loads and Dirichlet values
    (their histories too) are gathered from ``system`` (padding: unit mass, no load, fixed
    at zero), damping (alpha and beta) and dt broadcast to every part; the follower pressures act on each
    part's own facets (those of its elements). Traced values of ``problem`` and
    ``system`` stay traced."""
    from ..fem.forces._internal_force import force_model

    partition = layout.partition
    if partition.mesh is not problem.mesh and not (
            partition.mesh.n_nodes == problem.mesh.n_nodes
            and np.array_equal(partition.mesh.tets, problem.mesh.tets)) or partition.n_nodes != problem.n_nodes:
        raise PartitionError("the partition was made for another mesh: partition problem.mesh")
    n_parts = layout.n_parts

    def broadcast(x):
        return jnp.broadcast_to(x, (n_parts,) + jnp.shape(x))

    from ..fem.forces._follower import part_follower_pressures
    from ..fem.forces._support import Dashpot, part_surface_springs

    def split_blocks(blocks):  # (n_nodes, 3, 3) -> (P, n_local, 3, 3)
        local = layout.split(blocks.reshape(blocks.shape[0], 9), 0.0)
        return local.reshape(local.shape[:-1] + (3, 3))

    local_loads = layout.split(system.load_vectors, 0.0)  # (P, n_loads, n_local, 3)
    d = system.dashpot
    stacked = ExplicitSystem(
        stiffness=force_model(mode).part_operators(problem, layout.parts, layout.n_local),
        mass=layout.split(system.mass, 1.0), damping=broadcast(system.damping), dt=broadcast(system.dt),
        load_vectors=local_loads, load_times=jax.tree_util.tree_map(broadcast, system.load_times),
        fixed=layout.split(system.fixed, True), fixed_values=layout.split(system.fixed_values, 0.0),
        moving=None if system.moving is None else layout.split(system.moving, 0.0),
        moving_times=jax.tree_util.tree_map(broadcast, system.moving_times),
        spring=part_surface_springs(problem, layout.parts, layout.n_local),
        dashpot=None if d is None else Dashpot(split_blocks(d.inverse), split_blocks(d.coupling),
                                               split_blocks(d.prescribed)),
        follower=part_follower_pressures(problem, layout.parts, layout.n_local),
        stiffness_damping=None if system.stiffness_damping is None else broadcast(system.stiffness_damping))
    tables = getattr(partition, "element_tables", None)
    return PartSystems(stacked, jnp.asarray(layout.shared_local), jnp.asarray(layout.shared_interface),
                       None if layout.owned is None else jnp.asarray(layout.owned),
                       None if tables is None else tuple(jnp.asarray(a) for a in tables()))
