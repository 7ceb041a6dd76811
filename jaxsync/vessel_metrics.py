"""What a researcher reads from a vessel run: the pressure-diameter and pressure-volume
loops over a pulse, distensibility, compliance, the energy dissipated per cycle, and the
peak wall stress and strain by region, with where and when they occur.

Definitions (CGS units: barye, cm, s; 1 mmHg = :data:`MMHG` barye):

- **Lumen pressure** p(t): the sum of ``magnitude * time(t)`` of the problem's
  :class:`jaxsync.Pressure` loads on the lumen facet set (:func:`lumen_pressure`), at
  the time of each saved snapshot.
- **Lumen volume** V: the volume enclosed by the deformed lumen surface closed at each
  open end by a flat fan from the centroid of the end's boundary loop
  (:func:`enclosed_volume`; by the divergence theorem, V = |sum of the signed volumes of
  the tetrahedra (origin, triangle)|). Any number of open ends (branches) is closed the
  same way; a surface that is already closed needs no cap.
- **Mean lumen diameter** D = 4 V / A, A the deformed lumen (wall) area without the
  caps: the hydraulic diameter, equal to the diameter of a circular cylinder of any
  length, needing no centreline or length (:func:`lumen_geometry`). A uniform radial
  expansion by a factor s scales D by s and V by s^2. On a polygonal lumen of n sides
  it is twice the apothem, 2 r cos(pi/n).
- **Over a pulse**: the last full cycle, the snapshots in [t_end - T, t_end], T the
  period of the pressure's time function (its ``period``); without one (no periodic
  factor), the whole record. Distensibility (D_max - D_min) / (D_min (p_max - p_min))
  [1/barye], diameter compliance (D_max - D_min) / (p_max - p_min) [cm/barye], volume
  compliance (V_max - V_min) / (p_max - p_min) [cm^3/barye], and the hysteresis
  loop integral of p dV_w over the last full cycle [erg]: the work the lumen pressure
  does on the wall per cycle, the energy the wall dissipates per cycle in a periodic
  state (positive for a dissipative, clockwise loop in the (V, p) plane). V_w is the
  volume whose change is the pressure load's work per unit pressure: the enclosed
  volume V for a follower pressure (it acts on the deformed surface); for a dead
  pressure (on the reference surface) its first-order change V_0 + integral of u . n
  over the reference lumen, n into the lumen (:func:`linearized_volume`). The two
  differ by O(strain) relative, so a dead load's loop in V alone would not balance its
  work.
- **Stress**: the Cauchy stress at the quadrature points of the total-Lagrangian rule
  (:func:`jaxsync.fem.forces._total_lagrangian.reference_geometry`): for a finite-strain law
  sigma = P F^T / J with P the law's ``first_piola(F, fibres)``; for the linear law
  sigma = lambda tr(eps) I + 2 mu eps, eps the small strain (:func:`cauchy_stress`). A
  law with internal variables reports its ``first_piola`` (the instantaneous,
  elastic response; the viscous branches' history is not in a trajectory).
- **Strain**: the largest principal Green-Lagrange strain of E = (F^T F - I) / 2 and
  its logarithmic strain ln(lambda) = ln(1 + 2 E) / 2.
- **Regions**: the elements that have a face on each facet set of the mesh (e.g.
  ``lumen``, ``outer``, ``inlet``), and ``wall``, every element
  (:func:`facet_regions`); or any name -> element ids given.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .errors import ProblemError

__all__ = ["MMHG", "boundary_loops", "lumen_triangles", "enclosed_volume", "lumen_geometry", "lumen_pressure",
           "pulse_period", "last_cycle", "loop_work", "linearized_volume", "PressureDiameterLoop",
           "pressure_diameter_loop", "VesselMetrics", "vessel_metrics", "cauchy_stress", "element_peaks",
           "facet_regions", "Peak", "RegionPeaks", "region_peaks", "NotAVessel"]

MMHG = 1333.22387415
"""Barye per mmHg (the conventional millimetre of mercury, 133.322387415 Pa)."""


class NotAVessel(ProblemError):
    """The problem has no pressure load: there is no lumen pressure to read a loop from."""


def boundary_loops(triangles) -> list[np.ndarray]:
    """The open ends of a triangulated surface: its boundary edges (those of one triangle
    only), oriented as in their triangle, grouped by connected loop.

    Args:
        triangles: (n_f, 3) node ids, consistently oriented.

    Returns:
        One (n_e, 2) array of directed edges per boundary loop (empty for a closed surface).
    """
    tri = np.asarray(triangles, dtype=np.int64)
    edges = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    key = np.sort(edges, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = edges[counts[inverse.ravel()] == 1]
    if not len(boundary):
        return []
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    nodes, local = np.unique(boundary, return_inverse=True)
    local = local.reshape(-1, 2)
    graph = coo_matrix((np.ones(len(local)), (local[:, 0], local[:, 1])), shape=(len(nodes), len(nodes)))
    _, component = connected_components(graph, directed=False)
    label = component[local[:, 0]]
    return [boundary[label == k] for k in np.unique(label)]


def lumen_triangles(mesh, surface: str = "lumen") -> np.ndarray:
    """(n_f, 3) the vertex triples of the facet set ``surface`` of ``mesh``, each ordered so
    that its right-hand normal points out of the solid (into the lumen).

    Raises:
        MeshError or ProblemError: no such facet set (the message names the mesh's).
    """
    from .fem._space import function_space
    from .fem.forces._follower import facet_nodes

    return facet_nodes(function_space(mesh, "P1"), surface)[0]


def _signed_volume(x, tri) -> np.ndarray:
    """(..., ) sum over triangles of a . (b x c) / 6 for points x (..., n, 3)."""
    a, b, c = x[..., tri[:, 0], :], x[..., tri[:, 1], :], x[..., tri[:, 2], :]
    return np.einsum("...fi,...fi->...", a, np.cross(b, c)) / 6.0


def enclosed_volume(points, triangles, loops=None) -> np.ndarray:
    """The volume enclosed by a surface closed at its open ends (module docstring) [cm^3].

    Args:
        points: (n_nodes, 3) or (T, n_nodes, 3) node coordinates [cm].
        triangles: (n_f, 3) consistently oriented triangles (either way round).
        loops: :func:`boundary_loops` of ``triangles`` (computed when None).

    Returns:
        () or (T,) volumes.
    """
    return np.abs(_closed_signed_volume(points, triangles, loops))


def _closed_signed_volume(points, triangles, loops=None) -> np.ndarray:
    """The signed volume of :func:`enclosed_volume`: positive when the triangles' right-hand
    normals point out of the enclosed volume."""
    x = np.asarray(points, dtype=float)
    tri = np.asarray(triangles, dtype=np.int64)
    loops = boundary_loops(tri) if loops is None else loops
    total = _signed_volume(x, tri)
    for edges in loops:
        centre = x[..., np.unique(edges), :].mean(axis=-2)  # (..., 3)
        # the cap triangles (centre, b, a) run each boundary edge the other way: a closed, oriented surface
        a, b = x[..., edges[:, 0], :], x[..., edges[:, 1], :]
        total = total + np.einsum("...i,...fi->...", centre, np.cross(b, a)) / 6.0
    return total


def lumen_geometry(points, triangles, loops=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(volume [cm^3], wall area [cm^2], mean diameter D = 4 V / A [cm]) of a lumen surface
    (module docstring), each () or (T,) as ``points`` is (n, 3) or (T, n, 3)."""
    x = np.asarray(points, dtype=float)
    tri = np.asarray(triangles, dtype=np.int64)
    a, b, c = x[..., tri[:, 0], :], x[..., tri[:, 1], :], x[..., tri[:, 2], :]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=-1).sum(axis=-1)
    volume = enclosed_volume(x, tri, loops)
    return volume, area, 4.0 * volume / area


