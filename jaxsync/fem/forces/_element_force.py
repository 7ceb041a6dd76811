"""Matrix-free internal force of P1 tetrahedra, formed element by element every step.

This is the paper's "element-recompute" mode (Remark 2): instead of a stored sparse K,
each step forms the element geometry (shape-function gradients, volume), strains and
stresses, and sums the element forces at the nodes. It stands in for nonlinear
materials, where element quantities must be recomputed, and moves fewer bytes per step
than a stored K at the price of more flops.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from ...options import Mode, choices
from ...pytree import pytree_dataclass

__all__ = ["ElementStiffness", "element_forces", "MODES"]

MODES = choices(Mode)  # ("preassembled", "recompute"), defined in jaxsync.options


@pytree_dataclass
class ElementStiffness:
    """Matrix-free internal force that forms element quantities every step.

    Attributes:
        points: (n_nodes, 3) node coordinates [cm].
        tets: (n_elements, 4) int32 connectivity.
        weight: (n_elements,) 1 for real elements, 0 for padding.
        lam, mu: Lame parameters [dyn/cm^2].
    """

    points: Any
    tets: Any
    weight: Any
    lam: Any
    mu: Any

    def matvec(self, u):
        """K u (n_nodes, 3) from per-element strains and stresses."""
        forces = element_forces(self.points, self.tets, u, self.lam, self.mu) * self.weight[:, None, None]
        return jax.ops.segment_sum(forces.reshape(-1, 3), self.tets.reshape(-1),
                                   num_segments=u.shape[0])

    def damped_matvec(self, u, velocity, beta):
        """K (u + beta v): the force of u plus the stiffness-proportional damping force of
        the velocity v (n_nodes, 3) [cm/s], beta [s] (K is linear: one evaluation)."""
        return self.matvec(u + beta * velocity)


def element_forces(points, tets, u, lam, mu):
    """(n_elements, 4, 3) nodal internal forces V sigma grad N_a of P1 tetrahedra.

    Shape-function gradients come from the cofactors of the edge matrix R (rows
    x_i - x_0): grad N_1..3 = (r2 x r3, r3 x r1, r1 x r2) / det R, grad N_0 = -their sum."""
    x = points[tets]
    r1, r2, r3 = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]
    c1, c2, c3 = jnp.cross(r2, r3), jnp.cross(r3, r1), jnp.cross(r1, r2)
    det = jnp.sum(r1 * c1, axis=1)
    g123 = jnp.stack([c1, c2, c3], axis=1) / det[:, None, None]
    grads = jnp.concatenate([-g123.sum(axis=1, keepdims=True), g123], axis=1)  # (m, 4, 3)
    ue = u[tets]  # (m, 4, 3)
    H = jnp.einsum("mai,maj->mij", ue, grads)
    eps = 0.5 * (H + jnp.swapaxes(H, 1, 2))
    trace = eps[:, 0, 0] + eps[:, 1, 1] + eps[:, 2, 2]
    sigma = 2.0 * mu * eps + (lam * trace)[:, None, None] * jnp.eye(3)[None]
    volume = det / 6.0
    return volume[:, None, None] * jnp.einsum("mij,maj->mai", sigma, grads)
