"""The :class:`Mesh` container: checks on its arrays, topology (coincident nodes, connected
pieces) and the bridge to scikit-fem.

Layout follows meshio (``points`` is (n_nodes, 3), ``tets`` is (n_elements, 4)), the
transpose of scikit-fem's ``p``/``t``. Boundary facet sets are named triangle lists.
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import Mapping

import numpy as np

from ..errors import MeshError

COINCIDENT_TOLERANCE = 1e-9
"""Nodes closer than this times the bounding-box diagonal count as coincident."""


class MeshWarning(UserWarning):
    """Something in a mesh was repaired at load (inverted elements, unused nodes), or looks
    wrong (coincident nodes that cut it, disconnected pieces)."""


@dataclasses.dataclass(frozen=True, eq=False)
class Mesh:
    """A mesh of linear (4-node) tetrahedra.

    Building one checks its arrays as a file's are checked (:class:`MeshError` naming the
    element or node: wrong shapes, non-finite coordinates, out-of-range indices, repeated
    nodes, zero-volume or inverted elements, nodes used by no element, facets off the node
    list). It repairs nothing: :meth:`from_arrays` (and :func:`read_mesh` for files)
    re-orients inverted elements and drops unused nodes, with a :class:`MeshWarning`.

    Attributes:
        points: (n_nodes, 3) float64 node coordinates [cm].
        tets: (n_elements, 4) int64 node indices, positively oriented.
        facet_sets: name -> (n_facets, 3) int64 node triples of boundary triangles.
        source_node_ids: (n_nodes,) int64 index of each node in the file it was read
            from (differs from ``arange`` when unused nodes were dropped; for a SimVascular
            volume with point data ``GlobalNodeID``, that number - 1).
        mid_nodes: a quadratic mesh's own edge nodes (read from ``tetra10`` cells):
            (n_elements, 6, 3) coordinates, per element in VTK's edge order (vertex pairs
            (0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3)); None for a linear mesh. A
            problem on such a mesh uses quadratic elements by default
            (:mod:`jaxsync.fem`).
    """

    points: np.ndarray
    tets: np.ndarray
    facet_sets: Mapping[str, np.ndarray] = dataclasses.field(default_factory=dict)
    source_node_ids: np.ndarray | None = None
    mid_nodes: np.ndarray | None = None

    def __post_init__(self):
        # the checks of every route to a mesh (files, folders, arrays); repairs are explicit:
        # Mesh.from_arrays / read_mesh re-orient inverted elements and drop unused nodes
        points, tets, vol = _checked_arrays(self.points, self.tets, origin="Mesh")
        inverted = np.flatnonzero(vol < 0)
        if inverted.size:
            e = int(inverted[0])
            raise MeshError(
                f"Mesh: element {e} (nodes {tets[e].tolist()}) is inverted (negative volume {vol[e]:.3e}; "
                f"{inverted.size} such elements): list each element's nodes in right-handed order, or build the "
                "mesh with jaxsync.Mesh.from_arrays(points, tets, facet_sets), which re-orients them (as "
                "jaxsync.read_mesh does for files)")
        used = np.zeros(len(points), dtype=bool)
        used[tets.ravel()] = True
        if not used.all():
            unused = np.flatnonzero(~used)
            raise MeshError(
                f"Mesh: {unused.size} nodes are used by no element (first: node {int(unused[0])}); they would "
                "have no mass: remove them, or build the mesh with jaxsync.Mesh.from_arrays(points, tets, "
                "facet_sets), which drops them and renumbers (as jaxsync.read_mesh does for files)")
        points, tets = np.ascontiguousarray(points), np.ascontiguousarray(tets)
        facets = {k: np.ascontiguousarray(v) for k, v in _checked_facets(self.facet_sets, len(points),
                                                                           "Mesh").items()}
        src = (np.arange(len(points), dtype=np.int64) if self.source_node_ids is None
               else np.asarray(self.source_node_ids, dtype=np.int64))
        if src.shape != (len(points),):
            raise MeshError(f"Mesh: source_node_ids must have shape ({len(points)},), one per node, got {src.shape}")
        mids = None
        if self.mid_nodes is not None:
            mids = np.ascontiguousarray(self.mid_nodes, dtype=np.float64)
            if mids.shape != (len(tets), 6, 3):
                raise MeshError(f"mid_nodes must have shape (n_elements, 6, 3) = ({len(tets)}, 6, 3), got {mids.shape}")
            mids.setflags(write=False)
        for arr in (points, tets, src, *facets.values()):
            arr.setflags(write=False)
        object.__setattr__(self, "mid_nodes", mids)
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "tets", tets)
        object.__setattr__(self, "facet_sets", facets)
        object.__setattr__(self, "source_node_ids", src)

    @property
    def n_nodes(self) -> int:
        return self.points.shape[0]

    @property
    def n_elements(self) -> int:
        return self.tets.shape[0]

    @property
    def n_dofs(self) -> int:
        return 3 * self.n_nodes

    @property
    def bounding_box(self) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) corners, each (3,)."""
        return self.points.min(axis=0), self.points.max(axis=0)

    def volumes(self) -> np.ndarray:
        """(n_elements,) element volumes [cm^3]."""
        return tet_volumes(self.points, self.tets)

    def boundary_facets(self) -> np.ndarray:
        """(n_boundary_facets, 3) node triples of faces that belong to one element only,
        ordered so that their right-hand normal points out of the mesh."""
        local = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
        faces = self.tets[:, local].reshape(-1, 3)
        key = np.sort(faces, axis=1)
        _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        return faces[counts[inverse.ravel()] == 1]

    def nodes_where(self, predicate) -> np.ndarray:
        """Indices of nodes whose coordinates satisfy ``predicate(points) -> (n,) bool``."""
        mask = np.asarray(predicate(self.points), dtype=bool).reshape(-1)
        if mask.shape != (self.n_nodes,):
            raise MeshError(
                f"node predicate returned shape {mask.shape}, expected ({self.n_nodes},): "
                "write it to take the (n_nodes, 3) coordinate array and return one bool per node"
            )
        return np.flatnonzero(mask)

    def facet_nodes(self, name: str) -> np.ndarray:
        """Sorted unique node indices of the facet set ``name``."""
        return np.unique(self.facet_set(name))

    def facet_set(self, name: str) -> np.ndarray:
        """(n_facets, 3) triangles of the facet set ``name``; clear error if unknown."""
        if name not in self.facet_sets:
            known = ", ".join(sorted(self.facet_sets)) or "none"
            raise MeshError(
                f"the mesh has no facet set named {name!r} (known: {known}); tag the surface "
                "as a physical group in gmsh or pick one of the known names"
            )
        return self.facet_sets[name]

    @classmethod
    def from_arrays(cls, points, tets, facet_sets=None) -> "Mesh":
        """A mesh from raw arrays, checked and repaired as :func:`read_mesh` does a file's:
        inverted elements re-oriented and unused nodes dropped (each with a
        :class:`MeshWarning`; ``source_node_ids`` maps the new numbering to the arrays'),
        and warnings for coincident nodes and disconnected pieces
        (:func:`jaxsync.mesh.validated_mesh`). The constructor ``Mesh(points, tets)``
        runs the same checks but repairs nothing: it refuses such arrays.

        Args:
            points: (n_nodes, 3) coordinates [cm].
            tets: (n_elements, 4) node indices.
            facet_sets: name -> (n_facets, 3) node triples of boundary triangles.
        """
        return validated_mesh(points, tets, facet_sets, origin="Mesh.from_arrays")

    def __repr__(self) -> str:
        names = ", ".join(f"{k}: {len(v)}" for k, v in self.facet_sets.items())
        return f"Mesh(n_nodes={self.n_nodes}, n_elements={self.n_elements}, facet_sets={{{names}}})"