def linearized_volume(points, triangles, displacement) -> np.ndarray:
    """V_0 + integral over the reference surface of u . n dA, n the normal out of the
    enclosed volume (:func:`enclosed_volume`; exact for u linear on each flat triangle):
    the volume change to first order, the work of a unit dead pressure acting from the
    inside [cm^3]. ``points`` (n, 3) reference, ``displacement`` (n, 3) or (T, n, 3)."""
    X = np.asarray(points, dtype=float)
    tri = np.asarray(triangles, dtype=np.int64)
    a, b, c = X[tri[:, 0]], X[tri[:, 1]], X[tri[:, 2]]
    n_area = 0.5 * np.cross(b - a, c - a)  # (n_f, 3): normal times area
    u = np.asarray(displacement, dtype=float)
    mean_u = (u[..., tri[:, 0], :] + u[..., tri[:, 1], :] + u[..., tri[:, 2], :]) / 3.0
    signed = float(_closed_signed_volume(X, tri))  # its sign: whether the normals point out of the volume
    return abs(signed) + np.sign(signed) * np.einsum("fi,...fi->...", n_area, mean_u)


def _pressure_loads(problem) -> list:
    from .fem._loads import Pressure

    return [load for load in problem.loads if isinstance(load, Pressure)]


def lumen_pressure(problem, times, surface: str | None = None) -> tuple[str, np.ndarray]:
    """(the lumen facet set, p (T,) [barye]): the sum of magnitude * time(t) of the
    pressure loads on ``surface`` (None: the surface of the first pressure load).

    Raises:
        NotAVessel: the problem has no pressure load (on ``surface``).
    """
    loads = _pressure_loads(problem)
    if not loads:
        raise NotAVessel("the problem has no pressure load (jaxsync.Pressure / [[pressure]]): it is not a vessel "
                         "under a lumen pressure, so it has no pressure-diameter loop")
    surface = loads[0].surface if surface is None else surface
    on = [load for load in loads if load.surface == surface]
    if not on:
        raise NotAVessel(f"no pressure load acts on the facet set {surface!r}; the problem's pressures act on "
                         f"{sorted({load.surface for load in loads})}")
    t = np.asarray(times, dtype=float)
    p = sum(float(load.magnitude) * np.asarray(load.time(t), dtype=float) for load in on)
    return surface, np.broadcast_to(np.asarray(p, dtype=float), t.shape).copy()


