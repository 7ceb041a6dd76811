"""Paper figure 19's check of mass scaling: the same problem at its CFL step and mass-scaled
to a larger step, compared at the node that moves most."""

from __future__ import annotations

import numpy as np

__all__ = ["mass_scaling_check", "mass_scaling_figure"]


def mass_scaling_check(problem_cfl, problem_scaled, added_percent: float, seconds: float, *,
                       progress: bool = True) -> dict:
    """Paper figure 19's check: the same problem at its CFL step and mass-scaled to a
    larger one, single-device runs over ``seconds`` of physical time, compared at the
    node that moves most (the scaled run interpolated linearly to the CFL run's times).

    Returns a JSON-ready dict: ``dt_cfl``, ``dt_scaled`` [s], ``added_mass_percent``,
    ``node``, ``seconds``, ``max_abs_displacement`` (the node's largest |d| at the CFL
    step [cm]), ``max_abs_difference`` (largest |d_scaled - d_cfl| of the node's
    displacement vector [cm]), ``relative_difference`` (their ratio), and the curves
    ``times``, ``cfl``, ``scaled`` (the node's displacement norm [cm]) for the figure.
    """
    from .. import HostExecutor, simulate

    dt_cfl, dt_scaled = float(problem_cfl.dt), float(problem_scaled.dt)
    n_scaled = max(1, int(round(seconds / dt_scaled)))
    n_cfl = max(1, int(round(n_scaled * dt_scaled / dt_cfl)))
    samples = 200
    every_cfl, every_scaled = max(1, n_cfl // samples), max(1, n_scaled // samples)
    n_cfl, n_scaled = n_cfl - n_cfl % every_cfl, n_scaled - n_scaled % every_scaled
    cfl = simulate(problem_cfl, n_cfl, save=every_cfl, executor=HostExecutor(progress=progress))
    scaled = simulate(problem_scaled, n_scaled, save=every_scaled, executor=HostExecutor(progress=progress))
    d_cfl, d_scaled = np.asarray(cfl.displacement), np.asarray(scaled.displacement)
    node = int(np.argmax(np.linalg.norm(d_cfl, axis=2).max(axis=0)))
    t = np.asarray(cfl.times)
    keep = t <= float(np.asarray(scaled.times)[-1]) + 1e-12
    at = np.stack([np.interp(t[keep], scaled.times, d_scaled[:, node, k]) for k in range(3)], axis=1)
    diff = np.linalg.norm(at - d_cfl[keep, node], axis=1)
    amplitude = float(np.linalg.norm(d_cfl[:, node], axis=1).max())
    return {"dt_cfl": dt_cfl, "dt_scaled": dt_scaled, "added_mass_percent": float(added_percent), "node": node,
            "coordinates": [float(v) for v in problem_cfl.mesh.points[node]], "seconds": float(t[keep][-1]),
            "n_steps_cfl": int(n_cfl), "n_steps_scaled": int(n_scaled),
            "max_abs_displacement": amplitude, "max_abs_difference": float(diff.max()),
            "relative_difference": float(diff.max() / amplitude) if amplitude > 0 else None,
            "us_per_step_cfl": cfl.stats.us_per_step, "us_per_step_scaled": scaled.stats.us_per_step,
            "times": t[keep].tolist(), "cfl": np.linalg.norm(d_cfl[keep, node], axis=1).tolist(),
            "scaled": np.linalg.norm(at, axis=1).tolist()}


def mass_scaling_figure(check: dict):
    """Paper figure 19: the node's displacement at the CFL step and at the scaled step,
    and their difference, from :func:`mass_scaling_check`."""
    from .figures import new_figure

    fig = new_figure(8.0, 5.5)
    top, bottom = fig.subplots(2, 1, sharex=True, height_ratios=[2.5, 1.0])
    t = np.asarray(check["times"])
    top.plot(t, check["cfl"], color="0.6", lw=3.0, label=f"CFL step {check['dt_cfl']:.3e} s")
    top.plot(t, check["scaled"], color="C3", lw=1.2,
             label=f"mass-scaled step {check['dt_scaled']:.3e} s (+{check['added_mass_percent']:.2f} % mass)")
    bottom.plot(t, np.asarray(check["scaled"]) - np.asarray(check["cfl"]), color="C0", lw=1.0)
    x, y, z = check["coordinates"]
    top.set_title(f"Mass scaling: node {check['node']} at ({x:.3g}, {y:.3g}, {z:.3g}) cm, largest difference "
                  f"{100 * (check['relative_difference'] or 0.0):.2f} % of its amplitude", fontsize=9)
    top.set_ylabel("|d| [cm]")
    bottom.set_ylabel("difference [cm]")
    bottom.set_xlabel("time t [s]")
    for ax in (top, bottom):
        ax.grid(True, alpha=0.3)
    top.legend(fontsize=8)
    return fig
