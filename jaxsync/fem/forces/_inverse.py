"""The internal force of an unknown reference configuration at a known deformed one: the
weak form of the inverse (zero-pressure) problem (Govindjee & Mihalic 1996).

A vessel imaged under the blood pressure gives the deformed node positions x; the
reference (unloaded) positions X are the unknowns. With the isoparametric map of each
element, dX/dxi = sum_a X_a (x) dN_a/dxi, the shape-function gradients of the reference
are grad_X N_a = dN_a/dxi (dX/dxi)^-1, the deformation gradient is
F = sum_a x_a (x) grad_X N_a, and the element's nodal forces are

    f_a(X) = sum_q w_q det(dX/dxi)_q P(F_q) grad_X N_a(xi_q)    [dyn],

the total-Lagrangian force (:mod:`jaxsync.fem.forces`) written as a function of
X at fixed x. Every quantity is a JAX function of X and of the law's parameters, so the
tangent dR/dX of the inverse problem is exact (``jax.jacfwd``, element by element) and its
products are ``jax.jvp`` s. The quadrature rule is that of the reference geometry the
problem will have: one point for P1, the 4-point degree-4 rule of curved (isoparametric) P2
(the unloaded geometry's edge nodes leave their edges' midpoints).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ...errors import ProblemError
from ...pytree import pytree_dataclass
from .._kinematics import determinant

__all__ = ["InverseForce", "inverse_operator", "split_fibres"]


def split_fibres(material) -> tuple:
    """(the law without its fibres, fibres (n_elements, 2, 3) or None): the fibres are handed
    to the stress element by element, as :class:`jaxsync.fem.forces.TotalLagrangian`
    does. Works on traced laws."""
    if not hasattr(material, "fibres"):
        return material, None
    if material.fibres is None:
        raise ProblemError("HolzapfelGasserOgden needs fibre directions: give fibres= (n_elements, 2, 3), for "
                           "instance jaxsync.helical_fibres(mesh.points[mesh.tets].mean(axis=1), axis, angle)")
    return material.replace(fibres=None), jnp.asarray(material.fibres)


@pytree_dataclass
class InverseForce:
    """f_int of reference positions X (n_nodes, 3) [cm] at the fixed deformed positions
    ``current`` (module docstring), a pytree.

    Attributes:
        cells: (n_elements, k) int32 each element's nodes (k = 4 for P1, 10 for P2).
        derivatives: (n_q, k, 3) dN_a/dxi at the quadrature points of the reference tetrahedron.
        rule: (n_q,) the rule's weights on the reference tetrahedron.
        current: (n_nodes, 3) the deformed (imaged) node positions x [cm].
        material: the hyperelastic law (its fibres, if any, in ``fibres``).
        fibres: (n_elements, 2, 3) fibre directions of the reference configuration, or None.
    """

    cells: Any
    derivatives: Any
    rule: Any
    current: Any
    material: Any
    fibres: Any

    def _element(self, Xe, xe, fibres):
        """(k, 3) one element's nodal forces [dyn] and (n_q,) det dX/dxi, det F."""
        jac = jnp.einsum("ka,qkr->qar", Xe, self.derivatives)  # dX_a / dxi_r
        grads = jnp.einsum("qkr,qrj->qkj", self.derivatives, jnp.linalg.inv(jac))  # grad_X N_a
        F = jnp.einsum("ka,qkj->qaj", xe, grads)
        P = self.material.first_piola(F, None if fibres is None else fibres[None])
        volume = determinant(jac)
        return jnp.einsum("q,qij,qkj->ki", volume * self.rule, P, grads), volume, determinant(F)

    def _per_element(self, X, function):
        Xe, xe = X[self.cells], self.current[self.cells]
        if self.fibres is None:
            return jax.vmap(lambda a, b: function(a, b, None))(Xe, xe)
        return jax.vmap(function)(Xe, xe, self.fibres)

    def force(self, X):
        """(n_nodes, 3) the internal force f_int [dyn] of reference X at the current positions."""
        forces = self._per_element(X, lambda a, b, f: self._element(a, b, f)[0])
        return jax.ops.segment_sum(forces.reshape(-1, 3), self.cells.reshape(-1), num_segments=X.shape[0])

    def jacobians(self, X):
        """(n_elements, n_q, 2) det dX/dxi (the reference element's orientation) and
        det F at the quadrature points: both positive for a valid reference."""
        return self._per_element(X, lambda a, b, f: jnp.stack(self._element(a, b, f)[1:], axis=-1))

    def blocks(self, X):
        """(n_elements, 3k, 3k) d f_e / d X_e [dyn/cm] (node-interleaved), by ``jax.jacfwd``."""
        def one(Xe, xe, fibres):
            return jax.jacfwd(lambda v: self._element(v.reshape(Xe.shape), xe, fibres)[0].reshape(-1))(
                Xe.reshape(-1))

        return self._per_element(X, one)


