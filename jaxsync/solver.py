"""Single-device explicit solver: central differences with lumped mass (paper eq. 7).

With lumped mass M and C = alpha M the update is, per dof,

    d(n+1) = [dt^2 (f(t_n) - K d(n)) / m + 2 d(n) - (1 - alpha dt / 2) d(n-1)]
             / (1 + alpha dt / 2),

with Dirichlet values imposed after every update. ``f`` is evaluated at the time of the
current displacement d(n), as in the paper's published code. The start follows the
paper: a0 from the consistent-mass system, d(-1) = d0 - dt v0 + dt^2/2 a0.

State is explicit (:class:`SolverState`); :func:`step` is a pure function; the driver
:func:`simulate` runs it in compiled ``lax.scan`` chunks, saves every ``save_every``
steps, shows progress, checks for divergence and checkpoints between chunks.
"""

from __future__ import annotations

import hashlib
import math
import os
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .errors import CheckpointError, ProblemError, StabilityError
from .pytree import is_traced, pytree_dataclass, static_field
from .sparse import BlockEll

__all__ = ["ExplicitSystem", "SolverState", "build_system", "initial_state", "step",
           "central_difference", "apply_dirichlet", "external_force", "advance",
           "simulate", "steady_state"]


@pytree_dataclass
class ExplicitSystem:
    """Everything one explicit step needs, as JAX arrays (a pytree).

    Attributes:
        stiffness: K in node-blocked ELL form [dyn/cm].
        mass: (n_nodes, 3) lumped mass per dof [g].
        damping: alpha [1/s].
        dt: time step [s].
        load_vectors: (n_loads, n_nodes, 3) full-magnitude nodal loads [dyn].
        load_times: tuple of time functions g_l(t), one per load.
        dirichlet_dofs: (k,) flat dof indices (3 * node + component).
        dirichlet_values: (k,) prescribed values [cm].
    """

    stiffness: BlockEll
    mass: Any
    damping: Any
    dt: Any
    load_vectors: Any
    load_times: tuple
    dirichlet_dofs: Any
    dirichlet_values: Any


@pytree_dataclass
class SolverState:
    """State of the two-step scheme.

    Attributes:
        displacement: (n_nodes, 3) d(n) [cm].
        previous: (n_nodes, 3) d(n-1) [cm].
        step: n (int); the time is n * dt.
    """

    displacement: Any
    previous: Any
    step: Any


def build_system(problem, dt) -> ExplicitSystem:
    """Assemble the JAX-side system of ``problem`` for time step ``dt`` [s].

    Traceable in the material, damping, load magnitudes and dt (differentiable)."""
    adjacency, K_lambda, K_mu, _ = problem.operators.block_ell
    m = problem.material
    blocks = m.lam * jnp.asarray(K_lambda) + m.mu * jnp.asarray(K_mu)
    mass = jnp.repeat(jnp.asarray(problem.lumped_mass())[:, None], 3, axis=1)
    vectors, times = problem.load_vectors()
    n = problem.mesh.n_nodes
    load_vectors = jnp.stack(vectors) if vectors else jnp.zeros((0, n, 3))
    dofs, values = problem.dirichlet_dofs()
    return ExplicitSystem(
        stiffness=BlockEll(jnp.asarray(adjacency), blocks), mass=mass,
        damping=jnp.asarray(problem.damping, dtype=float), dt=jnp.asarray(dt, dtype=float),
        load_vectors=load_vectors, load_times=tuple(times),
        dirichlet_dofs=jnp.asarray(dofs, dtype=jnp.int32),
        dirichlet_values=jnp.asarray(values, dtype=float))


def external_force(system: ExplicitSystem, t):
    """(n_nodes, 3) external nodal force at time t [dyn]: sum_l g_l(t) F_l."""
    force = jnp.zeros_like(system.mass)
    for l, g in enumerate(system.load_times):
        force = force + g(t) * system.load_vectors[l]
    return force


def central_difference(system: ExplicitSystem, state: SolverState, internal_force):
    """d(n+1) before Dirichlet values are imposed, given K d(n) = ``internal_force``."""
    dt = system.dt
    f = external_force(system, state.step * dt)
    half_damp = 0.5 * system.damping * dt
    return (dt * dt * (f - internal_force) / system.mass + 2.0 * state.displacement
            - (1.0 - half_damp) * state.previous) / (1.0 + half_damp)