def tet_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volumes (n_elements,) of tetrahedra; positive for right-handed ordering."""
    p = points[tets]
    a, b, c = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
    return np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0


def _checked_arrays(points, tets, *, origin: str = "mesh") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points float64 (n_nodes, 3), tets int64 (n_elements, 4), signed volumes
    (n_elements,)) of raw arrays, or :class:`MeshError` for what cannot be repaired: no
    tetrahedra, wrong shapes or types, non-finite coordinates, out-of-range indices,
    repeated nodes within an element, zero-volume elements. The one check of every route
    to a :class:`Mesh` (files, folders, arrays, trajectories)."""
    try:
        points = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise MeshError(f"{origin}: points must be an (n_nodes, 3) array of numbers ({exc})") from None
    tets = np.asarray(tets)
    if points.ndim != 2 or points.shape[1] not in (2, 3):
        raise MeshError(f"{origin}: points must have shape (n_nodes, 3), got {points.shape}")
    if points.shape[1] == 2:
        raise MeshError(f"{origin}: points are 2-D (shape {points.shape}); jaxsync needs a 3-D tetrahedral mesh: "
                        "give three coordinates per node")
    if tets.size == 0:
        raise MeshError(
            f"{origin}: the mesh has no tetrahedra; export a 3-D volume mesh "
            "(in gmsh: Mesh > 3D, and include the volume in a physical group)"
        )
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise MeshError(f"{origin}: tets must have shape (n_elements, 4), got {tets.shape}")
    if not np.issubdtype(tets.dtype, np.integer):
        raise MeshError(f"{origin}: element connectivity must be integers, got {tets.dtype}")
    tets = tets.astype(np.int64)
    bad_points = np.flatnonzero(~np.isfinite(points).all(axis=1))
    if bad_points.size:
        raise MeshError(
            f"{origin}: node {bad_points[0]} has non-finite coordinates {points[bad_points[0]]} "
            f"({bad_points.size} such nodes); fix the mesh file or the coordinate array"
        )
    out_of_range = np.flatnonzero(((tets < 0) | (tets >= len(points))).any(axis=1))
    if out_of_range.size:
        e = out_of_range[0]
        raise MeshError(
            f"{origin}: element {e} refers to node indices {tets[e].tolist()} outside "
            f"0..{len(points) - 1} ({out_of_range.size} such elements); the connectivity "
            "does not match the node list"
        )
    sorted_tets = np.sort(tets, axis=1)
    repeated = np.flatnonzero((sorted_tets[:, 1:] == sorted_tets[:, :-1]).any(axis=1))
    if repeated.size:
        e = repeated[0]
        raise MeshError(
            f"{origin}: element {e} repeats a node ({tets[e].tolist()}), so it has zero volume; "
            "remove degenerate elements from the mesh"
        )
    vol = tet_volumes(points, tets)
    # Degenerate: volume at round-off level relative to the element's own longest edge.
    p = points[tets]
    longest = np.max([np.linalg.norm(p[:, i] - p[:, j], axis=1)
                      for i in range(4) for j in range(i + 1, 4)], axis=0)
    tiny = np.abs(vol) <= 1e-10 * longest**3
    if tiny.any():
        e = np.flatnonzero(tiny)[0]
        raise MeshError(
            f"{origin}: element {e} (nodes {tets[e].tolist()}) has zero volume "
            f"({vol[e]:.3e}); {int(tiny.sum())} degenerate elements in all: remesh or remove them"
        )
    return points, tets, vol