def inverse_operator(problem, current=None) -> InverseForce:
    """The :class:`InverseForce` of ``problem`` (its hyperelastic law; P1, or P2 with the
    curved rule) with the deformed positions ``current`` (n_nodes, 3) [cm] (default: the
    problem's nodes, the imaged geometry)."""
    from .._reference_element import shape_derivatives

    if not problem.material.finite_strain:
        raise ProblemError("the zero-pressure geometry needs a hyperelastic law, got "
                           f"{type(problem.material).__name__}: "
                           "use jaxsync.NeoHookean, NearlyIncompressibleNeoHookean or HolzapfelGasserOgden")
    space = problem.space
    material, fibres = split_fibres(problem.material)
    if fibres is not None and fibres.shape != (problem.mesh.n_elements, 2, 3):
        raise ProblemError(f"HolzapfelGasserOgden.fibres has shape {fibres.shape}, the mesh has "
                           f"{problem.mesh.n_elements} elements: give (n_elements, 2, 3)")
    dN, w = shape_derivatives(space, 1 if space.element == "P1" else 4)
    x = space.points if current is None else np.asarray(current, dtype=float)
    return InverseForce(cells=jnp.asarray(space.cells, dtype=jnp.int32), derivatives=jnp.asarray(dN),
                        rule=jnp.asarray(w, dtype=float), current=jnp.asarray(x), material=material, fibres=fibres)


@jax.jit
def inverse_force(op: InverseForce, X):
    """``op.force(X)`` compiled (one program per mesh size)."""
    return op.force(X)


@jax.jit
def inverse_jacobians(op: InverseForce, X):
    """``op.jacobians(X)`` compiled."""
    return op.jacobians(X)


@jax.jit
def inverse_blocks(op: InverseForce, X):
    """``op.blocks(X)`` compiled."""
    return op.blocks(X)


@jax.jit
def inverse_product(op: InverseForce, X, V):
    """(n_nodes, 3) the directional derivative (d f_int / d X) V [dyn] (a ``jax.jvp``)."""
    return jax.jvp(op.force, (X,), (V,))[1]


def tangent(op: InverseForce, X):
    """d f_int / d X (scipy CSR, (3 n_nodes, 3 n_nodes) [dyn/cm], node-interleaved) at
    reference positions X (n_nodes, 3) [cm]: the element blocks summed at the nodes."""
    import scipy.sparse as sp

    blocks = np.asarray(inverse_blocks(op, jnp.asarray(X)))
    cells = np.asarray(op.cells)
    dofs = (3 * cells[:, :, None] + np.arange(3)).reshape(len(cells), -1)
    size = dofs.shape[1]
    rows = np.broadcast_to(dofs[:, :, None], (len(cells), size, size)).ravel()
    cols = np.broadcast_to(dofs[:, None, :], (len(cells), size, size)).ravel()
    n = 3 * int(np.shape(X)[0])
    return sp.coo_matrix((blocks.ravel(), (rows, cols)), shape=(n, n)).tocsr()