def apply_dirichlet(system: ExplicitSystem, displacement):
    """``displacement`` (n_nodes, 3) with the prescribed values written in."""
    flat = displacement.reshape(-1).at[system.dirichlet_dofs].set(system.dirichlet_values)
    return flat.reshape(displacement.shape)


def step(system: ExplicitSystem, state: SolverState) -> SolverState:
    """One central-difference step: (d(n), d(n-1), n) -> (d(n+1), d(n), n + 1)."""
    new = central_difference(system, state, system.stiffness.matvec(state.displacement))
    return SolverState(apply_dirichlet(system, new), state.displacement, state.step + 1)


def initial_state(problem, system: ExplicitSystem) -> SolverState:
    """The paper's start: a0 solves M a0 = f(0) - C v0 - K d0 with the CONSISTENT mass
    (Dirichlet rows and columns replaced by the identity, so a0 = 0 there), then
    d(-1) = d0 - dt v0 + dt^2 / 2 a0. Solved by conjugate gradients (differentiable)."""
    from .assembly import consistent_mass
    from .sparse import block_ell_values

    n = problem.mesh.n_nodes
    d0 = jnp.zeros((n, 3)) if problem.initial_displacement is None else jnp.asarray(
        problem.initial_displacement, dtype=float)
    v0 = jnp.zeros((n, 3)) if problem.initial_velocity is None else jnp.asarray(
        problem.initial_velocity, dtype=float)
    d0 = apply_dirichlet(system, d0)
    free = jnp.ones(3 * n).at[system.dirichlet_dofs].set(0.0).reshape(n, 3)
    adjacency, _, _, M_1 = problem.operators.block_ell
    if problem.density_scale is not None:
        M_1 = block_ell_values(consistent_mass(problem.mesh, problem.density_scale), adjacency)
    mass = BlockEll(jnp.asarray(adjacency), problem.material.rho * jnp.asarray(M_1))
    rhs = external_force(system, 0.0) - system.damping * mass.matvec(v0) - system.stiffness.matvec(d0)
    rhs = free * rhs

    def operator(x):
        return free * mass.matvec(free * x) + (1.0 - free) * x

    # The consistent P1 mass is well conditioned: CG converges in a few dozen iterations.
    a0, _ = jax.scipy.sparse.linalg.cg(operator, rhs, tol=1e-14, maxiter=1000)
    dt = system.dt
    previous = apply_dirichlet(system, d0 - dt * v0 + 0.5 * dt * dt * a0)
    return SolverState(d0, previous, jnp.asarray(0, dtype=jnp.int32))


def advance(system: ExplicitSystem, state: SolverState, n_saves: int, save_every: int):
    """Run ``n_saves * save_every`` steps; returns (final state, (n_saves, n_nodes, 3)
    displacements after every ``save_every`` steps). Pure; jit it at the call site."""

    def inner(s, _):
        return step(system, s), None

    def outer(s, _):
        s, _ = jax.lax.scan(inner, s, None, length=save_every)
        return s, s.displacement

    return jax.lax.scan(outer, state, None, length=n_saves)


_advance_jit = jax.jit(advance, static_argnums=(2, 3))


def steady_state(problem) -> np.ndarray:
    """Static solution K u = f with every load at full magnitude (time factor 1) and the
    Dirichlet values imposed; (n_nodes, 3) [cm]. Direct sparse solve (scipy)."""
    import scipy.sparse.linalg as spla

    m = problem.material
    K = problem.operators.stiffness(m.lam, m.mu)
    vectors, _ = problem.load_vectors()
    f = np.zeros(problem.mesh.n_dofs)
    for v in vectors:
        f += np.asarray(v, dtype=float).reshape(-1)
    fixed, values = problem.dirichlet_dofs()
    free = np.setdiff1d(np.arange(K.shape[0]), fixed)
    u = np.zeros(K.shape[0])
    u[fixed] = values
    rhs = f[free] - K[free][:, fixed] @ values
    singular = ProblemError("the static problem is singular: the Dirichlet conditions do not "
                            "prevent rigid-body motion; clamp more nodes")
    K_free = K[free][:, free].tocsc()
    try:
        u[free] = spla.splu(K_free).solve(rhs)
    except RuntimeError as exc:  # SuperLU: "Factor is exactly singular"
        raise singular from exc
    residual = np.linalg.norm(K_free @ u[free] - rhs)
    if not np.all(np.isfinite(u)) or residual > 1e-8 * max(np.linalg.norm(rhs), 1e-300):
        raise singular
    return u.reshape(-1, 3)


