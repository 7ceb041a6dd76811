"""Follower pressure: a pressure that acts on the deformed surface.

A lumen pressure pushes on the wall as it is, not as it was: its traction is -p n da on
the CURRENT surface (n its outward normal, da its area), so its nodal forces depend on the
displacement (Bonet & Wood, section 8.4):

    f_a(u, t) = -p(t) integral over the reference triangle of N_a (x_,xi x x_,eta) dxi deta    [dyn],

x = X + u the current positions of the facet's nodes (3 for P1 triangles, 6 for P2),
x_,xi and x_,eta its tangents, their cross product the current normal times the area
change (the same as J F^-T N dA of the reference surface). P1: one quadrature point
(exact: the cross product is constant and f_a = -p A n / 3 at each vertex); P2: the
degree-4 rule of scikit-fem on the reference triangle (exact: N_a is quadratic and so is
the cross product of the quadratic facet's tangents).

A follower pressure is a displacement-dependent load, so the explicit step computes it
beside the internal force (:func:`jaxsync.fem._stepper.internal_forces`), every facet on the
part that holds its element (its partial sums at shared nodes are completed by the same
exchange as the internal force's). Its load stiffness -d f / d u (non-symmetric) enters
Newton's tangent (:func:`jaxsync.steady_state`); it is left out of the stable step (for a
pressure far below the elastic modulus it changes the highest frequency by O(p / E)).
On a closed surface, or one whose boundary does not move, the pressure is conservative,
with potential p (V(x) - V(X)), V(x) = 1/3 integral of x . n da over the loaded surface
(n out of the solid): the volume of the solid when the surface closes it.
"""

from __future__ import annotations

from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ...errors import ProblemError
from ...pytree import pytree_dataclass

__all__ = ["FollowerPressure", "follower_pressure", "full_follower_pressure",
           "part_follower_pressures", "follower_loads", "facet_nodes",
           "load_stiffness", "facet_rule"]


@pytree_dataclass
class FollowerPressure:
    """The nodal forces of the follower pressures of a mesh (or of a part), a pytree.

    Attributes:
        facets: (n_facets, k_f) int32 nodes of each loaded facet (k_f = 3 for P1, 6 for P2:
            vertices, then the edge nodes of (0, 1), (1, 2), (0, 2)), ordered so that the
            right-hand normal points out of the solid.
        points: (n_nodes, 3) reference node coordinates [cm].
        shape: (n_q, k_f) the facet's shape functions at the quadrature points.
        tangents: (n_q, 2, k_f) their derivatives in the reference coordinates (xi, eta).
        weights: (n_facets, n_q) the rule's weights (zero on a part's padding facets).
        load: (n_facets,) int32 which load (of ``magnitudes``) acts on each facet.
        magnitudes: (n_loads,) pressures at full magnitude [barye].
        times: tuple of the loads' time functions g_l(t).
    """

    facets: Any
    points: Any
    shape: Any
    tangents: Any
    weights: Any
    load: Any
    magnitudes: Any
    times: tuple

    def pressures(self, t):
        """(n_loads,) the pressures p_l g_l(t) at time t [barye]."""
        return jnp.stack([m * g(t) for m, g in zip(jnp.unstack(jnp.asarray(self.magnitudes)), self.times)])

    def facet_forces(self, u, t):
        """(n_facets, k_f, 3) each facet's nodal forces [dyn] at displacements u (n_nodes, 3) [cm]."""
        one = jax.vmap(_facet_force, in_axes=(0, None, None, 0, 0))
        return one((self.points + u)[self.facets], self.tangents, self.shape, self.weights,
                   self.pressures(t)[self.load])

    def force(self, u, t):
        """(n_nodes, 3) the nodal forces of the follower pressures [dyn] at displacements u
        (n_nodes, 3) [cm] and time t [s]."""
        forces = self.facet_forces(u, t)
        return jax.ops.segment_sum(forces.reshape(-1, 3), self.facets.reshape(-1), num_segments=u.shape[0])


def _facet_force(x, tangents, shape, weights, pressure):
    """(k_f, 3) one facet's nodal forces [dyn] at its nodes' current positions x (k_f, 3)
    [cm]: -p sum_q w_q N_a (x_,xi x x_,eta) at the rule's points."""
    a = jnp.einsum("qdk,ki->qdi", tangents, x)  # (q, 2, 3) current tangents
    normal = jnp.cross(a[:, 0], a[:, 1])  # (q, 3): n da / (dxi deta)
    return -pressure * jnp.einsum("q,qk,qi->ki", weights, shape, normal)


