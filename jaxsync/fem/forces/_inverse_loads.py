"""The supports and dead loads of the inverse (zero-pressure) problem, as functions of the
unknown reference positions X at the known imaged positions x.

In the forward problem the elastic supports' springs (:mod:`jaxsync.fem.forces`) and the
dead loads (body force per unit reference volume, traction and non-follower pressure on the
reference surface, :mod:`jaxsync.fem`) are integrals over the reference geometry. When
the reference is the unknown, they are functions of X (x fixed), with the isoparametric map
of each facet or element (tangents X_,xi and X_,eta, area element |X_,xi x X_,eta|, volume
element det dX/dxi):

* spring, k_s per unit area: f_a = k_s sum_q w_q |A_q| N_a P_q sum_b N_b (x_b - X_b), with
  A_q = X_,xi x X_,eta and P_q = I, or n n^T (n = A_q / |A_q|) for ``normal_only``: S u with
  u = x - X, the forward spring force;
* traction t and dead pressure p on a facet: f_a = sum_q w_q N_a (|A_q| t - p A_q) (A_q
  points out of the solid);
* body force b: f_a = sum_q w_q N_a det(dX/dxi)_q b.

The rules are those the forward problem assembles the same terms with on the unloaded mesh
(scikit-fem's, :meth:`jaxsync.fem.FunctionSpace.basis` and ``facet_basis``; the
support's exact rule of degree 2 for P1 and 4 for P2), so that the inverse problem is the
forward one's equilibrium written in X: inflating the unloaded geometry gives back x at
round-off. Their derivatives in X are exact (``jax.jacfwd``, facet by facet and element by
element) and enter the tangent of the inverse problem.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ...errors import ProblemError
from ...pytree import pytree_dataclass, static_field

__all__ = ["SpringTerm", "SurfaceLoadTerm", "VolumeLoadTerm", "InverseLoads", "inverse_loads", "loads_tangent",
           "inverse_loads_force", "inverse_loads_product"]


def _area_vectors(Xf, tangents):
    """(n_q, 3) X_,xi x X_,eta at the rule's points of a facet with nodes Xf (k_f, 3)."""
    a = jnp.einsum("qdk,ki->qdi", tangents, Xf)
    return jnp.cross(a[:, 0], a[:, 1])


@pytree_dataclass
class SpringTerm:
    """An elastic support's spring on its facets (module docstring).

    Attributes:
        cells: (n_f, k_f) int32 the facets' nodes (vertices, then edge nodes).
        shape: (n_q, k_f) shape functions at the rule's points.
        tangents: (n_q, 2, k_f) their derivatives in (xi, eta).
        weights: (n_q,) the rule's weights on the reference triangle.
        stiffness: k_s [dyn/cm^3].
        normal_only: the spring acts along the reference normal only.
    """

    cells: Any
    shape: Any
    tangents: Any
    weights: Any
    stiffness: Any
    normal_only: bool = static_field(default=False)

    def local(self, Xc, xc):
        """(k_f, 3) the facet's spring forces [dyn] at reference Xc and imaged xc (k_f, 3)."""
        A = _area_vectors(Xc, self.tangents)
        area = jnp.linalg.norm(A, axis=1)
        u = jnp.einsum("qk,ki->qi", self.shape, xc - Xc)  # displacement at the points
        if self.normal_only:
            n = A / area[:, None]
            u = jnp.einsum("qi,qj,qj->qi", n, n, u)
        return self.stiffness * jnp.einsum("q,q,qk,qi->ki", self.weights, area, self.shape, u)