def pulse_period(time_function) -> float | None:
    """The period [s] of a time function or of the first periodic factor in it (a
    ``period`` attribute, looked for through ``factors`` and ``inner``); None if none."""
    period = getattr(time_function, "period", None)
    if period is not None:
        return float(period)
    for inner in (*getattr(time_function, "factors", ()), getattr(time_function, "inner", None)):
        if inner is not None and (found := pulse_period(inner)) is not None:
            return found
    return None


def last_cycle(times, period: float | None) -> np.ndarray | None:
    """Indices of the snapshots of the last full cycle, t in [t_end - period, t_end]
    (a relative tolerance of 1e-9 of the period at the start); None when ``period`` is
    None or the record is shorter than a period."""
    t = np.asarray(times, dtype=float)
    if period is None or len(t) < 3:
        return None
    start = t[-1] - period
    if t[0] > start + 1e-9 * period:
        return None
    return np.flatnonzero(t >= start - 1e-9 * period)


def loop_work(pressure, volume) -> float:
    """The loop integral of p dV [erg] over the closed polygon of the samples (p_k, V_k)
    (trapezoids, the last sample joined to the first): positive for a clockwise loop in
    the (V, p) plane (loading at higher pressure than unloading: energy dissipated)."""
    p, v = np.asarray(pressure, float), np.asarray(volume, float)
    if p.shape != v.shape or p.ndim != 1:
        raise ProblemError(f"loop_work needs two (T,) arrays of equal length, got {p.shape} and {v.shape}")
    p_next, v_next = np.roll(p, -1), np.roll(v, -1)
    return float(np.sum(0.5 * (p + p_next) * (v_next - v)))


@dataclasses.dataclass(frozen=True)
class PressureDiameterLoop:
    """The lumen's pressure, volume and diameter at every snapshot of a run.

    Attributes:
        surface: the lumen facet set.
        times: (T,) [s]; pressure: (T,) [barye]; volume: (T,) [cm^3]; area: (T,) lumen
            wall area [cm^2]; diameter: (T,) D = 4 V / A [cm].
        period: of the pressure's time function [s], or None.
        cycle: indices of the last full cycle's snapshots (:func:`last_cycle`), or None.
    """

    surface: str
    times: np.ndarray
    pressure: np.ndarray
    volume: np.ndarray
    area: np.ndarray
    diameter: np.ndarray
    work_volume: np.ndarray
    period: float | None
    cycle: np.ndarray | None

    def to_dict(self) -> dict:
        return {"surface": self.surface, "period": self.period,
                "cycle": None if self.cycle is None else [int(self.cycle[0]), int(self.cycle[-1])],
                **{k: np.asarray(getattr(self, k)).tolist() for k in ("times", "pressure", "volume", "area",
                                                                       "diameter", "work_volume")}}


def _snapshots(space, displacement) -> np.ndarray:
    d = np.asarray(displacement, dtype=float)
    if d.ndim == 2:
        d = d[None]
    if d.ndim != 3 or d.shape[1:] != (space.n_nodes, 3):
        raise ProblemError(f"displacement of shape {np.shape(displacement)} does not fit the space's "
                           f"{space.n_nodes} nodes: give (T, {space.n_nodes}, 3) or ({space.n_nodes}, 3)")
    return d


