"""Finite-strain viscoelasticity: Prony series of Maxwell branches on the isochoric part of
the nearly incompressible neo-Hookean law and of the Holzapfel-Gasser-Ogden law (Simo
1987; Holzapfel 2000, section 6.10; Holzapfel & Gasser 2001).

The model. An elastic law whose second Piola-Kirchhoff stress splits into named parts,
S = sum_a S_a (``stress_parts(F, fibres)``: "volumetric" and "isochoric" for
:class:`jaxsync.NearlyIncompressibleNeoHookean`, plus "fibres" for
:class:`jaxsync.HolzapfelGasserOgden`), gets Maxwell branches on some of its parts: branch
i of part a, of relative stiffness beta_i >= 0 and relaxation time tau_i > 0, carries a
non-equilibrium stress Q_i that follows the convolution

    Q_i(t) = int_0^t beta_i exp(-(t - s)/tau_i) dS_a/ds ds,

and the stress of the viscoelastic law is S = sum_a S_a + sum_i Q_i, P = F S. The branches
act on the isochoric part (of the neo-Hookean law; of the HGO ground matrix) and, for the
HGO law, optionally on its fibre part with branches of their own: Holzapfel & Gasser
(2001, "A viscoelastic model for fibre-reinforced composites at finite strains") give the
matrix and each fibre family their own relaxation (their own beta and tau), driven by the
stress of that constituent; here both fibre families share the fibre branches, and the
fibre stress is that of the law (its full, not isochoric, invariants, as
:class:`jaxsync.HolzapfelGasserOgden` writes it). The volumetric part never relaxes.

The update. Over a step dt each Q_i follows the recursive midpoint rule of its integral
(Simo 1987; Holzapfel 2000, eq. 6.175),

    Q_i(n+1) = exp(-dt/tau_i) Q_i(n) + beta_i exp(-dt/(2 tau_i)) (S_a(n+1) - S_a(n)),

exact to O((dt/tau_i)^2), with S_a(n) the part's stress of the step before, both carried
per quadrature point (:meth:`PronySeries.internal_variables`). At small strain a stretch
held from t_0 on relaxes as S_vol + S_iso (1 + sum_i beta_i exp(-(t - t_0)/tau_i)): the
instantaneous shear modulus is (1 + sum_i beta_i) mu, the long-term one mu.

The elastic response the law reports (``first_piola``, ``energy``, ``tangent``) is the
instantaneous one, sum_a (1 + sum_{i of a} beta_i) S_a: the stable step, the element steps
and the run-time stability check come from it (the stiffest the law can be); the internal
force of a run is that of ``stress_update``. The state starts at the reference
configuration (Q = 0, S_a = 0): an initial displacement counts as applied suddenly at
t = 0. The state a :class:`jaxsync.fem.SolverState` holds is that of the force of
its ``previous`` displacement.

One piece, :class:`PronySeries`, does this for any law with ``stress_parts`` and
``energy_parts``; the laws here are its concrete, configurable forms:
:class:`ViscoelasticNeoHookean`, :class:`ViscoelasticHGO`, and
:class:`StandardLinearSolid` (one branch on the neo-Hookean law, with its own state
layout).
"""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
import numpy as np

from ...errors import MaterialError
from ...pytree import concrete_scalar, pytree_dataclass
from ._hyperelastic import (
    HolzapfelGasserOgden,
    NearlyIncompressibleNeoHookean,
    SmallStrain,
    check_numbers,
    check_positive,
    check_young_poisson,
)
from ._law import FiniteStrainLaw, MaterialParameters

__all__ = ["PronySeries", "ViscoelasticNeoHookean", "ViscoelasticHGO", "StandardLinearSolid", "STATE_NAMES",
           "check_branches"]

STATE_NAMES = {"isochoric": ("Q", "S_iso"), "fibres": ("Q_fibres", "S_fibres")}
"""{relaxing part: (name of its branches' stresses Q, (n_elements, n_points, n_branches, 3,
3); name of its stress of the step before, (n_elements, n_points, 3, 3))} in the internal
variables."""


