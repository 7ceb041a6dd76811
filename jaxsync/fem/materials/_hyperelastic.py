"""Hyperelastic materials for total-Lagrangian explicit dynamics (finite strain).

Each law is a frozen pytree dataclass (fields may be JAX tracers, so ``jax.grad`` with
respect to its parameters works) deriving from
:class:`jaxsync.fem.materials.FiniteStrainLaw` (which answers the material-law protocol
through the total-Lagrangian force model), with

* ``energy(F, fibres=None)``: the strain energy density psi(F) per unit reference volume,
  (...,) [dyn/cm^2 = erg/cm^3], for deformation gradients F (..., 3, 3);
* ``first_piola(F, fibres=None)``: the first Piola-Kirchhoff stress P = d psi / d F,
  (..., 3, 3) [dyn/cm^2];
* ``tangent(F, fibres=None)``: the material tangent A = d P / d F, (..., 3, 3, 3, 3)
  [dyn/cm^2] (automatic differentiation of ``first_piola``);
* the small-strain constants ``E``, ``nu``, ``lam``, ``mu`` and ``rho``: every law here
  linearises at F = I to isotropic linear elasticity with these Lame parameters, so the
  lumped mass, the reference stable step and the linear solver's machinery apply as they
  are (:class:`HolzapfelGasserOgden`: of its ground matrix; its fibres add stiffness in
  tension only);
* ``dilatational_wave_speed``: sqrt((lam + 2 mu) / rho) [cm/s] at F = I (plus the fibres'
  stiffness along them, for :class:`HolzapfelGasserOgden`).

Notation: J = det F, C = F^T F, I1 = tr C, I4 = a . C a for a fibre direction a (a unit
vector of the reference configuration), barred quantities isochoric (J^-2/3 I1).

Hand-written P or ``jax.grad`` of the energy: each law uses the faster, measured (jax
0.10.2, CPU, float64, 200 000 points, jit, median of 60 calls, two runs, on 2 cores shared
with other jobs, so +/- 15 %): NeoHookean hand 10.7 / 9.7 ms vs autodiff 9.2 / 8.6 ms (so
its P is the autodiff one); NearlyIncompressibleNeoHookean hand 16.1 / 16.6 ms vs autodiff
19.4 / 20.2 ms; HolzapfelGasserOgden (two fibre families) hand 62 / 64 ms vs autodiff
75 / 76 ms (both hand-written). ``tests/fem/test_hyperelastic.py`` checks every P against the
autodiff of its energy and against closed-form stresses.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ...errors import MaterialError
from ...pytree import concrete_scalar, pytree_dataclass
from .._kinematics import cofactor, det_from_cofactor, determinant, sum3, sum_squares
from .._parameter_checks import check_number
from ._law import FiniteStrainLaw
from ._linear_elastic import first_lame, shear_modulus

__all__ = ["NeoHookean", "NearlyIncompressibleNeoHookean", "HolzapfelGasserOgden", "HYPERELASTIC",
           "is_hyperelastic", "helical_fibres", "determinant", "cofactor", "material_parameters",
           "split_neo_hookean_stresses"]


def _isochoric_volumetric(F, cof, J, mu, bulk):
    """P of mu/2 (J^-2/3 I1 - 3) + K/4 (J^2 - 1 - 2 ln J): a F + b cof F with scalar a, b
    (written as two scalar fields, not as products of 3 x 3 fields: ~25 % faster)."""
    j23 = jnp.exp(-2.0 / 3.0 * jnp.log(J))
    i1 = sum_squares(F)
    a = mu * j23
    b = (0.5 * bulk * (J * J - 1.0) - a * i1 / 3.0) / J
    return a[..., None, None] * F + b[..., None, None] * cof


def split_neo_hookean_stresses(F, mu, bulk) -> dict:
    """The second Piola-Kirchhoff stresses of mu/2 (J^-2/3 I1 - 3) + K/4 (J^2 - 1 - 2 ln J)
    split into {"volumetric": K/2 (J^2 - 1) C^-1, "isochoric": mu J^-2/3 (I - I1/3 C^-1)},
    each (..., 3, 3) [dyn/cm^2], of F (..., 3, 3) (the parts viscoelastic branches act on,
    :mod:`jaxsync.fem.materials`)."""
    cof = cofactor(F)
    J = determinant(F)
    c_inv = jnp.einsum("...iJ,...iK->...JK", cof, cof) / (J * J)[..., None, None]
    i1 = jnp.sum(F * F, axis=(-2, -1))
    eye = jnp.broadcast_to(jnp.eye(3, dtype=F.dtype), F.shape)
    s_iso = (mu * J ** (-2.0 / 3.0))[..., None, None] * (eye - (i1 / 3.0)[..., None, None] * c_inv)
    s_vol = (0.5 * bulk * (J * J - 1.0))[..., None, None] * c_inv
    return {"volumetric": s_vol, "isochoric": s_iso}


def _split_neo_hookean_energies(F, mu, bulk) -> dict:
    """{"volumetric": K/4 (J^2 - 1 - 2 ln J), "isochoric": mu/2 (J^-2/3 I1 - 3)} (...,) [erg/cm^3]."""
    J = determinant(F)
    i1 = jnp.sum(F * F, axis=(-2, -1))
    return {"volumetric": 0.25 * bulk * (J * J - 1.0 - 2.0 * jnp.log(J)),
            "isochoric": 0.5 * mu * (J ** (-2.0 / 3.0) * i1 - 3.0)}


def check_positive(law: str = "", **values) -> None:
    """:class:`~jaxsync.MaterialError` naming ``<law>.<name>`` unless every value is a
    finite number above 0."""
    for name, value in values.items():
        check_number(value, f"{law}.{name}" if law else name, error=MaterialError, above=0.0)


def check_numbers(material) -> None:
    """:class:`~jaxsync.MaterialError` naming the field where a law's parameter is a
    string, not a number."""
    for name, value in vars(material).items():
        if isinstance(value, str):
            raise MaterialError(f"material parameter {name} must be a number, got {value!r}")


def check_young_poisson(E, nu, rho, *, law: str) -> None:
    """:class:`~jaxsync.MaterialError` unless E, rho > 0 and -1 < nu < 0.5."""
    check_positive(law, E=E, rho=rho)
    check_number(nu, f"{law}.nu (Poisson ratio)", error=MaterialError, above=-1.0, below=0.5,
                 hint="-1 < nu < 0.5; nu = 0.5 has no finite bulk modulus; for nearly incompressible tissue "
                      "use nu = 0.49 to 0.499 with P2 elements")


class SmallStrain(FiniteStrainLaw):
    """The small-strain constants of a law given by E and nu."""

    @property
    def mu(self):
        """Shear modulus E / (2 (1 + nu)) [dyn/cm^2]."""
        return shear_modulus(self.E, self.nu)

    @property
    def lam(self):
        """First Lame parameter E nu / ((1 + nu)(1 - 2 nu)) [dyn/cm^2]."""
        return first_lame(self.E, self.nu)

    @property
    def bulk(self):
        """Bulk modulus lam + 2 mu / 3 [dyn/cm^2]."""
        return self.lam + 2.0 * self.mu / 3.0

    @property
    def dilatational_wave_speed(self):
        """sqrt((lam + 2 mu) / rho) [cm/s] at F = I."""
        return jnp.sqrt((self.lam + 2.0 * self.mu) / self.rho)



# Flops per quadrature point of each law's P(F), operation by operation of its formula (a
# transcendental function, a division, a comparison or a select counts as one flop, as in
# XLA's cost analysis); cof F = det F F^-T, J = det F (jaxsync.perf.roofline).
_COFACTOR_J = {"cof F: 9 entries, 2 products and a difference each": 27,
               "J = F_0 . cof_0": 5}
_ISOCHORIC_VOLUMETRIC = {
    **_COFACTOR_J,
    "J^-2/3 = exp(-2/3 ln J)": 3,
    "I1 = F : F": 17,  # 9 squares + 8 additions
    "a = mu J^-2/3": 1,
    "b = (K/2 (J^2 - 1) - a I1 / 3) / J": 7,
    "P = a F + b cof F": 27,
}


@pytree_dataclass
class NeoHookean(SmallStrain):
    """Compressible neo-Hookean solid (Bonet & Wood, eq. 6.28; felupe ``NeoHookeCompressible``):

        psi = mu/2 (I1 - 3) - mu ln J + lam/2 (ln J)^2,
        P = mu (F - F^-T) + lam ln J F^-T,

    with mu and lam the Lame parameters of E and nu (so it linearises to
    :class:`jaxsync.LinearElastic` of the same E, nu).

    Attributes:
        E: small-strain Young's modulus [dyn/cm^2] (> 0).
        nu: small-strain Poisson ratio (-1 < nu < 0.5).
        rho: reference density [g/cm^3] (> 0).
    """

    E: Any = 1.0e6
    nu: Any = 0.3
    rho: Any = 1.0

    point_flops = {**_COFACTOR_J, "ln J": 1, "s = (lam ln J - mu) / J": 3, "P = mu F + s cof F": 27}

    def __post_init__(self):
        check_numbers(self)
        check_young_poisson(self.E, self.nu, self.rho, law="NeoHookean")

    def energy(self, F, fibres=None):
        """psi(F) (...,) [erg/cm^3] of F (..., 3, 3); ``fibres`` is ignored (isotropic)."""
        log_j = jnp.log(determinant(F))
        i1 = sum_squares(F)
        return 0.5 * self.mu * (i1 - 3.0) - self.mu * log_j + 0.5 * self.lam * log_j**2

    def first_piola(self, F, fibres=None):
        """P(F) = mu F + (lam ln J - mu) F^-T (..., 3, 3) [dyn/cm^2], as the reverse-mode
        gradient of :meth:`energy` (faster here than the formula: module docstring)."""
        return jax.grad(lambda G: jnp.sum(self.energy(G)))(F)


@pytree_dataclass
class NearlyIncompressibleNeoHookean(SmallStrain):
    """Neo-Hookean solid split into an isochoric and a volumetric part, for nearly
    incompressible tissue (nu close to 0.5, with P2 elements):

        psi = mu/2 (J^-2/3 I1 - 3) + K/4 (J^2 - 1 - 2 ln J),
        P = mu J^-2/3 (F - I1/3 F^-T) + K/2 (J^2 - 1) F^-T,

    with K = lam + 2 mu / 3 the bulk modulus. The volumetric term (Simo & Taylor 1982) is
    convex in J and grows without bound as J -> 0 and as J -> infinity; U''(1) = K, so the
    law linearises to :class:`jaxsync.LinearElastic` of the same E, nu.

    Attributes:
        E: small-strain Young's modulus [dyn/cm^2] (> 0).
        nu: small-strain Poisson ratio (-1 < nu < 0.5).
        rho: reference density [g/cm^3] (> 0).
    """

    E: Any = 1.0e6
    nu: Any = 0.45
    rho: Any = 1.0

    point_flops = dict(_ISOCHORIC_VOLUMETRIC)

    def __post_init__(self):
        check_numbers(self)
        check_young_poisson(self.E, self.nu, self.rho, law="NearlyIncompressibleNeoHookean")

    def energy(self, F, fibres=None):
        """psi(F) (...,) [erg/cm^3]; ``fibres`` is ignored (isotropic)."""
        J = determinant(F)
        i1 = jnp.sum(F * F, axis=(-2, -1))
        return (0.5 * self.mu * (J ** (-2.0 / 3.0) * i1 - 3.0)
                + 0.25 * self.bulk * (J * J - 1.0 - 2.0 * jnp.log(J)))

    def first_piola(self, F, fibres=None):
        """P(F) (..., 3, 3) [dyn/cm^2]."""
        cof = cofactor(F)
        J = det_from_cofactor(F, cof)
        return _isochoric_volumetric(F, cof, J, self.mu, self.bulk)

    def stress_parts(self, F, fibres=None) -> dict:
        """S = 2 d psi / d C split into {"volumetric", "isochoric"} (..., 3, 3) [dyn/cm^2]
        (:func:`split_neo_hookean_stresses`); they sum to F^-1 P."""
        return split_neo_hookean_stresses(F, self.mu, self.bulk)

    def energy_parts(self, F, fibres=None) -> dict:
        """psi split as :meth:`stress_parts` (...,) [erg/cm^3]."""
        return _split_neo_hookean_energies(F, self.mu, self.bulk)


_I4_ROUNDOFF = 1e-12
"""A fibre family with I4 >= 1 - this counts as in tension (:class:`HolzapfelGasserOgden`)."""


@pytree_dataclass
class HolzapfelGasserOgden(FiniteStrainLaw):
    """Holzapfel-Gasser-Ogden arterial wall (Gasser, Ogden & Holzapfel 2006): an isochoric
    neo-Hookean ground matrix, a volumetric term and two families of collagen fibres::

        psi = mu/2 (J^-2/3 I1 - 3) + K/4 (J^2 - 1 - 2 ln J)
              + sum_i [I4_i >= 1] k1/(2 k2) (exp(k2 E_i^2) - 1),
        E_i = kappa (I1 - 3) + (1 - 3 kappa)(I4_i - 1),   I4_i = a_i . C a_i,

    kappa the fibre dispersion (0: perfectly aligned, 1/3: isotropic). The fibre term uses
    the full (not isochoric) invariants, so that the fibres also resist volume change (Nolan
    et al. 2014: the isochoric split of the anisotropic term misses that). Fibres bear no
    compression: a family with I4_i < 1 contributes nothing. With kappa = 0 the fibre stress
    is zero at I4 = 1 either way (continuous there); with kappa > 0 a family switches on
    with E_i = kappa (I1 - 3), not zero in general, so stress and energy jump where I4
    crosses 1 (a run's loss is then piecewise smooth in the parameters). The tangent at
    I4 = 1 is the tension one (from I4 >= 1 - 1e-12, so that the round-off of unit fibre
    vectors does not drop it), so that the stable step of the reference state accounts for
    the fibres.

    The fibre directions a_i are per element: ``fibres`` (n_elements, 2, 3) unit vectors of
    the reference configuration (:func:`helical_fibres` makes the usual +/- helix), which
    :class:`jaxsync.fem.forces.TotalLagrangian` hands element by element to
    :meth:`energy` and :meth:`first_piola`.

    Attributes:
        mu: shear modulus of the ground matrix [dyn/cm^2] (> 0).
        k1: fibre stiffness [dyn/cm^2] (>= 0).
        k2: fibre exponential coefficient [-] (> 0).
        kappa_bulk: bulk modulus K [dyn/cm^2] (> 0; about 100 mu or more for nearly
            incompressible tissue).
        rho: reference density [g/cm^3] (> 0).
        dispersion: fibre dispersion kappa, 0 <= kappa <= 1/3 (default 0).
        fibres: (n_elements, 2, 3) unit fibre directions, or None (give them before use).

    For instance the media of a rabbit carotid artery (Holzapfel, Gasser & Ogden 2000):
    mu = 3.0 kPa = 3.0e4 dyn/cm^2, k1 = 2.3632e4 dyn/cm^2, k2 = 0.8393, fibres at +/- 29
    degrees from the circumferential direction.
    """

    mu: Any
    k1: Any
    k2: Any
    kappa_bulk: Any
    rho: Any = 1.0
    dispersion: Any = 0.0
    fibres: Any = None

    point_flops = {
        **_ISOCHORIC_VOLUMETRIC,
        "F a_i, two families": 30,  # 9 products + 6 additions each
        "I4_i = |F a_i|^2": 10,
        "E_i = kappa (I1 - 3) + (1 - 3 kappa)(I4_i - 1)": 8,  # 2 shared + 3 per family
        "slope_i = k1 E_i exp(k2 E_i^2)": 10,
        "in tension: I4_i >= 1, else slope_i = 0": 4,  # a comparison and a select each
        "2 kappa (slope_1 + slope_2) F, added to P": 20,
        "slope_i F a_i (x) a_i, summed over the families": 33,  # 2 (3 + 9) + 9
        "2 (1 - 3 kappa) times that, added to P": 18,
    }

    def __post_init__(self):
        check_numbers(self)
        check_positive("HolzapfelGasserOgden", mu=self.mu, k2=self.k2, kappa_bulk=self.kappa_bulk, rho=self.rho)
        check_number(self.k1, "HolzapfelGasserOgden.k1 (fibre stiffness)", error=MaterialError, at_least=0.0,
                     unit="dyn/cm^2", hint="k1 = 0 leaves the neo-Hookean ground matrix alone")
        check_number(self.dispersion, "HolzapfelGasserOgden.dispersion", error=MaterialError)
        kappa = concrete_scalar(self.dispersion)
        if kappa is not None and not 0.0 <= kappa <= 1.0 / 3.0:
            raise MaterialError(f"HolzapfelGasserOgden: the fibre dispersion must satisfy 0 <= kappa <= 1/3, got "
                                f"{kappa} (0: aligned fibres, 1/3: isotropic)")
        if self.fibres is not None and not isinstance(self.fibres, jax.core.Tracer):
            a = np.asarray(self.fibres)
            if a.dtype != object:  # (not the placeholders JAX rebuilds pytrees with)
                if a.ndim != 3 or a.shape[1:] != (2, 3):
                    raise MaterialError(f"HolzapfelGasserOgden.fibres must have shape (n_elements, 2, 3), got "
                                        f"{a.shape}: two unit directions per element (jaxsync.helical_fibres)")
                norms = np.linalg.norm(a, axis=-1)
                if not np.all(np.abs(norms - 1.0) < 1e-6):
                    raise MaterialError("HolzapfelGasserOgden.fibres must be unit vectors (largest |1 - |a|| "
                                        f"{float(np.max(np.abs(norms - 1.0))):.3g}): normalise them")

    @property
    def bulk(self):
        """Bulk modulus K [dyn/cm^2] (``kappa_bulk``)."""
        return self.kappa_bulk

    @property
    def lam(self):
        """First Lame parameter of the ground matrix, K - 2 mu / 3 [dyn/cm^2]."""
        return self.kappa_bulk - 2.0 * self.mu / 3.0

    @property
    def E(self):
        """Small-strain Young's modulus of the ground matrix, 9 K mu / (3 K + mu) [dyn/cm^2]."""
        return 9.0 * self.kappa_bulk * self.mu / (3.0 * self.kappa_bulk + self.mu)

    @property
    def nu(self):
        """Small-strain Poisson ratio of the ground matrix, (3 K - 2 mu) / (2 (3 K + mu))."""
        return (3.0 * self.kappa_bulk - 2.0 * self.mu) / (2.0 * (3.0 * self.kappa_bulk + self.mu))

    @property
    def dilatational_wave_speed(self):
        """An upper bound of the fastest small-strain wave [cm/s], reached when both fibre
        families are aligned and in tension: sqrt((lam + 2 mu + 8 k1 (1 - 2 kappa)^2) / rho)
        (each family adds 4 k1 (kappa v.n + (1 - 3 kappa)(v.a)(n.a))^2 <= 4 k1 (1 - 2 kappa)^2
        to the acoustic tensor's v.Q(n)v)."""
        fibres = 8.0 * self.k1 * (1.0 - 2.0 * self.dispersion) ** 2
        return jnp.sqrt((self.lam + 2.0 * self.mu + fibres) / self.rho)

    def _fibre_terms(self, F, fibres):
        """(E_i (..., 2), active (..., 2), F a_i (..., 2, 3)) of both families."""
        if fibres is None:
            raise MaterialError("HolzapfelGasserOgden needs fibre directions: pass fibres= (n_elements, 2, 3), "
                                "for instance jaxsync.helical_fibres(...)")
        Fa = jnp.einsum("...ij,...fj->...fi", F, fibres)
        i4 = sum3(Fa * Fa)
        i1 = sum_squares(F)[..., None]
        kappa = self.dispersion
        strain = kappa * (i1 - 3.0) + (1.0 - 3.0 * kappa) * (i4 - 1.0)
        # active from I4 = 1 on, less the round-off of a unit vector's |a|^2 (helical fibres
        # give 1 - 1.1e-16 at rest: without it the reference tangent would drop the fibres)
        return strain, i4 >= 1.0 - _I4_ROUNDOFF, Fa

    def energy(self, F, fibres=None):
        """psi(F) (...,) [erg/cm^3]; ``fibres`` (..., 2, 3) the reference fibre directions."""
        J = determinant(F)
        i1 = jnp.sum(F * F, axis=(-2, -1))
        ground = (0.5 * self.mu * (J ** (-2.0 / 3.0) * i1 - 3.0)
                  + 0.25 * self.kappa_bulk * (J * J - 1.0 - 2.0 * jnp.log(J)))
        strain, active, _ = self._fibre_terms(F, fibres)
        fibre = jnp.where(active, self.k1 / (2.0 * self.k2) * jnp.expm1(self.k2 * strain**2), 0.0)
        return ground + jnp.sum(fibre, axis=-1)

    def first_piola(self, F, fibres=None):
        """P(F) (..., 3, 3) [dyn/cm^2]; ``fibres`` (..., 2, 3) the reference fibre directions."""
        cof = cofactor(F)
        J = det_from_cofactor(F, cof)
        P = _isochoric_volumetric(F, cof, J, self.mu, self.kappa_bulk)
        strain, active, Fa = self._fibre_terms(F, fibres)
        # d psi_i / d E_i; dE_i/dF = 2 kappa F + 2 (1 - 3 kappa) F a_i (x) a_i
        slope = jnp.where(active, self.k1 * strain * jnp.exp(self.k2 * strain**2), 0.0)
        kappa = self.dispersion
        P = P + (2.0 * kappa * (slope[..., 0] + slope[..., 1]))[..., None, None] * F
        a = jnp.broadcast_to(fibres, Fa.shape)
        return P + 2.0 * (1.0 - 3.0 * kappa) * jnp.einsum("...f,...fi,...fj->...ij", slope, Fa, a)

    def stress_parts(self, F, fibres=None) -> dict:
        """S = 2 d psi / d C split into {"volumetric", "isochoric"} of the ground matrix
        (:func:`split_neo_hookean_stresses`) and "fibres", sum_i 2 slope_i (kappa I +
        (1 - 3 kappa) a_i (x) a_i) with slope_i = k1 E_i exp(k2 E_i^2) in tension, 0 in
        compression (each (..., 3, 3) [dyn/cm^2]; they sum to F^-1 P)."""
        parts = split_neo_hookean_stresses(F, self.mu, self.kappa_bulk)
        strain, active, _ = self._fibre_terms(F, fibres)
        slope = jnp.where(active, self.k1 * strain * jnp.exp(self.k2 * strain**2), 0.0)
        kappa = self.dispersion
        a = jnp.broadcast_to(fibres, strain.shape + (3,))
        eye = jnp.broadcast_to(jnp.eye(3, dtype=F.dtype), F.shape)
        parts["fibres"] = (2.0 * kappa * jnp.sum(slope, axis=-1))[..., None, None] * eye + 2.0 * (
            1.0 - 3.0 * kappa) * jnp.einsum("...f,...fi,...fj->...ij", slope, a, a)
        return parts

    def energy_parts(self, F, fibres=None) -> dict:
        """psi split as :meth:`stress_parts` (...,) [erg/cm^3]."""
        parts = _split_neo_hookean_energies(F, self.mu, self.kappa_bulk)
        strain, active, _ = self._fibre_terms(F, fibres)
        fibre = jnp.where(active, self.k1 / (2.0 * self.k2) * jnp.expm1(self.k2 * strain**2), 0.0)
        parts["fibres"] = jnp.sum(fibre, axis=-1)
        return parts


HYPERELASTIC = (NeoHookean, NearlyIncompressibleNeoHookean, HolzapfelGasserOgden)
"""The hyperelastic laws a :class:`jaxsync.Problem` takes (with
:class:`jaxsync.fem.forces.TotalLagrangian`)."""


def is_hyperelastic(material) -> bool:
    """True for a finite-strain law (its :attr:`~jaxsync.fem.materials.MaterialLaw.finite_strain`):
    a thin alias kept for existing code; jaxsync itself asks the law
    (:mod:`jaxsync.fem.materials`)."""
    return bool(getattr(material, "finite_strain", False))


def material_parameters(material) -> tuple[str, dict, str | None]:
    """(the law's class name, {parameter: float} of its scalar fields, sha256 hex of its fibre
    directions or None) of a concrete law: its
    :meth:`~jaxsync.fem.materials.MaterialLaw.parameters` as a tuple (an alias kept for
    existing code)."""
    p = material.parameters()
    return p.name, dict(p.values), p.fibres


def helical_fibres(centres, axis=(0.0, 0.0, 1.0), angle: float = 40.0, origin=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Two helical fibre families per element, at +/- ``angle`` from the circumferential
    direction around an axis (the usual arterial-wall layout of the HGO model).

    Args:
        centres: (n_elements, 3) element centroids [cm] (``mesh.points[mesh.tets].mean(axis=1)``).
        axis: (3,) the vessel's axis direction, or (n_elements, 3) the local centreline
            tangent at each element (a curved vessel); need not be unit.
        angle: the fibre angle [degrees] from the circumferential direction towards the
            axis (0: hoop fibres, 90: axial fibres).
        origin: (3,) a point on the axis, or (n_elements, 3) the centreline point nearest
            each element.

    Returns:
        (n_elements, 2, 3) unit vectors cos(angle) e_theta +/- sin(angle) e_axis, with
        e_theta = e_axis x e_r and e_r the unit radial direction of the centroid (an
        element on the axis itself takes any direction normal to it as e_r).
    """
    centres = np.asarray(centres, dtype=float)
    if centres.ndim != 2 or centres.shape[1] != 3:
        raise MaterialError(f"helical_fibres: centres must have shape (n_elements, 3), got {centres.shape}")
    e_axis = np.broadcast_to(np.asarray(axis, dtype=float), centres.shape)
    length = np.linalg.norm(e_axis, axis=1, keepdims=True)
    if not np.all(length > 0):
        raise MaterialError("helical_fibres: the axis direction must be non-zero")
    e_axis = e_axis / length
    radial = centres - np.broadcast_to(np.asarray(origin, dtype=float), centres.shape)
    radial = radial - np.sum(radial * e_axis, axis=1, keepdims=True) * e_axis
    r = np.linalg.norm(radial, axis=1, keepdims=True)
    # on the axis: any normal direction (the cross product with the least aligned unit vector)
    pick = np.eye(3)[np.argmin(np.abs(e_axis), axis=1)]
    fallback = np.cross(e_axis, pick)
    fallback /= np.linalg.norm(fallback, axis=1, keepdims=True)
    scale = float(np.max(r, initial=0.0)) or 1.0
    e_r = np.where(r > 1e-12 * scale, radial / np.maximum(r, 1e-300), fallback)
    e_theta = np.cross(e_axis, e_r)
    c, s = np.cos(np.deg2rad(angle)), np.sin(np.deg2rad(angle))
    return np.stack([c * e_theta + s * e_axis, c * e_theta - s * e_axis], axis=1)
