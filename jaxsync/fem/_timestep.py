"""Stable time step: the default rule, the exact bound, and artificial mass scaling.

CFL rule of the paper's published code: ``dt = alpha_s * min_e h_e / c_e`` with
``h_e = 2 * (shortest edge of e) / sqrt(24)`` (the in-sphere diameter of a regular
tetrahedron with that edge), ``c_e = sqrt(E / (rho_e (1 - nu^2)))`` and alpha_s = 0.9.
The exact stability bound of the central difference scheme with lumped mass (with or
without mass-proportional damping) is ``2 / omega_max``, omega_max^2 the largest
eigenvalue of M^-1 K on the free dofs.

Stiffness-proportional (Rayleigh) damping beta K (``Problem.stiffness_damping``) takes its
force from the backward velocity (d(n) - d(n-1)) / dt, which keeps the step explicit and
lowers the bound to ``(2 / omega_max) (sqrt(1 + xi^2) - xi)``, xi = beta omega_max / 2,
that is ``sqrt((2 / omega_max)^2 + beta^2) - beta`` (:func:`damped_bound`; the root of the
mode's characteristic polynomial at z = -1). The mass-proportional part alpha M and the
supports' dashpots enter the update with the centred velocity (d(n+1) - d(n-1)) / (2 dt)
and leave the bound where it is. The bound decreases with omega, so the fastest mode
(or element) still sets it: every bound of a problem with beta > 0 (:func:`stable_step`'s
``exact``, the hyperelastic run-time check) is the undamped one passed through
:func:`damped_bound`, and the default step is the law's rule where that is at most alpha_s
times the damped bound, else alpha_s times it.

The paper's c_e is the plate wave speed: it ignores the dilatational wave speed
sqrt((lambda + 2 mu) / rho), which grows without bound as nu -> 0.5, so for nearly
incompressible tissue (nu >= ~0.44 on the cantilever) the paper's rule lies above the
exact bound and the run diverges. The default step (:func:`stable_step`,
``Problem.dt``) is therefore ``min(paper CFL step, alpha_s * 2 / omega_max)``: the paper's
step wherever it is at most alpha_s times the bound (every case of the paper), never
above the bound.

Hyperelastic laws (:mod:`jaxsync.fem.materials`) ask their force model,
:class:`~jaxsync.fem.forces.TotalLagrangian`, for the bound at rest (the initial
displacement, zero if none): the exact bound 2 / omega_max of the TANGENT stiffness there
(:func:`~jaxsync.fem.forces.exact_stable_dt`; for the Holzapfel-Gasser-Ogden law
the fibres' stiffness included; the supports' springs too), which :func:`check_dt` refuses
to exceed. The default step is ``alpha_s * min(element rule, 2 / omega_max)``, the element
rule being 2 / max_e omega_e of the element tangent stiffnesses over their lumped masses
(:func:`~jaxsync.fem.forces.stable_dt`, ``rule="element"``: never above the exact
bound, Irons' element eigenvalue bound; 0.7-0.9 of it on P1 and P2 beams), the rule the
run-time check screens deformed states with: a deformed state has another bound, which
the host executor checks between chunks (:class:`~jaxsync.fem.RunCheck`).
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from ..errors import ProblemError, StabilityError
from ..pytree import concrete_scalar as concrete_or_none

__all__ = ["ALPHA_S", "DENSE_EIGEN_DOFS", "unit_bound", "MassScalingWarning", "StableStep", "element_size",
           "element_dt", "cfl_dt",
           "max_stable_dt", "stable_step", "small_strain_step", "small_strain_max_stable_dt", "damped_bound",
           "hyperelastic_step", "check_dt", "divergence_advice", "mass_scaling"]

ALPHA_S = 0.9

MASS_SCALING_WARN_PERCENT = 10.0
"""Default threshold of :func:`mass_scaling`'s warning: added mass in percent."""

DENSE_EIGEN_DOFS = 400
"""Up to this many free dofs the largest eigenvalue comes from a dense solver."""


class MassScalingWarning(UserWarning):
    """Artificial mass scaling added more mass than the caller's threshold."""