def check_branches(law: str, betas, taus, *, betas_name: str = "betas", taus_name: str = "taus",
                   required: bool = True) -> tuple:
    """(betas, taus) as tuples, checked: as many of each, at least one when ``required``,
    every beta >= 0 and every tau > 0 (a finite number).

    Raises:
        MaterialError: naming the field and the fix."""
    if betas is None and taus is None:
        if required:
            raise MaterialError(f"{law} needs its Maxwell branches: give {betas_name} = [beta_1, ...] (relative "
                                f"stiffnesses, >= 0) and {taus_name} = [tau_1, ...] (relaxation times [s], > 0), "
                                "one of each per branch")
        return (), ()
    if betas is None or taus is None:
        raise MaterialError(f"{law}: give both {betas_name} and {taus_name} (one relative stiffness and one "
                            f"relaxation time per branch), got only {taus_name if betas is None else betas_name}")
    betas, taus = (tuple(np.asarray(v).ravel()) if isinstance(v, np.ndarray) else tuple(v) for v in (betas, taus))
    if len(betas) != len(taus):
        raise MaterialError(f"{law}: {betas_name} has {len(betas)} entries and {taus_name} {len(taus)}; give one "
                            "relative stiffness and one relaxation time per branch")
    if required and not betas:
        raise MaterialError(f"{law}: {betas_name} and {taus_name} are empty; give at least one branch (or use the "
                            "elastic law)")
    for i, (beta, tau) in enumerate(zip(betas, taus)):
        if isinstance(beta, str) or isinstance(tau, str):
            raise MaterialError(f"{law}: branch {i} must be numbers, got beta={beta!r}, tau={tau!r}")
        value = concrete_scalar(beta)
        if value is not None and not value >= 0.0:
            raise MaterialError(f"{law}.{betas_name}[{i}] (a branch's relative stiffness) must be >= 0, got {value} "
                                "(0: a branch that carries no stress)")
        check_positive(law, **{f"{taus_name}[{i}] (relaxation time [s])": tau})
    return betas, taus


class PronySeries(FiniteStrainLaw):
    """Maxwell branches on the parts of an elastic law's stress (module docstring): a mixin
    for a frozen pytree dataclass. A subclass writes

    * ``elastic_law()``: the elastic law, with ``stress_parts(F, fibres)`` and
      ``energy_parts(F, fibres)`` ({part: (..., 3, 3) second Piola-Kirchhoff stress
      [dyn/cm^2]} and {part: (...,) energy [erg/cm^3]} that sum to its S and psi);
    * ``relaxation()``: {part: (betas, taus)} the branches on each relaxing part (a part
      of :data:`STATE_NAMES`), in the order of the parts.
    """

    def elastic_law(self):  # pragma: no cover - every law writes it
        raise NotImplementedError(f"{type(self).__name__} must define elastic_law()")

    def relaxation(self) -> dict:  # pragma: no cover - every law writes it
        raise NotImplementedError(f"{type(self).__name__} must define relaxation()")

    def _relaxing(self) -> dict:
        """{part: (betas, taus)} of the parts with at least one branch."""
        return {part: branches for part, branches in self.relaxation().items() if len(branches[0])}

    def _instantaneous(self, parts: dict):
        """sum_a (1 + sum_i beta_i) x_a over the parts ``parts`` (stresses or energies)."""
        relaxing = self._relaxing()
        total = None
        for name, value in parts.items():
            if name in relaxing:
                betas = relaxing[name][0]
                stiffening = betas[0]
                for beta in betas[1:]:
                    stiffening = stiffening + beta
                value = (1.0 + stiffening) * value
            total = value if total is None else total + value
        return total

    def energy(self, F, fibres=None):
        """The instantaneous energy sum_a (1 + sum_i beta_i) psi_a (...,) [erg/cm^3]."""
        return self._instantaneous(self.elastic_law().energy_parts(F, fibres))

    def first_piola(self, F, fibres=None):
        """The instantaneous P = F sum_a (1 + sum_i beta_i) S_a (..., 3, 3) [dyn/cm^2]."""
        return F @ self._instantaneous(self.elastic_law().stress_parts(F, fibres))

    def internal_variables(self, n_elements: int, n_points: int) -> dict:
        """For each relaxing part, its branches' stresses (n_elements, n_points, n_branches,
        3, 3) and its stress of the step before (n_elements, n_points, 3, 3), zeros
        [dyn/cm^2] (the reference state), named as in :data:`STATE_NAMES`."""
        state = {}
        for part, (betas, _) in self._relaxing().items():
            q_name, s_name = STATE_NAMES[part]
            state[q_name] = jnp.zeros((n_elements, n_points, len(betas), 3, 3))
            state[s_name] = jnp.zeros((n_elements, n_points, 3, 3))
        return state

    def stress_update(self, F, fibres, internal, dt):
        """(P (..., 3, 3) [dyn/cm^2], the updated variables) of a step of ``dt`` [s] to F
        (..., 3, 3): every branch's recursive update (module docstring), then
        P = F (sum_a S_a + sum_i Q_i)."""
        parts = self.elastic_law().stress_parts(F, fibres)
        S = None
        for value in parts.values():
            S = value if S is None else S + value
        updated = {}
        for part, (betas, taus) in self._relaxing().items():
            q_name, s_name = STATE_NAMES[part]
            shape = (1,) * (internal[q_name].ndim - 3) + (len(betas), 1, 1)  # the branch axis, explicitly
            beta = jnp.stack([jnp.asarray(b, dtype=F.dtype) for b in betas]).reshape(shape)
            decay = jnp.exp(-dt / jnp.stack([jnp.asarray(t, dtype=F.dtype) for t in taus])).reshape(shape)
            # exp(-dt/(2 tau)) as sqrt(exp(-dt/tau)): one transcendental per branch
            q = decay * internal[q_name] + (beta * jnp.sqrt(decay)) * (parts[part] - internal[s_name])[..., None, :, :]
            S = S + jnp.sum(q, axis=-3)
            updated[q_name], updated[s_name] = q, parts[part]
        return F @ S, updated

    def parameters(self) -> MaterialParameters:
        """The class name, every scalar field, every branch (``betas[0]``, ``taus[0]``, ...)
        and the sha256 of the fibres (if any)."""
        import dataclasses
        import hashlib

        values = {}
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if field.name == "fibres" or value is None:
                continue
            if isinstance(value, tuple):
                values.update({f"{field.name}[{i}]": float(v) for i, v in enumerate(value)})
            else:
                values[field.name] = float(value)
        fibres = getattr(self, "fibres", None)
        digest = None if fibres is None else hashlib.sha256(
            np.ascontiguousarray(np.asarray(fibres, dtype=float)).tobytes()).hexdigest()
        return MaterialParameters(type(self).__name__, values, digest)


