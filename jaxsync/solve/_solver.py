"""The one entry point of the explicit solver (:func:`simulate`) and the static solution
(:func:`steady_state`).

The numerics (central differences with lumped mass, paper eq. 7; the paper's start) are
the pure stepper of :mod:`jaxsync.fem`. :func:`simulate` checks its inputs, lowers
its coupling (:mod:`jaxsync.solve.coupling`: synchronized, or synchronization-avoiding)
into the run's plan -- the schedule of phases and the coupling's own policy -- builds the
global system and the start, and hands the plan to an executor: the host executor
(:mod:`jaxsync.solve.executors`: compiled chunks, progress, divergence checks, checkpoints) for
concrete inputs, the traced executor (:mod:`jaxsync.solve.executors`: one JAX program,
differentiable) for traced ones.
"""

from __future__ import annotations

import functools

import jax
import numpy as np

from ..errors import ProblemError
from ..fem._stepper import build_system, initial_state
from ..fem.forces._internal_force import run_force_model
from ..pytree import is_traced
from ._strategies import SaveAt, SolverCheckpoint, TracedExecutor, choose_executor
from .coupling._base import as_coupling, exchange_of

__all__ = ["simulate", "steady_state", "SteadyState"]


NEWTON_LOAD_STEPS = 10
"""Default number of load increments of :func:`steady_state` for a hyperelastic law."""


class SteadyState(np.ndarray):
    """What :func:`steady_state` returns, for every law: the static displacement, a numpy
    array (n_nodes, 3) [cm], with

    Attributes:
        residuals: per load increment, the relative residuals of its Newton iterations (a
            tuple of tuples of floats; empty for a linear law, solved directly).

    It is an ``np.ndarray`` in every use (indexing, NumPy and JAX functions, files);
    arithmetic on it gives plain arrays, which carry no residuals.
    """

    residuals: tuple

    def __new__(cls, displacement, residuals=()):
        solution = np.asarray(displacement, dtype=float).view(cls)
        solution.residuals = tuple(tuple(float(r) for r in increment) for increment in residuals)
        return solution

    def __array_finalize__(self, obj):  # views (slices, reshapes) keep the residuals
        self.residuals = getattr(obj, "residuals", ())

    def __array_wrap__(self, array, context=None, return_scalar=False):
        # ufunc results are new fields, not this solution: plain arrays (or scalars)
        array = np.asarray(array).view(np.ndarray)
        return array[()] if return_scalar else array


def steady_state(problem, *, load_steps: int | None = None, tol: float = 1e-10, max_iter: int = 25,
                 history: bool = False, guess=None) -> SteadyState:
    """Static solution with every load at full magnitude (time factor 1) and the Dirichlet
    values imposed (those following a time function at their full value): a
    :class:`SteadyState`, the (n_nodes, 3) displacement [cm] as a numpy array whose
    ``residuals`` hold the Newton iterations' relative residuals per increment.

    A linear elastic law: K u = f, K including the elastic supports' springs, one direct
    sparse solve (scipy; ``load_steps``, ``tol``, ``max_iter`` are not used).

    A hyperelastic law: f_int(u) + S u = f (S the supports' springs) by Newton's method
    with the exact tangent (:func:`jaxsync.fem.forces.tangent_matrix`: the
    element Hessians of the stored energy by ``jax.jacfwd``, summed into a scipy sparse
    matrix) and scipy's sparse direct solver, in ``load_steps`` equal increments of the
    loads and of the Dirichlet values (default :data:`NEWTON_LOAD_STEPS`, 10). The first
    iteration of an increment moves the prescribed dofs to their new values and predicts
    the free ones with the tangent; an iteration whose update would invert an element, or
    make the residual NaN, is halved (up to 10 times). An increment has converged when the
    largest out-of-balance force at the free dofs is at most ``tol`` times the force scale
    (the largest load or reaction of the increment, |f| and |f_int - f| at the prescribed
    dofs).

    Args:
        problem: a :class:`jaxsync.Problem`.
        load_steps: hyperelastic laws: the number of load increments (>= 1).
        tol: hyperelastic laws: the relative residual of convergence.
        max_iter: hyperelastic laws: Newton iterations per increment at most.
        history: deprecated: return the pair ``(u, u.residuals)`` as before
            :class:`SteadyState` carried the residuals (read ``u.residuals`` instead).
        guess: hyperelastic laws: (n_nodes, 3) [cm] the displacement Newton's method starts
            from (default zero), for instance the solution of a nearby problem; with
            ``load_steps=1`` the full load is applied to it at once.

    Raises:
        ConvergenceError: an increment did not converge in ``max_iter`` iterations (or
            every halved update inverted an element); the message names the increment,
            the residual and the fix, ``error.displacement`` holds the last converged
            increment's solution.
        ProblemError: the Dirichlet conditions leave a rigid-body motion free (singular);
            traced inputs (inside ``jax.grad``, ``jit`` or ``vmap``).
    """
    if is_traced(problem.material, problem.loads, [bc.value for bc in problem.dirichlet], problem.supports,
                 problem.density_scale):
        raise ProblemError(
            "steady_state solves on the host (scipy's sparse direct solver), so it cannot take traced inputs "
            "(jax.grad, jit or vmap): call it with concrete values; for the derivative of the static solution "
            "in a parameter theta use the implicit function theorem, du/dtheta = -K_T^-1 dr/dtheta, with "
            "K_T from jaxsync.fem.forces.tangent_matrix (a hyperelastic law) and dr/dtheta from "
            "jax.jacfwd of the residual (docs: Gradients)")
    if problem.material.finite_strain:  # a force nonlinear in u: Newton's method
        u = SteadyState(*_newton_steady_state(problem, NEWTON_LOAD_STEPS if load_steps is None else load_steps,
                                              tol, max_iter, guess))
    else:
        u = SteadyState(_linear_steady_state(problem))
    if history:
        import warnings

        warnings.warn("steady_state(history=True) is deprecated: steady_state returns one type, whose "
                      "residuals attribute holds the Newton residuals (u = steady_state(problem); u.residuals)",
                      DeprecationWarning, stacklevel=2)
        return u, list(map(list, u.residuals))
    return u


