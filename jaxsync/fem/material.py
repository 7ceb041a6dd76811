"""Isotropic linear elastic material (small strain)."""

from __future__ import annotations

import jax.numpy as jnp

from ..errors import MaterialError
from ..pytree import pytree_dataclass
from .parameter_checks import check_number

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
        check_number(self.E, "LinearElastic.E (Young's modulus)", error=MaterialError, above=0.0, unit="dyn/cm^2")
        check_number(self.rho, "LinearElastic.rho (density)", error=MaterialError, above=0.0, unit="g/cm^3")
        check_number(self.nu, "LinearElastic.nu (Poisson ratio)", error=MaterialError, above=-1.0, below=0.5,
                     hint="-1 < nu < 0.5; nu = 0.5 is incompressible, which linear P1 elements cannot represent")

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
