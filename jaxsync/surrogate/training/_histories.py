"""The shared-node histories a surrogate is trained on, read from distributed trajectories,
and the padded shared-dof layout of a partition's parts (the replicas' width)."""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from jaxsync.errors import CheckpointError
from jaxsync.io.trajectory import Trajectory

__all__ = ["shared_dof_layout", "SharedHistories", "read_shared_histories"]


def shared_dof_layout(partition) -> tuple[int, np.ndarray]:
    """The replicas' dof layout of a :class:`jaxsync.Partition`: ``(n_dof, counts)`` with
    ``counts`` (n_parts,) the real shared-dof counts (3 per shared node) and ``n_dof`` the
    padded width, ``max(counts.max(), 3)``."""
    counts = np.array([3 * p.n_shared for p in partition.parts])
    return max(int(counts.max()), 3), counts


# ----------------------------------------------------------------------------- trajectories


@dataclasses.dataclass(frozen=True)
class SharedHistories:
    """Per-part shared-dof histories of a distributed trajectory, ready for training.

    Attributes:
        histories: per part, (n_rows, 3 n_shared_p) displacements every ``stride`` steps
            from step 0, float64.
        shared_nodes: per part, (n_shared_p,) int64 global node ids.
        dt: time step (s).
        load_parameter: the run's load parameter alpha_f (the problem parameter
            ``load_parameter`` of the trajectory), or None.
        synchronized: (n_steps,) bool flags of a synchronization-avoiding trajectory
            (False where the step was predicted by surrogates), None for a synchronized run.
        stride: steps between rows of ``histories``.
        last_load_jump: the last step at which a load of the run jumps (the trajectory's
            ``parameters["last_load_jump"]``), or None.
        load_jumps: every step at which a load of the run jumps (``parameters["load_jumps"]``;
            for a trajectory written before those were kept, its last one only).
        load_signal: (n_rows, n_u) the run's known load signals at the rows of
            ``histories`` (the trajectory's ``load_signal``), or None: not recorded.
        load_inputs: their :class:`~jaxsync.fem.LoadInput` descriptions.
    """

    histories: tuple[np.ndarray, ...]
    shared_nodes: tuple[np.ndarray, ...]
    dt: float
    load_parameter: float | None
    synchronized: np.ndarray | None = None
    stride: int = 1
    last_load_jump: int | None = None
    load_jumps: tuple = ()
    load_signal: np.ndarray | None = None
    load_inputs: tuple = ()

    def for_sampling(self, n_s: int) -> int:
        """The row stride that samples these histories every ``n_s`` steps.

        Raises:
            CheckpointError: ``stride`` does not divide ``n_s``."""
        if n_s % self.stride:
            raise CheckpointError(
                f"the trajectory keeps the shared nodes every {self.stride} steps, which does not divide "
                f"the sampling stride n_s={n_s}; rerun the solver with shared_every dividing n_s "
                f"(jaxsync simulate --shared-every, e.g. 1 or {n_s}), or choose n_s a multiple of {self.stride}")
        return n_s // self.stride

    @property
    def n_predicted(self) -> int:
        """Number of steps whose shared displacements came from surrogates, not the solver."""
        return 0 if self.synchronized is None else int(np.count_nonzero(~self.synchronized))