def pressure_diameter_loop(problem, displacement, times, surface: str | None = None) -> PressureDiameterLoop:
    """The :class:`PressureDiameterLoop` of a run of ``problem``.

    Args:
        problem: the :class:`jaxsync.Problem` that was run (its pressure loads and mesh).
        displacement: (T, n_nodes, 3) [cm] on the mesh's vertices first (P1 or P2
            nodes; the lumen surface is taken flat between its vertices).
        times: (T,) [s] of the snapshots.
        surface: the lumen facet set (None: that of the first pressure load).

    Raises:
        NotAVessel: no pressure load; ProblemError: shapes that do not fit.
    """
    surface, p = lumen_pressure(problem, times, surface)
    n = problem.mesh.n_nodes
    d = np.asarray(displacement, dtype=float)
    if d.ndim != 3 or d.shape[0] != len(p) or d.shape[1] < n or d.shape[2] != 3:
        raise ProblemError(f"displacement of shape {d.shape} does not fit {len(p)} snapshots of a mesh of {n} "
                           "vertices")
    triangles = lumen_triangles(problem.mesh, surface)
    x = problem.mesh.points[None] + d[:, :n]
    volume, area, diameter = lumen_geometry(x, triangles)
    on = [load for load in _pressure_loads(problem) if load.surface == surface]
    periods = [found for load in on if (found := pulse_period(load.time)) is not None]
    period = periods[0] if periods else None
    # the pressure's work: p dV on the deformed surface (follower), p dV_lin on the reference one (dead)
    work_volume = volume if all(load.follower for load in on) else linearized_volume(
        problem.mesh.points, triangles, d[:, :n])
    return PressureDiameterLoop(surface=surface, times=np.asarray(times, float), pressure=p, volume=volume,
                                area=area, diameter=diameter, work_volume=work_volume,
                                period=period,
                                cycle=last_cycle(times, period))


@dataclasses.dataclass(frozen=True)
class VesselMetrics:
    """Distensibility, compliance and hysteresis over the last full cycle (module docstring).

    Attributes:
        full_cycle: True when measured over the last full cycle, False over the whole
            record (no period, or a record shorter than one).
        t_start, t_end: the measured interval [s].
        p_min, p_max [barye]; d_min, d_max [cm]; v_min, v_max [cm^3].
        distensibility: [1/barye]; diameter_compliance: [cm/barye];
        volume_compliance: [cm^3/barye] (None where p_max = p_min).
        hysteresis: the loop integral of p dV_w over the last full cycle [erg] (None
            without a full cycle; V_w the :attr:`PressureDiameterLoop.work_volume`).
    """

    full_cycle: bool
    t_start: float
    t_end: float
    p_min: float
    p_max: float
    d_min: float
    d_max: float
    v_min: float
    v_max: float
    distensibility: float | None
    diameter_compliance: float | None
    volume_compliance: float | None
    hysteresis: float | None

    def to_dict(self) -> dict:
        out = dataclasses.asdict(self)
        if self.distensibility is not None:
            out["distensibility_per_mmHg"] = self.distensibility * MMHG
        return out

    def summary(self) -> str:
        if self.distensibility is None:
            return f"lumen pressure constant at {self.p_max / MMHG:.4g} mmHg: no distensibility"
        hysteresis = "n/a (no full cycle)" if self.hysteresis is None else f"{self.hysteresis:.4g} erg/cycle"
        return (f"{'last cycle' if self.full_cycle else 'whole record'}: p {self.p_min / MMHG:.4g}-"
                f"{self.p_max / MMHG:.4g} mmHg, D {10 * self.d_min:.4g}-{10 * self.d_max:.4g} mm; distensibility "
                f"{100 * self.distensibility * MMHG:.4g} %/mmHg, compliance {1e3 * self.volume_compliance * MMHG:.4g} "
                f"uL/mmHg, hysteresis {hysteresis}")


