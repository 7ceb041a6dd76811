"""The material-law protocol: what a constitutive law tells the rest of jaxsync.

Nothing outside a law asks which law it is. Every law a :class:`jaxsync.Problem` takes
implements :class:`MaterialLaw`, and the solver, the stable step, checkpoints, the error
estimate and the cost model ask it:

* which internal-force model runs it (:meth:`MaterialLaw.force_model`): the stored
  stiffness for :class:`jaxsync.LinearElastic` (whichever linear mode was asked for),
  the total-Lagrangian model (:class:`jaxsync.fem.forces.TotalLagrangian`) for
  a finite-strain law;
* its default stable step and exact bound at the problem's initial state
  (:meth:`~MaterialLaw.stable_step`, :meth:`~MaterialLaw.max_stable_dt`), each element's
  own step (:meth:`~MaterialLaw.element_steps`) and the density that raises it to a
  target (:meth:`~MaterialLaw.scaled_density`, mass scaling);
* its assembled tangent stiffness at a displacement (:meth:`~MaterialLaw.tangent_stiffness`,
  the error estimate's linearisation) and whether that tangent changes with the state
  (:attr:`~MaterialLaw.state_dependent_tangent`: the host then refreshes it);
* what identifies it (:meth:`~MaterialLaw.parameters`, memo keys;
  :meth:`~MaterialLaw.fingerprint`, checkpoint fingerprints);
* its cost per quadrature point (:meth:`~MaterialLaw.cost`, :mod:`jaxsync.perf.roofline`);
* the check a run applies to its state between chunks (:meth:`~MaterialLaw.run_check`);
* the per-quadrature-point state it carries, with its initial values
  (:meth:`~MaterialLaw.internal_variables`; empty for elastic laws).

A finite-strain law needs only its stress: derive it from :class:`FiniteStrainLaw`, write
``first_piola(F, fibres)`` (and ``energy`` for the static solver and energy checks) and
the small-strain constants ``E``, ``nu``, ``rho``, ``lam``, ``mu``; the base class
answers the rest through the total-Lagrangian machinery. A law that carries internal
variables also overrides :meth:`FiniteStrainLaw.internal_variables` and
:meth:`FiniteStrainLaw.stress_update` (:mod:`jaxsync.fem.materials` is one).
docs/guides/extending-materials.md walks through both.
"""

from __future__ import annotations

import dataclasses
import hashlib
from typing import Any, ClassVar, Mapping, Protocol, runtime_checkable

import jax
import jax.numpy as jnp
import numpy as np

from ...errors import ProblemError
from .._timestep import ALPHA_S, StableStep, hyperelastic_step

__all__ = ["MaterialLaw", "FiniteStrainLaw", "MaterialParameters", "LawCost", "check_material_law",
           "PROTOCOL_MEMBERS"]


@dataclasses.dataclass(frozen=True)
class MaterialParameters:
    """What identifies a concrete law.

    Attributes:
        name: the law's class name.
        values: {field name: float} of its scalar parameters.
        fibres: sha256 hex of its fibre directions, or None (no per-element data).
    """

    name: str
    values: Mapping[str, float]
    fibres: str | None = None

    def key(self) -> tuple:
        """A hashable key (memoised stable steps)."""
        return (self.name, tuple(self.values.items()), self.fibres)


@dataclasses.dataclass(frozen=True)
class LawCost:
    """The work of a law's stress at one quadrature point (:mod:`jaxsync.perf.roofline`).

    Attributes:
        point_flops: {operation: flops} of P(F) at one point (a transcendental function,
            a division, a comparison or a select counts as one flop).
        element_bytes: bytes of per-element law data read each step (fibre directions:
            2 x 3 float64 = 48), 0 if none.
        point_bytes: bytes of internal variables read and written per quadrature point
            each step, 0 if none.
    """

    point_flops: Mapping[str, int]
    element_bytes: int = 0
    point_bytes: int = 0


