"""Stable time step: the paper's CFL rule, the exact bound, and artificial mass scaling.

CFL rule of the paper's published code: ``dt = alpha_s * min_e h_e / c_e`` with
``h_e = 2 * (shortest edge of e) / sqrt(24)`` (the in-sphere diameter of a regular
tetrahedron with that edge), ``c_e = sqrt(E / (rho_e (1 - nu^2)))`` and alpha_s = 0.9.
The exact stability bound of the undamped central difference scheme with lumped mass is
``2 / omega_max``, omega_max^2 the largest eigenvalue of M^-1 K on the free dofs.
"""

from __future__ import annotations

import warnings

import numpy as np

from ..errors import StabilityError

__all__ = ["ALPHA_S", "MassScalingWarning", "element_size", "element_dt", "cfl_dt",
           "max_stable_dt", "mass_scaling"]

ALPHA_S = 0.9

MASS_SCALING_WARN_PERCENT = 10.0
"""Default threshold of :func:`mass_scaling`'s warning: added mass in percent."""


class MassScalingWarning(UserWarning):
    """Artificial mass scaling added more mass than the caller's threshold."""


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


def max_stable_dt(problem, *, tol: float = 1e-10, max_iter: int = 20000, seed: int = 0) -> float:
    """Exact stability bound 2 / omega_max [s] by power iteration on the symmetric form
    M^-1/2 K M^-1/2 restricted to the free dofs (lumped mass, concrete material only).

    The Rayleigh quotient is iterated until its relative change is below ``tol``.
    """
    m = problem.material
    K = problem.operators.stiffness(m.lam, m.mu)
    mass = np.repeat(np.asarray(problem.lumped_mass(), dtype=float), 3)
    fixed, _ = problem.dirichlet_dofs()
    free = np.setdiff1d(np.arange(K.shape[0]), fixed)
    Kf = K[free][:, free].tocsr()
    s = 1.0 / np.sqrt(mass[free])
    x = np.random.default_rng(seed).standard_normal(len(free))
    x /= np.linalg.norm(x)
    lam_old = 0.0
    for _ in range(max_iter):
        y = s * (Kf @ (s * x))
        lam = float(x @ y)
        x = y / np.linalg.norm(y)
        if abs(lam - lam_old) <= tol * abs(lam):
            break
        lam_old = lam
    return 2.0 / np.sqrt(lam)


def check_dt(problem, dt: float) -> None:
    """Raise :class:`StabilityError` when ``dt`` exceeds the exact bound 2/omega_max.

    The power iteration runs only when ``dt`` is above the (conservative) CFL step."""
    dt = float(dt)
    if not dt > 0 or not np.isfinite(dt):
        raise StabilityError(f"time step must be positive and finite, got dt={dt}")
    if dt <= problem.dt:
        return
    bound = max_stable_dt(problem)
    if dt > bound:
        raise StabilityError(
            f"dt={dt:.4e} s is above the stability bound 2/omega_max={bound:.4e} s of the "
            f"central difference scheme (CFL step {problem.dt:.4e} s): use a smaller dt, "
            "or jaxsync.mass_scaling to raise the stable step")


def mass_scaling(problem, beta: float | None = None, *, dt_target: float | None = None,
                 alpha_s: float = ALPHA_S,
                 warn_above_percent: float | None = MASS_SCALING_WARN_PERCENT):
    """Artificial mass scaling (paper Algorithm 2).

    Every element whose own CFL step is below the target ``dt_hat = beta * problem.dt``
    (or ``dt_target``) gets density ``E dt_hat^2 / (alpha_s^2 h_e^2 (1 - nu^2))``, which
    raises its step to exactly dt_hat. The scaled problem's ``dt`` (the default step of
    :func:`jaxsync.simulate`) is then dt_hat, or the unscaled CFL step when that is larger.

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
    m = problem.material
    E, nu, rho = float(m.E), float(m.nu), float(m.rho)
    h = element_size(problem.mesh.points, problem.mesh.tets)
    scale = (np.ones(problem.mesh.n_elements) if problem.density_scale is None
             else np.asarray(problem.density_scale, dtype=float).copy())
    dt_e = alpha_s * h / np.sqrt(E / (rho * scale * (1.0 - nu**2)))
    small = dt_e < dt_hat
    new_density = E * dt_hat**2 / (alpha_s**2 * h**2 * (1.0 - nu**2))
    scale[small] = new_density[small] / rho
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