def read_shared_histories(trajectory, *, allow_predicted: bool = False) -> SharedHistories:
    """The per-part shared-dof histories of a distributed trajectory, checked for training.

    The trajectory (a :class:`jaxsync.Trajectory` or the path of a file, read with
    :meth:`jaxsync.Trajectory.load`) must be distributed and by default be a synchronized
    run. Its shared histories may be thinned (``shared_stride`` > 1, e.g.
    ``simulate(..., save_every=n_s)``): training samples every n_s steps only, so any
    stride dividing n_s serves (:meth:`SharedHistories.for_sampling`) and a long run need
    not keep its shared nodes at every step (at the paper's vessel size that would be
    69 GB for 1e6 steps). A synchronization-avoiding (``jaxsync predict``) trajectory,
    whose ``synchronized`` flags have False entries, is refused unless
    ``allow_predicted``: it holds surrogate predictions at the shared dofs, and training
    on them would teach the networks their own errors.

    Args:
        trajectory: a :class:`jaxsync.Trajectory` or a trajectory file.
        allow_predicted: accept a synchronization-avoiding trajectory anyway.

    Raises:
        CheckpointError: missing or foreign file, a run that is not distributed,
            inconsistent shapes, or a predicted trajectory without ``allow_predicted``.
    """
    if isinstance(trajectory, Trajectory):
        name, traj = "the trajectory", trajectory
    else:
        name, traj = f"trajectory file {os.fspath(trajectory)}", Trajectory.load(trajectory)
    if not traj.parts:
        raise CheckpointError(
            f"{name} holds no parts: it is not a distributed run; rerun the solver with partitions=n "
            "(jaxsync simulate --parts n)"
        )
    synchronized = None
    if traj.synchronized is not None:
        synchronized = np.asarray(traj.synchronized, bool)
        n_pred = int(np.count_nonzero(~synchronized))
        if n_pred and not allow_predicted:
            raise CheckpointError(
                f"{name} is a synchronization-avoiding run: {n_pred} of its {synchronized.size} snapshots "
                "were predicted by surrogates, not computed by the synchronized solver; train on the "
                "synchronized reference run instead, or pass --allow-predicted (allow_predicted=True) if "
                "you really mean to"
            )
    histories, nodes = [], []
    for p, part in enumerate(traj.parts):
        disp = np.asarray(part.shared_displacement, np.float64)
        ids = np.asarray(part.shared_nodes, np.int64)
        if disp.ndim != 2 or disp.shape[1] != 3 * ids.size:
            raise CheckpointError(
                f"{name}: part {p} has shared_displacement {disp.shape} for {ids.size} shared nodes; "
                f"expected (n_saved, {3 * ids.size})"
            )
        histories.append(disp)
        nodes.append(ids)
    empty = [p for p, ids in enumerate(nodes) if ids.size == 0]
    if len(nodes) == 1 and empty:
        raise CheckpointError(
            f"{name} has 1 part and so no shared nodes: there is nothing for a surrogate to predict; rerun the "
            "solver with 2 parts or more (jaxsync simulate --parts n, n >= 2; partitions=n)"
        )
    if empty:
        raise CheckpointError(
            f"{name}: part{'s' if len(empty) > 1 else ''} {', '.join(map(str, empty))} of {len(nodes)} "
            "share no nodes with any other part, so a surrogate has nothing to predict there; partition a "
            "connected mesh (or use fewer parts) and rerun the solver"
        )
    lengths = {h.shape[0] for h in histories}
    if len(lengths) > 1:
        raise CheckpointError(f"{name}: parts hold different numbers of steps {sorted(lengths)}")
    if synchronized is not None and traj.save_every == 1 and synchronized.size != histories[0].shape[0]:
        raise CheckpointError(
            f"{name}: 'synchronized' has {synchronized.size} flags for {histories[0].shape[0]} saved steps; "
            "the file is damaged"
        )
    load, jump = traj.parameters.get("load_parameter"), traj.parameters.get("last_load_jump")
    jumps = traj.parameters.get("load_jumps", [] if jump is None else [jump])
    jumps = tuple(int(j) for j in np.atleast_1d(jumps))
    signal = None if traj.load_signal is None else np.asarray(traj.load_signal, np.float64)
    if signal is not None and (signal.ndim != 2 or signal.shape[0] != histories[0].shape[0]
                               or signal.shape[1] != len(traj.load_inputs)):
        raise CheckpointError(f"{name}: load_signal has shape {signal.shape} for {histories[0].shape[0]} shared rows "
                              f"and {len(traj.load_inputs)} described signals; the file is damaged")
    return SharedHistories(tuple(histories), tuple(nodes), float(traj.dt), None if load is None else float(load),
                           synchronized, int(traj.shared_stride), None if jump is None else int(jump), jumps,
                           signal, tuple(traj.load_inputs))