def _checked_facets(facet_sets, n_nodes: int, origin: str) -> dict[str, np.ndarray]:
    """name -> (n_facets, 3) int64 of ``facet_sets``, or :class:`MeshError` for a set that
    is not triangles of the mesh's nodes."""
    facets = {}
    for name, tri in dict(facet_sets or {}).items():
        tri = np.asarray(tri)
        if tri.size and not np.issubdtype(tri.dtype, np.integer):
            raise MeshError(f"{origin}: facet set {name!r} must hold integer node indices, got {tri.dtype}")
        if tri.size % 3 or (tri.ndim == 2 and tri.shape[1] != 3) or tri.ndim > 2:
            raise MeshError(f"{origin}: facet set {name!r} must have shape (n_facets, 3) (node triples), got "
                            f"{tri.shape}")
        tri = tri.astype(np.int64).reshape(-1, 3)
        bad = np.flatnonzero(((tri < 0) | (tri >= n_nodes)).any(axis=1))
        if bad.size:
            raise MeshError(f"{origin}: facet {bad[0]} of the set {name!r} refers to node indices "
                            f"{tri[bad[0]].tolist()} outside 0..{n_nodes - 1}; the facet set does not match "
                            "the node list")
        facets[str(name)] = tri
    return facets


def validated_mesh(points, tets, facet_sets=None, source_node_ids=None, *, origin="mesh",
                   mid_nodes=None, mid_node_ids=None) -> Mesh:
    """Check and repair raw arrays into a :class:`Mesh` (what :func:`read_mesh` does with
    a file's arrays; also :meth:`Mesh.from_arrays`).

    Errors (:class:`MeshError`) for: no tetrahedra, wrong shapes, non-finite coordinates,
    out-of-range indices, repeated nodes within an element, zero-volume elements.
    Repairs (with a :class:`MeshWarning`): inverted elements are re-oriented; nodes used
    by no element are dropped and the remaining nodes renumbered (``source_node_ids``
    keeps the original numbering; facet sets are renumbered too). Warnings for coincident
    nodes that cut the mesh and for disconnected pieces.

    ``mid_nodes``: a quadratic mesh's edge nodes (:attr:`Mesh.mid_nodes`), kept aligned
    with re-oriented elements; ``mid_node_ids``: the nodes that are edge nodes (dropped
    from the vertex mesh without a warning).
    """
    points, tets, vol = _checked_arrays(points, tets, origin=origin)
    inverted = vol < 0
    if mid_nodes is not None:
        mid_nodes = np.array(mid_nodes, dtype=np.float64)
    if inverted.any():
        tets = tets.copy()
        tets[inverted] = tets[inverted][:, [0, 2, 1, 3]]
        if mid_nodes is not None and mid_nodes.shape == (len(tets), 6, 3):  # swapping vertices 1, 2 permutes edges
            mid_nodes[inverted] = mid_nodes[inverted][:, [2, 1, 0, 3, 5, 4]]
        warnings.warn(
            f"{origin}: {int(inverted.sum())} inverted elements (negative volume) were "
            f"re-oriented, first: element {int(np.flatnonzero(inverted)[0])}",
            MeshWarning, stacklevel=3,
        )
    facet_sets = _checked_facets(facet_sets, len(points), origin)
    src = np.arange(len(points)) if source_node_ids is None else np.asarray(source_node_ids)
    used = np.zeros(len(points), dtype=bool)
    used[tets.ravel()] = True
    expected = np.zeros(len(points), dtype=bool)
    if mid_node_ids is not None:
        expected[np.asarray(mid_node_ids, dtype=np.int64)] = True
    if not used.all():
        new_index = np.full(len(points), -1, dtype=np.int64)
        new_index[used] = np.arange(used.sum())
        unused = int((~used & ~expected).sum())
        if unused:
            warnings.warn(
                f"{origin}: {unused} nodes are used by no element and were dropped "
                "(Mesh.source_node_ids maps the new numbering to the file's)",
                MeshWarning, stacklevel=3,
            )
        tets = new_index[tets]
        kept = {}
        for name, tri in facet_sets.items():
            ok = used[tri].all(axis=1)
            kept[name] = new_index[tri[ok]]
        facet_sets = kept
        points, src = points[used], src[used]
    mesh = Mesh(points=points, tets=tets, facet_sets=facet_sets, source_node_ids=src, mid_nodes=mid_nodes)
    warn_about_topology(mesh, origin=origin, stacklevel=4)
    return mesh