@pytree_dataclass
class ViscoelasticNeoHookean(PronySeries, SmallStrain):
    """:class:`jaxsync.NearlyIncompressibleNeoHookean` with a Prony series of Maxwell
    branches on its isochoric part (module docstring).

    Attributes:
        E: long-term (relaxed) small-strain Young's modulus [dyn/cm^2] (> 0).
        nu: long-term small-strain Poisson ratio (-1 < nu < 0.5).
        rho: reference density [g/cm^3] (> 0).
        betas: (n_branches,) each branch's stiffness relative to the long-term isochoric
            one [-] (>= 0): the instantaneous shear modulus is (1 + sum betas) mu.
        taus: (n_branches,) their relaxation times [s] (> 0).

    The fields may be JAX tracers (``jax.grad`` in betas or taus through a run).
    """

    E: Any = 1.0e6
    nu: Any = 0.45
    rho: Any = 1.0
    betas: tuple[float, ...] | None = None
    taus: tuple[float, ...] | None = None

    def __post_init__(self):
        check_numbers(self)
        check_young_poisson(self.E, self.nu, self.rho, law="ViscoelasticNeoHookean")
        betas, taus = check_branches("ViscoelasticNeoHookean", self.betas, self.taus)
        object.__setattr__(self, "betas", betas)
        object.__setattr__(self, "taus", taus)

    def elastic_law(self) -> NearlyIncompressibleNeoHookean:
        """The long-term elastic law."""
        return NearlyIncompressibleNeoHookean(self.E, self.nu, self.rho)

    def relaxation(self) -> dict:
        """{"isochoric": (betas, taus)}."""
        return {"isochoric": (self.betas, self.taus)}


