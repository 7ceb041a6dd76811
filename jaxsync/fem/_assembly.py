"""Finite-element assembly with scikit-fem: unit operators independent of the material.

The stiffness is assembled as two unit matrices, ``K = lambda K_lambda + mu K_mu``, and
the mass as ``M = rho M_1``, so that material parameters enter JAX as plain numbers and
the solver is differentiable with respect to them. Degrees of freedom are
node-interleaved: dof ``3 i + c`` is component c (x, y, z) of node i, the nodes those of
the problem's :class:`~jaxsync.fem.FunctionSpace` (P1: the mesh's vertices; P2: the
vertices, then one node per edge). Every function takes a space, or a mesh (its P1 space).

Quadrature is exact for the linear law: stiffness and surface loads with the rules of
degree 0 (P1) and 2 (P2), the consistent mass with degree 2 (P1) and 4 (P2).

Lumped mass: P1 takes the row sums of the consistent mass (a quarter of each element's
volume at each vertex). Row sums of the P2 consistent mass put a NEGATIVE mass at the
vertices (-1/20 of the element's, per vertex), so P2 lumps by HRZ (Hinton, Rock &
Zienkiewicz 1976): the consistent mass's diagonal, scaled element by element so that the
element's total is its own (rho V per component). Every HRZ mass is positive (for a
straight tetrahedron 1/36 of the element's mass at each vertex, 4/27 at each edge node);
the lumped scheme converges at second order in the frequencies of smooth modes (measured
in ``tests/fem/test_p2.py``).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import scipy.sparse as sp

from ..errors import ProblemError
from ..mesh import Mesh, to_skfem

__all__ = ["UnitOperators", "assemble_unit_operators", "consistent_mass", "lumped_mass",
           "body_force_vectors", "pressure_vector", "traction_vectors", "boundary_facet_indices", "element_blocks"]


def _space(space_or_mesh):
    """A :class:`~jaxsync.fem.FunctionSpace` (a mesh: its P1 space)."""
    from ._space import function_space

    return function_space(space_or_mesh, "P1") if isinstance(space_or_mesh, Mesh) else space_or_mesh


@dataclasses.dataclass(frozen=True, eq=False)
class UnitOperators:
    """Material-independent FE operators of one space (scipy CSR, node-interleaved dofs).

    Attributes:
        mesh: the mesh they were assembled on (identity is used to detect staleness).
        K_lambda: (n_dofs, n_dofs) stiffness for lambda = 1, mu = 0 [cm].
        K_mu: (n_dofs, n_dofs) stiffness for lambda = 0, mu = 1 [cm].
        M_1: (n_dofs, n_dofs) consistent mass for unit density [cm^3].
        volumes: (n_elements,) element volumes [cm^3].
        space: the :class:`~jaxsync.fem.FunctionSpace` (P1 or P2 nodes).

    Problems on the same mesh share one ``UnitOperators`` (:meth:`Problem.replace
    <jaxsync.fem.Problem.replace>` carries it), and so share what is derived from
    the space alone, each computed on first use by :meth:`derived` (the unit surface
    loads, the supports' unit blocks, the follower facets), and the stability bounds that
    do not depend on E and rho (:meth:`stability_bound`: an eigenvalue solve that a
    problem with another E, damping or loads does not repeat). Both are pure functions of
    the space and their key.
    """

    mesh: Mesh
    K_lambda: sp.csr_matrix
    K_mu: sp.csr_matrix
    M_1: sp.csr_matrix
    volumes: np.ndarray
    space: object = None
    # {(kind, key): value} of derived() and stability_bound(): values of pure functions
    _derived: dict = dataclasses.field(default_factory=dict, init=False, repr=False, compare=False)

    def derived(self, kind: str, key, compute):
        """A material-independent array (or tuple of arrays) of this space: ``compute()``
        the first time ``(kind, key)`` is asked for, the same object after.

        Args:
            kind: what it is (``"pressure"``, ``"support blocks"``, ...).
            key: what it depends on besides the space (hashable: a surface name, ...).
            compute: the pure function of the space that makes it.
        """
        if (kind, key) not in self._derived:
            self._derived[kind, key] = compute()
        return self._derived[kind, key]

    def stability_bound(self, kind: str, key, compute):
        """A stability bound of problems on this space that does not depend on E and rho
        (they scale it by sqrt(rho / E)): ``compute()`` the first time ``(kind, key)`` is
        asked for. ``key`` holds everything else the bound depends on (Poisson's ratio or
        the law's parameters, density scaling, Dirichlet dofs, supports, initial
        displacement), as hashable values."""
        return self.derived(f"stability: {kind}", key, compute)

    @functools.cached_property
    def block_ell(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Node-blocked ELL form (adjacency (n_nodes, width) int32, and the blocks
        (n_nodes, 3, width, 3) of K_lambda, K_mu and M_1 on it), built once."""
        from ._sparse import block_ell_values, node_adjacency

        space = _space(self.mesh if self.space is None else self.space)
        adjacency = node_adjacency(space.cells, space.n_nodes)
        return (adjacency, *(block_ell_values(A, adjacency)
                             for A in (self.K_lambda, self.K_mu, self.M_1)))

    def stiffness(self, lam: float, mu: float) -> sp.csr_matrix:
        """K = lam K_lambda + mu K_mu as a scipy matrix (concrete values only)."""
        return (float(lam) * self.K_lambda + float(mu) * self.K_mu).tocsr()


def assemble_unit_operators(space) -> UnitOperators:
    """Assemble K_lambda, K_mu (exact rule: one point for P1, degree 2 for P2) and the unit
    consistent mass of a space (or of a mesh's P1 space)."""
    from skfem import asm
    from skfem.models.elasticity import linear_elasticity

    space = _space(space)
    stiff_basis = space.basis()
    K_lambda = asm(linear_elasticity(1.0, 0.0), stiff_basis).tocsr()
    K_mu = asm(linear_elasticity(0.0, 1.0), stiff_basis).tocsr()
    return UnitOperators(mesh=space.mesh, K_lambda=K_lambda, K_mu=K_mu,
                         M_1=consistent_mass(space), volumes=space.mesh.volumes(), space=space)


def _mass_basis(space):
    """The vector basis whose rule integrates the consistent mass exactly."""
    return space.basis(intorder=2 if space.element == "P1" else 4)


def consistent_mass(space, density_scale: np.ndarray | None = None) -> sp.csr_matrix:
    """Consistent mass (n_dofs, n_dofs) for density ``density_scale`` per element (default 1)."""
    from skfem import BilinearForm, asm
    from skfem.helpers import dot

    space = _space(space)
    basis = _mass_basis(space)
    scale = np.ones(space.mesh.n_elements) if density_scale is None else np.asarray(density_scale, float)

    @BilinearForm
    def mass(u, v, w):
        return w.density * dot(u, v)

    density = np.repeat(scale[:, None], basis.X.shape[1], axis=1)
    return asm(mass, basis, density=density).tocsr()


def lumped_mass(space, density_scale: np.ndarray | None = None) -> np.ndarray:
    """Lumped mass (n_nodes,) per unit density (module docstring): P1 row sums, a
    quarter of each element's (scaled) volume at each of its nodes; P2 by HRZ, every
    mass positive, each element's total exact."""
    space = _space(space)
    scale = 1.0 if density_scale is None else np.asarray(density_scale, float)
    if space.element == "P1":
        weights = space.mesh.volumes() / 4.0
        if density_scale is not None:
            weights = weights * scale
        out = np.zeros(space.n_nodes)
        np.add.at(out, space.cells, np.repeat(weights[:, None], 4, axis=1))
        return out
    diagonal = _hrz_diagonals(space)  # (n_elements, 10) of a unit density
    volumes = _curved_volumes(space) if space.curved else space.mesh.volumes()
    weights = diagonal * (volumes / diagonal.sum(axis=1))[:, None] * np.broadcast_to(scale, volumes.shape)[:, None]
    out = np.zeros(space.n_nodes)
    np.add.at(out, space.cells, weights)
    return out


def _hrz_diagonals(space) -> np.ndarray:
    """(n_elements, nodes per cell) the diagonal of each element's scalar consistent mass."""
    from skfem import Basis, BilinearForm

    basis = Basis(space.skfem_mesh(), space.scalar_element(), intorder=4)

    @BilinearForm
    def mass(u, v, w):
        return u * v

    local = np.asarray(mass.elemental(basis).tolocal())  # (n_elements, k, k)
    return np.einsum("eii->ei", local)


def _curved_volumes(space) -> np.ndarray:
    """(n_elements,) volumes of isoparametric elements (integral of 1)."""
    from skfem import Basis, Functional

    basis = Basis(space.skfem_mesh(), space.scalar_element(), intorder=4)

    @Functional
    def one(w):
        return 1.0 + 0.0 * w.x[0]

    return np.asarray(one.elemental(basis))


def body_force_vectors(space) -> np.ndarray:
    """(3, n_nodes, 3) nodal loads of a unit body force along x, y, z [cm^3]:
    entry [d] is the load vector of the body force e_d (integral of N_i e_d)."""
    return _unit_component_loads(_space(space).basis())


def _unit_component_loads(basis) -> np.ndarray:
    """(3, n_nodes, 3): entry [d] integrates N_i e_d over ``basis``'s cells or facets."""
    from skfem import LinearForm, asm

    out = []
    for d in range(3):
        @LinearForm
        def unit(v, w, d=d):
            return v[d]

        out.append(asm(unit, basis).reshape(-1, 3))
    return np.stack(out)


def pressure_vector(space, surface: str) -> np.ndarray:
    """(n_nodes, 3) nodal loads of a unit pressure on facet set ``surface``: the
    integral of -n . v over its triangles, with n the outward normal [cm^2]."""
    from skfem import LinearForm, asm
    from skfem.helpers import dot

    space = _space(space)
    skmesh = to_skfem(space.mesh)
    basis = space.facet_basis(boundary_facet_indices(space.mesh, skmesh, surface, what="a pressure"))

    @LinearForm
    def unit_pressure(v, w):
        return -dot(w.n, v)

    return asm(unit_pressure, basis).reshape(-1, 3)


def traction_vectors(space, surface: str) -> np.ndarray:
    """(3, n_nodes, 3) nodal loads of a unit traction along x, y, z on the facet set
    ``surface``: entry [d] is the integral of N_i e_d over its triangles [cm^2] (for P1, a
    third of each triangle's area at each of its nodes)."""
    space = _space(space)
    skmesh = to_skfem(space.mesh)
    return _unit_component_loads(space.facet_basis(boundary_facet_indices(space.mesh, skmesh, surface,
                                                                          what="a traction")))


def boundary_facet_indices(mesh: Mesh, skmesh, surface: str, *, what: str) -> np.ndarray:
    """Indices into ``skmesh.facets`` of the facet set ``surface``, checked to be a
    non-empty set of boundary faces (``what`` acts there: named in the errors)."""
    triangles = mesh.facet_set(surface)
    if len(triangles) == 0:
        raise ProblemError(f"facet set {surface!r} is empty: {what} needs a surface")
    facet_index = _facet_indices(skmesh, triangles)
    boundary = np.zeros(skmesh.facets.shape[1], dtype=bool)
    boundary[skmesh.boundary_facets()] = True
    if not boundary[facet_index].all():
        raise ProblemError(
            f"facet set {surface!r} contains {int((~boundary[facet_index]).sum())} interior faces; "
            f"{what} acts on the boundary only: tag the boundary surface")
    return facet_index


def _facet_indices(skmesh, triangles: np.ndarray) -> np.ndarray:
    """Indices into ``skmesh.facets`` of the given node triples (any order)."""
    # int64: scikit-fem stores facets as int32, and the key below is ~n^3, which
    # overflows int32 beyond ~1290 nodes (every pressure on a realistic mesh failed)
    facets = np.sort(skmesh.facets.T, axis=1).astype(np.int64)
    wanted = np.sort(np.asarray(triangles), axis=1).astype(np.int64)
    n = int(max(facets.max(), wanted.max())) + 1
    key = lambda a: (a[:, 0] * n + a[:, 1]) * n + a[:, 2]  # noqa: E731
    fkey, wkey = key(facets), key(wanted)
    order = np.argsort(fkey)
    pos = np.searchsorted(fkey[order], wkey)
    pos = np.minimum(pos, len(order) - 1)
    found = fkey[order][pos] == wkey
    if not found.all():
        bad = wanted[np.flatnonzero(~found)[0]]
        raise ProblemError(f"triangle {bad.tolist()} of a facet set is not a face of any element")
    return order[pos]


def element_blocks(space) -> tuple[np.ndarray, np.ndarray]:
    """Element stiffness blocks (n_elements, 3 k, 3 k), k nodes per element, for
    (lambda=1, mu=0) and (0, 1), element dofs ordered node-interleaved like the global
    ones (the nodes of ``space.cells``)."""
    from skfem.models.elasticity import linear_elasticity

    space = _space(space)
    basis = space.basis()
    k = space.nodes_per_cell
    target = (3 * space.cells[:, :, None] + np.arange(3)).reshape(-1, 3 * k)
    # skfem orders an element's dofs as (node of the cell, component): the global interleaving.
    if not np.array_equal(basis.element_dofs.T, target):
        raise ProblemError("unexpected scikit-fem dof layout of the element blocks")
    blocks = []
    for lam, mu in ((1.0, 0.0), (0.0, 1.0)):
        local = np.asarray(linear_elasticity(lam, mu).elemental(basis).tolocal())
        blocks.append(np.ascontiguousarray(local))  # (n_elements, 3 k, 3 k)
    return blocks[0], blocks[1]