@pytree_dataclass
class SurfaceLoadTerm:
    """A traction ``vector`` [dyn/cm^2] and a dead ``pressure`` [barye] on facets (module
    docstring); fields as :class:`SpringTerm`'s, the facets oriented out of the solid."""

    cells: Any
    shape: Any
    tangents: Any
    weights: Any
    vector: Any
    pressure: Any

    def local(self, Xc, xc):
        """(k_f, 3) the facet's nodal forces [dyn] at reference Xc (k_f, 3)."""
        A = _area_vectors(Xc, self.tangents)
        t = jnp.linalg.norm(A, axis=1)[:, None] * self.vector[None, :] - self.pressure * A
        return jnp.einsum("q,qk,qi->ki", self.weights, self.shape, t)


@pytree_dataclass
class VolumeLoadTerm:
    """A body force ``vector`` [dyn/cm^3] per unit reference volume on the elements.

    Attributes:
        cells: (n_elements, k) int32 each element's nodes.
        shape: (n_q, k) shape functions at the rule's points of the reference tetrahedron.
        derivatives: (n_q, k, 3) their derivatives in xi.
        weights: (n_q,) the rule's weights.
        vector: (3,) the force density.
    """

    cells: Any
    shape: Any
    derivatives: Any
    weights: Any
    vector: Any

    def local(self, Xc, xc):
        """(k, 3) the element's nodal forces [dyn] at reference Xc (k, 3)."""
        volume = jnp.linalg.det(jnp.einsum("ka,qkr->qar", Xc, self.derivatives))
        return jnp.einsum("q,q,qk,i->ki", self.weights, volume, self.shape, self.vector)


def _term_force(term, X, x):
    forces = jax.vmap(term.local)(X[term.cells], x[term.cells])
    return jax.ops.segment_sum(forces.reshape(-1, 3), term.cells.reshape(-1), num_segments=X.shape[0])


def _term_blocks(term, X, x):
    """(n_cells, 3 k, 3 k) d f_c / d X_c, node-interleaved."""
    def one(Xc, xc):
        return jax.jacfwd(lambda v: term.local(v.reshape(Xc.shape), xc).reshape(-1))(Xc.reshape(-1))

    return jax.vmap(one)(X[term.cells], x[term.cells])


@pytree_dataclass
class InverseLoads:
    """The X-dependent external terms of the inverse problem's residual,
    R(X) = f_int(X) + springs(X) - fraction (loads(X) + f_follower(x)).

    Attributes:
        springs: tuple of :class:`SpringTerm`.
        loads: tuple of :class:`SurfaceLoadTerm` and :class:`VolumeLoadTerm` (at full
            magnitude, time factor 1).
        current: (n_nodes, 3) the imaged positions x [cm].
    """

    springs: tuple
    loads: tuple
    current: Any

    def force(self, X, fraction):
        """(n_nodes, 3) springs(X) - fraction loads(X) [dyn]."""
        total = jnp.zeros_like(X)
        for term in self.springs:
            total = total + _term_force(term, X, self.current)
        for term in self.loads:
            total = total - fraction * _term_force(term, X, self.current)
        return total

    def blocks(self, X, fraction):
        """Per term, its (n_cells, 3 k, 3 k) blocks of d force / d X [dyn/cm]."""
        return ([_term_blocks(term, X, self.current) for term in self.springs]
                + [-fraction * _term_blocks(term, X, self.current) for term in self.loads])

    @property
    def empty(self) -> bool:
        return not self.springs and not self.loads


