"""Finite-element assembly with scikit-fem: unit operators independent of the material.

The stiffness is assembled as two unit matrices, ``K = lambda K_lambda + mu K_mu``, and
the mass as ``M = rho M_1``, so that material parameters enter JAX as plain numbers and
the solver is differentiable with respect to them. Degrees of freedom are
node-interleaved: dof ``3 i + c`` is component c (x, y, z) of node i.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import scipy.sparse as sp

from ..errors import ProblemError
from .mesh import Mesh, to_skfem

__all__ = ["UnitOperators", "assemble_unit_operators", "consistent_mass", "lumped_mass",
           "body_force_vectors", "pressure_vector", "element_blocks"]


@dataclasses.dataclass(frozen=True, eq=False)
class UnitOperators:
    """Material-independent FE operators of one mesh (scipy CSR, node-interleaved dofs).

    Attributes:
        mesh: the mesh they were assembled on (identity is used to detect staleness).
        K_lambda: (n_dofs, n_dofs) stiffness for lambda = 1, mu = 0 [cm].
        K_mu: (n_dofs, n_dofs) stiffness for lambda = 0, mu = 1 [cm].
        M_1: (n_dofs, n_dofs) consistent mass for unit density [cm^3].
        volumes: (n_elements,) element volumes [cm^3].
        stable_step_memo: exact stability bounds already computed on this mesh, by
            (nu, density scaling, Dirichlet dofs), for E = rho = 1
            (:func:`jaxsync.fem.timestep.max_stable_dt`): a pure function's memo, so that
            problems derived with ``replace`` (new E, damping, loads) do not solve again.
    """

    mesh: Mesh
    K_lambda: sp.csr_matrix
    K_mu: sp.csr_matrix
    M_1: sp.csr_matrix
    volumes: np.ndarray
    stable_step_memo: dict = dataclasses.field(default_factory=dict, repr=False)

    @functools.cached_property
    def block_ell(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Node-blocked ELL form (adjacency (n_nodes, width) int32, and the blocks
        (n_nodes, 3, width, 3) of K_lambda, K_mu and M_1 on it), built once."""
        from .sparse import block_ell_values, node_adjacency

        adjacency = node_adjacency(self.mesh.tets, self.mesh.n_nodes)
        return (adjacency, *(block_ell_values(A, adjacency)
                             for A in (self.K_lambda, self.K_mu, self.M_1)))

    def stiffness(self, lam: float, mu: float) -> sp.csr_matrix:
        """K = lam K_lambda + mu K_mu as a scipy matrix (concrete values only)."""
        return (float(lam) * self.K_lambda + float(mu) * self.K_mu).tocsr()


def _vector_basis(mesh: Mesh, intorder: int):
    from skfem import Basis, ElementTetP1, ElementVectorH1

    return Basis(to_skfem(mesh), ElementVectorH1(ElementTetP1()), intorder=intorder)


def assemble_unit_operators(mesh: Mesh) -> UnitOperators:
    """Assemble K_lambda, K_mu (one-point rule, exact for P1) and the unit consistent mass."""
    from skfem import asm
    from skfem.models.elasticity import linear_elasticity

    stiff_basis = _vector_basis(mesh, intorder=1)
    K_lambda = asm(linear_elasticity(1.0, 0.0), stiff_basis).tocsr()
    K_mu = asm(linear_elasticity(0.0, 1.0), stiff_basis).tocsr()
    return UnitOperators(mesh=mesh, K_lambda=K_lambda, K_mu=K_mu,
                         M_1=consistent_mass(mesh), volumes=mesh.volumes())


def consistent_mass(mesh: Mesh, density_scale: np.ndarray | None = None) -> sp.csr_matrix:
    """Consistent mass (n_dofs, n_dofs) for density ``density_scale`` per element (default 1)."""
    from skfem import BilinearForm, asm
    from skfem.helpers import dot

    basis = _vector_basis(mesh, intorder=2)
    scale = np.ones(mesh.n_elements) if density_scale is None else np.asarray(density_scale, float)

    @BilinearForm
    def mass(u, v, w):
        return w.density * dot(u, v)

    density = np.repeat(scale[:, None], basis.X.shape[1], axis=1)
    return asm(mass, basis, density=density).tocsr()


def lumped_mass(mesh: Mesh, density_scale: np.ndarray | None = None) -> np.ndarray:
    """Lumped mass (n_nodes,) per unit density: row sums of the consistent mass, which for
    P1 tetrahedra is a quarter of each element's (scaled) volume at each of its nodes."""
    weights = mesh.volumes() / 4.0
    if density_scale is not None:
        weights = weights * np.asarray(density_scale, float)
    out = np.zeros(mesh.n_nodes)
    np.add.at(out, mesh.tets, np.repeat(weights[:, None], 4, axis=1))
    return out


def body_force_vectors(mesh: Mesh) -> np.ndarray:
    """(3, n_nodes, 3) nodal loads of a unit body force along x, y, z [cm^3]:
    entry [d] is the load vector of the body force e_d (integral of N_i e_d)."""
    from skfem import LinearForm, asm

    basis = _vector_basis(mesh, intorder=1)
    out = []
    for d in range(3):
        @LinearForm
        def unit(v, w, d=d):
            return v[d]

        out.append(asm(unit, basis).reshape(-1, 3))
    return np.stack(out)


def pressure_vector(mesh: Mesh, surface: str) -> np.ndarray:
    """(n_nodes, 3) nodal loads of a unit pressure on facet set ``surface``: the
    integral of -n . v over its triangles, with n the outward normal [cm^2]."""
    from skfem import ElementTetP1, ElementVectorH1, FacetBasis, LinearForm, asm
    from skfem.helpers import dot

    triangles = mesh.facet_set(surface)
    if len(triangles) == 0:
        raise ProblemError(f"facet set {surface!r} is empty: a pressure needs a surface")
    skmesh = to_skfem(mesh)
    facet_index = _facet_indices(skmesh, triangles)
    boundary = np.zeros(skmesh.facets.shape[1], dtype=bool)
    boundary[skmesh.boundary_facets()] = True
    if not boundary[facet_index].all():
        raise ProblemError(
            f"facet set {surface!r} contains interior faces; a pressure acts on the "
            "boundary only: tag the boundary surface")
    basis = FacetBasis(skmesh, ElementVectorH1(ElementTetP1()), facets=facet_index, intorder=1)

    @LinearForm
    def unit_pressure(v, w):
        return -dot(w.n, v)

    return asm(unit_pressure, basis).reshape(-1, 3)


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


def element_blocks(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """Element stiffness blocks (n_elements, 12, 12) for (lambda=1, mu=0) and (0, 1),
    element dofs ordered node-interleaved like the global ones."""
    from skfem.models.elasticity import linear_elasticity

    basis = _vector_basis(mesh, intorder=1)
    target = (3 * mesh.tets[:, :, None] + np.arange(3)).reshape(-1, 12)
    # skfem orders an element's dofs as (node of t, component): the global interleaving.
    assert np.array_equal(basis.element_dofs.T, target), "unexpected skfem dof layout"
    blocks = []
    for lam, mu in ((1.0, 0.0), (0.0, 1.0)):
        local = np.asarray(linear_elasticity(lam, mu).elemental(basis).tolocal())
        blocks.append(np.ascontiguousarray(local))  # (n_elements, 12, 12)
    return blocks[0], blocks[1]
