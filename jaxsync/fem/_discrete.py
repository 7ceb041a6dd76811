"""A problem lowered to the arrays the solver reads, once per problem.

A :class:`~jaxsync.fem.Problem` describes the physics (mesh, material, conditions,
loads); every consumer that runs or checks it needs the same arrays on the problem's
nodes: the lumped mass, the nodal loads and their time functions, the prescribed dofs and
their values, the damping. :func:`lower` computes them, and :attr:`Problem.discrete
<jaxsync.fem.Problem.discrete>` keeps the result, so that the explicit system
(:func:`~jaxsync.fem.build_system`), the parts' systems, the error estimate, the
stability bounds, a checkpoint's fingerprint and the problem's own accessors
(:meth:`~jaxsync.fem.Problem.lumped_mass`, ``load_vectors``, ``prescribed``,
``dirichlet_dofs``) all read one object instead of lowering the problem again.

Concrete values are lowered with NumPy, traced ones (a material, load magnitude or
prescribed value inside ``jax.grad``) with ``jax.numpy``: the lowered problem is a pytree
whose arrays are traced exactly where the problem's values are, so lowering a concrete
problem inside a traced function leaves no tracer behind.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..pytree import is_traced, pytree_dataclass, static_field

__all__ = ["DiscreteProblem", "lower"]


@pytree_dataclass
class DiscreteProblem:
    """A :class:`~jaxsync.fem.Problem` as arrays on its nodes (a pytree).

    Attributes:
        mass: (n_nodes,) lumped nodal mass [g]: rho times the unit lumped mass (density
            scaling included).
        load_vectors: (n_loads, n_nodes, 3) nodal forces [dyn] of the loads at full
            magnitude, on the reference configuration; follower pressures, whose forces
            follow the displacement, are not among them.
        load_times: their time functions, one per load.
        fixed: (n_nodes, 3) bool, True on prescribed dofs.
        fixed_values: (n_nodes, 3) the constant prescribed values [cm] (zero elsewhere,
            and on dofs that follow a time function).
        moving: (n_moving, n_nodes, 3) the values [cm] of each condition that follows a
            time function (zero off its dofs), or None: the prescribed displacement at t
            is ``fixed_values + sum_k moving_times[k](t) moving[k]``.
        moving_times: their time functions.
        damping: alpha [1/s].
        stiffness_damping: beta [s].
        n_nodes: solution nodes.
    """

    mass: Any
    load_vectors: Any
    load_times: tuple
    fixed: Any
    fixed_values: Any
    moving: Any
    moving_times: tuple
    damping: Any
    stiffness_damping: Any
    n_nodes: int = static_field()

    def dirichlet_dofs(self) -> tuple[np.ndarray, np.ndarray]:
        """(dofs (k,) int64 sorted, values (k,) float64) of the prescribed dofs: a
        condition that follows a time function at its full value (time factor 1), zero
        where that value is traced."""
        dofs = np.flatnonzero(np.asarray(self.fixed).reshape(-1))
        values = np.asarray(self.fixed_values, dtype=float).reshape(-1)[dofs]
        if self.moving is not None and not is_traced(self.moving):
            values = values + np.asarray(self.moving, dtype=float).sum(axis=0).reshape(-1)[dofs]
        return dofs, values


def lower(problem) -> DiscreteProblem:
    """The :class:`DiscreteProblem` of ``problem`` (use :attr:`Problem.discrete
    <jaxsync.fem.Problem.discrete>`, which lowers once)."""
    from ._assembly import lumped_mass
    from ._loads import Pressure

    n = problem.n_nodes
    rho = problem.material.rho
    unit_mass = np.asarray(lumped_mass(problem.space, problem.density_scale), dtype=float)
    mass = rho * unit_mass if is_traced(rho) else float(rho) * unit_mass
    loads = [load for load in problem.loads if not (isinstance(load, Pressure) and load.follower)]
    vectors = [problem.load_vector(load) for load in loads]
    xp = _array_module(vectors)
    load_vectors = xp.stack([xp.asarray(v, dtype=float) for v in vectors]) if vectors else np.zeros((0, n, 3))

    owner = problem.dirichlet_owner().reshape(-1, 3)
    fixed = owner >= 0
    fixed_values = np.zeros(owner.shape)
    moving, moving_times = [], []
    for k, bc in enumerate(problem.dirichlet):
        mine = owner == k
        if not mine.any():
            continue
        if bc.time is None:
            fixed_values[mine] = np.broadcast_to(np.asarray(bc.value, dtype=float), (3,))[np.nonzero(mine)[1]]
            continue
        xp = _array_module(bc.value)
        value = xp.broadcast_to(xp.asarray(bc.value, dtype=float), (3,))
        moving.append(xp.where(mine, value[None, :], 0.0))
        moving_times.append(bc.time)
    if moving:
        xp = _array_module(moving)
        moving = xp.stack(moving)
    else:
        moving = None
    fixed.setflags(write=False)
    fixed_values.setflags(write=False)
    return DiscreteProblem(mass=mass, load_vectors=load_vectors, load_times=tuple(load.time for load in loads),
                           fixed=fixed, fixed_values=fixed_values, moving=moving, moving_times=tuple(moving_times),
                           damping=problem.damping, stiffness_damping=problem.stiffness_damping, n_nodes=n)


def _array_module(values):
    """``jax.numpy`` where ``values`` hold a tracer, NumPy otherwise."""
    if is_traced(values):
        import jax.numpy as jnp

        return jnp
    return np
