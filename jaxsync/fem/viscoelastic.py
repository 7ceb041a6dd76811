"""Finite-strain viscoelasticity: a standard linear solid with one Maxwell branch on the
isochoric part of the neo-Hookean law (Simo 1987; Holzapfel 2000, section 6.10).

The law carries one internal variable per quadrature point, the branch's non-equilibrium
second Piola-Kirchhoff stress Q (3 x 3), beside the isochoric stress of the step before
(its history). With the split neo-Hookean energy of
:class:`jaxsync.NearlyIncompressibleNeoHookean`,

    S_vol = K/2 (J^2 - 1) C^-1,    S_iso = mu J^-2/3 (I - I1/3 C^-1),

C = F^T F, I1 = tr C, J = det F, the stress of a step is S = S_vol + S_iso + Q, P = F S,
with Q updated by the midpoint rule of its convolution integral
Q(t) = int_0^t beta exp(-(t - s)/tau) dS_iso/ds ds:

    Q(n+1) = exp(-dt/tau) Q(n) + beta exp(-dt/(2 tau)) (S_iso(n+1) - S_iso(n)),

exact to O((dt/tau)^2) (dt the run's step). A stretch held from t_0 on relaxes as
S(t) = S_vol + S_iso (1 + beta exp(-(t - t_0)/tau)) at small strain: the instantaneous
shear modulus is (1 + beta) mu, the long-term one mu. The elastic response the law
reports (:meth:`StandardLinearSolid.first_piola`, its energy and tangent) is the
instantaneous one, S_vol + (1 + beta) S_iso: the stable step, the element steps and the
run-time stability check come from it (the stiffest the law can be); the internal force
of a run is that of :meth:`StandardLinearSolid.stress_update`.

The state starts at the reference configuration (Q = 0, S_iso = 0): an initial
displacement counts as applied suddenly at t = 0. The internal force updates the state
each time a step evaluates it; the state a :class:`jaxsync.fem.stepper.SolverState` holds
is that of the force of its ``previous`` displacement. Prony series of several branches
build on this one (one Q per branch).
"""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp

from ..errors import MaterialError
from ..pytree import pytree_dataclass
from .hyperelastic import SmallStrain, check_numbers, check_positive, check_young_poisson
from .kinematics import cofactor, determinant

__all__ = ["StandardLinearSolid"]


@pytree_dataclass
class StandardLinearSolid(SmallStrain):
    """A nearly incompressible neo-Hookean solid with one Maxwell branch on its isochoric
    part (module docstring), a :class:`jaxsync.fem.material_law.MaterialLaw` with internal
    variables.

    Attributes:
        E: long-term (relaxed) small-strain Young's modulus [dyn/cm^2] (> 0).
        nu: long-term small-strain Poisson ratio (-1 < nu < 0.5).
        rho: reference density [g/cm^3] (> 0).
        beta: the branch's stiffness relative to the isochoric long-term one [-] (>= 0):
            the instantaneous shear modulus is (1 + beta) mu.
        tau: the branch's relaxation time [s] (> 0).

    The fields may be JAX tracers (``jax.grad`` in beta or tau through a run).
    """

    E: Any = 1.0e6
    nu: Any = 0.45
    rho: Any = 1.0
    beta: Any = 1.0
    tau: Any = 0.01

    point_flops = {"cof F and J": 32, "C^-1 = cof F^T cof F / J^2": 63, "I1, J^-2/3": 21,
                   "S_iso, S_vol": 40, "Q update": 45, "P = F (S_vol + S_iso + Q)": 63}

    def __post_init__(self):
        check_numbers(self)
        check_young_poisson(self.E, self.nu, self.rho, law="StandardLinearSolid")
        check_positive("StandardLinearSolid", tau=self.tau)
        from ..pytree import concrete_scalar

        beta = concrete_scalar(self.beta)
        if beta is not None and not beta >= 0.0:
            raise MaterialError(f"StandardLinearSolid.beta (the Maxwell branch's relative stiffness) must be >= 0, "
                                f"got {beta} (0: the elastic neo-Hookean law)")

    @classmethod
    def cost(cls):
        """Its stress's flops, and its two 3 x 3 variables read and written per point."""
        from .material_law import LawCost

        return LawCost(dict(cls.point_flops), 0, 2 * 2 * 9 * 8)

    def _stresses(self, F):
        """(S_vol, S_iso) (..., 3, 3) [dyn/cm^2] of F (..., 3, 3)."""
        cof = cofactor(F)
        J = determinant(F)
        c_inv = jnp.einsum("...iJ,...iK->...JK", cof, cof) / (J * J)[..., None, None]
        i1 = jnp.sum(F * F, axis=(-2, -1))
        eye = jnp.broadcast_to(jnp.eye(3, dtype=F.dtype), F.shape)
        s_iso = (self.mu * J ** (-2.0 / 3.0))[..., None, None] * (eye - (i1 / 3.0)[..., None, None] * c_inv)
        s_vol = (0.5 * self.bulk * (J * J - 1.0))[..., None, None] * c_inv
        return s_vol, s_iso

    def energy(self, F, fibres=None):
        """The instantaneous energy psi_vol + (1 + beta) psi_iso (...,) [erg/cm^3]."""
        J = determinant(F)
        i1 = jnp.sum(F * F, axis=(-2, -1))
        return ((1.0 + self.beta) * 0.5 * self.mu * (J ** (-2.0 / 3.0) * i1 - 3.0)
                + 0.25 * self.bulk * (J * J - 1.0 - 2.0 * jnp.log(J)))

    def first_piola(self, F, fibres=None):
        """The instantaneous P = F (S_vol + (1 + beta) S_iso) (..., 3, 3) [dyn/cm^2]."""
        s_vol, s_iso = self._stresses(F)
        return F @ (s_vol + (1.0 + self.beta) * s_iso)

    def internal_variables(self, n_elements: int, n_points: int) -> dict:
        """{"Q": the branch stress, "S_iso": the isochoric stress of the last step}, both
        (n_elements, n_points, 3, 3) zeros [dyn/cm^2] (the reference state)."""
        zero = jnp.zeros((n_elements, n_points, 3, 3))
        return {"Q": zero, "S_iso": zero}

    def stress_update(self, F, fibres, internal, dt):
        """(P (..., 3, 3) [dyn/cm^2], {"Q", "S_iso"} updated) of a step to F (module docstring)."""
        s_vol, s_iso = self._stresses(F)
        decay = jnp.exp(-dt / self.tau)
        q = decay * internal["Q"] + (self.beta * jnp.sqrt(decay)) * (s_iso - internal["S_iso"])
        return F @ (s_vol + s_iso + q), {"Q": q, "S_iso": s_iso}
