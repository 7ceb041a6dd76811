"""The static solution of a hyperelastic problem as a differentiable function of its law
(:func:`static_displacement`), and the adjoint of one static solve that it and the MULF
prestress (:func:`jaxsync.prestress`) differentiate through (:func:`law_cotangent`).

:func:`jaxsync.steady_state` solves on the host (Newton with scipy's sparse LU). Its
solution u(theta) satisfies r(u, theta) = f_int(u; theta) + S u - f_ext - f_p(u) = 0 at
the free dofs (theta: the law's leaves, its moduli and, for :class:`jaxsync.Prestressed`,
its prestrain F0), so by the implicit function theorem a cotangent u-bar of u gives the
law's cotangent

    theta-bar = -(d r / d theta)^T lambda,    K_T^T lambda = u-bar (at the free dofs),

K_T = d r / d u the exact tangent of the converged solve (the law's, the supports' springs,
the follower pressures' load stiffness): one transposed sparse solve and one ``jax.vjp`` of
the internal force.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ProblemError
from ..pytree import is_traced

__all__ = ["static_displacement", "law_cotangent", "differentiable_in_law"]


def _tangent(problem, u):
    """d r / d u (scipy CSR) of ``problem`` at u (n_nodes, 3): the law's tangent, the
    springs, the follower pressures' load stiffness (loads at full magnitude)."""
    from ..fem.forces._follower import full_follower_pressure, load_stiffness
    from ..fem.forces._support import spring_matrix
    from ..fem.forces._total_lagrangian import TotalLagrangian, tangent_matrix

    K = tangent_matrix(TotalLagrangian().operator(problem), u)
    springs = spring_matrix(problem)
    follower = full_follower_pressure(problem)
    if springs is not None:
        K = K + springs
    if follower is not None:
        K = K + load_stiffness(follower, u)
    return K.tocsr()


def law_cotangent(problem, u, cotangent) -> list:
    """The cotangents of ``problem.material``'s leaves (``jax.tree_util.tree_leaves`` order)
    of a scalar whose cotangent in the converged static displacement u (n_nodes, 3) [cm] of
    ``problem`` (concrete) is ``cotangent`` (n_nodes, 3) (module docstring)."""
    import scipy.sparse.linalg as spla

    from ..fem.forces._total_lagrangian import TotalLagrangian

    u = np.asarray(u, dtype=float)
    fixed, _ = problem.dirichlet_dofs()
    free = np.setdiff1d(np.arange(u.size), fixed)
    K = _tangent(problem, u)[free][:, free]
    try:
        factor = spla.splu(K.T.tocsc())
    except RuntimeError as exc:  # SuperLU: "Factor is exactly singular"
        raise ProblemError("the static problem is singular: the Dirichlet conditions do not prevent rigid-body "
                           "motion; clamp more nodes") from exc
    adjoint = np.zeros(u.size)
    adjoint[free] = factor.solve(np.asarray(cotangent, dtype=float).reshape(-1)[free])
    leaves, treedef = jax.tree_util.tree_flatten(problem.material)

    def force(values):
        law = jax.tree_util.tree_unflatten(treedef, values)
        return TotalLagrangian().operator(problem.replace(material=law)).matvec(jnp.asarray(u))

    values = [jnp.asarray(v, dtype=float) for v in leaves]
    return list(jax.vjp(force, values)[1](jnp.asarray(-adjoint.reshape(u.shape)))[0])


def static_displacement(problem, *, load_steps: int | None = None, tol: float = 1e-10, max_iter: int = 25):
    """(n_nodes, 3) the static displacement [cm] of a hyperelastic ``problem``, as
    :func:`jaxsync.steady_state` finds it, differentiable in the law's leaves
    (``problem.material``'s parameters and, for :class:`jaxsync.Prestressed`, its
    prestrain may be JAX tracers under ``jax.grad``, not under ``jit``): the reverse pass is
    the adjoint of the converged solve (module docstring).

    Raises:
        as :func:`jaxsync.steady_state`; ProblemError for a small-strain law (its
        derivative needs no Newton solve: differentiate K^-1 f directly).
    """
    if not problem.material.finite_strain:
        raise ProblemError(f"static_displacement differentiates the Newton solve of a hyperelastic law, got "
                           f"{type(problem.material).__name__}: use jaxsync.steady_state")
    from ._solver import steady_state

    return differentiable_in_law(
        problem, lambda p: steady_state(p, load_steps=load_steps, tol=tol, max_iter=max_iter), law_cotangent,
        "static_displacement")


def differentiable_in_law(problem, solve, cotangent, name: str):
    """``solve(problem)`` -- an array computed on the host from a concrete problem (a Newton
    solve) -- as a function JAX differentiates in the leaves of ``problem.material`` (JAX
    tracers under ``jax.grad``, not under ``jit``): the reverse pass is
    ``cotangent(problem, result, result_bar)``, the list of the leaves' cotangents (an
    adjoint solve at the converged result). Over the law's leaves, not the law: a
    cotangent is no valid law (a zero density...). ``name`` is the function named in the
    error where it is traced under ``jit``."""
    leaves, treedef = jax.tree_util.tree_flatten(problem.material)

    def concrete(values):
        if is_traced(values):
            raise ProblemError(f"{name} solves on the host: differentiate it with jax.grad (or jax.vjp) outside jit")
        return problem.replace(material=jax.tree_util.tree_unflatten(treedef, values))

    @jax.custom_vjp
    def result(*values):
        return jnp.asarray(solve(concrete(values)))

    def forward(*values):
        found = result(*values)
        return found, (values, found)

    def backward(saved, result_bar):
        values, found = saved
        return tuple(cotangent(concrete(values), found, result_bar))

    result.defvjp(forward, backward)
    return result(*leaves)
