"""Isotropic linear elastic material (small strain)."""

from __future__ import annotations

import jax.numpy as jnp

from ..errors import MaterialError
from ..pytree import concrete_scalar, pytree_dataclass

__all__ = ["LinearElastic", "shear_modulus", "first_lame"]


def shear_modulus(E, nu):
    """mu = E / (2 (1 + nu)) [dyn/cm^2] of Young's modulus E [dyn/cm^2] and Poisson ratio nu."""
    return E / (2.0 * (1.0 + nu))


def first_lame(E, nu):
    """lambda = E nu / ((1 + nu)(1 - 2 nu)) [dyn/cm^2] of Young's modulus E [dyn/cm^2] and
    Poisson ratio nu."""
    return E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


@pytree_dataclass
class LinearElastic:
    """Isotropic linear elastic material, CGS units as in the paper.

    Attributes:
        E: Young's modulus [dyn/cm^2] (> 0).
        nu: Poisson ratio (-1 < nu < 0.5).
        rho: density [g/cm^3] (> 0).

    The fields may be JAX tracers (for ``jax.grad`` with respect to them); range checks
    run on concrete scalar values.
    """

    E: float = 1.0e6
    nu: float = 0.3
    rho: float = 1.0

    def __post_init__(self):
        E, nu, rho = (concrete_scalar(v) for v in (self.E, self.nu, self.rho))
        if E is not None and not E > 0:
            raise MaterialError(f"Young's modulus must be positive, got E={E}")
        if rho is not None and not rho > 0:
            raise MaterialError(f"density must be positive, got rho={rho}")
        if nu is not None and not -1.0 < nu < 0.5:
            raise MaterialError(
                f"Poisson ratio must satisfy -1 < nu < 0.5, got nu={nu} "
                "(nu = 0.5 is incompressible, which linear P1 elements cannot represent)")
        for name, value in (("E", self.E), ("nu", self.nu), ("rho", self.rho)):
            if isinstance(value, str):
                raise MaterialError(f"material parameter {name} must be a number, got {value!r}")

    @property
    def mu(self):
        """Shear modulus E / (2 (1 + nu)) [dyn/cm^2]."""
        return shear_modulus(self.E, self.nu)

    @property
    def lam(self):
        """First Lame parameter E nu / ((1 + nu)(1 - 2 nu)) [dyn/cm^2]."""
        return first_lame(self.E, self.nu)

    @property
    def wave_speed(self):
        """sqrt(E / (rho (1 - nu^2))) [cm/s], the speed in the paper's CFL rule."""
        return jnp.sqrt(self.E / (self.rho * (1.0 - self.nu**2)))
