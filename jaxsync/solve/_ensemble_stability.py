"""The stable time step of every member of an ensemble
(:mod:`jaxsync.solve`): the bound used per member (:func:`member_bounds`),
the default step (:func:`default_dt`) and the check that names the first member above its
bound (:func:`check_members_dt`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..errors import ProblemError, StabilityError
from ..pytree import is_traced
from ._ensemble_members import EnsembleSetup

__all__ = ["member_bounds", "default_dt", "check_members_dt"]


def _basis_eigenvalues(problem) -> tuple[float, float, float]:
    """(a, b, s): the largest eigenvalues of M_1^-1 K_lambda, M_1^-1 K_mu and M_1^-1 S on the
    free dofs (M_1 the lumped mass of unit density, density scaling included; S the
    supports' springs, 0 without), computed once per key on the problem's operators."""
    fixed, _ = problem.dirichlet_dofs()
    scale = problem.density_scale
    key = (fixed.tobytes(), None if scale is None else np.asarray(scale, dtype=float).tobytes(),
           tuple((s.surface, float(s.stiffness), s.normal_only) for s in problem.supports))
    return problem.operators.stability_bound("ensemble basis eigenvalues", key,
                                             lambda: _largest_basis_eigenvalues(problem, fixed))


def _largest_basis_eigenvalues(problem, fixed) -> tuple[float, float, float]:
    """:func:`_basis_eigenvalues`, computed."""
    from ..fem._assembly import lumped_mass
    from ..fem._timestep import DENSE_EIGEN_DOFS
    from ..fem.forces._support import spring_matrix

    scale = problem.density_scale
    mass = np.repeat(np.asarray(lumped_mass(problem.space, scale), dtype=float), 3)
    free = np.setdiff1d(np.arange(problem.n_dofs), fixed)
    if len(free) == 0:
        raise StabilityError("every dof is prescribed: there is no free motion to bound")
    w = 1.0 / np.sqrt(mass[free])
    springs = spring_matrix(problem)
    out = []
    for K in (problem.operators.K_lambda, problem.operators.K_mu, springs):
        if K is None:
            out.append(0.0)
            continue
        A = K.tocsr()[free][:, free].multiply(w[:, None]).multiply(w[None, :]).tocsr()
        if len(free) <= DENSE_EIGEN_DOFS:
            import scipy.linalg

            out.append(float(scipy.linalg.eigvalsh(A.toarray())[-1]))
        else:
            import scipy.sparse.linalg as sla

            v0 = np.random.default_rng(0).standard_normal(len(free))
            # a slightly loose Lanczos value, raised by its tolerance: still an upper bound
            value = float(sla.eigsh(A, k=1, which="LA", tol=1e-8, maxiter=20000, v0=v0,
                                    return_eigenvectors=False)[0])
            out.append(value * (1.0 + 1e-7))
    return tuple(out)


def member_bounds(setup: EnsembleSetup) -> tuple[np.ndarray, bool]:
    """((n_runs,) a lower bound on each member's exact stable step [s], whether it is the
    exact bound itself) for the linear law (concrete values).

    The members' K = lambda K_lambda + mu K_mu (+ the supports' springs S) and M = rho M_1.
    Where nu is shared and there are no springs the bound is exact: 2 / omega_max of one
    eigenvalue at E = rho = 1 (:func:`jaxsync.fem.max_stable_dt`'s), scaled by
    sqrt(rho / E). Otherwise omega_max^2 = lambda_max(M^-1 K) <= (max(lambda, 0) a + mu b
    + s) / rho, a, b and s the largest eigenvalues of M_1^-1 K_lambda, M_1^-1 K_mu and
    M_1^-1 S (positive semidefinite: the largest eigenvalue of a sum is at most the sum of
    theirs), three eigenvalues for all members: a lower bound on each exact bound. Either
    passes through :func:`jaxsync.fem.damped_bound` with the member's beta."""
    from ..fem._timestep import unit_bound
    from ..fem.forces._support import spring_ratios
    from ..fem.materials._linear_elastic import first_lame, shear_modulus

    base, values = setup.base, setup.law_values()
    E, nu, rho = (np.asarray(values[k], dtype=float) for k in ("E", "nu", "rho"))
    beta = (np.asarray(setup.stiffness_damping, dtype=float) if setup.stiffness_damping is not None
            else np.full(setup.n_runs, float(base.stiffness_damping)))
    shared_nu = np.all(nu == nu[0])
    if shared_nu and not spring_ratios(base):
        unit_problem = base if float(base.material.nu) == nu[0] else base.replace(
            material=dataclasses.replace(base.material, nu=float(nu[0])))
        undamped = unit_bound(unit_problem, 1e-10, 20000, 0) * np.sqrt(rho / E)
        exact = True
    else:
        a, b, s = _basis_eigenvalues(base)
        omega2 = (np.maximum(first_lame(E, nu), 0.0) * a + shear_modulus(E, nu) * b + s) / rho
        undamped = 2.0 / np.sqrt(omega2)
        exact = False
    return undamped * undamped / (np.hypot(undamped, beta) + beta), exact


def _distinct_members(setup: EnsembleSetup) -> list[int]:
    """One run of each distinct (law parameters, alpha, beta, initial displacement)."""
    if not setup.varies:
        return [0]
    columns = [np.asarray(v, dtype=float).reshape(setup.n_runs, -1) for v in
               (*setup.law.values(), setup.damping, setup.stiffness_damping, setup.initial_displacement)
               if v is not None]
    _, first = np.unique(np.concatenate(columns, axis=1), axis=0, return_index=True)
    return sorted(int(r) for r in first)


def default_dt(setup: EnsembleSetup):
    """The ensemble's default step [s]: the smallest member's default step.

    Runs that share the base's material and damping: the base's ``dt``. The linear law:
    each member's min(paper CFL step, alpha_s times its bound), P2 alpha_s times its bound,
    the bound that of :func:`member_bounds` (exact when nu is shared and no springs, else
    the lower bound there: then a little below each member's own default). A hyperelastic
    law: the smallest default step of the distinct members (one eigenvalue problem each).

    Raises:
        ProblemError: traced member parameters (pass dt=)."""
    from ..fem._timestep import ALPHA_S, element_size

    base = setup.base
    if not setup.varies:
        return base.dt
    if is_traced(setup.law, setup.damping, setup.stiffness_damping):
        raise ProblemError("the default step of an ensemble whose members differ in material or damping comes from "
                           "their stability bounds, computed on the host, so it cannot follow traced member "
                           "parameters: pass dt= explicitly (for instance the default step of the ensemble at "
                           "concrete values)")
    if base.material.finite_strain:
        return min(float(setup.member(r).dt) for r in _distinct_members(setup))
    bounds, _ = member_bounds(setup)
    steps = ALPHA_S * bounds
    if base.element == "P1":
        values = setup.law_values()
        E, nu, rho = (np.asarray(values[k], dtype=float) for k in ("E", "nu", "rho"))
        scale = 1.0 if base.density_scale is None else np.asarray(base.density_scale, dtype=float)
        h = float(np.min(element_size(base.mesh.points, base.mesh.tets) * np.sqrt(scale)))
        steps = np.minimum(steps, ALPHA_S * h * np.sqrt(rho * (1.0 - nu ** 2) / E))
    return float(np.min(steps))


def check_members_dt(setup: EnsembleSetup, dt: float) -> None:
    """Raise :class:`jaxsync.StabilityError` naming the first member whose exact stability
    bound ``dt`` exceeds. The linear law: every member against :func:`member_bounds`' bound
    (vectorised), and a member above a lower bound against its own exact bound
    (:func:`jaxsync.fem.check_dt`, one eigenvalue per distinct nu); a hyperelastic
    law: each distinct member's exact bound of its tangent at rest."""
    from ..fem._timestep import check_dt

    if not setup.varies:
        check_dt(setup.base, dt)
        return
    dt = float(dt)
    if not dt > 0 or not np.isfinite(dt):
        raise StabilityError(f"time step must be positive and finite, got dt={dt}")
    if setup.base.material.finite_strain:
        suspects = _distinct_members(setup)
    else:
        bounds, exact = member_bounds(setup)
        suspects = [int(r) for r in np.flatnonzero(dt > bounds)]
        if exact and suspects:
            r = suspects[0]
            raise StabilityError(
                f"member {r} of the ensemble ({_describe(setup, r)}): dt={dt:.4e} s is above its stability bound "
                f"{bounds[r]:.4e} s{_also(suspects)}: use dt <= {0.9 * bounds.min():.4e} s (or leave dt unset: "
                f"the default step is the smallest member's, {default_dt(setup):.4e} s)")
    for r in suspects:
        try:
            check_dt(setup.member(r), dt)
        except StabilityError as error:
            raise StabilityError(f"member {r} of the ensemble ({_describe(setup, r)}): {error} (or leave dt unset: "
                                 "the default step is the smallest member's)") from None


def _also(runs) -> str:
    """The other members above the bound, in words."""
    if len(runs) < 2:
        return ""
    return f" (also members {runs[1:6]}{'...' if len(runs) > 6 else ''})"


def _describe(setup: EnsembleSetup, run: int) -> str:
    """The member's own parameters, in words."""
    parts = [f"{k}={float(v[run]):g}" for k, v in setup.law.items()]
    for name, label in (("damping", "alpha"), ("stiffness_damping", "beta")):
        value = getattr(setup, name)
        if value is not None:
            parts.append(f"{label}={float(value[run]):g}")
    return ", ".join(parts) or "the base problem's material"