def follower_loads(problem) -> list:
    """The problem's follower pressures (:class:`jaxsync.Pressure` with ``follower=True``)."""
    from .._loads import Pressure

    return [load for load in problem.loads if isinstance(load, Pressure) and load.follower]


def facet_rule(element: str, intorder: int | None = None):
    """(shape (n_q, k_f), tangents (n_q, 2, k_f), weights (n_q,)) on the reference triangle
    (0, 0), (1, 0), (0, 1): scikit-fem's rule of degree ``intorder`` (None: P1 one point,
    P2 the degree-4 rule)."""
    from skfem.quadrature import get_quadrature
    from skfem.refdom import RefTri

    xi, w = get_quadrature(RefTri, (1 if element == "P1" else 4) if intorder is None else intorder)
    s, t = xi
    L = np.stack([1.0 - s - t, s, t])  # barycentric coordinates (3, n_q)
    dL = np.array([[-1.0, -1.0], [1.0, 0.0], [0.0, 1.0]])  # (3, 2): d L_i / d (xi, eta)
    if element == "P1":
        shape = L.T
        tangents = np.broadcast_to(dL.T[None], (len(w), 2, 3))
    else:
        pairs = ((0, 1), (1, 2), (0, 2))
        shape = np.concatenate([(L * (2.0 * L - 1.0)).T, np.stack([4.0 * L[i] * L[j] for i, j in pairs], axis=1)],
                               axis=1)
        vertex = (4.0 * L[:, :, None] - 1.0) * dL[:, None, :]  # (3, n_q, 2)
        edge = np.stack([4.0 * (L[i][:, None] * dL[j] + L[j][:, None] * dL[i]) for i, j in pairs])  # (3, n_q, 2)
        tangents = np.concatenate([vertex, edge]).transpose(1, 2, 0)
    return np.ascontiguousarray(shape), np.ascontiguousarray(tangents), np.asarray(w, dtype=float)


def facet_nodes(space, surface: str) -> tuple[np.ndarray, np.ndarray]:
    """(nodes (n_f, k_f) of the facets of ``surface``, outward oriented (as
    :class:`FollowerPressure` holds them), element (n_f,) of each facet)."""
    from ...mesh import to_skfem
    from .._assembly import boundary_facet_indices

    skmesh = to_skfem(space.mesh)
    index = boundary_facet_indices(space.mesh, skmesh, surface, what="a follower pressure")
    vertices = np.asarray(skmesh.facets[:, index].T, dtype=np.int64)  # (n_f, 3)
    elements = np.asarray(skmesh.f2t[0, index], dtype=np.int64)
    tets = space.mesh.tets[elements]
    opposite = tets.sum(axis=1) - vertices.sum(axis=1)  # the element's vertex off the facet
    X = space.mesh.points
    a, b, c = (X[vertices[:, i]] for i in range(3))
    inward = np.einsum("fi,fi->f", np.cross(b - a, c - a), X[opposite] - a) > 0
    vertices[inward] = vertices[inward][:, [0, 2, 1]]
    if space.element == "P1":
        return vertices, elements
    pairs = np.stack([vertices[:, [0, 1]], vertices[:, [1, 2]], vertices[:, [0, 2]]], axis=1).reshape(-1, 2)
    edges = space.edge_nodes(pairs).reshape(-1, 3)
    return np.concatenate([vertices, edges], axis=1), elements


def _facets(problem):
    """(nodes (n_f, k_f), element (n_f,), load index (n_f,)) of every follower facet,
    computed once per space and set of surfaces."""
    loads = follower_loads(problem)

    def compute():
        found = [facet_nodes(problem.space, load.surface) for load in loads]
        return (np.concatenate([f for f, _ in found]), np.concatenate([e for _, e in found]),
                np.concatenate([np.full(len(e), k, dtype=np.int64) for k, (_, e) in enumerate(found)]))

    return problem.operators.derived("follower facets", tuple(load.surface for load in loads), compute)


def _operator(problem, facets, load, weights, points) -> FollowerPressure:
    loads = follower_loads(problem)
    shape, tangents, _ = facet_rule(problem.element)
    return FollowerPressure(
        facets=jnp.asarray(facets, dtype=jnp.int32), points=jnp.asarray(points), shape=jnp.asarray(shape),
        tangents=jnp.asarray(tangents), weights=jnp.asarray(weights), load=jnp.asarray(load, dtype=jnp.int32),
        magnitudes=jnp.stack([jnp.asarray(x.magnitude, dtype=float) for x in loads]),
        times=tuple(x.time for x in loads))


