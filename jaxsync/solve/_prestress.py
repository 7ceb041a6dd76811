"""The prestress of an imaged structure (:func:`prestress`): the imaged geometry kept as the
reference, with a prestrain F0 at every quadrature point (:class:`jaxsync.Prestressed`)
that puts it in equilibrium under the loads at imaging.

Two routes to F0:

* ``"zero-pressure"``: F0 = dx/dX, the deformation gradient of the imaged geometry x over
  its zero-pressure geometry X (:func:`jaxsync.zero_pressure_geometry`), at the imaged
  element's quadrature points. The prestressed problem is then the forward problem from X
  written on x: the same equilibrium, the same response to further loads.
* ``"mulf"``: the modified updated Lagrangian formulation (Gee, Foerster & Wall 2010),
  a fixed point: from F0 = I, solve the static problem on the imaged reference with the
  current prestrain (:func:`jaxsync.steady_state`), fold the deformation into the prestrain,
  F0 <- (I + grad_x u) F0, forget the displacement, and repeat until it vanishes. It needs
  no unloaded geometry, and its F0 need not be the gradient of one.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from ..errors import ConvergenceError, ProblemError
from ..options import PrestressMethod, choices
from ..pytree import is_traced

__all__ = ["PrestressResult", "prestress", "out_of_balance", "PRESTRESS_METHODS"]

PRESTRESS_METHODS = choices(PrestressMethod)
"""The methods of :func:`prestress`."""


@dataclasses.dataclass(frozen=True)
class PrestressResult:
    """The prestress found by :func:`prestress`.

    Attributes:
        material: the :class:`jaxsync.Prestressed` law (the problem's law and F0); use it as
            ``problem.replace(material=result.material)``.
        method: ``"zero-pressure"`` or ``"mulf"``.
        iterations: Newton iterations (zero-pressure) or static solves (MULF); None for a
            traced law's zero-pressure route.
        residuals: per iteration, zero-pressure: the inverse problem's relative residuals;
            MULF: the largest displacement of the static solve over the geometry's size.
        residual: the relative out-of-balance force of the imaged geometry with the
            prestress, at the free dofs (:func:`out_of_balance`); None for a traced law.
        density_scale: (n_elements,) 1 / det F0 (averaged over the element's points): the
            ``Problem.density_scale`` that gives each element the mass of its stress-free
            state (the law's rho is per stress-free volume; the imaged one is det F0 larger).
    """

    material: object
    method: str
    iterations: int
    residuals: tuple
    residual: float
    density_scale: np.ndarray


def _result(problem, material, method, iterations, residuals) -> PrestressResult:
    scale = 1.0 / np.mean(np.linalg.det(np.asarray(material.prestrain)), axis=1)
    return PrestressResult(material, method, iterations, tuple(residuals),
                           out_of_balance(problem.replace(material=material)), scale)


def out_of_balance(problem, displacement=None) -> float:
    """The largest out-of-balance force f_int(u) + S u - f_ext - f_follower(u) at the free
    dofs over the force scale (the largest load, follower pressure force or reaction) of a
    hyperelastic ``problem`` with every load at full magnitude (time factor 1), at
    ``displacement`` (n_nodes, 3) [cm] (default zero: the reference is in equilibrium when
    this is at round-off)."""
    from ..fem.forces._follower import full_follower_pressure
    from ..fem.forces._support import spring_matrix
    from ..fem.forces._total_lagrangian import TotalLagrangian

    u = jnp.zeros((problem.n_nodes, 3)) if displacement is None else jnp.asarray(displacement, dtype=float)
    r = np.asarray(TotalLagrangian().operator(problem).matvec(u)).reshape(-1)
    loads = np.zeros_like(r)
    for v in problem.load_vectors()[0]:
        loads += np.asarray(v, dtype=float).reshape(-1)
    follower = full_follower_pressure(problem)
    if follower is not None:
        loads += np.asarray(follower.force(u, 0.0)).reshape(-1)
    springs = spring_matrix(problem)
    r = r - loads + (0.0 if springs is None else springs @ np.asarray(u).reshape(-1))
    fixed, _ = problem.dirichlet_dofs()
    free = np.setdiff1d(np.arange(r.size), fixed)
    scale = max(float(np.abs(loads).max(initial=0.0)), float(np.abs(r[fixed]).max(initial=0.0)))
    return float(np.abs(r[free]).max(initial=0.0)) / scale if scale > 0 else 0.0


def prestress(problem, *, method: str = "zero-pressure", tol: float = 1e-12, max_iter: int = 100,
              load_steps: int = 4) -> PrestressResult:
    """The prestrain that puts the imaged ``problem`` in equilibrium (module docstring).

    Args:
        problem: a :class:`jaxsync.Problem` with an elastic hyperelastic law on the imaged
            geometry, its loads at full magnitude those at imaging (as for
            :func:`jaxsync.zero_pressure_geometry`).
        method: ``"zero-pressure"`` (F0 from the Newton zero-pressure geometry) or
            ``"mulf"``; both take every load and support of the forward problem.
        tol: zero-pressure: the inverse problem's relative residual; MULF: the largest
            displacement of a static solve over the geometry's size (its bounding-box
            diagonal).
        max_iter: Newton iterations per increment (zero-pressure) or static solves (MULF).
        load_steps: pressure increments of the first solve.

    Returns:
        :class:`PrestressResult`. Differentiable: with the law's parameters JAX tracers
        (under ``jax.grad``, not ``jit``) its prestrain and ``density_scale`` are JAX
        functions of them (zero-pressure: through the adjoint of the Newton solve,
        :func:`jaxsync.zero_pressure_points`; MULF: back through its static solves, each by
        its adjoint), and ``iterations`` (zero-pressure), ``residuals`` and ``residual``,
        host quantities, are None or empty.

    Raises:
        ConvergenceError: as :func:`jaxsync.zero_pressure_geometry`, or MULF iterations that
            do not converge in ``max_iter``.
        ProblemError: bad options; a law that :class:`jaxsync.Prestressed` does not take.
    """
    from ..fem.forces._total_lagrangian import TotalLagrangian
    from ..fem.materials._prestress import Prestressed

    if method not in PRESTRESS_METHODS:
        raise ProblemError(f"method must be one of {', '.join(map(repr, PRESTRESS_METHODS))}, got {method!r}")
    for name, value in (("max_iter", max_iter), ("load_steps", load_steps)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ProblemError(f"{name} must be an integer >= 1, got {value!r}")
    if not (isinstance(tol, (int, float)) and np.isfinite(tol) and tol > 0):
        raise ProblemError(f"tol must be a positive number, got {tol!r}")
    law = problem.material
    Prestressed(law)  # refuses a law it cannot take, before any solve
    grad = TotalLagrangian().operator(problem)  # the imaged geometry's shape-function gradients
    x = problem.space.points
    if is_traced(law):
        return _traced_prestress(problem, method, grad, tol, max_iter, load_steps)
    if method == "zero-pressure":
        from ._zero_pressure import zero_pressure_geometry

        geometry = zero_pressure_geometry(problem, method="newton", tol=tol, max_iter=max_iter,
                                          load_steps=load_steps)
        # F0 = dx/dX = (dX/dx)^-1, dX/dx = I + grad_x (X - x) at the imaged points
        F0 = np.linalg.inv(np.asarray(grad.deformation_gradient(jnp.asarray(geometry.points - x))))
        return _result(problem, Prestressed(law, F0), method, geometry.iterations, geometry.residuals)
    F0s, us = _mulf(problem, grad, tol, max_iter, load_steps)
    size = float(np.linalg.norm(np.ptp(x, axis=0)))
    residuals = [float(np.abs(u).max(initial=0.0)) / size for u in us]
    return _result(problem, Prestressed(law, F0s[-1]), method, len(us), residuals)


def _traced_prestress(problem, method, grad, tol, max_iter, load_steps) -> PrestressResult:
    """:func:`prestress` of a law with traced parameters (under ``jax.grad``): F0 as a JAX
    function of them (as :func:`jaxsync.solve.static_displacement` differentiates a law)."""
    from ..fem.materials._prestress import Prestressed

    law = problem.material
    x = jnp.asarray(problem.space.points)
    grad = dataclasses.replace(grad, material=None)  # the geometry only: no traced law closed over
    if method == "zero-pressure":
        from ._zero_pressure import zero_pressure_points

        X = zero_pressure_points(problem, tol=tol, max_iter=max_iter, load_steps=load_steps)
        F0 = jnp.linalg.inv(grad.deformation_gradient(X - x))
        iterations = None
    else:
        F0, iterations = _mulf_points(problem, grad, tol, max_iter, load_steps)
    scale = 1.0 / jnp.mean(jnp.linalg.det(F0), axis=1)
    return PrestressResult(Prestressed(law, F0), method, iterations, (), None, scale)


def _mulf_points(problem, grad, tol, max_iter, load_steps):
    """(F0 (n_elements, n_q, 3, 3) of the MULF iteration as a differentiable function of the
    law's leaves, the static solves taken): the forward pass iterates on the host; the
    reverse pass runs back through the iterations, F0(k+1) = (I + grad u_k) F0(k), each
    static solve u_k(theta, F0(k)) by its adjoint (:func:`jaxsync.solve._static_adjoint.law_cotangent`)."""
    import jax

    from ..fem.materials._prestress import Prestressed
    from ._static_adjoint import law_cotangent

    leaves, treedef = jax.tree_util.tree_flatten(problem.material)
    found = {}

    def iterate(values):
        law = jax.tree_util.tree_unflatten(treedef, values)
        F0s, us = _mulf(problem.replace(material=law), grad, tol, max_iter, load_steps)
        found["iterations"] = len(us)
        return F0s, us

    @jax.custom_vjp
    def prestrain(*values):
        return jnp.asarray(iterate(values)[0][-1])

    def forward(*values):
        F0s, us = iterate(values)
        return jnp.asarray(F0s[-1]), (values, F0s, us)

    def backward(saved, cotangent):
        values, F0s, us = saved
        law = jax.tree_util.tree_unflatten(treedef, values)
        n_law = len(values)
        total = [jnp.zeros_like(jnp.asarray(v, dtype=float)) for v in values]
        bar = jnp.asarray(cotangent)  # of F0(k+1)
        for k in range(len(us) - 1, -1, -1):
            _, pullback = jax.vjp(lambda u, F0: grad.deformation_gradient(u) @ F0, jnp.asarray(us[k]),
                                  jnp.asarray(F0s[k]))
            bar_u, bar_F0 = pullback(bar)
            # the static solve u_k of the law with prestrain F0(k): its leaves are the law's, then F0
            cot = law_cotangent(problem.replace(material=Prestressed(law, F0s[k])), us[k], bar_u)
            total = [t + c for t, c in zip(total, cot[:n_law])]
            bar = bar_F0 + cot[n_law]
        return tuple(total)

    prestrain.defvjp(forward, backward)
    F0 = prestrain(*leaves)
    return F0, found.get("iterations")


def _mulf(problem, grad, tol, max_iter, load_steps):
    """The MULF iteration on the host (module docstring): (F0 before every static solve and
    the converged one, list of n + 1 arrays; the n static displacements)."""
    from ..fem.materials._prestress import Prestressed
    from ._solver import steady_state

    x = problem.space.points
    law = problem.material
    size = float(np.linalg.norm(np.ptp(x, axis=0)))
    F0s = [np.broadcast_to(np.eye(3), np.shape(grad.weights) + (3, 3)).copy()]
    us = []
    for iteration in range(1, max_iter + 1):
        current = problem.replace(material=Prestressed(law, F0s[-1]))
        try:
            u = np.asarray(steady_state(current, load_steps=load_steps if iteration == 1 else 1, tol=1e-12))
        except ConvergenceError as exc:
            raise ConvergenceError(f"the MULF prestress iteration {iteration} did not converge ({exc})",
                                   increment=iteration) from exc
        us.append(u)
        F0s.append(np.asarray(grad.deformation_gradient(jnp.asarray(u))) @ F0s[-1])
        if float(np.abs(u).max(initial=0.0)) / size <= tol:
            return F0s, us
    raise ConvergenceError(f"the MULF prestress did not converge in {max_iter} static solves: the last displaced "
                           f"the imaged geometry by {float(np.abs(us[-1]).max()) / size:.3e} of its size (tolerance "
                           f"{tol:g}); raise max_iter, or use method='zero-pressure'", increment=max_iter,
                           residual=float(np.abs(us[-1]).max()) / size)