def vessel_metrics(loop: PressureDiameterLoop) -> VesselMetrics:
    """The :class:`VesselMetrics` of a loop over its last full cycle (else the whole record)."""
    at = np.arange(len(loop.times)) if loop.cycle is None else loop.cycle
    p, d, v = loop.pressure[at], loop.diameter[at], loop.volume[at]
    dp = float(p.max() - p.min())
    ratio = (lambda x: float(x.max() - x.min()) / dp) if dp > 0 else (lambda x: None)
    dist = ratio(d)
    return VesselMetrics(
        full_cycle=loop.cycle is not None, t_start=float(loop.times[at[0]]), t_end=float(loop.times[at[-1]]),
        p_min=float(p.min()), p_max=float(p.max()), d_min=float(d.min()), d_max=float(d.max()),
        v_min=float(v.min()), v_max=float(v.max()),
        distensibility=None if dist is None else dist / float(d.min()), diameter_compliance=dist,
        volume_compliance=ratio(v),
        hysteresis=None if loop.cycle is None else loop_work(p, np.asarray(loop.work_volume)[at]))


def _gradients(space):
    from .fem.forces._total_lagrangian import reference_geometry

    return reference_geometry(space)[0]  # (m, q, k, 3)


def cauchy_stress(material, space, displacement, fibres=None) -> np.ndarray:
    """The Cauchy stress at the quadrature points (module docstring) [dyn/cm^2].

    Args:
        material: the problem's law: one with ``first_piola(F, fibres)`` (finite strain),
            or the linear law (``lam``, ``mu``).
        space: a :class:`jaxsync.fem.FunctionSpace` (``Trajectory.space``) or a
            :class:`jaxsync.Mesh` (its P1 space).
        displacement: (T, n_nodes, 3) or (n_nodes, 3) [cm].
        fibres: (n_elements, 2, 3) fibre directions of an anisotropic law (default: the
            law's own ``fibres``, if any).

    Returns:
        (T, n_elements, n_q, 3, 3).
    """
    from .fem._space import function_space

    space = space if hasattr(space, "cells") else function_space(space, "P1")
    d = _snapshots(space, displacement)
    return _stress(material, _displacement_gradients(d, space, _gradients(space)), fibres)


def _displacement_gradients(d, space, gradients) -> np.ndarray:
    """grad_X u (t, m, q, 3, 3) of the displacements d (t, n_nodes, 3) at the quadrature points."""
    return np.einsum("tmka,mqkj->tmqaj", d[:, np.asarray(space.cells)], gradients)


def _stress(material, H, fibres=None) -> np.ndarray:
    """Cauchy stress (..., 3, 3) of the displacement gradients H (t, m, q, 3, 3)."""
    eye = np.eye(3)
    if not hasattr(material, "first_piola"):  # the small-strain law: sigma = C eps
        eps = 0.5 * (H + np.swapaxes(H, -1, -2))
        trace = np.trace(eps, axis1=-2, axis2=-1)[..., None, None]
        return float(material.lam) * trace * eye + 2.0 * float(material.mu) * eps
    F = eye + H
    fibres = getattr(material, "fibres", None) if fibres is None else fibres
    law = dataclasses.replace(material, fibres=None) if getattr(material, "fibres", None) is not None else material
    if fibres is not None and np.shape(fibres) != (H.shape[1], 2, 3):
        raise ProblemError(f"fibres of shape {np.shape(fibres)} do not fit the {H.shape[1]} elements: give "
                           f"({H.shape[1]}, 2, 3), two unit directions per element")
    a = None if fibres is None else np.asarray(fibres, float)[None, :, None]  # (1, m, 1, 2, 3)
    P = np.asarray(law.first_piola(F, a))
    return np.einsum("...ij,...kj->...ik", P, F) / np.linalg.det(F)[..., None, None]