def follower_pressure(problem) -> FollowerPressure | None:
    """The :class:`FollowerPressure` of the whole mesh (None without follower pressures)."""
    if not follower_loads(problem):
        return None
    facets, _, load = _facets(problem)
    _, _, w = facet_rule(problem.element)
    return _operator(problem, facets, load, np.broadcast_to(w, (len(facets), len(w))), problem.space.points)


def full_follower_pressure(problem) -> FollowerPressure | None:
    """The follower pressures at full magnitude (every time factor 1, as
    :func:`jaxsync.steady_state` applies the loads), or None without any."""
    import dataclasses

    from .._loads import Constant

    follower = follower_pressure(problem)
    if follower is None:
        return None
    return dataclasses.replace(follower, times=tuple(Constant() for _ in follower.times))


def part_follower_pressures(problem, parts: Sequence, n_local: int) -> FollowerPressure | None:
    """The parts' :class:`FollowerPressure` stacked on a leading part axis (None without
    follower pressures): each part holds the facets of its own elements, in its local
    numbering, padded to the largest part (padding: the part's first facet, or node 0,
    with weight 0). ``parts``: objects with ``elements``, ``nodes`` and ``local_tets``."""
    if not follower_loads(problem):
        return None
    facets, elements, load = _facets(problem)
    _, _, w = facet_rule(problem.element)
    cells = problem.space.cells
    # each facet node's slot in its element (the same slot in a part's local_tets)
    slot = np.argmax(cells[elements][:, None, :] == facets[:, :, None], axis=2)  # (n_f, k_f)
    chosen = []
    for part in parts:
        position = np.full(problem.mesh.n_elements, -1, dtype=np.int64)
        position[np.asarray(part.elements)] = np.arange(len(part.elements))
        keep = np.flatnonzero(position[elements] >= 0)
        local = np.asarray(part.local_tets)[position[elements[keep]][:, None], slot[keep]]
        chosen.append((keep, local))
    n_pad = max(max(len(keep) for keep, _ in chosen), 1)
    k_f = facets.shape[1]
    stacked = []
    for part, (keep, local) in zip(parts, chosen):
        f = np.zeros((n_pad, k_f), dtype=np.int64)
        weights = np.zeros((n_pad, len(w)))
        which = np.zeros(n_pad, dtype=np.int64)
        f[:len(keep)], weights[:len(keep)], which[:len(keep)] = local, w, load[keep]
        if len(keep):
            f[len(keep):] = local[0]
        points = np.zeros((n_local, 3))
        points[:len(part.nodes)] = problem.space.points[np.asarray(part.nodes)]
        stacked.append(_operator(problem, f, which, weights, points))
    return jax.tree_util.tree_map(lambda *x: jnp.stack(x), *stacked)


def load_stiffness(operator: FollowerPressure, u, t=0.0):
    """The load stiffness -d f / d u (scipy CSR, (3 n_nodes, 3 n_nodes) [dyn/cm], dofs
    node-interleaved, non-symmetric) of the follower pressures at displacements u
    (n_nodes, 3) [cm] and time t [s]: the facets' forward-mode derivatives summed at the nodes."""
    import scipy.sparse as sp

    if np.ndim(operator.weights) != 2:
        raise ProblemError("this is a partition's stacked operator: pass the whole mesh's follower_pressure(problem)")
    u = jnp.asarray(u, dtype=float)
    blocks = -np.asarray(_facet_jacobians(operator, u, jnp.asarray(t, dtype=float)))  # (n_f, 3k, 3k)
    facets = np.asarray(operator.facets)
    dofs = (3 * facets[:, :, None] + np.arange(3)).reshape(len(facets), -1)
    size = dofs.shape[1]
    rows = np.broadcast_to(dofs[:, :, None], (len(facets), size, size)).ravel()
    cols = np.broadcast_to(dofs[:, None, :], (len(facets), size, size)).ravel()
    n = 3 * int(u.shape[0])
    return sp.coo_matrix((blocks.ravel(), (rows, cols)), shape=(n, n)).tocsr()


@jax.jit
def _facet_jacobians(op: FollowerPressure, u, t):
    """(n_facets, 3 k_f, 3 k_f) d f_facet / d u_facet (node-interleaved)."""
    def one(x, weights, pressure):
        force = lambda v: _facet_force(v.reshape(x.shape), op.tangents, op.shape, weights, pressure).reshape(-1)  # noqa: E731
        return jax.jacfwd(force)(x.reshape(-1))

    return jax.vmap(one)((op.points + u)[op.facets], op.weights, op.pressures(t)[op.load])
