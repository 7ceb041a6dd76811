"""The solution nodes of a problem: linear (P1) or quadratic (P2) tetrahedra on a mesh.

A :class:`FunctionSpace` says where the displacement lives: for P1 at the mesh's
vertices, for P2 at the vertices and at one node per edge (scikit-fem's
``ElementTetP2``). Its nodes are numbered the vertices first (the mesh's numbering), then
the edge nodes (scikit-fem's edge numbering), and ``cells`` gives each element's nodes in
scikit-fem's local order (4 vertices, then its 6 edges). Fields of a problem are
(n_nodes, 3) on these nodes; the mesh keeps the geometry and the facet sets.

Edge nodes sit at the straight edges' midpoints on a linear mesh; a quadratic mesh read
from a file (``tetra10``) keeps its own mid nodes, and a mid node off its edge's midpoint
(a curved boundary) makes the elements isoparametric (scikit-fem's ``MeshTet2``). P2 on a
tet4 mesh is the same space as a tet10 mesh with straight edges.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Callable

import numpy as np

from ..errors import MeshError, ProblemError
from ..mesh import Mesh
from ..options import Element, choices

__all__ = ["FunctionSpace", "ELEMENTS", "function_space", "VTK_TETRA10_ORDER", "vtk_cells"]

ELEMENTS = choices(Element)
"""The elements a :class:`jaxsync.Problem` takes: linear or quadratic tetrahedra."""

VTK_TETRA10_ORDER = ((0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3))
"""The vertex pairs of VTK's (and meshio's) tetra10 nodes 4-9, in order."""


@dataclasses.dataclass(frozen=True, eq=False)
class FunctionSpace:
    """The solution nodes of ``element`` on ``mesh``.

    Attributes:
        mesh: the (vertex) mesh: geometry, facet sets.
        element: ``"P1"`` or ``"P2"``.
        points: (n_nodes, 3) coordinates of the solution nodes [cm]: the mesh's vertices,
            then (P2) the edge nodes.
        cells: (n_elements, 4 or 10) int64 each element's nodes in scikit-fem's local order.
        edges: (n_edges, 2) int64 the vertex pairs of the edge nodes (P2; empty for P1).
        curved: True when an edge node lies off its edge's midpoint (isoparametric P2).
    """

    mesh: Mesh
    element: str
    points: np.ndarray
    cells: np.ndarray
    edges: np.ndarray
    curved: bool = False

    @property
    def n_nodes(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_dofs(self) -> int:
        return 3 * self.n_nodes

    @property
    def nodes_per_cell(self) -> int:
        return int(self.cells.shape[1])

    @property
    def n_vertices(self) -> int:
        return self.mesh.n_nodes

    def skfem_mesh(self):
        """The scikit-fem mesh of the space: ``MeshTet`` (straight elements) or the
        isoparametric ``MeshTet2`` with the edge nodes as given."""
        from ..mesh import to_skfem

        skmesh = to_skfem(self.mesh)
        if not self.curved:
            return skmesh
        from skfem import MeshTet2

        return MeshTet2(np.ascontiguousarray(self.points.T), np.ascontiguousarray(self.mesh.tets.T), sort_t=False)

    def scalar_element(self):
        from skfem import ElementTetP1, ElementTetP2

        return ElementTetP2() if self.element == "P2" else ElementTetP1()

    def basis(self, intorder: int | None = None):
        """The scikit-fem vector basis of the space (``intorder`` None: the element's
        exact rule for stiffness, degree 0 for P1 and 2 for P2)."""
        from skfem import Basis, ElementVectorH1

        if intorder is None:  # exact for straight elements; curved ones integrate rational terms
            intorder = 1 if self.element == "P1" else (4 if self.curved else 2)
        return Basis(self.skfem_mesh(), ElementVectorH1(self.scalar_element()), intorder=intorder)

    def facet_basis(self, facets: np.ndarray, intorder: int | None = None):
        """The vector basis on the given facets (indices into scikit-fem's facets)."""
        from skfem import ElementVectorH1, FacetBasis

        if intorder is None:
            intorder = 1 if self.element == "P1" else 2
        return FacetBasis(self.skfem_mesh(), ElementVectorH1(self.scalar_element()), facets=facets, intorder=intorder)

    @functools.cached_property
    def _edge_index(self) -> dict:
        return {(int(a), int(b)): k for k, (a, b) in enumerate(self.edges)}

    def edge_nodes(self, pairs: np.ndarray) -> np.ndarray:
        """(n,) the P2 nodes on the edges given as (n, 2) vertex pairs (either order)."""
        pairs = np.sort(np.asarray(pairs, dtype=np.int64).reshape(-1, 2), axis=1)
        index = self._edge_index
        return self.n_vertices + np.array([index[(int(a), int(b))] for a, b in pairs], dtype=np.int64)

    def facet_nodes(self, name: str) -> np.ndarray:
        """Sorted solution nodes on the facet set ``name``: its vertices and, for P2, the
        nodes of its triangles' edges."""
        tri = self.mesh.facet_set(name)
        vertices = np.unique(tri)
        if self.element == "P1" or len(tri) == 0:
            return vertices
        pairs = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [0, 2]]]), axis=1)
        return np.concatenate([vertices, self.edge_nodes(np.unique(pairs, axis=0))])

    def nodes_where(self, predicate: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """Sorted solution nodes whose coordinates satisfy ``predicate(points) -> bool``."""
        mask = np.asarray(predicate(self.points), dtype=bool)
        if mask.shape != (self.n_nodes,):
            raise ProblemError(f"node predicate must return a ({self.n_nodes},) bool array, got {mask.shape}")
        return np.flatnonzero(mask)

    def volumes(self) -> np.ndarray:
        """(n_elements,) element volumes [cm^3] (of the straight elements)."""
        return self.mesh.volumes()


def _skfem_cells(skmesh, element) -> np.ndarray:
    """(n_elements, nodes per cell) solution nodes of each element (scikit-fem's dofs of
    the scalar element: one per node)."""
    from skfem import Basis

    return np.ascontiguousarray(Basis(skmesh, element, intorder=1).element_dofs.T, dtype=np.int64)


@functools.lru_cache(maxsize=32)
def _cached(mesh_id: int, mesh: Mesh, element: str) -> FunctionSpace:
    from skfem import ElementTetP2

    from ..mesh import to_skfem

    if element == "P1":
        return FunctionSpace(mesh, "P1", mesh.points, mesh.tets.astype(np.int64), np.zeros((0, 2), np.int64))
    skmesh = to_skfem(mesh)
    edges = np.ascontiguousarray(np.sort(skmesh.edges.T, axis=1), dtype=np.int64)
    midpoints = 0.5 * (mesh.points[edges[:, 0]] + mesh.points[edges[:, 1]])
    points = np.concatenate([mesh.points, midpoints])
    curved = False
    if mesh.mid_nodes is not None:  # a quadratic mesh's own edge nodes
        given = _edge_points_of(mesh, edges)
        scale = float(np.linalg.norm(np.ptp(mesh.points, axis=0))) or 1.0
        curved = bool(np.abs(given - midpoints).max() > 1e-12 * scale)
        points = np.concatenate([mesh.points, given])
    cells = _skfem_cells(skmesh, ElementTetP2())
    if cells.shape[1] != 10 or cells[:, :4].tolist() != mesh.tets.tolist():
        raise ProblemError("unexpected scikit-fem P2 dof layout (vertices first, then edges)")
    return FunctionSpace(mesh, "P2", points, cells, edges, curved)


def _edge_points_of(mesh: Mesh, edges: np.ndarray) -> np.ndarray:
    """(n_edges, 3) the coordinates of a quadratic mesh's edge nodes
    (``mesh.mid_nodes``: per element, the VTK-ordered mid-node coordinates)."""
    found = {}
    mids = np.asarray(mesh.mid_nodes)
    for (a, b), column in zip(VTK_TETRA10_ORDER, range(6)):
        pair = np.sort(mesh.tets[:, [a, b]], axis=1)
        for key, point in zip(map(tuple, pair), mids[:, column]):
            found.setdefault(key, point)
    missing = [tuple(e) for e in edges if tuple(e) not in found]
    if missing:
        raise MeshError(f"the quadratic mesh has no mid node on {len(missing)} edges (e.g. {missing[0]})")
    return np.array([found[(int(a), int(b))] for a, b in edges])


def function_space(mesh: Mesh, element: str = "P1") -> FunctionSpace:
    """The :class:`FunctionSpace` of ``element`` (``"P1"`` or ``"P2"``) on ``mesh``
    (computed once per mesh and element)."""
    if element not in ELEMENTS:
        raise ProblemError(f"element must be one of {', '.join(map(repr, ELEMENTS))}, got {element!r}")
    return _cached(id(mesh), mesh, element)


def vtk_cells(space: FunctionSpace) -> tuple[str, np.ndarray]:
    """(cell type, cells) of the space as VTK / XDMF / meshio write them: ``"tetra"`` with
    the mesh's tetrahedra, or ``"tetra10"`` with the edge nodes in VTK's order."""
    if space.element == "P1":
        return "tetra", space.mesh.tets
    vertex = space.cells[:, :4]
    order = [space.edge_nodes(vertex[:, [a, b]]) for a, b in VTK_TETRA10_ORDER]  # each pair's edge node
    return "tetra10", np.concatenate([vertex, np.stack(order, axis=1)], axis=1)
