"""Element partitions of a mesh (METIS through pymetis) and their index maps.

Each part owns a set of elements; its *local nodes* are the nodes of those elements,
numbered locally in increasing global order. A node is *shared* when elements of two or
more parts touch it. The *interface* numbers all shared nodes globally (sorted by global
id); its dofs are node-interleaved (interface dof ``3 k + c``). Like dolfinx's index
maps, each part knows where its shared nodes sit both locally and in the interface.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from ..errors import PartitionError
from ..mesh import Mesh

__all__ = ["Part", "Partition", "partition", "partition_from_elements", "partition_of"]


@dataclasses.dataclass(frozen=True, eq=False)
class Part:
    """One part of a partition.

    Attributes:
        index: part number p.
        elements: (n_elements_p,) global element ids, increasing.
        nodes: (n_local,) global node ids of the local nodes, increasing (local numbering).
        local_tets: (n_elements_p, 4) the elements in local node numbering.
        shared_local: (n_shared_p,) local indices of the part's shared nodes.
        shared_interface: (n_shared_p,) their positions in the interface numbering.
    """

    index: int
    elements: np.ndarray
    nodes: np.ndarray
    local_tets: np.ndarray
    shared_local: np.ndarray
    shared_interface: np.ndarray

    @property
    def shared_nodes(self) -> np.ndarray:
        """(n_shared_p,) global ids of the part's shared nodes (increasing)."""
        return self.nodes[self.shared_local]

    @property
    def n_local(self) -> int:
        return len(self.nodes)

    @property
    def n_shared(self) -> int:
        return len(self.shared_local)