@runtime_checkable
class MaterialLaw(Protocol):
    """What every material law implements (module docstring).

    Attributes:
        E, nu, rho: the small-strain Young's modulus [dyn/cm^2], Poisson ratio and the
            reference density [g/cm^3] (the lumped mass, the locking warning, summaries).
        finite_strain: True when the law's force follows the deformed configuration (it
            takes follower pressures; its static solution needs Newton's method).
        state_dependent_tangent: True when the tangent stiffness changes with the state
            (the host relinearises the error estimate at synchronized states).
    """

    E: Any
    nu: Any
    rho: Any
    finite_strain: bool
    state_dependent_tangent: bool

    def force_model(self, requested):
        """The force model (:class:`jaxsync.fem.forces.ForceModel`) that runs this
        law when ``requested`` was asked for (``requested`` itself, or another one)."""

    def stable_step(self, problem, alpha_s: float = ALPHA_S) -> StableStep:
        """The default step of ``problem`` at its initial state and the rule that set it."""

    def max_stable_dt(self, problem, *, tol: float = 1e-10, max_iter: int = 20000, seed: int = 0):
        """The exact bound 2 / omega_max [s] of the central difference scheme at the
        initial state (traced where the law's parameters are and the law allows it)."""

    def element_steps(self, problem) -> np.ndarray:
        """(n_elements,) each element's own stable step [s] (alpha_s = 1)."""

    def scaled_density(self, problem, dt_hat: float, alpha_s: float = ALPHA_S) -> tuple:
        """(density_scale (n_elements,), scaled (n_elements,) bool): the problem's density
        scale with every element whose own step (alpha_s times :meth:`element_steps`) is
        below ``dt_hat`` [s] made heavier so that its step is dt_hat (artificial mass
        scaling, :func:`jaxsync.mass_scaling`), and which elements that changed."""

    def tangent_stiffness(self, problem, displacement=None):
        """The assembled tangent stiffness (scipy sparse, (n_dofs, n_dofs) [dyn/cm],
        symmetric) at ``displacement`` (n_nodes, 3) [cm] (None: the reference state),
        without the elastic supports' springs."""

    def parameters(self) -> MaterialParameters:
        """What identifies the (concrete) law."""

    def fingerprint(self) -> bytes:
        """What the law adds to a problem's fingerprint besides E, nu and rho, which every
        fingerprint holds (b"" for a law those three identify)."""

    def cost(self) -> LawCost | None:
        """Its stress's work per quadrature point, or None for a law whose cost is that of
        its force mode (the linear law)."""

    def run_check(self, problem, system, dt):
        """The between-chunks check of a run (``check(state)``), or None."""

    def internal_variables(self, n_elements: int, n_points: int) -> dict:
        """{name: (n_elements, n_points, ...) initial values} of the state the law carries
        at every quadrature point; {} for a law without state."""


PROTOCOL_MEMBERS = ("E", "nu", "rho", "finite_strain", "state_dependent_tangent", "force_model", "stable_step",
                    "max_stable_dt", "element_steps", "scaled_density", "tangent_stiffness", "parameters",
                    "fingerprint", "cost", "run_check", "internal_variables")
"""The members of :class:`MaterialLaw`."""


def check_material_law(material, where: str = "Problem.material") -> None:
    """Raise :class:`jaxsync.ProblemError` naming what ``material`` lacks of :class:`MaterialLaw`."""
    missing = [name for name in PROTOCOL_MEMBERS if not hasattr(material, name)]
    if missing:
        raise ProblemError(
            f"{where} must be a material law (jaxsync.LinearElastic, jaxsync.NeoHookean, "
            f"NearlyIncompressibleNeoHookean, HolzapfelGasserOgden, StandardLinearSolid, or a law of your own "
            f"deriving from jaxsync.fem.materials.FiniteStrainLaw); {type(material).__name__} lacks "
            f"{', '.join(missing)}")


def _scalar_fields(material) -> dict:
    return {f.name: float(getattr(material, f.name)) for f in dataclasses.fields(material) if f.name != "fibres"}


def _tangent(material, F, fibres):
    """A = dP/dF (..., 3, 3, 3, 3) by forward-mode differentiation of ``first_piola``."""
    flat = F.reshape(-1, 3, 3)
    if fibres is None:
        A = jax.vmap(jax.jacfwd(lambda f: material.first_piola(f)))(flat)
    else:
        a = jnp.broadcast_to(fibres, F.shape[:-2] + (2, 3)).reshape(-1, 2, 3)
        A = jax.vmap(jax.jacfwd(lambda f, b: material.first_piola(f, b)))(flat, a)
    return A.reshape(F.shape + (3, 3))


