"""The zero-pressure (unloaded) geometry of an imaged structure (:func:`zero_pressure_geometry`).

A vessel segmented from CT or MRI is already inflated by the blood pressure at imaging.
Given the imaged node positions x (the problem's mesh) and the loads at imaging (the
problem's loads at full magnitude, time factor 1: a lumen follower pressure), find the
reference X whose static solution under those loads is x, phi_X(X) = x. Two methods:

* ``"newton"``: Newton's method on the inverse problem (Govindjee & Mihalic 1996). The
  unknown is X, the residual R(X) = f_int(X; x) - f_p(x) the internal force at the deformed
  configuration x computed with reference X (:mod:`jaxsync.fem.forces`) minus the follower
  pressure's force on x, which does not depend on X, plus the elastic supports' springs and
  minus the dead loads (body force, traction, dead pressure), integrals over the unknown
  reference (:func:`jaxsync.fem.forces.inverse_loads`). Its tangent dR/dX is exact (JAX),
  solved by scipy's sparse direct solver (``linear_solver="direct"``) or by GMRES on
  ``jax.jvp`` products with a node-block Jacobi preconditioner (``"krylov"``, for meshes
  whose factorisation does not fit). The loads are applied in ``load_steps`` increments
  (the springs at full stiffness throughout).
* ``"fixed-point"``: the backward-displacement method (Bols et al. 2013),
  X(k+1) = x - u(X(k)), u(X) the static displacement (:func:`jaxsync.steady_state`) of the
  problem on reference X; every forward solve starts from the previous one's displacement.
  It takes every load and support the forward problem takes.

The imaged state is taken as at rest under the imaging loads: a viscoelastic law (a Prony
series, :class:`jaxsync.fem.materials.PronySeries`) is unloaded with its long-term
(relaxed) elastic law, its ``elastic_law()``, the response its branches relax to under a
held pressure. Prescribed displacements g keep their dofs at X = x - g. :func:`zero_pressure_points` is
the Newton solve as a differentiable function of the law's parameters: its reverse pass is
the adjoint of the converged solve (implicit function theorem),
dX/dtheta = -(dR/dX)^-1 dR/dtheta.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConvergenceError, MeshError, ProblemError
from ..options import LinearSolver, ZeroPressureMethod, choices
from ..pytree import is_traced

__all__ = ["ZeroPressureGeometry", "zero_pressure_geometry", "zero_pressure_points", "problem_on",
           "ZERO_PRESSURE_METHODS", "LINEAR_SOLVERS"]

ZERO_PRESSURE_METHODS = choices(ZeroPressureMethod)
"""The methods of :func:`zero_pressure_geometry`."""

LINEAR_SOLVERS = choices(LinearSolver)
"""The linear solvers of the Newton method."""


@dataclasses.dataclass(frozen=True)
class ZeroPressureGeometry:
    """The unloaded geometry found by :func:`zero_pressure_geometry`.

    Attributes:
        mesh: the unloaded :class:`jaxsync.Mesh` (the imaged mesh's topology, facet sets and
            node ids; for P2 its edge nodes as ``mid_nodes``).
        points: (n_nodes, 3) the unloaded positions of the problem's solution nodes [cm].
        method: ``"newton"`` or ``"fixed-point"``.
        iterations: the iterations taken (Newton: summed over the increments; fixed point:
            the forward solves).
        residuals: per iteration, Newton: the relative out-of-balance force at the free dofs
            (over the pressure force and reactions); fixed point: the largest distance
            between the inflated reference and the imaged nodes over the imaged geometry's
            size (its bounding-box diagonal).
    """

    mesh: object
    points: np.ndarray
    method: str
    iterations: int
    residuals: tuple

    def problem(self, problem):
        """``problem`` on the unloaded mesh (:func:`problem_on`)."""
        return problem_on(problem, self.mesh)


@dataclasses.dataclass(frozen=True)
class _Nodes:
    """A Dirichlet predicate selecting fixed node indices, whatever the coordinates."""

    indices: tuple

    def __call__(self, points):
        mask = np.zeros(len(points), dtype=bool)
        mask[list(self.indices)] = True
        return mask


def _at_rest(problem):
    """``problem`` with a viscoelastic law replaced by its long-term elastic law (module
    docstring): the imaged state is relaxed."""
    relaxed = getattr(problem.material, "elastic_law", None)
    return problem if relaxed is None else problem.replace(material=relaxed())


def problem_on(problem, mesh):
    """``problem`` with ``mesh`` (same topology, other coordinates) in place of its own: the
    Dirichlet conditions keep their nodes (a predicate is evaluated on the original
    coordinates), every other field as it is."""
    if mesh.n_nodes != problem.mesh.n_nodes or not np.array_equal(mesh.tets, problem.mesh.tets):
        raise ProblemError("problem_on needs a mesh of the same topology (nodes and tetrahedra) as the problem's")
    kept = tuple(dataclasses.replace(bc, where=_Nodes(tuple(int(i) for i in bc.nodes(problem.space))))
                 if callable(bc.where) else bc for bc in problem.dirichlet)
    return dataclasses.replace(problem, mesh=mesh, dirichlet=kept, operators=None)


def _mesh_at(problem, points):
    """The problem's mesh with its solution nodes moved to ``points`` (n_nodes, 3)."""
    from ..fem._space import vtk_cells
    from ..mesh import Mesh

    mesh, space = problem.mesh, problem.space
    mids = None
    if space.element == "P2":
        mids = points[vtk_cells(space)[1][:, 4:]]  # (n_elements, 6, 3) in VTK's edge order
    return Mesh(points=np.ascontiguousarray(points[:mesh.n_nodes]), tets=mesh.tets, facet_sets=dict(mesh.facet_sets),
                source_node_ids=mesh.source_node_ids, mid_nodes=mids)


