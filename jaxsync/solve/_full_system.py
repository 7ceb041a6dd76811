"""Full-system modeling (paper "Full system modeling"): one surrogate predicts every dof
after n_cri, with no solver step at all (the paper's baseline against which the
synchronization-avoiding solver is compared)."""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import CheckpointError, ProblemError, StabilityError
from ..surrogate._model import Surrogate
from ..surrogate._refill import refill_rollout

__all__ = ["simulate_full_system"]


def simulate_full_system(problem, reference, surrogates, *, n_cri: int, n_steps: int | None = None):
    """Full-system modeling (paper "Full system modeling"): one surrogate predicts every dof.

    The synchronized ``reference`` (saved at every step) supplies the first ``n_cri``
    steps; after that no solver step runs: refill cycles of the single surrogate,
    each consuming earlier predictions, produce all displacements. The network does not
    know the Dirichlet conditions; their predicted values are reported, not enforced (a
    dof that never moves in the training data normalizes with std 0, so a network trained
    by jaxsync predicts it at exactly its value).

    Args:
        problem: the problem (for its Dirichlet dofs).
        reference: :class:`jaxsync.Trajectory` saved at every step, at least n_cri + 1 long.
        surrogates: one predictor over all 3 n_nodes dofs: a one-replica
            :class:`jaxsync.surrogate.Surrogate` (a conditional one with its load parameter,
            ``Surrogate.with_load_parameter``), the record of its surrogate file
            (:func:`jaxsync.surrogate.load_surrogate`), or an
            :class:`~jaxsync.solve.coupling.OraclePredictor` (one part).
        n_cri: last step taken from the reference (>= n_p n_s + 1).
        n_steps: total steps (default: the reference's length).

    Returns:
        :class:`jaxsync.Trajectory` (saved every step) with ``synchronized`` flags and
        ``stats.dirichlet_max_abs_predicted``, the largest |predicted value| on the
        Dirichlet dofs, whose prescribed values the network does not enforce.
    """
    from ..io.surrogate_file import SavedSurrogate
    from ..io.trajectory import Trajectory
    from ..precision import require_float64
    from ..run_stats import FullSystemStats

    require_float64("simulate_full_system")
    if reference.save_every != 1:
        raise ProblemError("full-system modeling needs the reference saved at every step")
    n_steps = reference.n_saved - 1 if n_steps is None else int(n_steps)
    if isinstance(surrogates, (str, bytes)) or hasattr(surrogates, "__fspath__"):
        raise ProblemError(f"surrogates={surrogates!r} is a path: load the surrogate file first, "
                           "jaxsync.surrogate.load_surrogate(path)")
    n_dof = problem.n_dofs
    if isinstance(surrogates, SavedSurrogate):
        if surrogates.n_parts != 1 or surrogates.dof_counts[0] != n_dof:
            raise CheckpointError(f"full-system modeling needs one surrogate over all {n_dof} dofs; "
                                  f"the surrogate file has {surrogates.n_parts} replicas with "
                                  f"{list(surrogates.dof_counts)} dofs")
        surrogates = Surrogate.from_saved(surrogates)
    # a surrogate with load input reads the problem's load signals at the reference's step
    predictor = surrogates.for_problem(problem, reference.dt) if hasattr(surrogates, "for_problem") else surrogates
    history, cycle_steps = predictor.n_s * predictor.n_past, predictor.n_s * predictor.n_future
    if n_cri < history:
        raise ProblemError(f"n_cri={n_cri} is too small: the first refill reads the n_p * n_s = "
                           f"{history} known steps before it")
    if reference.n_saved < n_cri + 1:
        raise ProblemError(f"the reference holds {reference.n_saved} snapshots, fewer than n_cri + 1")
    known = np.asarray(reference.displacement[:n_cri + 1]).reshape(n_cri + 1, -1)
    n_cycles = -(-(n_steps - n_cri) // cycle_steps)
    one = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[0], predictor)

    # the one part closed over (not an argument): the same program as the offline rollout
    rollout = jax.jit(lambda buffer: refill_rollout(one, buffer, n_cri, n_cycles))

    buffer = jnp.asarray(known[-history:])
    start = time.perf_counter()
    compiled = rollout.lower(buffer).compile()
    compile_seconds = time.perf_counter() - start
    start = time.perf_counter()
    predicted = np.asarray(compiled(buffer))[:n_steps - n_cri]
    seconds = time.perf_counter() - start
    if not np.all(np.isfinite(predicted)):
        bad = n_cri + 1 + int(np.argmin(np.isfinite(predicted).all(axis=1)))
        raise StabilityError(f"the full-system surrogate predicted NaN/Inf for step {bad}; retrain it")
    displacement = np.concatenate([known, predicted]).reshape(n_steps + 1, -1, 3)
    fixed, values = problem.dirichlet_dofs()
    dirichlet_error = float(np.abs(predicted[:, fixed] - values).max()) if len(predicted) else 0.0
    return Trajectory(times=np.arange(n_steps + 1) * reference.dt, displacement=displacement,
                      mesh=problem.mesh, element=problem.element, dt=reference.dt, save_every=1,
                      parameters=dict(reference.parameters),
                      stats=FullSystemStats(**{"n_steps": n_steps, "n_cri": n_cri, "n_synchronized_steps": n_cri,
                                  "n_predicted_steps": n_steps - n_cri,
                                  "dirichlet_max_abs_predicted": dirichlet_error,
                                  "compile_seconds": compile_seconds,
                                  "us_per_step_predicted": 1e6 * seconds / max(n_steps - n_cri, 1)}),
                      synchronized=np.arange(n_steps + 1) <= n_cri)