class FiniteStrainLaw:
    """The :class:`MaterialLaw` of a finite-strain law given by its stress (a mixin for a
    frozen pytree dataclass whose fields are the law's parameters, JAX tracers allowed).

    A subclass writes ``first_piola(F, fibres=None)``: P (..., 3, 3) [dyn/cm^2] of
    deformation gradients F (..., 3, 3) (``fibres``: (..., 2, 3) reference fibre
    directions, or None), ``energy(F, fibres=None)`` (...,) [erg/cm^3] if it is
    hyperelastic, and the small-strain constants ``E``, ``nu``, ``rho``, ``lam``, ``mu``
    of its linearisation at F = I. Its internal force is the total-Lagrangian one, its
    stable step that of its tangent stiffness; a law with a ``fibres`` field hands them
    to the stress element by element.

    A law with internal variables overrides :meth:`internal_variables` (their initial
    values) and :meth:`stress_update` (the stress and the updated variables of a step).
    """

    finite_strain: ClassVar[bool] = True
    state_dependent_tangent: ClassVar[bool] = True
    point_flops: ClassVar[Mapping[str, int] | None] = None
    """{operation: flops} of P(F) at one quadrature point, or None (not costed)."""

    def replace(self, **changes):
        """A copy with some fields changed (``fibres=...``, ``k1=...``)."""
        return dataclasses.replace(self, **changes)

    def first_piola(self, F, fibres=None):  # pragma: no cover - every law writes it
        raise NotImplementedError(f"{type(self).__name__} must define first_piola(F, fibres=None)")

    def tangent(self, F, fibres=None):
        """A = dP/dF (..., 3, 3, 3, 3) [dyn/cm^2], A[..., i, J, k, L] = dP_iJ / dF_kL."""
        return _tangent(self, F, fibres)

    def internal_variables(self, n_elements: int, n_points: int) -> dict:
        """{} (an elastic law carries no state)."""
        return {}

    def stress_update(self, F, fibres, internal, dt):
        """(P (..., 3, 3) [dyn/cm^2], updated internal variables) of a step to F: an elastic
        law's P(F) and its (empty) variables unchanged."""
        return self.first_piola(F, fibres), internal

    def force_model(self, requested):
        """:class:`jaxsync.fem.forces.TotalLagrangian`, whatever was asked for (a
        nonlinear law has no stiffness to store); a stored stiffness's own setting
        (float32 blocks) is refused."""
        if getattr(requested, "blocks_dtype", "float64") != "float64":
            raise ProblemError(f"float32 stiffness blocks store the K of a linear law; the {type(self).__name__} "
                               "law has none (every mode runs the total-Lagrangian force): leave out blocks_dtype / "
                               "--float32-blocks")
        from ..forces._total_lagrangian import TotalLagrangian

        return TotalLagrangian()

    def stable_step(self, problem, alpha_s: float = ALPHA_S) -> StableStep:
        """alpha_s min(element rule, exact bound) of the tangent at the initial displacement
        (:func:`jaxsync.fem.forces.default_step`)."""
        from ..forces._total_lagrangian import default_step

        step = default_step(problem)
        return step if alpha_s == step.alpha_s else hyperelastic_step(
            step.cfl / step.alpha_s, step.exact, alpha_s, element=step.element, law=step.law)

    def max_stable_dt(self, problem, *, tol: float = 1e-10, max_iter: int = 20000, seed: int = 0):
        """The exact bound of the tangent at the initial displacement (memoised with the
        default step)."""
        return self.stable_step(problem).exact

    def element_steps(self, problem) -> np.ndarray:
        """2 / omega_e of each element's tangent stiffness at the initial displacement over
        its lumped mass (:func:`jaxsync.fem.forces.element_frequencies`)."""
        from ...pytree import is_traced

        if is_traced(self, problem.initial_displacement):
            raise ProblemError("the element steps are eigenvalues computed on the host: give concrete material "
                               "parameters and initial displacement")
        from ..forces._total_lagrangian import TotalLagrangian, element_frequencies

        op = TotalLagrangian().operator(problem)
        u0 = problem.initial_displacement
        u = jnp.zeros((problem.n_nodes, 3)) if u0 is None else jnp.asarray(u0, dtype=float)
        return 2.0 / np.sqrt(np.asarray(element_frequencies(op, u), dtype=float))

    def scaled_density(self, problem, dt_hat: float, alpha_s: float = ALPHA_S) -> tuple:
        """Each element below dt_hat gets its density times (dt_hat / its step)^2: its step
        goes as the square root of its density."""
        dt_e = alpha_s * self.element_steps(problem)
        scale = (np.ones(problem.mesh.n_elements) if problem.density_scale is None
                 else np.asarray(problem.density_scale, dtype=float).copy())
        small = dt_e < dt_hat
        scale[small] *= (dt_hat / dt_e[small]) ** 2
        return scale, small

    def tangent_stiffness(self, problem, displacement=None):
        """K_T(u) (:func:`jaxsync.fem.forces.tangent_matrix`), symmetrised (it is
        symmetric up to round-off)."""
        from ..forces._total_lagrangian import tangent_matrix

        u = np.zeros((problem.n_nodes, 3)) if displacement is None else np.asarray(displacement, dtype=float)
        if u.shape != (problem.n_nodes, 3):
            raise ProblemError(f"the error estimate's linearisation point has shape {u.shape}; give the "
                               f"displacement of the problem's {problem.n_nodes} nodes, ({problem.n_nodes}, 3)")
        K = tangent_matrix(problem, u)
        return (0.5 * (K + K.T)).tocsr()

    def parameters(self) -> MaterialParameters:
        """The class name, every scalar field and the sha256 of the fibres (if any)."""
        fibres = getattr(self, "fibres", None)
        digest = None if fibres is None else hashlib.sha256(
            np.ascontiguousarray(np.asarray(fibres, dtype=float)).tobytes()).hexdigest()
        return MaterialParameters(type(self).__name__, _scalar_fields(self), digest)

    def fingerprint(self) -> bytes:
        """The law's type, every parameter and its fibre directions."""
        p = self.parameters()
        return repr(("material", p.name, sorted(p.values.items()), p.fibres)).encode()

    @classmethod
    def cost(cls) -> LawCost | None:
        """:attr:`point_flops` (None: not costed), and the fibres' 48 bytes per element if
        the law has them (the same for every instance of the law)."""
        if cls.point_flops is None:
            return None
        return LawCost(dict(cls.point_flops), 2 * 3 * 8 if hasattr(cls, "fibres") else 0)

    def run_check(self, problem, system, dt):
        """:class:`jaxsync.fem.RunCheck` (inversion and the deformed state's step)."""
        from .._run_check import RunCheck

        return RunCheck(problem, system, dt)