def element_peaks(material, space, displacement, *, fibres=None, chunk_bytes: int = 2 ** 27):
    """Per snapshot and element, the largest over the element's quadrature points of the
    von Mises stress, the largest principal Cauchy stress [dyn/cm^2] and the largest
    principal Green-Lagrange strain [-].

    Args:
        material, space, displacement, fibres: as :func:`cauchy_stress`.
        chunk_bytes: working memory per block of snapshots (formed a block at a time).

    Returns:
        (von_mises, max_principal_stress, max_principal_strain), each (T, n_elements).
    """
    from .fem._space import function_space

    space = space if hasattr(space, "cells") else function_space(space, "P1")
    d = _snapshots(space, displacement)
    grads = _gradients(space)
    m, q = grads.shape[:2]
    block = max(1, int(chunk_bytes // max(1, m * q * 9 * 8 * 8)))
    out = [np.empty((len(d), m)) for _ in range(3)]
    for start in range(0, len(d), block):
        H = _displacement_gradients(d[start:start + block], space, grads)
        sigma = _stress(material, H, fibres)
        dev = sigma - np.trace(sigma, axis1=-2, axis2=-1)[..., None, None] * np.eye(3) / 3.0
        mises = np.sqrt(1.5 * np.sum(dev * dev, axis=(-2, -1)))
        E = 0.5 * (H + np.swapaxes(H, -1, -2) + np.einsum("...ka,...kb->...ab", H, H))
        rows = slice(start, start + len(H))
        out[0][rows] = mises.max(axis=2)
        out[1][rows] = np.linalg.eigvalsh(0.5 * (sigma + np.swapaxes(sigma, -1, -2)))[..., -1].max(axis=2)
        out[2][rows] = np.linalg.eigvalsh(E)[..., -1].max(axis=2)
    return tuple(out)


def facet_regions(mesh) -> dict[str, np.ndarray]:
    """``{"wall": every element}`` and, per facet set of ``mesh``, the elements with a
    face on it (name -> sorted element ids)."""
    from .fem._space import function_space
    from .fem.forces._follower import facet_nodes

    space = function_space(mesh, "P1")
    regions = {"wall": np.arange(mesh.n_elements)}
    for name in mesh.facet_sets:
        if len(mesh.facet_sets[name]):
            regions[name] = np.unique(facet_nodes(space, name)[1])
    return regions


@dataclasses.dataclass(frozen=True)
class Peak:
    """The largest value of a field over a region and the run: ``value``, the ``element``
    and ``snapshot`` (index) where and ``time`` [s] when it occurs, ``location`` the
    element's reference centroid [cm]."""

    value: float
    element: int
    snapshot: int
    time: float
    location: tuple

    def to_dict(self) -> dict:
        return dataclasses.asdict(self) | {"location": list(self.location)}


@dataclasses.dataclass(frozen=True)
class RegionPeaks:
    """The peaks of one region (:func:`region_peaks`): ``von_mises`` and
    ``max_principal_stress`` [dyn/cm^2], ``max_principal_strain`` (Green-Lagrange [-]) and
    its logarithmic strain ``max_log_strain``; ``n_elements``; ``history``: (T,) the
    region's largest von Mises stress at each snapshot [dyn/cm^2]."""

    region: str
    n_elements: int
    von_mises: Peak
    max_principal_stress: Peak
    max_principal_strain: Peak
    max_log_strain: float
    history: np.ndarray

    def to_dict(self) -> dict:
        return {"n_elements": self.n_elements, "von_mises": self.von_mises.to_dict(),
                "max_principal_stress": self.max_principal_stress.to_dict(),
                "max_principal_strain": self.max_principal_strain.to_dict(), "max_log_strain": self.max_log_strain}


def region_peaks(peaks, times, mesh, regions=None) -> dict[str, RegionPeaks]:
    """Region name -> :class:`RegionPeaks` of :func:`element_peaks` ``peaks``.

    Args:
        peaks: (von_mises, max_principal_stress, max_principal_strain), each (T, m).
        times: (T,) [s].
        mesh: the :class:`jaxsync.Mesh` (element centroids).
        regions: name -> element ids (None: :func:`facet_regions`).

    Raises:
        ProblemError: a region without elements or with ids outside the mesh.
    """
    regions = facet_regions(mesh) if regions is None else regions
    centroids = mesh.points[mesh.tets].mean(axis=1)
    times = np.asarray(times, float)

    def peak(field, elements):
        t, k = np.unravel_index(int(np.argmax(field[:, elements])), (field.shape[0], len(elements)))
        e = int(elements[k])
        return Peak(float(field[t, e]), e, int(t), float(times[t]), tuple(float(c) for c in centroids[e]))

    out = {}
    for name, elements in regions.items():
        elements = np.unique(np.asarray(elements, dtype=np.int64).ravel())
        if not elements.size or elements[0] < 0 or elements[-1] >= mesh.n_elements:
            raise ProblemError(f"region {name!r} must hold element ids in 0 .. {mesh.n_elements - 1}, got "
                               f"{elements.size} ids" + (f" from {elements[0]} to {elements[-1]}" if elements.size
                                                         else ""))
        strain = peak(peaks[2], elements)
        out[name] = RegionPeaks(region=name, n_elements=int(elements.size), von_mises=peak(peaks[0], elements),
                                max_principal_stress=peak(peaks[1], elements), max_principal_strain=strain,
                                max_log_strain=float(0.5 * np.log1p(2.0 * strain.value)),
                                history=peaks[0][:, elements].max(axis=1))
    return out