@dataclasses.dataclass(frozen=True, eq=False)
class Partition:
    """A partition of a mesh's elements into ``n_parts`` parts.

    Attributes:
        mesh: the mesh.
        element_part: (n_elements,) part of each element.
        parts: one :class:`Part` per part (its nodes those of ``space``: with P2 elements
            also the edge nodes of its elements; ``local_tets`` each element's nodes).
        shared_nodes: (n_interface,) global ids of all shared nodes (the interface).
        sharing_parts: tuple, for each interface node, of the parts that touch it.
        seed: the METIS seed used.
        space: the :class:`~jaxsync.fem.FunctionSpace` whose nodes the parts hold
            (default: the mesh's P1 space).
    """

    mesh: Mesh
    element_part: np.ndarray
    parts: tuple
    shared_nodes: np.ndarray
    sharing_parts: tuple
    seed: int = 0
    space: Any = None

    def __post_init__(self):
        if self.space is None:
            from ..fem._space import function_space

            object.__setattr__(self, "space", function_space(self.mesh, "P1"))

    @property
    def n_nodes(self) -> int:
        """Nodes of the space (the mesh's vertices for P1)."""
        return self.space.n_nodes

    @property
    def n_parts(self) -> int:
        return len(self.parts)

    @property
    def n_interface(self) -> int:
        """Number of shared nodes (the interface has 3 times as many dofs)."""
        return len(self.shared_nodes)

    def alone(self, index: int) -> "Partition":
        """This partition with part ``index`` only (its geometry unchanged): what the
        timings lay out to time one part by itself (:mod:`jaxsync.perf.timing`)."""
        return dataclasses.replace(self, parts=(self.parts[index],))

    def dirichlet_local(self, dofs: np.ndarray) -> list[np.ndarray]:
        """For global Dirichlet ``dofs``, the local dof indices (3 * local node + c) of
        each part, a list of arrays."""
        dofs = np.asarray(dofs, dtype=np.int64)
        out = []
        for part in self.parts:
            local_of = np.full(self.n_nodes, -1, dtype=np.int64)
            local_of[part.nodes] = np.arange(part.n_local)
            local_node = local_of[dofs // 3]
            keep = local_node >= 0
            out.append(3 * local_node[keep] + dofs[keep] % 3)
        return out

    def summary(self) -> str:
        """A printable table: elements, nodes and shared nodes per part, interface size."""
        lines = [f"Partition of {self.mesh.n_elements} elements / {self.n_nodes} nodes "
                 f"into {self.n_parts} parts (METIS seed {self.seed})",
                 f"{'part':>6} {'elements':>10} {'nodes':>8} {'shared':>8}"]
        for part in self.parts:
            lines.append(f"{part.index:>6} {len(part.elements):>10} {part.n_local:>8} {part.n_shared:>8}")
        lines.append(f"interface: {self.n_interface} shared nodes, {3 * self.n_interface} dofs")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return (f"Partition(n_parts={self.n_parts}, n_interface={self.n_interface}, "
                f"elements per part={[len(p.elements) for p in self.parts]})")


def _space_of(target):
    """The function space of a mesh (P1), a problem or a space."""
    from ..fem._space import FunctionSpace, function_space

    if isinstance(target, Mesh):
        return function_space(target, "P1")
    if isinstance(target, FunctionSpace):
        return target
    if hasattr(target, "space"):  # a Problem
        return target.space
    raise PartitionError(f"partition a jaxsync.Mesh, a Problem or a FunctionSpace, got {type(target).__name__}")


def partition(mesh, n_parts: int, seed: int = 0) -> Partition:
    """Partition the elements of ``mesh`` into ``n_parts`` face-connected parts with METIS.

    ``mesh``: a :class:`jaxsync.Mesh` (its vertices are the parts' nodes), or a
    :class:`jaxsync.Problem` or :class:`~jaxsync.fem.FunctionSpace` (the nodes of
    its elements: with P2, the edge nodes too). Uses ``pymetis.part_mesh`` on the dual
    graph (elements sharing a face, ``ncommon=3``). Deterministic for a given ``seed``.

    Raises:
        PartitionError: n_parts < 1, more parts than elements, or METIS left a part empty.
    """
    import pymetis

    space = _space_of(mesh)
    mesh = space.mesh

    if isinstance(n_parts, bool) or not isinstance(n_parts, (int, np.integer)) or n_parts < 1:
        raise PartitionError(f"n_parts must be a positive integer, got {n_parts!r}")
    n_parts = int(n_parts)
    if n_parts > mesh.n_elements:
        raise PartitionError(f"cannot split {mesh.n_elements} elements into {n_parts} parts: "
                             "use fewer parts or a finer mesh")
    if n_parts == 1:
        element_part = np.zeros(mesh.n_elements, dtype=np.int64)
    else:
        result = pymetis.part_mesh(n_parts, mesh.tets, options=pymetis.Options(seed=int(seed)),
                                   gtype=pymetis.GType.DUAL, ncommon=3)
        element_part = np.asarray(result.element_part, dtype=np.int64)
    counts = np.bincount(element_part, minlength=n_parts)
    if np.any(counts == 0):
        empty = np.flatnonzero(counts == 0)
        shown = ", ".join(str(int(p)) for p in empty[:5]) + (", ..." if empty.size > 5 else "")
        raise PartitionError(
            f"METIS left {empty.size} of the {n_parts} parts empty (part{'s' if empty.size > 1 else ''} {shown}) "
            f"when splitting {mesh.n_elements} elements ({mesh.n_elements / n_parts:.3g} per part): use fewer parts "
            f"(METIS needs several elements per part; {int(counts.astype(bool).sum())} parts were filled) or a "
            "finer mesh")
    return partition_from_elements(space, element_part, seed=seed)


def partition_from_elements(mesh, element_part: np.ndarray, seed: int = 0) -> Partition:
    """Build the index maps of a given element-to-part assignment (n_elements,) of a mesh
    (a problem or a space: see :func:`partition`)."""
    space = _space_of(mesh)
    mesh, cells = space.mesh, space.cells
    element_part = np.asarray(element_part, dtype=np.int64)
    if element_part.shape != (mesh.n_elements,) or element_part.min() < 0:
        raise PartitionError("element_part must give a part >= 0 for every element")
    n_parts = int(element_part.max()) + 1
    # touches[p, node]: does part p touch node?
    touches = np.zeros((n_parts, space.n_nodes), dtype=bool)
    touches[np.repeat(element_part, cells.shape[1]), cells.ravel()] = True
    n_touching = touches.sum(axis=0)
    shared_nodes = np.flatnonzero(n_touching >= 2)
    interface_of = np.full(space.n_nodes, -1, dtype=np.int64)
    interface_of[shared_nodes] = np.arange(len(shared_nodes))
    sharing_parts = tuple(np.flatnonzero(touches[:, node]) for node in shared_nodes)
    parts = []
    for p in range(n_parts):
        elements = np.flatnonzero(element_part == p)
        nodes = np.flatnonzero(touches[p])
        local_of = np.full(space.n_nodes, -1, dtype=np.int64)
        local_of[nodes] = np.arange(len(nodes))
        shared_local = np.flatnonzero(n_touching[nodes] >= 2)
        parts.append(Part(index=p, elements=elements, nodes=nodes,
                          local_tets=local_of[cells[elements]], shared_local=shared_local,
                          shared_interface=interface_of[nodes[shared_local]]))
    return Partition(mesh=mesh, element_part=element_part, parts=tuple(parts),
                     shared_nodes=shared_nodes, sharing_parts=sharing_parts, seed=int(seed), space=space)


def partition_of(trajectory) -> Partition:
    """The partition a distributed :class:`jaxsync.Trajectory` was computed on (rebuilt
    from the element lists it stores per part)."""
    if not trajectory.parts or any(part.elements is None for part in trajectory.parts):
        raise PartitionError("the trajectory holds no partition: it was not computed by the "
                             "distributed solver (simulate(..., partitions=n))")
    element_part = np.full(trajectory.mesh.n_elements, -1, dtype=np.int64)
    for p, part in enumerate(trajectory.parts):
        element_part[np.asarray(part.elements)] = p
    if np.any(element_part < 0):
        raise PartitionError("the trajectory's parts do not cover every element")
    return partition_from_elements(trajectory.space, element_part)