@pytree_dataclass
class ViscoelasticHGO(PronySeries):
    """:class:`jaxsync.HolzapfelGasserOgden` with a Prony series on the isochoric part of
    its ground matrix and, optionally, another on its fibres (module docstring; Holzapfel
    & Gasser 2001).

    Attributes:
        mu, k1, k2, kappa_bulk, rho, dispersion, fibres: the long-term law's
            (:class:`jaxsync.HolzapfelGasserOgden`).
        betas, taus: (n_branches,) the ground matrix's branches: relative stiffnesses [-]
            (>= 0) and relaxation times [s] (> 0).
        fibre_betas, fibre_taus: (n_fibre_branches,) the fibres' branches, or None (elastic
            fibres).
    """

    mu: Any
    k1: Any
    k2: Any
    kappa_bulk: Any
    rho: Any = 1.0
    dispersion: Any = 0.0
    fibres: Any = None
    betas: tuple[float, ...] | None = None
    taus: tuple[float, ...] | None = None
    fibre_betas: tuple[float, ...] | None = None
    fibre_taus: tuple[float, ...] | None = None

    def __post_init__(self):
        check_numbers(self)
        HolzapfelGasserOgden(self.mu, self.k1, self.k2, self.kappa_bulk, self.rho, self.dispersion, self.fibres)
        betas, taus = check_branches("ViscoelasticHGO", self.betas, self.taus)
        fibre_betas, fibre_taus = check_branches("ViscoelasticHGO", self.fibre_betas, self.fibre_taus,
                                                 betas_name="fibre_betas", taus_name="fibre_taus", required=False)
        for name, value in (("betas", betas), ("taus", taus), ("fibre_betas", fibre_betas),
                            ("fibre_taus", fibre_taus)):
            object.__setattr__(self, name, value)

    def elastic_law(self) -> HolzapfelGasserOgden:
        """The long-term elastic law (its fibres come with each call)."""
        return HolzapfelGasserOgden(self.mu, self.k1, self.k2, self.kappa_bulk, self.rho, self.dispersion)

    def relaxation(self) -> dict:
        """{"isochoric": (betas, taus), "fibres": (fibre_betas, fibre_taus)}."""
        return {"isochoric": (self.betas, self.taus), "fibres": (self.fibre_betas, self.fibre_taus)}

    @property
    def bulk(self):
        """Bulk modulus K [dyn/cm^2] (``kappa_bulk``)."""
        return self.kappa_bulk

    @property
    def lam(self):
        """First Lame parameter of the long-term ground matrix [dyn/cm^2]."""
        return self.elastic_law().lam

    @property
    def E(self):
        """Long-term small-strain Young's modulus of the ground matrix [dyn/cm^2]."""
        return self.elastic_law().E

    @property
    def nu(self):
        """Long-term small-strain Poisson ratio of the ground matrix."""
        return self.elastic_law().nu

    @property
    def dilatational_wave_speed(self):
        """The long-term law's bound [cm/s] (:attr:`jaxsync.HolzapfelGasserOgden.dilatational_wave_speed`)."""
        return self.elastic_law().dilatational_wave_speed


@pytree_dataclass
class StandardLinearSolid(PronySeries, SmallStrain):
    """A nearly incompressible neo-Hookean solid with one Maxwell branch on its isochoric
    part: :class:`ViscoelasticNeoHookean` with ``betas=(beta,)``, ``taus=(tau,)``, its
    internal variables {"Q", "S_iso"} both (n_elements, n_points, 3, 3) (no branch axis).

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
        beta = concrete_scalar(self.beta)
        if beta is not None and not beta >= 0.0:
            raise MaterialError(f"StandardLinearSolid.beta (the Maxwell branch's relative stiffness) must be >= 0, "
                                f"got {beta} (0: the elastic neo-Hookean law)")

    @classmethod
    def cost(cls):
        """Its stress's flops, and its two 3 x 3 variables read and written per point."""
        from ._law import LawCost

        return LawCost(dict(cls.point_flops), 0, 2 * 2 * 9 * 8)

    def elastic_law(self) -> NearlyIncompressibleNeoHookean:
        """The long-term elastic law."""
        return NearlyIncompressibleNeoHookean(self.E, self.nu, self.rho)

    def relaxation(self) -> dict:
        """{"isochoric": ((beta,), (tau,))}."""
        return {"isochoric": ((self.beta,), (self.tau,))}

    def internal_variables(self, n_elements: int, n_points: int) -> dict:
        """{"Q": the branch stress, "S_iso": the isochoric stress of the last step}, both
        (n_elements, n_points, 3, 3) zeros [dyn/cm^2] (the reference state)."""
        zero = jnp.zeros((n_elements, n_points, 3, 3))
        return {"Q": zero, "S_iso": zero}

    def stress_update(self, F, fibres, internal, dt):
        """(P (..., 3, 3) [dyn/cm^2], {"Q", "S_iso"} updated) of a step to F
        (:meth:`PronySeries.stress_update` of the one branch)."""
        P, updated = super().stress_update(F, fibres, {"Q": internal["Q"][..., None, :, :],
                                                       "S_iso": internal["S_iso"]}, dt)
        return P, {"Q": updated["Q"][..., 0, :, :], "S_iso": updated["S_iso"]}
