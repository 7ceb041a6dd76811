"""The reference elements of a function space, as the total-Lagrangian force uses them
(:mod:`jaxsync.fem.forces`): the shape-function gradients and quadrature weights
at the quadrature points, the rule's size, and each element's lumped mass per unit
density. Formed once, on the host (numpy), from scikit-fem's elements and rules."""

from __future__ import annotations

import numpy as np

from ..errors import ProblemError

__all__ = ["reference_geometry", "quadrature_order", "n_quadrature_points", "shape_derivatives"]


def reference_geometry(space, intorder: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(gradients (n_elements, n_q, k, 3) [1/cm], weights (n_elements, n_q) [cm^3]) of a
    :class:`~jaxsync.fem.FunctionSpace`: the reference shape-function gradients
    grad_X N_a at the quadrature points and the rule's weights times |det dX/dxi|.

    The shape functions and the rule are scikit-fem's (``ElementTetP1``/``ElementTetP2``,
    ``get_quadrature(RefTet, intorder)``); ``intorder`` None: 1 (one point) for P1, 2 (four
    points) for straight P2, 4 for isoparametric (curved) P2. The map X(xi) is the
    isoparametric one of the space's nodes (the straight map for a straight mesh)."""
    dN, w = shape_derivatives(space, intorder)
    X = space.points[space.cells]  # (m, k, 3)
    jac = np.einsum("mka,qkr->mqar", X, dN)  # dX_a / dxi_r
    det = np.linalg.det(jac)
    if not np.all(np.abs(det) > 0):
        raise ProblemError("degenerate element (zero volume) in the mesh: repair the mesh before a "
                           "total-Lagrangian run")
    grads = np.einsum("qkr,mqrj->mqkj", dN, np.linalg.inv(jac))  # dN/dX = dN/dxi . (dX/dxi)^-1
    return grads, np.abs(det) * w[None, :]


def shape_derivatives(space, intorder: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(dN (n_q, k, 3) the derivatives d N_a / d xi of the space's shape functions at the
    quadrature points of the reference tetrahedron, w (n_q,) the rule's weights), with the
    rule of :func:`reference_geometry` (``intorder`` None: :func:`quadrature_order`)."""
    from skfem.quadrature import get_quadrature
    from skfem.refdom import RefTet

    xi, w = get_quadrature(RefTet, quadrature_order(space) if intorder is None else intorder)
    element = space.scalar_element()
    dN = np.stack([element.lbasis(xi, a)[1].T for a in range(space.nodes_per_cell)], axis=1)
    return dN, np.asarray(w, dtype=float)


def quadrature_order(space) -> int:
    """The degree of the quadrature rule of the total-Lagrangian force on ``space``: 1 (one
    point) for P1, 2 (four points) for straight P2, 4 for isoparametric (curved) P2."""
    return 1 if space.element == "P1" else (4 if space.curved else 2)


def n_quadrature_points(space) -> int:
    """The quadrature points per element of :func:`reference_geometry` on ``space``."""
    from skfem.quadrature import get_quadrature
    from skfem.refdom import RefTet

    return len(get_quadrature(RefTet, quadrature_order(space))[1])


def element_unit_mass(space, density_scale) -> np.ndarray:
    """(n_elements, k) the lumped mass of each element at its nodes per unit density [cm^3]:
    P1 V/4 (row sums), P2 HRZ (the consistent mass's diagonal scaled to the element's
    volume), as :func:`jaxsync.fem.lumped_mass` assembles them."""
    from skfem.quadrature import get_quadrature
    from skfem.refdom import RefTet

    scale = np.ones(space.mesh.n_elements) if density_scale is None else np.asarray(density_scale, float)
    if space.element == "P1":
        return np.repeat((space.mesh.volumes() * scale / 4.0)[:, None], 4, axis=1)
    xi, w = get_quadrature(RefTet, 4)  # exact for N_a^2 on straight elements
    element = space.scalar_element()
    k = space.nodes_per_cell
    N = np.stack([element.lbasis(xi, a)[0] for a in range(k)], axis=1)  # (n_q, k)
    dN = np.stack([element.lbasis(xi, a)[1].T for a in range(k)], axis=1)
    det = np.abs(np.linalg.det(np.einsum("mka,qkr->mqar", space.points[space.cells], dN)))  # (m, n_q)
    diagonal = np.einsum("mq,qk->mk", det * w, N**2)
    volume = np.einsum("mq->m", det * w)
    return diagonal * (volume * scale / diagonal.sum(axis=1))[:, None]