def _singular() -> ProblemError:
    return ProblemError("the static problem is singular: the Dirichlet conditions do not "
                        "prevent rigid-body motion; clamp more nodes")


def _well_posed(K, factor) -> bool:
    """False when the factorised K has a rigid-body mode: a pivot at round-off shows as a
    random load's response ||K^-1 b|| / ||b|| reaching 1 / (eps ||K||)."""
    probe = np.random.default_rng(0).standard_normal(K.shape[0])
    row_norm = float(np.max(np.asarray(abs(K).sum(axis=1)), initial=0.0))  # ||K||_inf
    response = np.abs(factor.solve(probe)).max(initial=0.0) / np.abs(probe).max(initial=1.0)
    return bool(row_norm * response < 1e13)


@jax.jit
def _flat_force(op, x):
    return op.matvec(x.reshape(-1, 3)).reshape(-1)


@jax.jit
def _flat_jacobians(op, x):
    return op.jacobians(x.reshape(-1, 3))


@jax.jit
def _flat_follower_force(follower, x):
    return follower.force(x.reshape(-1, 3), 0.0).reshape(-1)


def _newton_steady_state(problem, load_steps, tol: float, max_iter: int, guess=None):
    """Newton's method with load increments (:func:`steady_state`); (u (n_nodes, 3), residuals)."""
    import scipy.sparse.linalg as spla

    from ..errors import ConvergenceError
    from ..fem.forces._follower import full_follower_pressure, load_stiffness
    from ..fem.forces._support import spring_matrix
    from ..fem.forces._total_lagrangian import TotalLagrangian, tangent_matrix

    for name, value in (("load_steps", load_steps), ("max_iter", max_iter)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ProblemError(f"{name} must be an integer >= 1, got {value!r}")
    if not (isinstance(tol, (int, float)) and np.isfinite(tol) and tol > 0):
        raise ProblemError(f"tol must be a positive number, got {tol!r}")
    load_steps, max_iter = int(load_steps), int(max_iter)
    op = TotalLagrangian().operator(problem)
    force = functools.partial(_flat_force, op)  # compiled once per mesh size and law, not per call
    jacobians = functools.partial(_flat_jacobians, op)
    springs = spring_matrix(problem)
    follower = full_follower_pressure(problem)  # at full magnitude (time factor 1), scaled by the increment
    if follower is not None:
        follower_force = functools.partial(_flat_follower_force, follower)
    n = problem.n_dofs
    f_full = np.zeros(n)
    for v in problem.load_vectors()[0]:
        f_full += np.asarray(v, dtype=float).reshape(-1)
    fixed, values = problem.dirichlet_dofs()
    free = np.setdiff1d(np.arange(n), fixed)
    u = np.zeros(n)
    if guess is not None:
        if np.shape(guess) != (problem.n_nodes, 3) or not np.all(np.isfinite(guess)):
            raise ProblemError(f"guess must be a finite displacement of shape ({problem.n_nodes}, 3), got shape "
                               f"{np.shape(guess)}")
        u = np.asarray(guess, dtype=float).reshape(-1).copy()
        u[fixed] = 0.0  # the prescribed dofs move to their values in the first increment

    def out_of_balance(x, f_ext, fraction):
        """f_int(x) + S x - f_ext - fraction f_follower(x), or None where an element is
        inverted or it is not finite."""
        J = np.asarray(jacobians(x))
        if not np.all(np.isfinite(J) & (J > 0)):
            return None
        r = np.asarray(force(x)) - f_ext
        r = r if springs is None else r + springs @ x
        r = r if follower is None else r - fraction * np.asarray(follower_force(x))
        return r if np.all(np.isfinite(r)) else None

    residuals = []
    for k in range(1, load_steps + 1):
        fraction = k / load_steps
        f_ext = fraction * f_full
        target = fraction * values  # the prescribed values of this increment
        converged = u.copy()  # the last converged state
        r = out_of_balance(u, f_ext, fraction)
        if r is None and k == 1 and guess is not None:  # a guess that inverts an element: start from rest
            u = np.zeros(n)
            converged, r = u.copy(), out_of_balance(u, f_ext, fraction)
        history = []
        for iteration in range(max_iter + 1):
            move = target - u[fixed]  # what the prescribed dofs still have to move
            pending = bool(np.any(move != 0))
            scale = max(float(np.abs(f_ext).max(initial=0.0)), float(np.abs(r[fixed]).max(initial=0.0)))
            if follower is not None:  # the follower pressures' forces count in the scale too
                scale = max(scale, fraction * float(np.abs(np.asarray(follower_force(u))).max(initial=0.0)))
            relative = float(np.abs(r[free]).max(initial=0.0)) / scale if scale > 0 else 0.0
            if not pending:
                history.append(relative)
                if relative <= tol:
                    break
            if iteration == max_iter:
                raise ConvergenceError(
                    f"Newton's method did not converge in load increment {k} of {load_steps}: relative residual "
                    f"{relative:.3e} after {max_iter} iterations (tolerance {tol:g}); raise load_steps (for "
                    f"instance to {2 * load_steps}) or max_iter, or check that the load does not exceed what the "
                    "structure can carry (a limit point, buckling) and that the Dirichlet set prevents every "
                    "rigid-body motion", increment=k, residual=relative, displacement=converged.reshape(-1, 3))
            K = tangent_matrix(op, u.reshape(-1, 3))
            if springs is not None:
                K = (K + springs).tocsr()
            if follower is not None:  # the load stiffness (non-symmetric)
                K = (K + fraction * load_stiffness(follower, u.reshape(-1, 3))).tocsr()
            K_free = K[free][:, free].tocsc()
            rhs = -r[free]
            if pending:  # the prescribed move, and the free dofs' response to it
                rhs = rhs - K[free][:, fixed] @ move
            try:
                factor = spla.splu(K_free)
            except RuntimeError as exc:  # SuperLU: "Factor is exactly singular"
                raise _singular() from exc
            du = factor.solve(rhs)
            if not np.all(np.isfinite(du)) or (k == 1 and iteration == 0 and not _well_posed(K_free, factor)):
                raise _singular()
            for _ in range(11):  # halve an update that inverts an element (a part of the move now)
                trial = u.copy()
                trial[free] += du
                trial[fixed] += move
                found = out_of_balance(trial, f_ext, fraction)
                if found is not None:
                    break
                du, move = 0.5 * du, 0.5 * move
            else:
                raise ConvergenceError(
                    f"Newton's method failed in load increment {k} of {load_steps}: every update, halved 10 "
                    "times, inverts an element (J <= 0) or gives a NaN residual (relative residual "
                    f"{relative:.3e}); raise load_steps (for instance to {4 * load_steps}), or check the loads' "
                    "magnitudes", increment=k, residual=relative, displacement=converged.reshape(-1, 3))
            u, r = trial, found
        residuals.append(history)
    return u.reshape(-1, 3), residuals


def _linear_steady_state(problem) -> np.ndarray:
    """K u = f by one direct sparse solve (:func:`steady_state`)."""
    import scipy.sparse.linalg as spla

    from ..fem.forces._support import stiffness_matrix

    K = stiffness_matrix(problem)
    vectors, _ = problem.load_vectors()
    f = np.zeros(problem.n_dofs)
    for v in vectors:
        f += np.asarray(v, dtype=float).reshape(-1)
    fixed, values = problem.dirichlet_dofs()
    free = np.setdiff1d(np.arange(K.shape[0]), fixed)
    u = np.zeros(K.shape[0])
    u[fixed] = values
    rhs = f[free] - K[free][:, fixed] @ values
    singular = _singular()
    K_free = K[free][:, free].tocsc()
    try:
        factor = spla.splu(K_free)
    except RuntimeError as exc:  # SuperLU: "Factor is exactly singular"
        raise singular from exc
    u[free] = factor.solve(rhs)
    for _ in range(3):  # iterative refinement: stiff (nu -> 0.5) systems lose digits in one solve
        if not np.all(np.isfinite(u)):
            break
        u[free] += factor.solve(rhs - K_free @ u[free])
    residual = np.abs(K_free @ u[free] - rhs).max(initial=0.0)
    # a successful solve leaves a residual at the round-off of K u (a backward error near
    # machine precision, however ill-conditioned K is as nu -> 0.5)
    row_norm = float(np.max(np.asarray(abs(K_free).sum(axis=1)), initial=0.0))  # ||K||_inf
    scale = row_norm * np.abs(u[free]).max(initial=0.0) + np.abs(rhs).max(initial=0.0)
    if not np.all(np.isfinite(u)) or residual > 1e-10 * max(scale, 1e-300):
        raise singular
    # ... and a rigid-body mode shows as a pivot at round-off: a random load's response
    # ||K^-1 b|| / ||b|| then reaches 1 / (eps ||K||)
    probe = np.random.default_rng(0).standard_normal(len(rhs))
    condition = row_norm * np.abs(factor.solve(probe)).max(initial=0.0) / np.abs(probe).max(initial=1.0)
    if not condition < 1e13:
        raise singular
    return u.reshape(-1, 3)


def simulate(problem, n_steps: int, *, dt=None, save=1, partitions=None, coupling=None, exchange=None, sync=None,
             mode="preassembled", checkpoint=None, executor=None):
    """Integrate ``problem`` for ``n_steps`` explicit steps.

    Args:
        problem: a :class:`jaxsync.Problem`.
        n_steps: number of time steps (a multiple of the save stride).
        dt: time step [s]; default ``problem.dt``: the paper's CFL step, or 0.9 times the
            exact bound 2/omega_max where that is smaller (``problem.time_step`` says which).
            A dt above the exact bound is refused (``HostExecutor(check_stability=False)``
            forces it through).
        save: what the run keeps: an int k (the displacement every k steps and at t = 0) or
            a :class:`jaxsync.SaveAt` (``SaveAt(every=k, shared_every=1)`` also keeps each
            part's shared-node displacements after every step: the surrogates' training data).
        partitions: None for one device; an int n_parts (METIS, seed 0) or a
            :class:`jaxsync.Partition` (``jaxsync.partition(mesh, n, seed=...)``) for the
            distributed solver (paper Algorithm 1, ``jax.shard_map`` over devices).
        coupling: how the parts are coupled at their shared nodes:
            :class:`jaxsync.Synchronized` (default: every step synchronized) or
            :class:`jaxsync.SyncAvoiding` (synchronized up to n_cri, then surrogates
            predict the shared nodes and the parts do not exchange, paper Algorithm 3,
            with error control; needs ``partitions``).
        exchange: distributed runs: how the parts exchange, :class:`jaxsync.Psum`,
            :class:`jaxsync.Ppermute`, :class:`jaxsync.Mpi` or :class:`jaxsync.Halo` (deep
            halos, exact; ``save`` and the depth must divide one another), any
            :class:`jaxsync.parallel.exchange.ExchangeStrategy`, or a registered name
            (:func:`jaxsync.solve.register_exchange`); default
            :func:`jaxsync.parallel.multiprocess.default_sync` (psum in one process, MPI
            across CPU processes). The exchanges carry the devices to run on.
        sync: another name for ``exchange`` (give one of them).
        mode: the internal force, ``"preassembled"`` (sparse K, stored once) or
            ``"recompute"`` (element quantities formed every step), paper Remark 2
            (:mod:`jaxsync.fem.forces`), or a force model. The preassembled K's
            product is chosen for the run's length (:attr:`jaxsync.fem.forces.Preassembled.product`:
            the form that compiles faster for short runs, the faster step for long ones).
        checkpoint: a :class:`jaxsync.SolverCheckpoint` or an HDF5 path for resumable runs
            (synchronized runs): the state is stored there as the run goes, and a run
            started again with the same problem continues from it, giving the same
            trajectory.
        executor: :class:`jaxsync.HostExecutor` (compiled chunks with progress, divergence
            checks and checkpoints: the default for concrete inputs) or
            :class:`jaxsync.TracedExecutor` (one traced program with a bounded-memory
            reverse pass: the default inside ``jax.grad``, ``jit`` or ``vmap``).

    Returns:
        :class:`jaxsync.Trajectory` with ``n_steps // every + 1`` snapshots (and, for
        distributed runs, the per-part shared-node histories in ``parts``, every
        ``shared_every`` steps). ``stats`` is typed by the coupling: a synchronized run's
        :class:`jaxsync.SynchronizedStats` holds ``us_per_step`` (compiled chunks only) and
        ``compile_seconds``; a synchronization-avoiding run's is a
        :class:`jaxsync.SyncAvoidingStats` (:class:`jaxsync.SyncAvoiding` says what else
        such a run returns). ``result`` says how the run ended (:class:`jaxsync.Result`).

    Raises:
        StabilityError: dt above the bound, or the run diverged (NaN/Inf or blow-up); the
            error's ``trajectory`` holds the snapshots saved before divergence.
        CheckpointError: the checkpoint file belongs to another problem or is corrupt.
        PartitionError: a partition that cannot be made or does not fit the mesh.
        ProblemError: a ``coupling`` that is not a coupling, both ``exchange`` and ``sync``,
            an exchange or ``shared_every`` without partitions, a checkpoint of a traced run.

    Differentiable: when the material, damping, loads, initial conditions, dt or the
    coupling's surrogates are JAX tracers, the traced executor runs the same phases as one
    ``lax.scan`` (over the parts under ``shard_map`` for a distributed run) and the
    trajectory holds JAX arrays; its reverse pass recomputes segments of the run
    (``TracedExecutor(adjoint=Recompute())``) so that memory grows like sqrt(n_steps).
    """
    from ..precision import require_float64

    require_float64("simulate")
    coupling = as_coupling(coupling)
    exchange = exchange_of(exchange, sync)
    save = SaveAt.of(save)
    n_steps = save.check_steps(n_steps)
    mode = run_force_model(mode, problem, n_steps)
    dt = problem.dt if dt is None else dt
    traced = is_traced(problem.material, problem.damping, problem.stiffness_damping, problem.loads, dt,
                       problem.initial_displacement, problem.initial_velocity, coupling)
    executor = choose_executor(executor, traced)
    plan = coupling.plan(problem, n_steps, dt=dt, save=save, partitions=partitions, exchange=exchange, mode=mode,
                         executor=executor)
    if isinstance(executor, TracedExecutor):
        if checkpoint is not None:  # the reason, not a missing feature
            raise ProblemError("checkpoint= needs the host executor: a traced run is one JAX program, with no "
                               "point between its steps where a file could be written; leave it out of traced runs")
        if plan.distributed is None:
            return _traced_run(problem, dt, mode, plan, save, executor)
        # one compiled program: eager transformations (jax.grad without jit) would otherwise
        # add cotangents that live on the parts' devices to ones on the default device
        return jax.jit(lambda: _traced_run(problem, dt, mode, plan, save, executor))()
    if checkpoint is not None and len(plan.schedule) > 1:
        raise ProblemError("checkpoint= resumes synchronized runs; a synchronization-avoiding run's predicted "
                           "phase and its re-synchronizations are not checkpointed: leave checkpoint out, or "
                           "checkpoint the synchronized reference run")
    if executor.check_stability:
        from ..fem._timestep import check_dt

        check_dt(problem, dt)
    from .executors._host import run_on_host

    system = build_system(problem, float(dt), mode)
    return run_on_host(problem, system, initial_state(problem, system), plan, save=save, executor=executor,
                       checkpoint=SolverCheckpoint.of(checkpoint))


def _traced_run(problem, dt, mode, plan, save, executor):
    """:func:`simulate` through the traced executor: a :class:`jaxsync.Trajectory` of JAX arrays."""
    from .executors._traced import run_traced

    system = build_system(problem, dt, mode)
    state = initial_state(problem, system)
    run = run_traced(problem, system, state, plan.schedule, save_every=save.every, adjoint=executor.adjoint,
                     distributed=plan.distributed, predictor=plan.predictor, record=save.records_every_step)
    return plan.traced_trajectory(problem, dt, system, state, run, save)