def inverse_loads(problem) -> InverseLoads:
    """The :class:`InverseLoads` of ``problem``'s elastic supports (their springs; a dashpot
    does not act at rest) and dead loads (body forces, tractions, non-follower pressures)
    at the imaged positions (the problem's nodes).

    Raises:
        ProblemError: a load of another kind (its force on an unknown reference is not known
            here): the message names it.
    """
    from skfem.quadrature import get_quadrature
    from skfem.refdom import RefTet

    from .._loads import BodyForce, Pressure, Traction
    from .._reference_element import shape_derivatives
    from ._follower import facet_nodes, facet_rule

    space, element = problem.space, problem.element
    springs = []
    for support in problem.supports:
        facets, _ = facet_nodes(space, support.surface)
        shape, tangents, w = facet_rule(element, 2 if element == "P1" else 4)
        springs.append(SpringTerm(jnp.asarray(facets, dtype=jnp.int32), jnp.asarray(shape), jnp.asarray(tangents),
                                  jnp.asarray(w), jnp.asarray(support.stiffness, dtype=float), support.normal_only))
    loads = []
    order = 1 if element == "P1" else 2  # the forward problem's facet rule for loads
    for load in problem.loads:
        if isinstance(load, Pressure) and load.follower:
            continue  # on the imaged surface: a constant of the inverse problem
        if isinstance(load, (Pressure, Traction)):
            facets, _ = facet_nodes(space, load.surface)
            shape, tangents, w = facet_rule(element, order)
            vector = jnp.zeros(3) if isinstance(load, Pressure) else jnp.asarray(load.vector, dtype=float)
            pressure = jnp.asarray(load.magnitude if isinstance(load, Pressure) else 0.0, dtype=float)
            loads.append(SurfaceLoadTerm(jnp.asarray(facets, dtype=jnp.int32), jnp.asarray(shape),
                                         jnp.asarray(tangents), jnp.asarray(w), vector, pressure))
        elif isinstance(load, BodyForce):
            intorder = 1 if element == "P1" else 4  # the unloaded P2 mesh is isoparametric
            dN, w = shape_derivatives(space, intorder)
            xi, _ = get_quadrature(RefTet, intorder)
            scalar = space.scalar_element()
            N = np.stack([scalar.lbasis(xi, a)[0] for a in range(space.nodes_per_cell)], axis=1)
            loads.append(VolumeLoadTerm(jnp.asarray(space.cells, dtype=jnp.int32), jnp.asarray(N), jnp.asarray(dN),
                                        jnp.asarray(w, dtype=float), jnp.asarray(load.vector, dtype=float)))
        else:
            raise ProblemError(f"the zero-pressure geometry does not take a {type(load).__name__} load: its force "
                               "on an unknown reference geometry is not defined here; use BodyForce, Traction or "
                               "Pressure (follower or dead)")
    return InverseLoads(tuple(springs), tuple(loads), jnp.asarray(space.points))


@jax.jit
def inverse_loads_force(loads: InverseLoads, X, fraction):
    """``loads.force(X, fraction)`` compiled."""
    return loads.force(X, fraction)


@jax.jit
def inverse_loads_product(loads: InverseLoads, X, fraction, V):
    """(n_nodes, 3) (d force / d X) V [dyn] (a ``jax.jvp``)."""
    return jax.jvp(lambda Y: loads.force(Y, fraction), (X,), (V,))[1]


@jax.jit
def _blocks(loads: InverseLoads, X, fraction):
    return loads.blocks(X, fraction)


def loads_tangent(loads: InverseLoads, X, fraction):
    """d force / d X (scipy CSR, (3 n_nodes, 3 n_nodes) [dyn/cm], node-interleaved) at
    reference positions X (n_nodes, 3) [cm], or None without terms."""
    import scipy.sparse as sp

    if loads.empty:
        return None
    n = 3 * int(np.shape(X)[0])
    total = sp.csr_matrix((n, n))
    terms = list(loads.springs) + list(loads.loads)
    for term, blocks in zip(terms, _blocks(loads, jnp.asarray(X), jnp.asarray(fraction, dtype=float))):
        cells = np.asarray(term.cells)
        dofs = (3 * cells[:, :, None] + np.arange(3)).reshape(len(cells), -1)
        size = dofs.shape[1]
        rows = np.broadcast_to(dofs[:, :, None], (len(cells), size, size)).ravel()
        cols = np.broadcast_to(dofs[:, None, :], (len(cells), size, size)).ravel()
        total = total + sp.coo_matrix((np.asarray(blocks).ravel(), (rows, cols)), shape=(n, n)).tocsr()
    return total
