"""Kinematics of 3 x 3 deformation gradients on batches: det F, cof F and the sums the
hyperelastic laws (:mod:`jaxsync.fem.materials`) and the total-Lagrangian force
(:mod:`jaxsync.fem.forces`) share, written for XLA:CPU's fusion."""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["determinant", "cofactor"]


def sum3(x):
    """The sum over the last axis (of length 3) of x, as two additions.

    Not ``jnp.sum``: XLA:CPU (jax 0.10.2) hands a reduction over a short trailing axis, with
    the elementwise operations around it, to its YNN fusion, which is slower on batches of
    3 x 3 matrices than the plain loop fusion the additions become. Measured (the
    total-Lagrangian force on the generated vessel, one core, chains of products in one
    call, best of 25 alternated calls; jnp.sum time over this one): P1, 5 000 elements:
    nearly incompressible 1.95x, Holzapfel-Gasser-Ogden 1.57x, neo-Hookean 1.0x; P1,
    38 000 elements: 1.5x, 1.45x, 1.04x; P2, 5 000 elements: 1.12x, 0.95x, 1.0x."""
    return x[..., 0] + x[..., 1] + x[..., 2]


def sum_squares(F):
    """(...,) sum of the squares of the entries of (..., 3, 3) F (I1 = tr F^T F)."""
    return sum3(sum3(F * F))


def determinant(F):
    """(...,) det F of (..., 3, 3) matrices (the cofactor expansion: several times faster than
    the LU of ``jnp.linalg.det`` on batches of 3 x 3 matrices)."""
    f0, f1, f2 = F[..., 0, :], F[..., 1, :], F[..., 2, :]
    return sum3(f0 * jnp.cross(f1, f2))


def cofactor(F):
    """(..., 3, 3) cof F = d(det F)/dF = det F * F^-T: its rows are the cross products of F's
    other two rows. Taken as the reverse-mode derivative of :func:`determinant`, which XLA
    lays out better than stacking the cross products (measured: 25 % faster neo-Hookean P)."""
    return jax.grad(lambda G: jnp.sum(determinant(G)))(F)


def det_from_cofactor(F, cof):
    """(...,) det F from its first row and cof F (no second set of cross products)."""
    return sum3(F[..., 0, :] * cof[..., 0, :])
