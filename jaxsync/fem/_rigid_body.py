"""Rigid-body motions that a problem's supports leave free.

A body whose Dirichlet conditions and elastic supports do not hold all six rigid-body
motions (three translations, three rotations) has a singular stiffness: a load with a
net force or moment along a free motion accelerates it without bound (the explicit run
drifts away, Newton's statics meet a singular system). :func:`free_rigid_motions` finds
those motions from the constrained dofs alone (no assembly), and
:func:`warn_about_free_motion` warns when a load or the initial velocity drives one.
"""

from __future__ import annotations

import warnings

import numpy as np

__all__ = ["RigidBodyWarning", "rigid_body_modes", "free_rigid_motions", "warn_about_free_motion"]


class RigidBodyWarning(UserWarning):
    """A load (or the initial velocity) drives a rigid-body motion that no Dirichlet
    condition or support holds: the body drifts or spins away without bound."""


_NAMES = ("translation along x", "translation along y", "translation along z",
          "rotation about x", "rotation about y", "rotation about z")


def rigid_body_modes(points: np.ndarray) -> np.ndarray:
    """(n_nodes, 3, 6) the six rigid-body motions at ``points`` (n_nodes, 3) [cm]: unit
    translations, then unit rotations about the axes through the centroid, scaled by the
    body's size so that all six are of the same magnitude."""
    x = points - points.mean(axis=0)
    size = max(float(np.abs(x).max(initial=0.0)), 1e-300)
    modes = np.zeros((len(points), 3, 6))
    modes[:, :, :3] = np.eye(3)
    for axis in range(3):
        e = np.zeros(3)
        e[axis] = 1.0
        modes[:, :, 3 + axis] = np.cross(e, x) / size
    return modes


def _support_rows(problem, modes: np.ndarray) -> list[np.ndarray]:
    """Constraint rows (k, 6) of the elastic supports: a support in every direction holds
    its nodes' three components, a normal-only one their normal component."""
    rows = []
    space = problem.space
    for support in problem.supports:
        nodes = space.facet_nodes(support.surface)
        if not support.normal_only:
            rows.append(modes[nodes].reshape(-1, 6))
            continue
        tri = problem.mesh.facet_set(support.surface)
        p = problem.mesh.points
        area_normal = np.cross(p[tri[:, 1]] - p[tri[:, 0]], p[tri[:, 2]] - p[tri[:, 0]])
        normals = np.zeros((problem.mesh.n_nodes, 3))
        for k in range(3):
            np.add.at(normals, tri[:, k], area_normal)
        vertices = np.unique(tri)
        length = np.linalg.norm(normals[vertices], axis=1, keepdims=True)
        unit = normals[vertices] / np.maximum(length, 1e-300)
        rows.append(np.einsum("nc,nck->nk", unit, modes[vertices]))
    return rows


def free_rigid_motions(problem) -> np.ndarray:
    """(n_nodes, 3, k) the rigid-body motions (combinations of :func:`rigid_body_modes`)
    that no Dirichlet condition or elastic support of ``problem`` holds; k = 0 for a
    supported body, 6 for a free one."""
    modes = rigid_body_modes(problem.points)
    dofs, _ = problem.dirichlet_dofs()
    rows = [modes.reshape(-1, 6)[dofs]]
    rows += _support_rows(problem, modes)
    constraints = np.concatenate(rows) if rows else np.zeros((0, 6))
    gram = constraints.T @ constraints
    values, vectors = np.linalg.eigh(gram)
    free = values <= 1e-10 * max(float(values.max(initial=0.0)), 1.0)
    return modes @ vectors[:, free]


def _describe(motion: np.ndarray, modes: np.ndarray) -> str:
    """The named rigid motions (:func:`rigid_body_modes`) that a free one is made of."""
    coefficients = np.abs(np.linalg.lstsq(modes.reshape(-1, 6), motion.reshape(-1), rcond=None)[0])
    return " and ".join(_NAMES[k] for k in np.flatnonzero(coefficients >= 0.3 * coefficients.max()))


def _where(where) -> str:
    """How a message names a Dirichlet condition's node set."""
    if isinstance(where, str):
        return f"facet set {where!r}"
    name = getattr(where, "__name__", "")
    return f"predicate {name!r}" if name and name != "<lambda>" else "a predicate"


def warn_about_free_motion(problem, *, stacklevel: int = 3) -> None:
    """:class:`RigidBodyWarning` when a load of ``problem`` (at full magnitude) or its
    initial velocity has a component along a rigid-body motion that nothing holds. Loads
    in equilibrium (a pressure on a closed surface) do not warn. Traced loads are not
    checked."""
    from ..pytree import is_traced

    free = free_rigid_motions(problem)
    if free.shape[-1] == 0 or is_traced(problem.loads, problem.initial_velocity):
        return
    drivers = []
    vectors = [problem.load_vector(load) for load in problem.loads]  # a follower pressure's: at rest
    basis = free.reshape(-1, free.shape[-1])
    for name, field in ([("the loads", sum(np.asarray(v, dtype=float) for v in vectors))] if vectors else []) + (
            [("the initial velocity", np.asarray(problem.initial_velocity, dtype=float))]
            if problem.initial_velocity is not None else []):
        field = np.asarray(field).reshape(-1)
        scale = float(np.abs(field).max(initial=0.0))
        if scale == 0.0:
            continue
        drive = basis.T @ field  # the generalised force (or momentum) along each free motion
        if np.abs(drive).max() > 1e-8 * scale * np.sqrt(len(field)):
            drivers.append((name, basis @ (drive / np.linalg.norm(drive))))
    if not drivers:
        return
    modes = rigid_body_modes(problem.points)
    motions = "; ".join(dict.fromkeys(_describe(m, modes) for _, m in drivers))
    held = ", ".join(f"{_where(bc.where)} selects {len(bc.nodes(problem.space))} node(s)" for bc in problem.dirichlet)
    names = [n for n, _ in drivers]
    warnings.warn(
        f"{' and '.join(names)} drive{'s' if names == ['the initial velocity'] else ''} "
        f"a rigid-body motion that no Dirichlet condition or support holds ({motions}; {free.shape[-1]} of the 6 "
        f"rigid-body motions are free; Dirichlet conditions: "
        f"{held or 'none'}): the body will drift or spin away without bound. Clamp at least three nodes "
        "not on one line (jaxsync.Dirichlet on a facet set), add a jaxsync.ElasticSupport, or check that the "
        "configuration's boundary conditions fit this mesh", RigidBodyWarning, stacklevel=stacklevel)