@dataclasses.dataclass(frozen=True)
class StableStep:
    """The default time step of a problem and the rule that set it.

    Attributes:
        dt: the step [s]: ``min(cfl, alpha_s * exact)`` (a JAX tracer when E or rho is).
        rule: ``"cfl"`` (the paper's CFL rule set it) or ``"exact"`` (alpha_s times the
            exact bound set it, because the CFL rule is above alpha_s times the bound).
        cfl: the paper's CFL step [s] (undamped).
        exact: the exact stability bound [s]: 2 / omega_max, with stiffness-proportional
            damping ``damped_bound(2 / omega_max, stiffness_damping)``.
        alpha_s: the safety factor applied to the exact bound.
        element: ``"P1"`` or ``"P2"``.
        law: the class name of a hyperelastic law, or None for the linear law. With a law,
            ``exact`` is the bound of its tangent at the initial displacement and ``cfl``
            holds the element eigenvalue rule's step there (alpha_s min_e 2 / omega_e, never
            above ``alpha_s * exact`` without springs; rule ``"element"`` when it set ``dt``).
        stiffness_damping: the problem's beta [s] that ``dt`` and ``exact`` include (0: none).
    """

    dt: float
    rule: str
    cfl: float
    exact: float
    alpha_s: float = ALPHA_S
    element: str = "P1"
    law: str | None = None
    stiffness_damping: float = 0.0

    def describe(self, dt=None) -> str:
        """One line: the step, the rule that set it and the exact bound.

        ``dt``: the step a run uses instead of the default [s] (``simulate(..., dt=)``,
        ``jaxsync simulate --dt``): the line then names it first, with the default and the
        bound beside it."""
        line = self._describe(dt)
        beta = concrete_or_none(self.stiffness_damping)
        if beta == 0.0:
            return line
        return line + (" (stiffness-proportional damping beta" + ("" if beta is None else f" = {beta:.4g} s")
                       + ": the bound is sqrt((2/omega_max)^2 + beta^2) - beta, the step at most alpha_s times it)")

    def _describe(self, dt=None) -> str:
        if dt is not None:
            try:
                given, default, exact = float(dt), float(self.dt), float(self.exact)
            except TypeError:  # traced
                return "time step: given (traced)"
            if given != default:
                return (f"dt {given:.4e} s (given; the default would be {default:.4e} s; exact stability bound "
                        f"2/omega_max {exact:.4e} s{' of the tangent at rest' if self.law is not None else ''})")
        try:
            dt, cfl, exact = float(self.dt), float(self.cfl), float(self.exact)
        except TypeError:  # traced material
            return f"time step set by the {'CFL rule' if self.rule == 'cfl' else 'exact bound'} (traced)"
        if self.law is not None:
            how = (f"{self.alpha_s:g} x the element eigenvalue bound of the {self.law} tangent at rest"
                   if self.rule == "element" else f"{self.alpha_s:g} x the exact bound")
            return (f"dt {dt:.4e} s ({how}; exact stability bound 2/omega_max of the tangent at rest {exact:.4e} "
                    "s; checked on the deformed state between chunks of a run)")
        if self.rule == "cfl":
            return (f"dt {dt:.4e} s (paper's CFL rule; exact stability bound 2/omega_max "
                    f"{exact:.4e} s)")
        if self.element != "P1":
            return (f"dt {dt:.4e} s ({self.alpha_s:g} x the exact stability bound 2/omega_max {exact:.4e} s: "
                    f"{self.element} elements take their step from the exact bound)")
        return (f"dt {dt:.4e} s ({self.alpha_s:g} x the exact stability bound 2/omega_max "
                f"{exact:.4e} s; the paper's CFL rule, {cfl:.4e} s, is above it: it ignores "
                "the dilatational wave speed, which grows as nu -> 0.5)")