def _fingerprint(problem, dt: float, save_every: int) -> str:
    """Hash of everything that determines a trajectory, to refuse foreign checkpoints."""
    h = hashlib.sha256()
    mesh = problem.mesh
    for arr in (mesh.points, mesh.tets):
        h.update(np.ascontiguousarray(arr).tobytes())
    m = problem.material
    dofs, values = problem.dirichlet_dofs()
    h.update(np.asarray([float(m.E), float(m.nu), float(m.rho), float(problem.damping), dt,
                         save_every], dtype=float).tobytes())
    h.update(dofs.tobytes())
    h.update(values.tobytes())
    for v in problem.load_vectors()[0]:
        h.update(np.asarray(v, dtype=float).tobytes())
    for ic in (problem.initial_displacement, problem.initial_velocity, problem.density_scale):
        if ic is not None:
            h.update(np.asarray(ic, dtype=float).tobytes())
    return h.hexdigest()


def simulate(problem, n_steps: int, *, dt=None, save_every: int = 1, progress: bool | None = None,
             checkpoint: str | os.PathLike | None = None, checkpoint_every: int | None = None,
             chunk_steps: int = 5000, blowup_factor: float = 1e3, check_stability: bool = True):
    """Integrate ``problem`` for ``n_steps`` explicit steps.

    Args:
        problem: a :class:`jaxsync.Problem`.
        n_steps: number of time steps (a multiple of ``save_every``).
        dt: time step [s]; default ``problem.dt`` (the paper's CFL rule). A dt above the
            CFL step is checked against the exact bound 2/omega_max and refused above it.
        save_every: keep the displacement every this many steps (and at t = 0).
        progress: show a tqdm progress bar (default: when n_steps >= 20000).
        checkpoint: HDF5 path for resumable runs: the state is stored there every
            ``checkpoint_every`` steps (rounded up to whole chunks), and a run started
            again with the same problem continues from it, giving the same trajectory.
        chunk_steps: steps per compiled chunk, between progress/divergence checks.
        blowup_factor: a displacement larger than this times the mesh's bounding-box
            diagonal counts as divergence.
        check_stability: set False to force a dt through without the bound check.

    Returns:
        :class:`jaxsync.Trajectory` with ``n_steps // save_every + 1`` snapshots.

    Raises:
        StabilityError: dt above the bound, or the run diverged (NaN/Inf or blow-up); the
            error's ``trajectory`` attribute holds the snapshots saved before divergence.
        CheckpointError: the checkpoint file belongs to another problem or is corrupt.

    Differentiable: when the material, damping, loads or dt are JAX tracers (inside
    ``jax.grad``), the whole run is one ``lax.scan`` without progress, divergence checks or
    checkpoints, and the trajectory holds JAX arrays.
    """
    from .trajectory import Trajectory

    n_steps, save_every = int(n_steps), int(save_every)
    if n_steps < 0 or save_every < 1:
        raise ProblemError(f"need n_steps >= 0 and save_every >= 1, got {n_steps}, {save_every}")
    if n_steps % save_every:
        raise ProblemError(f"n_steps={n_steps} is not a multiple of save_every={save_every}; "
                           f"use n_steps={n_steps - n_steps % save_every + save_every}")
    dt = problem.dt if dt is None else dt
    traced = is_traced(problem.material, problem.damping, problem.loads, dt,
                       problem.initial_displacement, problem.initial_velocity)
    if not traced and check_stability:
        from .timestep import check_dt

        check_dt(problem, dt)
    system = build_system(problem, dt)
    state = initial_state(problem, system)
    n_saves = n_steps // save_every
    if traced:
        _, saved = advance(system, state, n_saves, save_every)
        displacement = jnp.concatenate([state.displacement[None], saved])
        times = jnp.arange(n_saves + 1) * save_every * system.dt
        return Trajectory(times=times, displacement=displacement, mesh=problem.mesh,
                          dt=dt, save_every=save_every, parameters=_parameters(problem))

    dt = float(dt)
    saves_per_chunk = max(1, int(chunk_steps) // save_every)
    snapshots = [np.asarray(state.displacement)[None]]
    fingerprint = _fingerprint(problem, dt, save_every)
    if checkpoint is not None and os.path.exists(checkpoint):
        state, snapshots = _load_checkpoint(checkpoint, fingerprint, n_steps)
    checkpoint_chunks = max(1, math.ceil((checkpoint_every or chunk_steps) / (saves_per_chunk * save_every)))
    limit = blowup_factor * float(np.linalg.norm(np.ptp(problem.mesh.points, axis=0)))
    show = progress if progress is not None else n_steps >= 20000
    from tqdm import tqdm

    bar = tqdm(total=n_steps, initial=int(state.step), disable=not show, unit="step",
               desc="simulate", dynamic_ncols=True)
    chunks_done = 0
    try:
        while int(state.step) < n_steps:
            remaining_saves = (n_steps - int(state.step)) // save_every
            k = min(saves_per_chunk, remaining_saves)
            new_state, saved = _advance_jit(system, state, k, save_every)
            saved = np.asarray(saved)
            finite = np.isfinite(saved).all(axis=(1, 2)) & (np.abs(saved).max(axis=(1, 2), initial=0) <= limit)
            if not finite.all():
                first_bad = int(np.argmin(finite))
                snapshots.append(saved[:first_bad])
                bad_step = int(state.step) + (first_bad + 1) * save_every
                partial = _trajectory(problem, snapshots, dt, save_every)
                err = StabilityError(
                    f"the run diverged by step {bad_step} (t = {bad_step * dt:.6g} s): displacement "
                    f"is NaN/Inf or above {limit:.3g} cm. dt={dt:.4e} s vs CFL {problem.dt:.4e} s; "
                    f"reduce dt. The {partial.times.size} snapshots saved before are kept "
                    "(error.trajectory)")
                err.trajectory = partial
                raise err
            snapshots.append(saved)
            state = new_state
            chunks_done += 1
            bar.update(k * save_every)
            if checkpoint is not None and (chunks_done % checkpoint_chunks == 0
                                           or int(state.step) == n_steps):
                _save_checkpoint(checkpoint, fingerprint, state, snapshots)
    finally:
        bar.close()
    return _trajectory(problem, snapshots, dt, save_every)


def _trajectory(problem, snapshots, dt, save_every):
    from .trajectory import Trajectory

    displacement = np.concatenate(snapshots, axis=0)
    times = np.arange(len(displacement)) * save_every * dt
    return Trajectory(times=times, displacement=displacement, mesh=problem.mesh, dt=dt,
                      save_every=save_every, parameters=_parameters(problem))


def _parameters(problem) -> dict:
    """Problem parameters stored with a trajectory (concrete values only)."""
    m = problem.material
    out = {}
    for name, value in (("E", m.E), ("nu", m.nu), ("rho", m.rho), ("damping", problem.damping)):
        if not is_traced(value):
            out[name] = float(value)
    return out


def _save_checkpoint(path, fingerprint, state: SolverState, snapshots) -> None:
    from .trajectory import atomic_h5

    with atomic_h5(path) as f:
        f.attrs["kind"] = "jaxsync-solver-checkpoint"
        f.attrs["fingerprint"] = fingerprint
        f.attrs["step"] = int(state.step)
        f["displacement"] = np.asarray(state.displacement)
        f["previous"] = np.asarray(state.previous)
        f["snapshots"] = np.concatenate(snapshots, axis=0)


def _load_checkpoint(path, fingerprint, n_steps):
    import h5py

    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("kind") != "jaxsync-solver-checkpoint":
                raise CheckpointError(f"{path} is not a jaxsync solver checkpoint")
            if f.attrs["fingerprint"] != fingerprint:
                raise CheckpointError(
                    f"checkpoint {path} was written by a different problem, dt or save_every; "
                    "delete it or pass another checkpoint path")
            step_ = int(f.attrs["step"])
            state = SolverState(jnp.asarray(f["displacement"][...]), jnp.asarray(f["previous"][...]),
                                jnp.asarray(step_, dtype=jnp.int32))
            snapshots = [f["snapshots"][...]]
    except CheckpointError:
        raise
    except Exception as exc:
        raise CheckpointError(f"cannot read checkpoint {path}: {exc}; delete it to start over") from exc
    if step_ > n_steps:
        raise CheckpointError(f"checkpoint {path} is at step {step_}, beyond n_steps={n_steps}")
    return state, snapshots
