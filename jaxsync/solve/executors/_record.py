"""The :class:`jaxsync.Trajectory` of a run, built once from what its phases produced.

Both executors and the ensemble hand their snapshots here: :func:`synchronized_trajectory`
(a synchronized run, single-device or distributed, with the parts' shared-node
histories), :func:`online_trajectory` (a synchronization-avoiding run: synchronized and
predicted stretches, per-snapshot flags, each part's own predictions), and
:func:`run_parameters` (the problem parameters stored with a trajectory).
"""

from __future__ import annotations

import numpy as np

from ...fem._load_signals import record_load_signal
from ...fem._loads import load_jumps
from ...pytree import is_traced

__all__ = ["synchronized_trajectory", "online_trajectory", "run_parameters", "part_histories", "known_load_jumps",
           "load_signal_fields"]


def run_parameters(problem, jumps=None) -> dict:
    """Problem parameters stored with a trajectory (concrete values only): ``material``
    (the law's class name, e.g. ``"LinearElastic"``, ``"NeoHookean"``), its small-strain
    E, nu, rho, the damping alpha and the stiffness-proportional damping beta
    (``"stiffness_damping"``; a record without it had none); given the run's
    load jumps (:func:`jaxsync.fem.load_jumps`), also ``last_load_jump``, the last of
    them (absent when there is none), which the offline check of
    :func:`jaxsync.surrogate.train_surrogates` starts after, as an online run does, and
    ``load_jumps``, all of them, across which training takes no window."""
    m = problem.material
    out = {"material": type(m).__name__}
    for name, value in (("E", m.E), ("nu", m.nu), ("rho", m.rho), ("damping", problem.damping),
                        ("stiffness_damping", problem.stiffness_damping)):
        if not is_traced(value):
            out[name] = float(value)
    if jumps is not None and len(jumps):
        out["last_load_jump"] = int(jumps[-1])
        out["load_jumps"] = [int(j) for j in jumps]  # training leaves out windows across them
    return out


def known_load_jumps(loads, n_steps: int, dt):
    """The run's load jumps (:func:`jaxsync.fem.load_jumps`), found on concrete
    values even inside ``jit``; None when the time functions or dt are traced."""
    import jax

    try:
        with jax.ensure_compile_time_eval():
            return load_jumps(loads, n_steps, dt)
    except (jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError):
        return None


def load_signal_fields(problem, dt, n_rows: int, stride: int) -> dict:
    """``load_signal`` and ``load_inputs`` of a trajectory whose shared rows are every
    ``stride`` steps from step 0 (``n_rows`` of them): the problem's load signals there
    (:func:`jaxsync.fem.record_load_signal`); empty when traced."""
    recorded = record_load_signal(problem, dt, np.arange(int(n_rows)) * int(stride))
    if recorded is None:
        return {}
    signal, inputs = recorded
    return {"load_signal": signal, "load_inputs": inputs}


def part_histories(partition, shared, predicted=None) -> tuple:
    """One :class:`jaxsync.PartHistory` per part of ``partition``: its shared nodes and
    elements, ``shared[p]`` (n, 3 n_shared_p) and, when given, ``predicted[p]``."""
    from ...io.trajectory import PartHistory

    return tuple(PartHistory(part.shared_nodes, part.elements, shared[p],
                             None if predicted is None else predicted[p])
                 for p, part in enumerate(partition.parts))


def synchronized_trajectory(problem, displacement, dt, save, partition=None, recorded=None, *, stats=None,
                            result=None):
    """The trajectory of a synchronized run.

    Args:
        problem: the run's problem.
        displacement: (n_saved, n_nodes, 3) snapshots from step 0, every ``save.every``
            steps [cm] (numpy, or JAX arrays of a traced run).
        dt: the time step [s].
        save: the run's :class:`~jaxsync.solve.SaveAt`.
        partition: the run's :class:`jaxsync.Partition` (distributed runs), or None.
        recorded: per part, (n_steps + 1, 3 n_shared_p) shared-node rows after every step
            from step 0 (thinned here to ``save.shared_every``), or None: the shared
            histories are read from the snapshots.
        stats: :class:`jaxsync.RunStats` of the run; result: its result code.
    """
    from ...io.trajectory import Trajectory

    n_saved = len(displacement)
    times = np.arange(n_saved, dtype=np.float64) * save.every * dt
    n_steps = (n_saved - 1) * save.every  # snapshots from step 0
    parts, shared_every = (), None
    if partition is not None:
        if recorded is None:
            shared = [displacement[:, part.shared_nodes].reshape(n_saved, -1) for part in partition.parts]
            shared_every = save.every
        else:
            shared = [rows[::save.shared_every] for rows in recorded]
            shared_every = save.shared_every
        parts = part_histories(partition, shared)
    jumps = known_load_jumps(problem.loads, n_steps, dt)
    stride = save.every if shared_every is None else shared_every
    n_rows = n_saved if not parts else len(parts[0].shared_displacement)
    return Trajectory(times=times, displacement=displacement, mesh=problem.mesh, element=problem.element, dt=dt,
                      save_every=save.every,
                      parameters=run_parameters(problem, jumps), parts=parts, shared_every=shared_every,
                      stats=stats, result=result, **load_signal_fields(problem, dt, n_rows, stride))


def online_trajectory(problem, partition, pieces, dt, save_every: int, *, parameters, stats=None, result=None,
                      error_estimate=None):
    """The trajectory of a synchronization-avoiding run.

    ``pieces``: in order, (kind, displacement (n, n_nodes, 3), predictions (n_parts, n,
    n_dof) or None) of every stretch from step 0: ``"synchronized"`` ones (the first holds
    the snapshot at t = 0) and ``"predicted"`` ones (their global field the mean over the
    parts that hold each node, and each part's own predictions at the saved steps)."""
    from ...io.trajectory import Trajectory
    from ...surrogate.training._histories import shared_dof_layout

    n_dof, counts = shared_dof_layout(partition)
    displacement = np.concatenate([d for _, d, _ in pieces])
    flags = np.concatenate([np.full(len(d), kind == "synchronized") for kind, d, _ in pieces])
    preds = [p for kind, _, p in pieces if kind == "predicted"]
    pred = np.concatenate(preds, axis=1) if preds else np.zeros((partition.n_parts, 0, n_dof))
    n_saved = len(displacement)
    parts = part_histories(partition, [displacement[:, part.shared_nodes].reshape(n_saved, -1)
                                       for part in partition.parts],
                           [pred[p, :, :counts[p]] for p in range(partition.n_parts)])
    return Trajectory(times=np.arange(n_saved, dtype=np.float64) * save_every * dt, displacement=displacement,
                      mesh=problem.mesh, element=problem.element, dt=dt, save_every=save_every,
                      parameters=parameters, parts=parts, synchronized=flags, stats=stats, result=result,
                      error_estimate=error_estimate, **load_signal_fields(problem, dt, n_saved, save_every))