def element_size(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(n_elements,) h_e = 2 * shortest edge / sqrt(24) [cm]."""
    p = points[tets]
    edges = [np.linalg.norm(p[:, i] - p[:, j], axis=1) for i in range(4) for j in range(i + 1, 4)]
    return 2.0 * np.min(edges, axis=0) / np.sqrt(24.0)


def element_dt(problem, alpha_s: float = ALPHA_S):
    """(n_elements,) the CFL step of each element alone [s]: alpha_s h_e / c_e."""
    import jax.numpy as jnp

    h = element_size(problem.mesh.points, problem.mesh.tets)
    scale = 1.0 if problem.density_scale is None else jnp.asarray(problem.density_scale)
    m = problem.material
    c = jnp.sqrt(m.E / (m.rho * scale * (1.0 - m.nu**2)))
    return alpha_s * h / c


def cfl_dt(problem, alpha_s: float = ALPHA_S):
    """The paper's CFL step [s]: the smallest element step (a Python float unless the
    material is traced)."""
    import jax.numpy as jnp

    from ..pytree import is_traced

    dt = jnp.min(element_dt(problem, alpha_s))
    return dt if is_traced(dt) else float(dt)


def unit_bound(problem, tol: float, max_iter: int, seed: int) -> float:
    """2 / omega_max [s] of ``problem`` with E = 1 and rho = 1 (its nu, density scaling and
    Dirichlet set), computed once per key on the problem's operators
    (:meth:`~jaxsync.fem.UnitOperators.stability_bound`): the bound of any E and rho is
    this times sqrt(rho / E), so traced E or rho (inside ``jax.grad``) need no solve."""
    nu = problem.material.nu
    from ..pytree import is_traced

    if is_traced(nu):
        raise ProblemError(
            "the default time step depends on nu through the exact stability bound, an "
            "eigenvalue computed on the host, so it cannot follow a traced nu: pass dt= "
            "explicitly (for instance the problem.dt of the problem at a concrete nu)")
    nu = float(nu)
    from .forces._support import spring_ratios

    ratios = spring_ratios(problem)  # k_s / E: the springs at E = 1
    fixed, _ = problem.dirichlet_dofs()
    scale = problem.density_scale
    key = (nu, None if scale is None else np.asarray(scale, dtype=float).tobytes(), fixed.tobytes(), ratios)
    return problem.operators.stability_bound(
        "small strain, E = rho = 1", key, lambda: _unit_bound(problem, nu, ratios, fixed, tol, max_iter, seed))


def _unit_bound(problem, nu: float, ratios, fixed, tol: float, max_iter: int, seed: int) -> float:
    """:func:`unit_bound`, computed: the largest eigenvalue of M^-1 K at E = rho = 1."""
    from ._assembly import lumped_mass
    from .forces._support import spring_matrix

    scale = problem.density_scale

    lam, mu = nu / ((1.0 + nu) * (1.0 - 2.0 * nu)), 1.0 / (2.0 * (1.0 + nu))
    K = problem.operators.stiffness(lam, mu)
    if ratios:
        K = (K + spring_matrix(problem, 1.0 / float(problem.material.E))).tocsr()
    mass = np.repeat(np.asarray(lumped_mass(problem.space, scale), dtype=float), 3)
    free = np.setdiff1d(np.arange(K.shape[0]), fixed)
    if len(free) == 0:
        raise StabilityError("every dof is prescribed: there is no free motion to bound")
    s = 1.0 / np.sqrt(mass[free])
    # the symmetric form M^-1/2 K M^-1/2 has the eigenvalues of M^-1 K
    A = K[free][:, free].multiply(s[:, None]).multiply(s[None, :]).tocsr()
    if len(free) <= DENSE_EIGEN_DOFS:
        import scipy.linalg

        largest = float(scipy.linalg.eigvalsh(A.toarray())[-1])
    else:
        import scipy.sparse.linalg as sla

        v0 = np.random.default_rng(seed).standard_normal(len(free))
        try:
            largest = float(sla.eigsh(A, k=1, which="LA", tol=tol, maxiter=max_iter, v0=v0,
                                      return_eigenvectors=False)[0])
        except sla.ArpackNoConvergence as exc:
            if not len(exc.eigenvalues):
                raise StabilityError(
                    "the largest eigenvalue of M^-1 K (the exact stability bound) did not "
                    f"converge in {max_iter} iterations: pass dt= explicitly, or raise "
                    "max_iter") from None
            largest = float(np.max(exc.eigenvalues))
    return float(2.0 / np.sqrt(largest))


def max_stable_dt(problem, *, tol: float = 1e-10, max_iter: int = 20000, seed: int = 0):
    """Exact stability bound 2 / omega_max [s] of the central difference scheme at the
    problem's initial state, as its material law computes it
    (:meth:`jaxsync.fem.materials.MaterialLaw.max_stable_dt`): the linear law's
    :func:`small_strain_max_stable_dt`; a hyperelastic law's bound of its tangent at rest
    (module docstring, :meth:`jaxsync.fem.forces.TotalLagrangian.max_stable_dt`),
    memoised per law, fibres, initial displacement, density scaling, Dirichlet set and
    supports."""
    return problem.material.max_stable_dt(problem, tol=tol, max_iter=max_iter, seed=seed)


def small_strain_max_stable_dt(problem, *, tol: float = 1e-10, max_iter: int = 20000, seed: int = 0):
    """Exact stability bound 2 / omega_max [s] of the linear law: omega_max^2 the largest
    eigenvalue of the symmetric form M^-1/2 K M^-1/2 restricted to the free dofs (lumped
    mass), dense for small problems, else Lanczos (ARPACK) to relative accuracy ``tol``.
    Mass-proportional damping does not change the bound.

    The eigenvalue is computed once per mesh, nu, density scaling and Dirichlet set (for
    E = rho = 1) and scaled by sqrt(rho / E), so the bound is traced when E or rho are
    (a Python float otherwise); a traced nu raises :class:`jaxsync.ProblemError`.
    """
    import jax.numpy as jnp

    from ..pytree import is_traced

    m = problem.material
    unit = unit_bound(problem, tol, max_iter, seed)
    if is_traced(m.E, m.rho):
        return unit * jnp.sqrt(m.rho / m.E)
    return unit * float(np.sqrt(float(m.rho) / float(m.E)))


def hyperelastic_step(rule: float, exact: float, alpha_s: float = ALPHA_S, *, element: str,
                      law: str) -> StableStep:
    """The default step of a hyperelastic law from its bounds at rest [s]: ``rule`` the
    element eigenvalue rule's (alpha_s = 1), ``exact`` 2 / omega_max: ``alpha_s * min(rule,
    exact)`` (module docstring; :func:`jaxsync.fem.forces.default_step`)."""
    if rule <= exact:
        return StableStep(dt=alpha_s * rule, rule="element", cfl=alpha_s * rule, exact=exact, alpha_s=alpha_s,
                          element=element, law=law)
    return StableStep(dt=alpha_s * exact, rule="exact", cfl=alpha_s * rule, exact=exact, alpha_s=alpha_s,
                      element=element, law=law)


def stable_step(problem, alpha_s: float = ALPHA_S) -> StableStep:
    """The default time step of ``problem`` and its rule, as its material law sets it
    (:meth:`jaxsync.fem.materials.MaterialLaw.stable_step`): the linear law's
    :func:`small_strain_step`; a hyperelastic law's ``alpha_s * min(element rule, exact
    bound)`` of its tangent at the initial displacement, P1 and P2 (module docstring; a
    concrete law only). With stiffness-proportional damping beta (``problem.stiffness_damping``)
    the exact bound is the law's passed through :func:`damped_bound` and the step the law's
    where that is at most alpha_s times it, else alpha_s times it (rule ``"exact"``; when E
    or rho is traced the smaller of the two, the rule left as the law's)."""
    step = problem.material.stable_step(problem, alpha_s)
    if not problem.stiffness_damped:
        return step
    beta = problem.stiffness_damping
    exact = damped_bound(step.exact, beta)
    limit = step.alpha_s * exact
    if concrete_or_none(step.dt) is None or concrete_or_none(limit) is None:  # traced: the rule is not decided
        import jax.numpy as jnp

        return dataclasses.replace(step, dt=jnp.minimum(step.dt, limit), exact=exact, stiffness_damping=beta)
    if float(step.dt) <= float(limit):
        return dataclasses.replace(step, exact=exact, stiffness_damping=beta)
    return dataclasses.replace(step, dt=limit, rule="exact", exact=exact, stiffness_damping=beta)


def damped_bound(bound, stiffness_damping):
    """The stable step [s] of the central-difference scheme with stiffness-proportional
    damping beta = ``stiffness_damping`` [s] (its force from the backward velocity), given
    the undamped bound ``bound`` = 2 / omega [s] of the fastest mode:
    ``(2 / omega) (sqrt(1 + xi^2) - xi)`` with xi = beta omega / 2, i.e.
    ``sqrt(bound^2 + beta^2) - beta`` (module docstring), computed as
    ``bound^2 / (sqrt(bound^2 + beta^2) + beta)`` (no cancellation when beta >> bound).
    Increasing in ``bound``, equal to it at beta = 0. Python floats in, a float out;
    JAX tracers in, a tracer out (differentiable)."""
    if concrete_or_none(stiffness_damping) == 0.0:
        return bound
    if concrete_or_none(bound) is not None and concrete_or_none(stiffness_damping) is not None:
        b, beta = float(bound), float(stiffness_damping)
        return b * b / (float(np.hypot(b, beta)) + beta)
    import jax.numpy as jnp

    return bound * bound / (jnp.sqrt(bound * bound + stiffness_damping * stiffness_damping) + stiffness_damping)


def small_strain_step(problem, alpha_s: float = ALPHA_S) -> StableStep:
    """The linear law's default time step ``min(paper CFL step, alpha_s * 2 / omega_max)``
    and its rule (quadratic elements: ``alpha_s * 2 / omega_max``, the paper's rule being
    for P1).

    Both steps scale as sqrt(rho / E), so which of them is smaller depends only on nu, the
    mesh, the density scaling and the Dirichlet set: the rule is decided without the
    values of E and rho, and ``dt`` is traced when they are."""
    cfl = cfl_dt(problem, alpha_s)
    exact = small_strain_max_stable_dt(problem)
    if problem.element != "P1":  # the paper's rule is for linear tetrahedra
        return StableStep(dt=alpha_s * exact, rule="exact", cfl=cfl, exact=exact, alpha_s=alpha_s,
                          element=problem.element)
    m = problem.material
    # the same comparison at E = rho = 1: valid for traced E and rho alike
    h = element_size(problem.mesh.points, problem.mesh.tets)
    scale = 1.0 if problem.density_scale is None else np.asarray(problem.density_scale, dtype=float)
    cfl_unit = float(np.min(alpha_s * h * np.sqrt(scale * (1.0 - float(m.nu) ** 2))))
    if cfl_unit <= alpha_s * unit_bound(problem, 1e-10, 20000, 0):
        return StableStep(dt=cfl, rule="cfl", cfl=cfl, exact=exact, alpha_s=alpha_s)
    return StableStep(dt=alpha_s * exact, rule="exact", cfl=cfl, exact=exact, alpha_s=alpha_s)


def check_dt(problem, dt: float) -> None:
    """Raise :class:`StabilityError` when ``dt`` exceeds the exact bound 2/omega_max (a
    hyperelastic law: that of its tangent at rest, :func:`stable_step`)."""
    dt = float(dt)
    if not dt > 0 or not np.isfinite(dt):
        raise StabilityError(f"time step must be positive and finite, got dt={dt}")
    step = stable_step(problem)
    if dt <= step.dt:
        return
    if dt > step.exact:
        of = "" if step.law is None else f" (the {step.law} tangent stiffness at rest)"
        raise StabilityError(
            f"dt={dt:.4e} s is above the stability bound {_bound_name(step)}={step.exact:.4e} s of the "
            f"central difference scheme{of}: use dt <= {step.alpha_s * step.exact:.4e} s (the "
            f"default step is {step.dt:.4e} s), or jaxsync.mass_scaling to raise the stable step")


def _bound_name(step: StableStep) -> str:
    """How messages name ``step.exact``: 2/omega_max, or its damped form."""
    if concrete_or_none(step.stiffness_damping) == 0.0:
        return "2/omega_max"
    return "sqrt((2/omega_max)^2 + beta^2) - beta (stiffness-proportional damping beta)"


def divergence_advice(problem, dt: float) -> str:
    """What to do about a run that diverged at step ``dt`` [s]: the step that would work
    when ``dt`` is above the exact bound, else the other likely causes."""
    try:
        step = stable_step(problem)
    except (ProblemError, StabilityError):
        return f"dt={float(dt):.4e} s; reduce dt"
    dt = float(dt)
    if dt > step.exact:
        return (f"dt={dt:.4e} s is above the stability bound {_bound_name(step)}={step.exact:.4e} s: "
                f"rerun with dt <= {step.alpha_s * step.exact:.4e} s (or leave dt unset: the "
                f"default step is {step.dt:.4e} s)")
    if step.law is not None:
        return (f"dt={dt:.4e} s is within the stability bound 2/omega_max={step.exact:.4e} s of the {step.law} "
                "tangent at rest, but a deformed state has its own, often smaller, bound and an element "
                "can invert: rerun with a smaller dt or smaller loads, and check that every part of the "
                "mesh is supported")
    return (f"dt={dt:.4e} s is within the stability bound 2/omega_max={step.exact:.4e} s, so "
            "the step is not the cause: check the loads' magnitudes, that every part of the "
            "mesh is supported (an unsupported piece moves as a rigid body), and blowup_factor")


def mass_scaling(problem, beta: float | None = None, *, dt_target: float | None = None,
                 alpha_s: float = ALPHA_S,
                 warn_above_percent: float | None = MASS_SCALING_WARN_PERCENT):
    """Artificial mass scaling (paper Algorithm 2).

    Every element whose own step (its law's
    :meth:`~jaxsync.fem.materials.MaterialLaw.element_steps`, times alpha_s) is below
    the target ``dt_hat = beta * problem.dt`` (or ``dt_target``) is made heavier, which
    raises its step to exactly dt_hat (the law's
    :meth:`~jaxsync.fem.materials.MaterialLaw.scaled_density`): for the linear law,
    whose element step is the paper's CFL step, density
    ``E dt_hat^2 / (alpha_s^2 h_e^2 (1 - nu^2))``. The scaled problem's ``dt`` (the default step of
    :func:`jaxsync.simulate`, :func:`stable_step`) is then dt_hat, or the unscaled CFL step
    when that is larger, unless alpha_s times the scaled problem's exact bound is smaller
    (nearly incompressible materials): then that.

    A hyperelastic law (P1 or P2): an element's own step is alpha_s 2 / omega_e, omega_e^2
    the largest eigenvalue of its tangent stiffness at the initial displacement over its
    lumped mass (the element rule of :func:`jaxsync.fem.forces.stable_dt`, fibres
    included), and an element below dt_hat gets its density times (dt_hat / its step)^2,
    which raises its step to exactly dt_hat; the scaled problem's ``dt`` is then dt_hat
    unless alpha_s times its exact bound is smaller.

    Added mass slows the dynamics of the scaled elements, so a large increase changes the
    result: a :class:`MassScalingWarning` (with the percentage and dt_hat) is issued when
    the total mass grows by more than ``warn_above_percent`` percent (default 10; None
    never warns).

    Returns:
        (scaled_problem, mass_increase_percent): the problem with ``density_scale`` set,
        and R_m = 100 (M_scaled - M) / M for the total mass.
    """
    if (beta is None) == (dt_target is None):
        raise StabilityError("give exactly one of beta (dt_hat = beta * dt) or dt_target")
    dt_hat = float(dt_target) if dt_target is not None else float(beta) * problem.dt
    if not dt_hat > 0 or not np.isfinite(dt_hat):
        raise StabilityError(f"target time step must be positive and finite, got {dt_hat}"
                             + (f" (beta={beta})" if beta is not None else ""))
    if warn_above_percent is not None and not float(warn_above_percent) >= 0:
        raise StabilityError(f"warn_above_percent must be >= 0 (or None), got {warn_above_percent}")
    scale, small = problem.material.scaled_density(problem, dt_hat, alpha_s)  # by the law's own element rule
    rho = float(problem.material.rho)
    volumes = problem.operators.volumes
    old_mass = rho * np.sum(volumes * (1.0 if problem.density_scale is None
                                       else np.asarray(problem.density_scale, dtype=float)))
    new_mass = rho * np.sum(volumes * scale)
    percent = 100.0 * (new_mass - old_mass) / old_mass
    if warn_above_percent is not None and percent > float(warn_above_percent):
        warnings.warn(
            f"mass scaling to dt_hat={dt_hat:.4e} s (CFL step {float(problem.dt):.4e} s) added "
            f"{percent:.1f} % to the total mass ({int(small.sum())} of {len(small)} elements "
            f"made heavier), more than {float(warn_above_percent):g} %: the scaled elements "
            "respond slower and the result can differ noticeably; choose a smaller target, "
            "refine or repair the smallest elements, or raise warn_above_percent",
            MassScalingWarning, stacklevel=2)
    return problem.replace(density_scale=scale), percent

