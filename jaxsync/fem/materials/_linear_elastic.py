"""Isotropic linear elastic material (small strain), a :class:`jaxsync.fem.materials.MaterialLaw`."""

from __future__ import annotations

from typing import ClassVar

import jax.numpy as jnp
import numpy as np

from ...errors import MaterialError
from ...pytree import pytree_dataclass
from .._parameter_checks import check_number
from .._timestep import ALPHA_S

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

    As a :class:`jaxsync.fem.materials.MaterialLaw`: it runs on the force model asked
    for (its stiffness K = lambda K_lambda + mu K_mu stored, or formed element by
    element), its step is the paper's CFL rule capped by the exact bound
    (:func:`jaxsync.fem.small_strain_step`), its tangent is K, and it carries no
    state.
    """

    finite_strain: ClassVar[bool] = False
    state_dependent_tangent: ClassVar[bool] = False

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

    def force_model(self, requested):
        """``requested`` itself (the preassembled or element-recompute model of K)."""
        return requested

    def stable_step(self, problem, alpha_s: float = ALPHA_S):
        """:func:`jaxsync.fem.small_strain_step`: min(paper CFL step, alpha_s 2 / omega_max)."""
        from .._timestep import small_strain_step

        return small_strain_step(problem, alpha_s)

    def max_stable_dt(self, problem, *, tol: float = 1e-10, max_iter: int = 20000, seed: int = 0):
        """2 / omega_max of M^-1 K (:func:`jaxsync.fem._timestep.small_strain_max_stable_dt`;
        traced when E or rho are)."""
        from .._timestep import small_strain_max_stable_dt

        return small_strain_max_stable_dt(problem, tol=tol, max_iter=max_iter, seed=seed)

    def element_steps(self, problem) -> np.ndarray:
        """(n_elements,) the paper's CFL step of each P1 element alone, h_e / c_e [s]
        (:func:`jaxsync.fem.element_dt` at alpha_s = 1).

        Raises:
            ProblemError: P2 elements (the paper's rule is for P1; run them at their own step).
        """
        from ...errors import ProblemError
        from .._timestep import element_dt

        if problem.element != "P1":
            raise ProblemError("the paper's element step (and artificial mass scaling, its Algorithm 2) is the P1 "
                               f"CFL rule; this problem uses {problem.element} elements: run it at its own step "
                               "(problem.dt), or scale a P1 problem")
        return np.asarray(element_dt(problem, alpha_s=1.0), dtype=float)

    def scaled_density(self, problem, dt_hat: float, alpha_s: float = ALPHA_S) -> tuple:
        """Every P1 element whose CFL step alpha_s h_e / c_e is below dt_hat gets density
        E dt_hat^2 / (alpha_s^2 h_e^2 (1 - nu^2)) (paper Algorithm 2), which raises its
        step to dt_hat; returns (density_scale, scaled) as
        :meth:`jaxsync.fem.materials.MaterialLaw.scaled_density` says."""
        from .._timestep import element_size

        self.element_steps(problem)  # refuses P2
        E, nu, rho = float(self.E), float(self.nu), float(self.rho)
        scale = (np.ones(problem.mesh.n_elements) if problem.density_scale is None
                 else np.asarray(problem.density_scale, dtype=float).copy())
        h = element_size(problem.mesh.points, problem.mesh.tets)
        dt_e = alpha_s * h / np.sqrt(E / (rho * scale * (1.0 - nu**2)))
        small = dt_e < dt_hat
        new_density = E * dt_hat**2 / (alpha_s**2 * h**2 * (1.0 - nu**2))
        scale[small] = new_density[small] / rho
        return scale, small

    def tangent_stiffness(self, problem, displacement=None):
        """K (the same at every displacement), without the supports' springs."""
        return problem.operators.stiffness(self.lam, self.mu)

    def parameters(self):
        """(its class name, {E, nu, rho}, no fibres)."""
        from ._law import MaterialParameters

        return MaterialParameters(type(self).__name__, {"E": float(self.E), "nu": float(self.nu),
                                                    "rho": float(self.rho)})

    def fingerprint(self) -> bytes:
        """b"": E, nu and rho, which every fingerprint holds, identify the law."""
        return b""

    def cost(self):
        """None: the cost is that of the force mode (:func:`jaxsync.perf.roofline.step_costs`)."""
        return None

    def run_check(self, problem, system, dt):
        """None: the stable step of a linear law does not change during a run."""
        return None

    def internal_variables(self, n_elements: int, n_points: int) -> dict:
        """{}: no state."""
        return {}
