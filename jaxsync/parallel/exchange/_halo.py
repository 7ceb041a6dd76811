"""Deep halos: the exact communication-avoiding scheme for central differences.

Every node is *owned* by one part (the lowest-numbered part whose elements touch it).
With halo depth k, a part holds, besides its owned nodes O (graph distance 0), every node
within graph distance k of O (the node graph of the mesh: two nodes are neighbours when
an element holds both), and every element that touches a node within distance k - 1:

    N_0 = O,  N_j = N_(j-1) + neighbours of N_(j-1),
    elements = those touching N_(k-1),  local nodes = their nodes = N_k.

Why it is exact. The internal force at a node needs every element around it and the
displacements of its neighbours. If a part starts a cycle with d(n) and d(n-1) right on
all of N_k, its own step gives the full force on N_(k-1) (all their elements are local),
so d(n+1) is right on N_(k-1); after j steps d(n+j) is right on N_(k-j), and after k
steps on N_0 = O, with d(n+k-1) right on N_1. One exchange then copies both displacement
levels of every non-owned local node from its owner, and the next cycle starts right on
N_k again: one exchange every k steps instead of one force sum every step, for the cost
of the redundant work on the halo (which grows with k). k = 1 exchanges every step, like
the synchronized solver, but displacements instead of forces.

A material law's internal variables (:mod:`jaxsync.parallel`) go with the
elements, and a part carries those of all its elements, halo ones too. Inside a cycle a
part's element state is right where its forces are: after the cycle's last step, on the
elements touching its owned nodes (their nodes lie in N_1), not on the outer halo
elements, whose state went through displacements that were wrong there. So every element
has an *owner*, the part that owns its first node (the element touches that part's owned
nodes), and the exchange also copies the state of every element that several parts hold
(the *element interface*) from its owner, in the same collective: the next cycle starts
with every local element's state right, and a deep-halo run of a law with state equals
the synchronized run.

The exchange uses the machinery of :mod:`jaxsync.parallel.exchange` unchanged: the
*halo interface* numbers every node that is some part's halo node (sorted by global id),
each part's ``shared_local`` / ``shared_interface`` list its local nodes in that
interface, the part writes only the values of the nodes it owns (zeros elsewhere), and
:func:`~jaxsync.parallel.exchange.scatter_reverse` sums them (x + 0 = x: the owner's
value arrives bit for bit). A :class:`HaloPartition` therefore looks like a
:class:`~jaxsync.parallel.Partition` to
:class:`~jaxsync.parallel.PartLayout` (``mesh``, ``parts``, ``n_interface``), with
the owned nodes added (``owned_local``).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from ...errors import PartitionError
from ...fem._stepper import SolverState, advance
from ...options import check_halo_depth
from .._partitioning import Part, Partition
from ._index_maps import AXIS, LOCAL_AXIS, scatter_forward

__all__ = ["HaloPartition", "halo_partition", "check_halo_depth", "refresh_halo", "advance_halo",
           "check_save_every"]


@dataclasses.dataclass(frozen=True, eq=False)
class HaloPartition:
    """The parts of ``partition`` grown by ``depth`` layers of their neighbours' elements.

    Attributes:
        partition: the element partition it grows (:class:`Partition`).
        depth: k, steps between two exchanges.
        owner: (n_nodes,) the part that owns each node.
        parts: one :class:`Part` per part, grown: ``elements`` (every element touching a
            node within distance k - 1 of the owned nodes, increasing global ids),
            ``nodes`` (N_k, increasing), ``local_tets``, and ``shared_local`` /
            ``shared_interface``: the part's local nodes in the halo interface.
        owned_local: per part, (n_owned_p,) local indices of its owned nodes.
        halo_nodes: (n_interface,) global ids of the halo interface: every node that is a
            halo (non-owned local) node of some part, increasing.
        element_owner: (n_elements,) the part that owns each element (that of its first
            node), whose internal variables the exchange copies to the other parts.
        halo_elements: (n_element_interface,) global ids of the element interface: every
            element that several parts hold, increasing.
    """

    partition: Partition
    depth: int
    owner: np.ndarray
    parts: tuple
    owned_local: tuple
    halo_nodes: np.ndarray
    element_owner: np.ndarray
    halo_elements: np.ndarray

    @property
    def mesh(self):
        return self.partition.mesh

    @property
    def space(self):
        return self.partition.space

    @property
    def n_nodes(self) -> int:
        return self.partition.n_nodes

    @property
    def n_parts(self) -> int:
        return len(self.parts)

    @property
    def n_interface(self) -> int:
        """Nodes exchanged (each carries 2 levels x 3 components)."""
        return len(self.halo_nodes)

    @property
    def sharing_parts(self) -> tuple:
        """For each halo interface node, the parts that hold it (increasing), as
        :attr:`Partition.sharing_parts` (so that
        :func:`jaxsync.perf.costmodel.communication_pattern` takes a halo too, with
        ``dofs_per_node=6``: two displacement levels)."""
        holders = [[] for _ in range(self.n_interface)]
        for part in self.parts:
            for k in part.shared_interface:
                holders[k].append(part.index)
        return tuple(np.asarray(h, dtype=np.int64) for h in holders)

    @property
    def n_element_interface(self) -> int:
        """Elements whose internal variables are exchanged (held by several parts)."""
        return len(self.halo_elements)

    def element_tables(self) -> tuple:
        """(owned (P, m_max) bool, shared_local (P, n_max) int32, shared_interface (P,
        n_max) int32): per part, which of its element slots (the order of
        ``part.elements``, padded to the largest part, m_max) it owns, and the slots of its
        elements in the element interface with their interface index (padding: m_max and
        n_element_interface, out of range, so that the scatters drop it)."""
        m = max(len(p.elements) for p in self.parts)
        interface_of = np.full(self.mesh.n_elements, -1, dtype=np.int64)
        interface_of[self.halo_elements] = np.arange(self.n_element_interface)
        rows = [np.flatnonzero(interface_of[p.elements] >= 0) for p in self.parts]
        n = max(max(len(r) for r in rows), 1)
        owned = np.zeros((self.n_parts, m), dtype=bool)
        local = np.full((self.n_parts, n), m, dtype=np.int32)
        interface = np.full((self.n_parts, n), self.n_element_interface, dtype=np.int32)
        for k, (part, row) in enumerate(zip(self.parts, rows)):
            owned[k, :len(part.elements)] = self.element_owner[part.elements] == part.index
            local[k, :len(row)] = row
            interface[k, :len(row)] = interface_of[part.elements[row]]
        return owned, local, interface

    def alone(self, index: int) -> "HaloPartition":
        """These grown parts with part ``index`` only (as
        :meth:`jaxsync.parallel.Partition.alone`)."""
        return dataclasses.replace(self, parts=(self.parts[index],), owned_local=(self.owned_local[index],))

    def redundancy(self) -> float:
        """Elements held by all parts together over the mesh's elements (1 = no redundant
        work; grows with the depth)."""
        return sum(len(p.elements) for p in self.parts) / self.mesh.n_elements

    def summary(self) -> str:
        """A printable table: owned and local nodes and elements per part."""
        lines = [f"Halo of depth {self.depth} around {self.n_parts} parts: "
                 f"{self.n_interface} exchanged nodes, {self.redundancy():.2f}x the elements",
                 f"{'part':>6} {'elements':>10} {'owned':>8} {'local':>8} {'halo':>8}"]
        for part, owned in zip(self.parts, self.owned_local):
            lines.append(f"{part.index:>6} {len(part.elements):>10} {len(owned):>8} "
                         f"{part.n_local:>8} {part.n_local - len(owned):>8}")
        return "\n".join(lines)


def halo_partition(partition: Partition, depth: int) -> HaloPartition:
    """Grow the parts of ``partition`` by ``depth`` layers (definitions: module docstring).

    Raises:
        PartitionError: depth not a positive integer, or a part that owns no node (a part
            whose every node is shared with a lower-numbered part: use fewer parts).
    """
    depth = check_halo_depth(depth)
    mesh = partition.mesh
    n_nodes, tets = partition.n_nodes, partition.space.cells  # the element's nodes (P2: edges too)
    n_elements = mesh.n_elements
    k = tets.shape[1]
    # incidence (elements x nodes) and the node graph (neighbours through an element)
    incidence = sp.csr_matrix((np.ones(tets.size, dtype=np.int32),
                               (np.repeat(np.arange(n_elements), k), tets.ravel())),
                              shape=(n_elements, n_nodes))
    graph = (incidence.T @ incidence).tocsr()
    owner = np.full(n_nodes, np.iinfo(np.int64).max, dtype=np.int64)
    np.minimum.at(owner, tets.ravel(), np.repeat(partition.element_part, k))
    parts, owned_local, reach = [], [], []
    for p in range(partition.n_parts):
        ring = owner == p  # N_0
        if not ring.any():
            raise PartitionError(
                f"part {p} owns no node (every node of it is shared with a lower-numbered part), "
                f"so deep halos cannot be built: use fewer parts or a finer mesh")
        for _ in range(depth - 1):  # N_(k-1)
            ring = ring | (graph @ ring.astype(np.int32) > 0)
        elements = np.flatnonzero(incidence @ ring.astype(np.int32) > 0)
        nodes = np.unique(tets[elements])
        reach.append((elements, nodes))
    # the halo interface: every node some part holds without owning it
    in_halo = np.zeros(n_nodes, dtype=bool)
    for p, (_, nodes) in enumerate(reach):
        in_halo[nodes[owner[nodes] != p]] = True
    halo_nodes = np.flatnonzero(in_halo)
    interface_of = np.full(n_nodes, -1, dtype=np.int64)
    interface_of[halo_nodes] = np.arange(len(halo_nodes))
    for p, (elements, nodes) in enumerate(reach):
        local_of = np.full(n_nodes, -1, dtype=np.int64)
        local_of[nodes] = np.arange(len(nodes))
        exchanged = np.flatnonzero(in_halo[nodes])
        parts.append(Part(index=p, elements=elements, nodes=nodes, local_tets=local_of[tets[elements]],
                          shared_local=exchanged, shared_interface=interface_of[nodes[exchanged]]))
        owned_local.append(np.flatnonzero(owner[nodes] == p))
    held = np.bincount(np.concatenate([elements for elements, _ in reach]), minlength=n_elements)
    return HaloPartition(partition=partition, depth=depth, owner=owner, parts=tuple(parts),
                         owned_local=tuple(owned_local), halo_nodes=halo_nodes, element_owner=owner[tets[:, 0]],
                         halo_elements=np.flatnonzero(held > 1))


def check_save_every(save_every: int, depth: int) -> int:
    """Steps of the smallest whole chunk of a deep-halo run: ``max(save_every, depth)``
    when one divides the other, else :class:`PartitionError` naming the fix."""
    if save_every % depth and depth % save_every:
        raise PartitionError(
            f"with deep halos, save_every={save_every} and halo_depth={depth} must divide one "
            f"another (saves fall at whole exchange cycles, or cycles at whole saves); use "
            f"halo_depth={np.gcd(save_every, depth)} or save_every={np.lcm(save_every, depth)}")
    return max(save_every, depth)


def _interface_vector(values, shared_local, shared_interface, n_interface: int):
    """This part's (n_interface + 1, c) contribution to an interface vector (the local half
    of :func:`jaxsync.parallel.exchange.scatter_reverse`)."""
    interface = jnp.zeros((n_interface + 1,) + values.shape[1:], values.dtype)
    return interface.at[shared_interface].add(values[shared_local], mode="clip")


def refresh_halo(part, state: SolverState, n_interface: int, across=None, n_element_interface: int = 0) -> SolverState:
    """Both displacement levels of one part's non-owned local nodes replaced by their
    owners' values, and the internal variables of its elements in the element interface
    by their owners' (module docstring): one exchange of (n_interface + 1) x 6 values plus
    (n_element_interface + 1) x the variables of an element. Collective: every part of
    every device calls it at the same step. ``part``: that part's
    :class:`jaxsync.parallel.exchange.PartSystems` slice (with ``owned`` and, for a law
    with state, ``element_exchange``); ``across``: as in
    :func:`jaxsync.parallel.exchange.scatter_reverse` (None: ``psum``)."""
    levels = jnp.concatenate([state.displacement, state.previous], axis=1)  # (n_local, 6)
    mine = jnp.where(part.owned[:, None], levels, 0.0)  # every node has one owner: x + 0 = x
    pieces = [_interface_vector(mine, part.shared_local, part.shared_interface, n_interface)]
    leaves, tree = jax.tree_util.tree_flatten(state.internal)
    if leaves:  # the elements' state, one row of every variable per element slot
        owned, element_local, element_interface = part.element_exchange
        rows = jnp.concatenate([x.reshape(x.shape[0], -1) for x in leaves], axis=1)
        pieces.append(_interface_vector(jnp.where(owned[:, None], rows, 0.0), element_local, element_interface,
                                        n_element_interface))
    # one collective for both (MPI sums of one program must not be independent)
    flat = jax.lax.psum(jnp.concatenate([x.ravel() for x in pieces]), LOCAL_AXIS)
    flat = jax.lax.psum(flat, AXIS) if across is None else across(flat)
    total = flat[:pieces[0].size].reshape(pieces[0].shape)
    levels = scatter_forward(levels, total, part.shared_local, part.shared_interface)
    internal = state.internal
    if leaves:
        total = flat[pieces[0].size:].reshape(pieces[1].shape)
        rows = scatter_forward(rows, total, element_local, element_interface)
        sizes = np.cumsum([int(np.prod(x.shape[1:])) for x in leaves])[:-1]
        internal = jax.tree_util.tree_unflatten(
            tree, [r.reshape(x.shape) for r, x in zip(jnp.split(rows, sizes, axis=1), leaves)])
    return SolverState(levels[:, :3], levels[:, 3:], state.step, internal)


def advance_halo(part, state: SolverState, n_saves: int, save_every: int, exchange, *, loop=None):
    """``n_saves * save_every`` steps of one grown part with an exchange every
    ``exchange.halo_depth`` steps (:func:`refresh_halo`; ``exchange`` a
    :class:`jaxsync.parallel.exchange.Exchange`): (state, (n_saves, n_local, 3)
    displacements after every ``save_every`` steps). ``save_every`` and the depth divide
    one another (:func:`check_save_every`); saved snapshots inside a cycle are right on the
    owned nodes only (read those), at its end on every local node.

    ``loop(body, carry, n) -> (carry, stacked outputs)`` runs the outer loop (of saves, or
    of exchange cycles when a cycle holds several saves): ``lax.scan`` by default; the
    traced executor passes a recomputing one (:func:`jaxsync.solve._remat.recomputing_scan`)."""
    depth = exchange.halo_depth
    loop = (lambda body, c, n: jax.lax.scan(body, c, None, length=n)) if loop is None else loop

    def cycle(s, _):  # depth local steps, then the exchange; saves every save_every steps
        per_cycle = max(depth // save_every, 1)
        s, saved = advance(part.system, s, per_cycle, min(save_every, depth))
        return refresh_halo(part, s, exchange.n_interface, exchange.across, exchange.n_element_interface), saved

    if save_every >= depth:
        def one_save(s, _):
            s, _ = jax.lax.scan(cycle, s, None, length=save_every // depth)
            return s, s.displacement

        return loop(one_save, state, n_saves)
    state, saved = loop(cycle, state, n_saves * save_every // depth)
    return state, saved.reshape(n_saves, *saved.shape[2:])