def coincident_nodes(mesh: Mesh, tol: float | None = None) -> np.ndarray:
    """(n_pairs, 2) int64 pairs (i, j), i < j, of distinct nodes at most ``tol`` [cm] apart
    (default :data:`COINCIDENT_TOLERANCE` times the bounding-box diagonal).

    Found with a k-d tree (``scipy.spatial.cKDTree.query_pairs``): O(n log n), and unlike
    rounding to a grid it cannot miss a pair that straddles a grid line."""
    from scipy.spatial import cKDTree

    points = mesh.points
    if len(points) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    if tol is None:
        tol = COINCIDENT_TOLERANCE * float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    elif not np.isfinite(tol) or tol < 0:
        raise MeshError(f"coincident-node tolerance must be a finite distance >= 0 [cm], got {tol}")
    pairs = cKDTree(points).query_pairs(float(tol), output_type="ndarray")
    return np.sort(np.asarray(pairs, dtype=np.int64).reshape(-1, 2), axis=1)


def _components(n: int, edges: np.ndarray) -> np.ndarray:
    """(n,) connected-component label of each vertex of the graph with ``edges`` (k, 2)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components as components

    graph = sp.coo_matrix((np.ones(len(edges), dtype=np.int8), (edges[:, 0], edges[:, 1])), shape=(n, n))
    return components(graph, directed=False)[1]


def connected_components(mesh: Mesh) -> np.ndarray:
    """(n_elements,) int64 label of the piece each element belongs to: elements that
    share a node are connected (labels 0, 1, ... in order of each piece's first element;
    all 0 for a connected mesh)."""
    tets = mesh.tets
    # node graph with edges node0-node1, node0-node2, node0-node3 of each element: the same
    # pieces as the element-node incidence graph, with 3 edges per element
    edges = np.stack([np.repeat(tets[:, 0], 3), tets[:, 1:].ravel()], axis=1)
    label = _components(mesh.n_nodes, edges)[tets[:, 0]]
    _, first, inverse = np.unique(label, return_index=True, return_inverse=True)
    rank = np.empty(len(first), dtype=np.int64)
    rank[np.argsort(first)] = np.arange(len(first))
    return rank[inverse.ravel()]


def merge_coincident_nodes(mesh: Mesh, tol: float | None = None) -> Mesh:
    """The mesh with every group of coincident nodes (:func:`coincident_nodes`) replaced
    by its lowest-numbered node.

    Use it on a mesh cut by doubled nodes (two parts that meet at the same coordinates
    without sharing nodes, so that they are not connected). Nodes keep their order;
    elements and facet sets are renumbered; ``source_node_ids`` keeps each kept node's
    number in the file. A triangle that a facet set holds twice after the merge (the two
    faces of the cut, now one interior face) is dropped from that set.

    Args:
        mesh: the mesh to repair.
        tol: distance [cm] at or below which nodes coincide; default
            :data:`COINCIDENT_TOLERANCE` times the bounding-box diagonal.

    Returns:
        A new :class:`Mesh` (``mesh`` itself when no nodes coincide).

    Raises:
        MeshError: the merge would collapse an element (two of its own nodes coincide).
    """
    pairs = coincident_nodes(mesh, tol)
    if len(pairs) == 0:
        return mesh
    n = mesh.n_nodes
    group = _components(n, pairs)
    representative = np.full(group.max() + 1, n, dtype=np.int64)
    np.minimum.at(representative, group, np.arange(n))
    target = representative[group]  # each node's kept copy
    kept = target == np.arange(n)
    remap = (np.cumsum(kept) - 1)[target]
    tets = remap[mesh.tets]
    ordered = np.sort(tets, axis=1)
    collapsed = np.flatnonzero((ordered[:, 1:] == ordered[:, :-1]).any(axis=1))
    if collapsed.size:
        e = int(collapsed[0])
        raise MeshError(
            f"merging coincident nodes would collapse element {e} (nodes {mesh.tets[e].tolist()}; "
            f"{collapsed.size} such elements): two of its own nodes lie at the same place; pass a "
            "smaller tol, or remove the degenerate elements")
    facet_sets = {}
    for name, tri in mesh.facet_sets.items():
        tri = remap[tri]
        if len(tri):
            _, inverse, counts = np.unique(np.sort(tri, axis=1), axis=0, return_inverse=True,
                                           return_counts=True)
            tri = tri[counts[inverse.ravel()] == 1]
        facet_sets[name] = tri
    return Mesh(points=mesh.points[kept], tets=tets, facet_sets=facet_sets,
                source_node_ids=mesh.source_node_ids[kept], mid_nodes=mesh.mid_nodes)


def warn_about_topology(mesh: Mesh, *, origin: str = "mesh", stacklevel: int = 2) -> None:
    """:class:`MeshWarning` when coincident nodes are used by different elements (the mesh
    is cut there: the two sides are not connected) or when the mesh falls into several
    disconnected pieces (a piece without its own support moves as a rigid body). Both
    checks are O(n log n) (k-d tree, sparse connected components)."""
    pairs = coincident_nodes(mesh)
    labels = connected_components(mesh)
    n_pieces = int(labels.max()) + 1
    fix = "merge them with jaxsync.merge_coincident_nodes(mesh)"
    if len(pairs):
        where = mesh.points[pairs[0, 0]]
        warnings.warn(
            f"{origin}: {len(pairs)} pairs of coincident nodes are used by different elements "
            f"(first at ({where[0]:.6g}, {where[1]:.6g}, {where[2]:.6g})): the mesh is cut there, "
            f"its sides are not connected and move independently; {fix}, or fix the mesh export "
            "(in gmsh: Coherence, or Geometry.Tolerance); if the cut is intended (a crack, a "
            "contact gap), ignore this", MeshWarning, stacklevel=stacklevel)
    if n_pieces > 1:
        sizes = np.bincount(labels)
        shown = ", ".join(str(int(k)) for k in sizes[:8]) + (", ..." if n_pieces > 8 else "")
        cause = (" (the coincident nodes above cut it: merge them)" if len(pairs)
                 else "; jaxsync.mesh.connected_components(mesh) labels them")
        warnings.warn(
            f"{origin}: the mesh falls into {n_pieces} disconnected pieces of {shown} elements"
            f"{cause}; a piece without its own Dirichlet support moves as a rigid body",
            MeshWarning, stacklevel=stacklevel)


def to_skfem(mesh: Mesh):
    """The scikit-fem ``MeshTet`` of ``mesh`` (same node and element numbering)."""
    from skfem import MeshTet

    return MeshTet(np.ascontiguousarray(mesh.points.T), np.ascontiguousarray(mesh.tets.T),
                   sort_t=False)
