"""The pure explicit stepper: central differences with lumped mass (paper eq. 7).

With lumped mass M and C = alpha M the update is, per dof,

    d(n+1) = [dt^2 (f(t_n) - K d(n)) / m + 2 d(n) - (1 - alpha dt / 2) d(n-1)]
             / (1 + alpha dt / 2),

with Dirichlet values imposed after every update (their values at t_(n+1): a
prescribed displacement may follow a time function). Elastic supports
(:mod:`jaxsync.fem.forces`) add their springs to K d and their lumped dashpots B to the
damping, C = alpha M + B; the update is then, node by node, the 3 x 3 solve

    (m (1 + alpha dt / 2) I + dt / 2 B) d(n+1)
        = dt^2 (f - K d(n)) + m (2 d(n) - (1 - alpha dt / 2) d(n-1)) + dt / 2 B d(n-1).

``f`` is evaluated at the time of the current displacement d(n), as in the paper's published code. The start follows the
paper: a0 from the consistent-mass system, d(-1) = d0 - dt v0 + dt^2/2 a0.

Stiffness-proportional (Rayleigh) damping, C = alpha M + beta K (``Problem.stiffness_damping``
= beta [s]): its force beta K v is taken with the backward velocity v = (d(n) - d(n-1)) / dt
and added to the internal force before any exchange, which keeps the update explicit and
the same (K d(n) above becomes K d(n) + beta K v). For a linear law that is one product,
K (d(n) + (beta / dt) (d(n) - d(n-1))); a hyperelastic law adds the viscous stress
beta dP/dF[grad v] in its element kernel
(:meth:`jaxsync.fem.forces.HyperelasticForce.damped_matvec`), so no global
tangent is formed. The supports' springs count in K; the follower pressures (loads) do
not. Partial forces of parts, deep halos and predicted shared values (the
synchronization-avoiding phase, whose overwritten d(n) and d(n-1) give v there) all
follow. The stable step drops to sqrt((2 / omega_max)^2 + beta^2) - beta
(:func:`jaxsync.fem.damped_bound`).

State is explicit (:class:`SolverState`); :func:`step` is a pure function and
:func:`advance` runs it in a ``lax.scan``. The host drivers that call them, for one
device (:mod:`jaxsync.solve`) and for parts under ``shard_map``
(:mod:`jaxsync.solve.executors`), both build on this module.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

from ..pytree import pytree_dataclass
from ._sparse import BlockEll, in_compact_form
from .forces._support import apply_dashpot, dashpot, dashpot_blocks, surface_spring

__all__ = ["ExplicitSystem", "SolverState", "build_system", "initial_state", "start_levels", "step", "internal_forces",
           "internal_forces_and_variables", "backward_velocity",
           "central_difference", "apply_dirichlet", "prescribed_values", "external_force", "advance", "Probe",
           "STEP_UNROLL"]


@pytree_dataclass
class ExplicitSystem:
    """Everything one explicit step needs, as JAX arrays (a pytree).

    Attributes:
        stiffness: the internal-force operator, ``stiffness.matvec(u)`` = f_int(u) [dyn]
            (:mod:`jaxsync.fem.forces`: K in node-blocked ELL form, or formed
            element by element).
        mass: (n_nodes, 3) lumped mass per dof [g].
        damping: alpha [1/s].
        dt: time step [s].
        load_vectors: (n_loads, n_nodes, 3) full-magnitude nodal loads [dyn].
        load_times: tuple of time functions g_l(t), one per load.
        fixed: (n_nodes, 3) bool, True on prescribed dofs.
        fixed_values: (n_nodes, 3) constant prescribed values there [cm] (zero elsewhere).
        moving: (n_moving, n_nodes, 3) prescribed values of the conditions that follow a
            time function [cm] (zero elsewhere), or None: the prescribed displacement at t
            is ``fixed_values + sum_k moving_times[k](t) moving[k]``.
        moving_times: tuple of their time functions.
        spring: the elastic supports' springs (:class:`jaxsync.fem.forces.SurfaceSpring`),
            or None.
        dashpot: the update with the supports' dashpots
            (:class:`jaxsync.fem.forces.Dashpot`), or None.
        follower: the follower pressures, loads that depend on the displacement
            (:class:`jaxsync.fem.forces.FollowerPressure`), or None.
        stiffness_damping: beta [s] of the stiffness-proportional damping beta K, or None
            (the problem has none: the step is that of C = alpha M alone).
    """

    stiffness: BlockEll
    mass: Any
    damping: Any
    dt: Any
    load_vectors: Any
    load_times: tuple
    fixed: Any
    fixed_values: Any
    moving: Any = None
    moving_times: tuple = ()
    spring: Any = None
    dashpot: Any = None
    follower: Any = None
    stiffness_damping: Any = None


@pytree_dataclass
class SolverState:
    """State of the two-step scheme.

    Attributes:
        displacement: (n_nodes, 3) d(n) [cm].
        previous: (n_nodes, 3) d(n-1) [cm].
        step: n (int); the time is n * dt.
        internal: the material law's internal variables, {name: (n_elements, n_points,
            ...) array} at the quadrature points
            (:meth:`jaxsync.fem.materials.MaterialLaw.internal_variables`), as the
            force of d(n-1) left them; {} (the default) for a law without state. A
            part's state holds those of its own elements (padded to the largest part);
            they are never exchanged.
    """

    displacement: Any
    previous: Any
    step: Any
    internal: Any = dataclasses.field(default_factory=dict)


def build_system(problem, dt, mode="preassembled") -> ExplicitSystem:
    """Assemble the JAX-side system of ``problem`` for time step ``dt`` [s].

    ``mode``: the internal force's model (:func:`jaxsync.fem.forces.force_model`:
    ``"preassembled"``, K stored in node-blocked ELL form, or ``"recompute"``, element
    quantities formed every step, paper Remark 2; or a force model itself).
    Traceable in the material, damping (alpha and beta), load magnitudes and dt
    (differentiable).

    Raises:
        ProblemError: stiffness-proportional damping with a force model whose operator
            has no ``damped_matvec`` (the damping force beta K_T(u) v)."""
    from ..errors import ProblemError
    from .forces._follower import follower_pressure
    from .forces._internal_force import force_model

    stiffness = force_model(mode).operator(problem)
    lowered = problem.discrete  # the mass, loads, prescribed values and damping, lowered once per problem
    beta = None
    if problem.stiffness_damped:
        if not hasattr(stiffness, "damped_matvec"):
            raise ProblemError(f"stiffness_damping={problem.stiffness_damping} needs the damping force beta K v, "
                               f"but the force model {mode!r} gives an operator ({type(stiffness).__name__}) without "
                               "damped_matvec(u, velocity, beta): add that method, or set stiffness_damping=0")
        beta = jnp.asarray(lowered.stiffness_damping, dtype=float)
    mass = jnp.repeat(jnp.asarray(lowered.mass, dtype=float)[:, None], 3, axis=1)
    damping, dt = jnp.asarray(lowered.damping, dtype=float), jnp.asarray(dt, dtype=float)
    fixed = jnp.asarray(lowered.fixed)
    blocks = dashpot_blocks(problem)
    return ExplicitSystem(
        stiffness=stiffness, mass=mass, damping=damping, dt=dt,
        load_vectors=jnp.asarray(lowered.load_vectors, dtype=float), load_times=lowered.load_times,
        fixed=fixed, fixed_values=jnp.asarray(lowered.fixed_values),
        moving=None if lowered.moving is None else jnp.asarray(lowered.moving, dtype=float),
        moving_times=lowered.moving_times,
        spring=surface_spring(problem),
        dashpot=None if blocks is None else dashpot(mass, damping, dt, blocks, fixed),
        follower=follower_pressure(problem), stiffness_damping=beta)


def external_force(system: ExplicitSystem, t):
    """(n_nodes, 3) external nodal force at time t [dyn]: sum_l g_l(t) F_l."""
    force = jnp.zeros_like(system.mass)
    for k, g in enumerate(system.load_times):
        force = force + g(t) * system.load_vectors[k]
    return force


def central_difference(system: ExplicitSystem, state: SolverState, internal_force):
    """d(n+1) before Dirichlet values are imposed, given K d(n) = ``internal_force``."""
    dt = system.dt
    f = external_force(system, jnp.asarray(state.step, dtype=dt.dtype) * dt)
    half_damp = 0.5 * system.damping * dt
    if system.dashpot is not None:
        rhs = dt * dt * (f - internal_force) + system.mass * (2.0 * state.displacement
                                                              - (1.0 - half_damp) * state.previous)
        t_new = jnp.asarray(state.step + 1, dtype=dt.dtype) * dt
        return apply_dashpot(system.dashpot, rhs, state.previous, prescribed_values(system, t_new))
    return (dt * dt * (f - internal_force) / system.mass + 2.0 * state.displacement
            - (1.0 - half_damp) * state.previous) / (1.0 + half_damp)


def prescribed_values(system: ExplicitSystem, t):
    """(n_nodes, 3) prescribed displacement at time ``t`` [cm] (meaningful on the fixed
    dofs only): the constant values plus the moving conditions' values times their time
    functions."""
    values = system.fixed_values
    for k, g in enumerate(system.moving_times):
        values = values + g(t) * system.moving[k]
    return values


def apply_dirichlet(system: ExplicitSystem, displacement, t):
    """``displacement`` (n_nodes, 3) with the prescribed values at time ``t`` [s] written in."""
    return jnp.where(system.fixed, prescribed_values(system, t), displacement)


def internal_forces(system: ExplicitSystem, displacement, t=0.0, velocity=None):
    """(n_nodes, 3) K d [dyn]: the internal force of the (part's) elements plus the
    supports' springs, minus the follower pressures at time ``t`` [s] (the loads that
    depend on the displacement, on the part's own facets), before any exchange. A law
    with internal variables: its force from rest (its ``first_piola``). With a
    ``velocity`` v (n_nodes, 3) [cm/s] and the system's stiffness-proportional damping
    beta, plus the damping force beta K v (module docstring)."""
    damped = velocity is not None and system.stiffness_damping is not None
    force = (system.stiffness.damped_matvec(displacement, velocity, system.stiffness_damping) if damped
             else system.stiffness.matvec(displacement))
    return _springs_and_followers(system, displacement, force, t, velocity if damped else None)


def backward_velocity(system: ExplicitSystem, state: SolverState):
    """(n_nodes, 3) v = (d(n) - d(n-1)) / dt [cm/s], the velocity the damping force beta K v
    of a step uses, or None without stiffness-proportional damping."""
    if system.stiffness_damping is None:
        return None
    return (state.displacement - state.previous) / system.dt


def internal_forces_and_variables(system: ExplicitSystem, state: SolverState, t):
    """(K d(n) as :func:`internal_forces` computes it, with the damping force beta K v of
    the :func:`backward_velocity`, if any; the internal variables after it): a law with
    state updates its variables in the element kernel, with the force
    (``stiffness.update(u, internal, dt)``, :class:`jaxsync.fem.forces.HyperelasticForce`);
    a law without any returns them (empty) as they are."""
    velocity = backward_velocity(system, state)
    if not jax.tree_util.tree_leaves(state.internal):  # no state: the elastic kernel
        return internal_forces(system, state.displacement, t, velocity), state.internal
    if velocity is None:
        force, internal = system.stiffness.update(state.displacement, state.internal, system.dt)
    else:
        force, internal = system.stiffness.update(state.displacement, state.internal, system.dt, velocity,
                                                  system.stiffness_damping)
    return _springs_and_followers(system, state.displacement, force, t, velocity), internal


def _springs_and_followers(system: ExplicitSystem, displacement, force, t, velocity=None):
    """The elements' ``force`` plus the supports' springs (with their damping force
    beta S v when a ``velocity`` is given), minus the follower pressures."""
    if system.spring is not None:
        at = displacement if velocity is None else displacement + system.stiffness_damping * velocity
        force = force + system.spring.matvec(at)
    if system.follower is not None:
        force = force - system.follower.force(displacement, t)
    return force


def step(system: ExplicitSystem, state: SolverState, synchronize=None, overwrite=None, probe=None):
    """One central-difference step: (d(n), d(n-1), n) -> (d(n+1), d(n), n + 1).

    ``synchronize``, when given, maps the (partial) internal force K d of a part to the
    full one (the distributed solver's psum); the single-device solver needs none.
    ``overwrite``, when given, maps the updated displacement to the one kept before the
    Dirichlet values are imposed (the synchronization-avoiding solver writes its
    predicted shared-node displacements there).
    ``probe``, when given, is called as ``probe(state, internal, updated, new_state)``
    with the internal force the step used and the update before the overwrite; the step
    then returns ``(new_state, probe's value)`` (the synchronization-avoiding solver's
    force-balance defect, :func:`jaxsync.solve.executors.overwritten_steps`)."""
    t = jnp.asarray(state.step, dtype=system.dt.dtype) * system.dt
    internal, variables = internal_forces_and_variables(system, state, t)
    if synchronize is not None:
        internal = synchronize(internal)
    updated = central_difference(system, state, internal)
    new = updated if overwrite is None else overwrite(updated)
    t_new = jnp.asarray(state.step + 1, dtype=system.dt.dtype) * system.dt
    new_state = SolverState(apply_dirichlet(system, new, t_new), state.displacement, state.step + 1, variables)
    return new_state if probe is None else (new_state, probe(state, internal, updated, new_state))


def initial_state(problem, system: ExplicitSystem) -> SolverState:
    """The paper's start: a0 solves M a0 = f(0) - C v0 - K d0 with the CONSISTENT mass
    (C v0 = alpha M v0 + beta K v0 + the dashpots' B v0)
    (Dirichlet rows and columns replaced by the identity, so a0 = 0 there), then
    d(-1) = d0 - dt v0 + dt^2 / 2 a0. Solved by conjugate gradients (differentiable).

    Prescribed displacements that follow a time function g start consistent with it:
    d0 = g(0) and d(-1) = g(-dt) on their dofs, and their velocity and acceleration at t = 0
    (central differences of g over one step) enter the free dofs' a0 through the damping
    and the consistent mass."""
    from ._assembly import consistent_mass
    from ._sparse import block_ell_values

    n = problem.n_nodes
    d0 = jnp.zeros((n, 3)) if problem.initial_displacement is None else jnp.asarray(
        problem.initial_displacement, dtype=float)
    v0 = jnp.zeros((n, 3)) if problem.initial_velocity is None else jnp.asarray(
        problem.initial_velocity, dtype=float)
    adjacency, _, _, M_1 = problem.operators.block_ell
    if problem.density_scale is not None:
        M_1 = block_ell_values(consistent_mass(problem.mesh, problem.density_scale), adjacency)
    mass = BlockEll(jnp.asarray(adjacency), problem.material.rho * jnp.asarray(M_1), symmetric=True)
    d0, previous = start_levels(system, mass, d0, v0)
    from ._reference_element import n_quadrature_points

    variables = problem.material.internal_variables(problem.mesh.n_elements, n_quadrature_points(problem.space))
    return SolverState(d0, previous, jnp.asarray(0, dtype=jnp.int32), variables)


@jax.jit
def start_levels(system: ExplicitSystem, mass: BlockEll, d0, v0):
    """(d0, d(-1)) (n_nodes, 3) [cm] of :func:`initial_state`: the initial displacement
    ``d0`` with its Dirichlet values and the level before it from the initial velocity
    ``v0`` [cm/s] and the acceleration of the consistent ``mass`` (conjugate gradients),
    as one compiled program (op by op, its conjugate gradients compiled a hundred small
    programs); ``jax.vmap`` over runs gives an ensemble's starts."""
    # A one-shot program: its compilation, not its few dozen products, is the cost, so its
    # operators take the compact product whatever form the run's steps use (a coronary tree
    # of 3 481 tets: 6.9 s -> 1.7 s to compile and run at XLA's default level).
    system = dataclasses.replace(system, stiffness=in_compact_form(system.stiffness))
    mass = in_compact_form(mass)
    dt = system.dt
    d0 = apply_dirichlet(system, d0, 0.0)
    free = 1.0 - system.fixed.astype(float)
    accel_fixed = None
    if system.moving_times:  # the prescribed history's velocity and acceleration at t = 0
        before, now, after = (prescribed_values(system, t) for t in (-dt, 0.0, dt))
        v0 = jnp.where(system.fixed, (after - before) / (2.0 * dt), v0)
        accel_fixed = (1.0 - free) * (after - 2.0 * now + before) / (dt * dt)
    # with stiffness-proportional damping, C v0 includes beta K v0 (the tangent at d0)
    rhs = external_force(system, 0.0) - system.damping * mass.matvec(v0) - internal_forces(system, d0, 0.0, v0)
    if system.dashpot is not None:  # the supports' dashpots, B v0 (B = coupling / (dt / 2))
        rhs = rhs - jnp.einsum("nij,nj->ni", system.dashpot.coupling, v0) / (0.5 * dt)
    if accel_fixed is not None:
        rhs = rhs - mass.matvec(accel_fixed)
    rhs = free * rhs

    def operator(x):
        return free * mass.matvec(free * x) + (1.0 - free) * x

    # The consistent P1 mass is well conditioned: CG converges in a few dozen iterations.
    a0, _ = jax.scipy.sparse.linalg.cg(operator, rhs, tol=1e-14, maxiter=1000)
    return d0, apply_dirichlet(system, d0 - dt * v0 + 0.5 * dt * dt * a0, -dt)


class Probe(NamedTuple):
    """What :func:`advance` measures besides the saved displacements: ``per_step(state,
    internal, updated, new_state)`` after every step (a pytree), summed from
    ``initial(state)`` over each ``save_every`` steps, and ``finish(sum)`` of each sum,
    kept once per saved step (it may hold a collective: one per saved step)."""

    per_step: Callable
    initial: Callable
    finish: Callable


STEP_UNROLL = 2
"""Steps per iteration of the compiled time loop. With one step per iteration the carry
(d(n), d(n-1)) -> (d(n+1), d(n)) hands d(n) to another slot of the loop state, and XLA
copies the displacement fields (three (n_nodes, 3) copies per step, about 10 % of the
step's memory traffic); with two steps per iteration both outgoing fields are freshly
computed and the copies disappear. Results are bit-identical."""


def advance(system: ExplicitSystem, state: SolverState, n_saves: int, save_every: int,
            synchronize=None, record=None, overwrite=None, probe=None):
    """Run ``n_saves * save_every`` steps; returns (final state, (n_saves, n_nodes, 3)
    displacements after every ``save_every`` steps). Pure; jit it at the call site. The
    one time loop of every solver: synchronized, distributed and predicted.

    ``synchronize``: see :func:`step`. ``overwrite(j, new)``, when given, is the
    overwrite of :func:`step` at the j-th step of this call (j = 0, 1, ...): the
    synchronization-avoiding solver writes its prediction for that step there.
    ``record``, when given, maps a state to a small array kept after EVERY step (the
    distributed solver records its shared-node displacements, the surrogates' training
    data, while the full field is kept only every ``save_every`` steps); the second
    output is then the pair (saved, recorded (n_saves * save_every, ...)).
    ``probe``, when given (not with ``record``), is a :class:`Probe`: its ``per_step``
    values summed over each ``save_every`` steps and ``finish`` applied to each sum; the
    second output is then the pair (saved, probed (n_saves, ...)).
    """
    # the step index is a loop input only when an overwrite reads it
    indices = None if overwrite is None else (lambda first, n: first + jnp.arange(n))
    if probe is not None and record is not None:
        raise ValueError("advance: give record or probe, not both")

    def inner(s, j):
        change = None if overwrite is None else functools.partial(overwrite, j)
        if probe is None:
            s = step(system, s, synchronize, change)
            return s, None if record is None else record(s)
        s, total = s
        s, value = step(system, s, synchronize, change, probe.per_step)
        return (s, jax.tree_util.tree_map(jnp.add, total, value)), None

    def block(s, js, length):
        """``length`` steps, then the saved displacement and what is kept of them."""
        if probe is None:
            s, kept = jax.lax.scan(inner, s, js, length=length, unroll=STEP_UNROLL)
            return s, (s.displacement, kept)
        (s, total), _ = jax.lax.scan(inner, (s, probe.initial(s)), js, length=length, unroll=STEP_UNROLL)
        return s, (s.displacement, probe.finish(total))

    def outer(s, k):
        return block(s, None if indices is None else indices(k * save_every, save_every), save_every)

    ks = None if indices is None else indices(0, n_saves)
    if save_every == 1 and probe is None:  # without a loop of length 1 in each step
        def saved_step(s, j):
            s, kept = inner(s, j)
            return s, (s.displacement, kept)

        state, (saved, kept) = jax.lax.scan(saved_step, state, ks, length=n_saves, unroll=STEP_UNROLL)
    else:
        state, (saved, kept) = jax.lax.scan(outer, state, ks, length=n_saves)
        if record is not None:
            kept = kept.reshape(n_saves * save_every, *kept.shape[2:])
    return state, (saved if record is None and probe is None else (saved, kept))