def _pressures(problem) -> str:
    from ..fem._loads import Pressure

    found = [f"{float(load.magnitude):g} barye on {load.surface!r}" for load in problem.loads
             if isinstance(load, Pressure)]
    return "the imaging pressure " + (", ".join(found) if found else "(none)")


def _check(problem, method, tol, max_iter, load_steps, linear_solver):
    from ..precision import require_float64

    require_float64("zero_pressure_geometry")
    if method not in ZERO_PRESSURE_METHODS:
        raise ProblemError(f"method must be one of {', '.join(map(repr, ZERO_PRESSURE_METHODS))}, got {method!r}")
    if linear_solver not in LINEAR_SOLVERS:
        raise ProblemError(f"linear_solver must be one of {', '.join(map(repr, LINEAR_SOLVERS))}, "
                           f"got {linear_solver!r}")
    for name, value in (("max_iter", max_iter), ("load_steps", load_steps)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ProblemError(f"{name} must be an integer >= 1, got {value!r}")
    if not (isinstance(tol, (int, float)) and np.isfinite(tol) and tol > 0):
        raise ProblemError(f"tol must be a positive number, got {tol!r}")
    if not problem.material.finite_strain:
        raise ProblemError("the zero-pressure geometry needs a hyperelastic law, got "
                           f"{type(problem.material).__name__}: "
                           "a small-strain law has no distinct deformed configuration to unload; use "
                           "jaxsync.NeoHookean, NearlyIncompressibleNeoHookean or HolzapfelGasserOgden")
    if method == "newton":
        from ..fem.forces._inverse_loads import inverse_loads

        inverse_loads(problem)  # refuses a load it does not take, before any solve


def zero_pressure_geometry(problem, *, method: str = "newton", tol: float = 1e-10, max_iter: int = 50,
                           load_steps: int = 4, linear_solver: str = "direct") -> ZeroPressureGeometry:
    """The unloaded (zero-pressure) geometry of the imaged ``problem`` (module docstring).

    Args:
        problem: a :class:`jaxsync.Problem` with a hyperelastic law whose mesh is the imaged
            geometry and whose loads, at full magnitude (time factor 1), are those at imaging
            (a follower :class:`jaxsync.Pressure` on the lumen); Dirichlet conditions clamp
            it as in the forward problem.
        method: ``"newton"`` (the inverse problem) or ``"fixed-point"`` (backward
            displacement); both take every load and elastic support of the forward problem.
        tol: Newton: the relative out-of-balance force of convergence (as
            :func:`jaxsync.steady_state`); fixed point: the largest gap between the
            inflated reference and the imaged nodes over the imaged geometry's size.
        max_iter: Newton: iterations per increment; fixed point: forward solves.
        load_steps: the number of pressure increments (Newton; the fixed point's first
            forward solve).
        linear_solver: Newton's linear solves, ``"direct"`` (scipy's sparse LU) or
            ``"krylov"`` (GMRES on ``jax.jvp`` products).

    Returns:
        :class:`ZeroPressureGeometry`.

    Raises:
        ConvergenceError: no convergence in ``max_iter`` iterations (more ``load_steps``
            often help), or every update inverts an element of the reference (likely a
            pressure that would need a negative volume to unload); the message names the
            pressure and the iteration.
        ProblemError: bad options, a small-strain law, traced parameters (use
            :func:`zero_pressure_points`).
    """
    _check(problem, method, tol, max_iter, load_steps, linear_solver)
    problem = _at_rest(problem)
    if is_traced(problem.material, problem.loads):
        raise ProblemError("zero_pressure_geometry solves on the host, so it cannot take traced inputs (jax.grad, "
                           "jit, vmap): for derivatives of the unloaded positions use "
                           "jaxsync.zero_pressure_points(problem), differentiable in the material parameters")
    if method == "newton":
        points, residuals = _newton(problem, tol, max_iter, load_steps, linear_solver)
    else:
        points, residuals = _fixed_point(problem, tol, max_iter, load_steps)
    return ZeroPressureGeometry(mesh=_mesh_at(problem, points), points=points, method=method,
                                iterations=len(residuals) - 1 if method == "newton" else len(residuals),
                                residuals=tuple(residuals))


class _Inverse:
    """The inverse problem's residual and its Newton updates."""

    def __init__(self, problem, linear_solver: str):
        from ..fem.forces._follower import full_follower_pressure
        from ..fem.forces._inverse import inverse_operator
        from ..fem.forces._inverse_loads import inverse_loads, inverse_loads_force

        self.problem, self.linear_solver = problem, linear_solver
        self.op = inverse_operator(problem)
        x = problem.space.points
        follower = full_follower_pressure(problem)
        self.pressure = (np.zeros(x.size) if follower is None
                         else np.asarray(follower.force(jnp.zeros(x.shape), 0.0)).reshape(-1))
        self.loads = inverse_loads(problem)
        if not self.loads.empty:  # the dead loads' scale at the imaged geometry
            self.pressure_scale = max(float(np.abs(self.pressure).max(initial=0.0)), float(np.abs(np.asarray(
                inverse_loads_force(self.loads, jnp.asarray(x), 1.0)) - np.asarray(
                inverse_loads_force(self.loads, jnp.asarray(x), 0.0))).max(initial=0.0)))
        else:
            self.pressure_scale = float(np.abs(self.pressure).max(initial=0.0))
        fixed, values = problem.dirichlet_dofs()
        self.fixed, self.free = fixed, np.setdiff1d(np.arange(x.size), fixed)
        self.start = x.reshape(-1).copy()
        self.start[fixed] -= values  # a prescribed displacement g: X = x - g there

    def residual(self, X, fraction):
        """R(X) (n_dofs,) [dyn], or None where the reference or F is inverted or R not finite."""
        from ..fem.forces._inverse import inverse_force, inverse_jacobians

        Xn = jnp.asarray(X.reshape(-1, 3))
        J = np.asarray(inverse_jacobians(self.op, Xn))
        if not np.all(np.isfinite(J) & (J > 0)):
            return None
        r = np.asarray(inverse_force(self.op, Xn)).reshape(-1) - fraction * self.pressure
        if not self.loads.empty:
            from ..fem.forces._inverse_loads import inverse_loads_force

            r = r + np.asarray(inverse_loads_force(self.loads, Xn, fraction)).reshape(-1)
        return r if np.all(np.isfinite(r)) else None

    def relative(self, r, fraction) -> float:
        scale = max(fraction * self.pressure_scale,
                    float(np.abs(r[self.fixed]).max(initial=0.0)))
        return float(np.abs(r[self.free]).max(initial=0.0)) / scale if scale > 0 else 0.0

    def solve(self, X, rhs, fraction, *, transpose: bool = False):
        """The free dofs' K^-1 rhs (or K^-T rhs), K = dR/dX at X with the loads at
        ``fraction`` of their magnitude."""
        import scipy.sparse.linalg as spla

        from ..fem.forces._inverse import tangent
        from ..fem.forces._inverse_loads import loads_tangent

        if self.linear_solver == "direct" or transpose:
            K = tangent(self.op, X.reshape(-1, 3))
            extra = loads_tangent(self.loads, X.reshape(-1, 3), fraction)
            K = (K if extra is None else K + extra).tocsr()[self.free][:, self.free].tocsc()
            try:
                factor = spla.splu(K.T.tocsc() if transpose else K)
            except RuntimeError as exc:  # SuperLU: "Factor is exactly singular"
                raise ProblemError("the inverse problem is singular: the Dirichlet conditions do not prevent "
                                   "rigid-body motion; clamp more nodes") from exc
            return factor.solve(rhs)
        return self._krylov(X, rhs, fraction)

    def _krylov(self, X, rhs, fraction):
        import scipy.sparse.linalg as spla

        from ..fem.forces._inverse import inverse_blocks, inverse_product
        from ..fem.forces._inverse_loads import inverse_loads_product

        n = X.size
        Xn = jnp.asarray(X.reshape(-1, 3))
        # node-block Jacobi: the 3 x 3 diagonal blocks of the element blocks, summed at the nodes
        blocks = np.asarray(inverse_blocks(self.op, Xn))
        k = blocks.shape[1] // 3
        b = blocks.reshape(len(blocks), k, 3, k, 3)
        node_blocks = np.zeros((n // 3, 3, 3))
        for a in range(k):
            np.add.at(node_blocks, np.asarray(self.op.cells)[:, a], b[:, a, :, a, :])
        preconditioner = np.linalg.inv(node_blocks)
        free = self.free

        def matvec(v):
            full = np.zeros(n)
            full[free] = v
            V = jnp.asarray(full.reshape(-1, 3))
            product = np.asarray(inverse_product(self.op, Xn, V))
            if not self.loads.empty:
                product = product + np.asarray(inverse_loads_product(self.loads, Xn, fraction, V))
            return product.reshape(-1)[free]

        def precondition(v):
            full = np.zeros(n)
            full[free] = v
            return np.einsum("nij,nj->ni", preconditioner, full.reshape(-1, 3)).reshape(-1)[free]

        size = len(free)
        A = spla.LinearOperator((size, size), matvec=matvec, dtype=float)
        M = spla.LinearOperator((size, size), matvec=precondition, dtype=float)
        x, info = spla.gmres(A, rhs, M=M, rtol=1e-12, atol=0.0, restart=min(size, 200), maxiter=50)
        if info != 0:
            raise ConvergenceError(f"GMRES did not reach its tolerance in the Newton update of the inverse problem "
                                   f"(info {info}); use linear_solver='direct'")
        return x


def _newton(problem, tol, max_iter, load_steps, linear_solver):
    """(X (n_nodes, 3), the relative residual of every iteration) by Newton's method."""
    inverse = _Inverse(problem, linear_solver)
    free = inverse.free
    X = inverse.start.copy()
    residuals = []
    for k in range(1, load_steps + 1):
        fraction = k / load_steps
        r = inverse.residual(X, fraction)
        if r is None:
            raise ConvergenceError(f"the unloaded geometry at {_pressures(problem)} inverts an element before "
                                   f"increment {k} of {load_steps}: check the imaged mesh", increment=k)
        for iteration in range(max_iter + 1):
            relative = inverse.relative(r, fraction)
            residuals.append(relative)
            if relative <= tol:
                break
            if iteration == max_iter:
                raise ConvergenceError(
                    f"the zero-pressure geometry did not converge at {_pressures(problem)}: increment {k} of "
                    f"{load_steps} ({100 * fraction:.0f} % of the pressure), Newton iteration {iteration}, relative "
                    f"residual {relative:.3e} (tolerance {tol:g}); raise load_steps or max_iter, or check that the "
                    "wall can carry this pressure", increment=k, residual=relative)
            dX = inverse.solve(X, -r[free], fraction)
            for _ in range(11):  # halve an update that inverts an element of the reference
                trial = X.copy()
                trial[free] += dX
                found = inverse.residual(trial, fraction)
                if found is not None:
                    break
                dX = 0.5 * dX
            else:
                raise ConvergenceError(
                    f"no zero-pressure geometry at {_pressures(problem)}: in increment {k} of {load_steps} "
                    f"({100 * fraction:.0f} % of the pressure), at Newton iteration {iteration + 1}, every update "
                    "(halved 10 times) inverts an element of the unloaded geometry (det dX/dxi <= 0 or det F <= 0): "
                    "the pressure is likely too large for this wall and law (unloading it would need a negative "
                    f"volume); check the pressure's units (barye) and the law's moduli, or raise load_steps",
                    increment=k, residual=relative)
            X, r = trial, found
    return X.reshape(-1, 3), residuals


def _fixed_point(problem, tol, max_iter, load_steps):
    """(X (n_nodes, 3), the relative gap of every forward solve) by backward displacements."""
    from ._solver import steady_state

    x = problem.space.points
    fixed, values = problem.dirichlet_dofs()
    X = x.reshape(-1).copy()
    X[fixed] -= values
    size = float(np.linalg.norm(np.ptp(x, axis=0)))
    u, residuals = None, []
    for iteration in range(1, max_iter + 1):
        try:
            reference = problem_on(problem, _mesh_at(problem, X.reshape(-1, 3)))
        except MeshError as exc:
            raise ConvergenceError(f"no zero-pressure geometry at {_pressures(problem)}: at fixed-point iteration "
                                   f"{iteration} the unloaded geometry has inverted elements ({exc}); unloading "
                                   "would need a negative volume, so the pressure is too large for this wall and "
                                   "law", increment=iteration) from exc
        try:
            u = steady_state(reference, load_steps=1 if u is not None else load_steps, tol=1e-12, guess=u)
        except ConvergenceError:
            try:
                u = steady_state(reference, load_steps=2 * load_steps, tol=1e-12)
            except ConvergenceError as exc:
                raise ConvergenceError(f"no zero-pressure geometry at {_pressures(problem)}: at fixed-point "
                                       f"iteration {iteration} the forward problem does not converge ({exc})",
                                       increment=iteration) from exc
        u = np.asarray(u)
        gap = float(np.abs(X + u.reshape(-1) - x.reshape(-1)).max(initial=0.0)) / size
        residuals.append(gap)
        if gap <= tol:
            return X.reshape(-1, 3), residuals
        X = x.reshape(-1) - u.reshape(-1)
    raise ConvergenceError(f"the zero-pressure geometry did not converge at {_pressures(problem)}: after "
                           f"{max_iter} fixed-point iterations the inflated reference is {residuals[-1]:.3e} of the "
                           f"geometry's size from the imaged nodes (tolerance {tol:g}); raise max_iter, or use "
                           "method='newton' (quadratic convergence)", increment=max_iter, residual=residuals[-1])


@functools.partial(jax.jit, static_argnums=0)
def _law_cotangent(treedef, op, X, values, adjoint):
    """The law's leaves' cotangents adjoint . d f_int(X) / d theta (a ``jax.vjp``, compiled)."""
    from ..fem.forces._inverse import split_fibres

    def force(values):
        stripped, fibres = split_fibres(jax.tree_util.tree_unflatten(treedef, values))
        return dataclasses.replace(op, material=stripped, fibres=fibres).force(X).reshape(-1)

    return jax.vjp(force, values)[1](adjoint)[0]


def zero_pressure_points(problem, *, tol: float = 1e-12, max_iter: int = 50, load_steps: int = 4):
    """(n_nodes, 3) the unloaded positions of the solution nodes [cm], as
    :func:`zero_pressure_geometry` (``method="newton"``) finds them, differentiable in the
    law's parameters (``problem.material``'s fields may be JAX tracers under ``jax.grad``,
    not under ``jit``): the reverse pass solves the adjoint of the converged Newton system,
    dX/dtheta = -(dR/dX)^-1 dR/dtheta, with R the inverse problem's residual.

    Raises:
        as :func:`zero_pressure_geometry`.
    """
    from ._static_adjoint import differentiable_in_law

    _check(problem, "newton", tol, max_iter, load_steps, "direct")
    return differentiable_in_law(_at_rest(problem), lambda p: _newton(p, tol, max_iter, load_steps, "direct")[0],
                                 _points_cotangent, "zero_pressure_points")


def _points_cotangent(problem, X, X_bar) -> list:
    """The law's leaves' cotangents of a scalar whose cotangent in the unloaded points X
    (n_nodes, 3) of ``problem`` (concrete) is ``X_bar``: -(dR/dtheta)^T lambda with
    (dR/dX)^T lambda = X_bar at the free dofs."""
    from ..fem.forces._inverse import inverse_operator

    inverse = _Inverse(problem, "direct")
    X = np.asarray(X)
    adjoint = np.zeros(X.size)
    adjoint[inverse.free] = inverse.solve(X.reshape(-1), np.asarray(X_bar).reshape(-1)[inverse.free], 1.0,
                                          transpose=True)
    leaves, treedef = jax.tree_util.tree_flatten(problem.material)
    return list(_law_cotangent(treedef, inverse_operator(problem), jnp.asarray(X),
                               [jnp.asarray(v, dtype=float) for v in leaves], jnp.asarray(-adjoint)))
