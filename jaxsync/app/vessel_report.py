"""The vessel section of ``jaxsync report``: the pressure-diameter loop, distensibility,
compliance, hysteresis and peak wall stress and strain by region of a run
(:mod:`jaxsync.vessel_metrics`), as ``summary.json`` entries and figures.

:func:`vessel_section` computes it from the run's problem and trajectory; a problem
without a pressure load is not a vessel: the section is then ``{"skipped": true, "note":
...}`` and no figure is made. :func:`vessel_note` says why a report without the run's
problem (no ``--config``) has no section.
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np

__all__ = ["vessel_section", "write_vessel_section", "vessel_note", "problem_on_mesh", "LOOP_FIGURE",
           "STRESS_FIGURE"]

LOOP_FIGURE = "pressure_diameter.png"
STRESS_FIGURE = "wall_stress.png"


def problem_on_mesh(problem, mesh):
    """``problem`` on the trajectory's ``mesh`` (the same problem when the meshes agree;
    a run of another mesh file keeps its loads, which name facet sets)."""
    same = (problem.mesh.n_nodes == mesh.n_nodes and np.array_equal(problem.mesh.tets, mesh.tets)
            and np.allclose(problem.mesh.points, mesh.points))
    return problem if same else dataclasses.replace(problem, mesh=mesh)


def vessel_section(problem, trajectory, *, surface: str | None = None, regions=None) -> tuple[dict, dict]:
    """(the ``vessel`` entry of ``summary.json``, file name -> figure) of a run.

    The entry: ``surface`` (the lumen facet set), ``metrics``
    (:meth:`jaxsync.vessel_metrics.VesselMetrics.to_dict`: ``full_cycle``, ``t_start``,
    ``t_end``, ``p_min``, ``p_max`` [barye], ``d_min``, ``d_max`` [cm], ``v_min``, ``v_max``
    [cm^3], ``distensibility`` [1/barye] and ``distensibility_per_mmHg``,
    ``diameter_compliance`` [cm/barye], ``volume_compliance`` [cm^3/barye], ``hysteresis``
    [erg per cycle]), ``loop`` (the arrays ``times`` [s], ``pressure``, ``volume``,
    ``area``, ``diameter``, ``period`` and the first and last snapshot of ``cycle``), and
    ``peaks``: region -> ``n_elements``, ``von_mises``, ``max_principal_stress``
    [dyn/cm^2], ``max_principal_strain`` (Green-Lagrange) each with ``value``,
    ``element``, ``snapshot``, ``time`` and ``location`` (the element's centroid [cm]),
    and ``max_log_strain``. A problem without a pressure load gives ``{"skipped": true,
    "note": ...}`` and no figures.

    Args:
        problem: the :class:`jaxsync.Problem` that was run (loads, material).
        trajectory: its :class:`jaxsync.Trajectory`.
        surface: the lumen facet set (None: that of the first pressure load).
        regions: name -> element ids (None: :func:`jaxsync.vessel_metrics.facet_regions`).
    """
    from .. import vessel_metrics as vm
    from . import figures

    problem = problem_on_mesh(problem, trajectory.mesh)
    times = np.asarray(trajectory.times, float)
    displacement = np.asarray(trajectory.displacement, float)
    try:
        loop = vm.pressure_diameter_loop(problem, displacement, times, surface)
    except vm.NotAVessel as exc:
        return {"skipped": True, "note": f"no vessel section: {exc}"}, {}
    metrics = vm.vessel_metrics(loop)
    peaks = vm.region_peaks(vm.element_peaks(problem.material, trajectory.space, displacement), times,
                            problem.mesh, regions)
    entry = {"skipped": False, "surface": loop.surface, "material": type(problem.material).__name__,
             "metrics": metrics.to_dict(), "peaks": {name: r.to_dict() for name, r in peaks.items()},
             "loop": loop.to_dict()}
    return entry, {LOOP_FIGURE: figures.pressure_diameter_figure(loop, metrics),
                   STRESS_FIGURE: figures.wall_stress_figure(times, peaks)}


def write_vessel_section(problem, trajectory, out_dir, **kwargs) -> dict:
    """Write the figures of :func:`vessel_section` into ``out_dir``; return its entry."""
    from .figures import save_figure

    entry, made = vessel_section(problem, trajectory, **kwargs)
    if made:
        os.makedirs(out_dir, exist_ok=True)
    for name, fig in made.items():
        save_figure(fig, os.path.join(out_dir, name))
    return entry


def vessel_note(trajectory) -> dict:
    """The ``vessel`` entry of a report made without the run's problem: skipped, saying
    whether the trajectory's recorded loads (:attr:`jaxsync.Trajectory.load_inputs`) hold
    a pressure (then the run's TOML, ``--config``, gives what the section needs)."""
    kinds = {i.kind for i in trajectory.load_inputs}
    if "Pressure" in kinds:
        note = ("no vessel section: the run has a pressure load, but a trajectory does not hold its magnitude, "
                "surface or the material: give the run's TOML file with --config")
    elif kinds:
        note = ("no vessel section: the run has no pressure load (its loads: " + ", ".join(sorted(kinds)) +
                "), so it is not a vessel under a lumen pressure")
    else:
        note = "no vessel section: give the run's TOML file with --config (the loads and material of the run)"
    return {"skipped": True, "note": note}

