"""Synchronization-avoiding explicit solver (paper Algorithm 3).

Synchronized steps run up to ``n_cri`` (>= n_p n_s + 1). Then, in cycles: (a) one
batched refill prediction per part of its shared-node displacements for the next
n_s n_f steps, from the last n_p n_s steps of its history; (b) n_s n_f solver steps with
no psum, each followed by overwriting the part's shared dofs with its prediction and
imposing the Dirichlet values. Each part's predictor parameters live on its device (a
stacked pytree sharded on the parts axis); the whole predicted phase is one compiled
loop per chunk of cycles with no cross-device collective in it.

A shared node is held, and predicted, by every part that touches it, so after the
switch the parts' values there differ; the returned global trajectory takes the mean
over the parts, and each part's own predictions are kept in ``trajectory.parts`` for
the error estimates of :mod:`jaxsync.metrics`.

Predictors are pytrees with a method ``predict(buffer, cycle) -> (n_s n_f, n_dof)`` for
one part (``buffer`` (n_s n_p, n_dof) of the last known steps, ``cycle`` the cycle
index): :class:`SurrogatePredictor` (trained LSTM replicas) and :class:`OraclePredictor`
(replays known displacements; pins the coupling independently of network error).
"""

from __future__ import annotations

import dataclasses
import functools
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import PartitionSpec as P

from .distributed import AXIS, DistributedRunner, PartSystems
from .errors import CheckpointError, ProblemError, StabilityError
from .pytree import pytree_dataclass, static_field
from .solver import STEP_UNROLL, SolverState, build_system, drive, initial_state, step, us_per_step

__all__ = ["SurrogatePredictor", "OraclePredictor", "simulate_sync_avoiding", "simulate_full_system",
           "shared_dof_layout"]


@pytree_dataclass
class SurrogatePredictor:
    """Trained LSTM replicas as a predictor (stacked on a leading part axis).

    Attributes:
        params: stacked network parameters.
        mean, std: (n_parts, n_dof) normalization [cm].
        dof_mask: (n_parts, n_dof) 1 on real dofs, 0 on padding.
        cond: (n_parts,) load parameter of conditional networks (ignored otherwise).
        arch: the architecture (static).
        n_s: the sampling stride the replicas were trained with (static).
    """

    params: Any
    mean: Any
    std: Any
    dof_mask: Any
    cond: Any
    arch: Any = static_field(default=None)
    n_s: int = static_field(default=1)

    @property
    def n_past(self) -> int:
        return self.arch.n_past

    @property
    def n_future(self) -> int:
        return self.arch.n_future

    def predict(self, buffer, cycle):
        """(n_s n_f, n_dof) predictions of the next steps for one part."""
        from .surrogate.evaluate import refill_predict

        cond = self.cond if self.arch.conditional else None
        out = refill_predict(self.params, self.arch, self.mean, self.std, buffer, self.n_s,
                             cond, self.dof_mask)
        return out * self.dof_mask

    @classmethod
    def initialized(cls, partition, n_s: int, *, n_hidden: int = 100, n_layers: int = 2,
                    n_past: int = 20, n_future: int = 20, dtype: str = "float32",
                    seed: int = 0) -> "SurrogatePredictor":
        """Untrained (randomly initialized) replicas for ``partition``, unit normalization.

        For timing studies: an untrained network costs exactly what a trained one of the
        same architecture costs, and needs no training run. Its predictions are
        meaningless."""
        from .surrogate.lstm import LSTMArchitecture
        from .surrogate.train import init_replicas

        n_dof, counts = shared_dof_layout(partition)
        arch = LSTMArchitecture(n_dof=n_dof, n_hidden=n_hidden, n_layers=n_layers,
                                n_past=n_past, n_future=n_future, dtype=dtype)
        params = init_replicas(jax.random.PRNGKey(seed), arch, tuple(int(c) for c in counts))
        n = partition.n_parts
        # normalization and mask in float64, as a checkpoint stores them
        mask = (np.arange(n_dof)[None, :] < counts[:, None]).astype(np.float64)
        return cls(params=params, mean=np.zeros((n, n_dof)), std=np.ones((n, n_dof)),
                   dof_mask=mask, cond=np.zeros(n, dtype=np.float32), arch=arch, n_s=int(n_s))

    @classmethod
    def from_checkpoint(cls, checkpoint, cond: float | None = None) -> "SurrogatePredictor":
        """Predictor of a :class:`jaxsync.surrogate.SurrogateCheckpoint` (or its path)."""
        from .surrogate.checkpoint import SurrogateCheckpoint, load_checkpoint

        if not isinstance(checkpoint, SurrogateCheckpoint):
            checkpoint = load_checkpoint(checkpoint)
        n = checkpoint.n_parts
        if checkpoint.arch.conditional and cond is None:
            raise CheckpointError("the surrogates are conditional on a load parameter: pass cond=")
        return cls(params=checkpoint.params, mean=np.asarray(checkpoint.mean),
                   std=np.asarray(checkpoint.std), dof_mask=checkpoint.dof_mask.astype(np.asarray(checkpoint.mean).dtype),
                   cond=np.full(n, 0.0 if cond is None else float(cond), dtype=np.float32),
                   arch=checkpoint.arch, n_s=int(checkpoint.n_s))


@pytree_dataclass
class OraclePredictor:
    """Replays known shared displacements: ``future[p, k]`` is part p's shared dofs at
    step n_cri + 1 + k (padded to whole cycles). With the synchronized run's values the
    predicted phase must reproduce that run to round-off.

    Attributes:
        future: (n_parts, n_cycles * n_s * n_f, n_dof) [cm].
        n_s, n_past, n_future: the refill geometry it stands in for (static).
    """

    future: Any
    n_s: int = static_field(default=1)
    n_past: int = static_field(default=1)
    n_future: int = static_field(default=1)

    def predict(self, buffer, cycle):
        length = self.n_s * self.n_future
        return jax.lax.dynamic_slice_in_dim(self.future, cycle * length, length, axis=0)


def shared_dof_layout(partition) -> tuple[int, np.ndarray]:
    """(n_dof padded = 3 * max shared nodes, (n_parts,) real shared-dof counts)."""
    counts = np.array([3 * p.n_shared for p in partition.parts])
    return max(int(counts.max()), 3), counts


def _predicted_cycles(part: PartSystems, predictor, state: SolverState, buffer, first_cycle,
                      n_cycles: int, steps: int, save_every: int):
    """One part: ``n_cycles`` refill cycles of ``steps`` unsynchronized steps each.

    Returns (state, buffer, saved displacement (n_cycles, steps // save_every, n_local, 3),
    saved predictions (n_cycles, steps // save_every, n_dof))."""
    history = buffer.shape[0]
    n_dof = buffer.shape[1]

    def cycle(carry, c):
        state, buffer = carry
        pred = predictor.predict(buffer, first_cycle + c).astype(buffer.dtype)  # (L, n_dof)
        nodes = pred.reshape(pred.shape[0], -1, 3)

        def one_step(st, j):
            overwrite = lambda new: new.at[part.shared_local].set(nodes[j], mode="drop")  # noqa: E731
            return step(part.system, st, overwrite=overwrite), None

        def saved_block(st, k):
            st, _ = jax.lax.scan(one_step, st, k * save_every + jnp.arange(save_every),
                                 unroll=STEP_UNROLL)
            return st, (st.displacement, pred[(k + 1) * save_every - 1])

        def saved_step(st, j):  # save_every = 1: no inner loop (it costs ~50 % per step)
            st, _ = one_step(st, j)
            return st, (st.displacement, pred[j])

        if save_every == 1:
            state, (disp, kept) = jax.lax.scan(saved_step, state, jnp.arange(steps), unroll=STEP_UNROLL)
        else:
            state, (disp, kept) = jax.lax.scan(saved_block, state, jnp.arange(steps // save_every))
        buffer = jnp.concatenate([buffer, pred])[-history:]
        return (state, buffer), (disp, kept)

    (state, buffer), (disp, kept) = jax.lax.scan(cycle, (state, buffer), jnp.arange(n_cycles))
    return state, buffer, disp, kept.reshape(n_cycles, -1, n_dof)


class _OnlineRunner:
    """Compiles and runs the predicted phase under ``shard_map`` (no collectives)."""

    def __init__(self, runner: DistributedRunner, predictor, save_every: int):
        self.runner = runner
        self.predictor = runner._put(predictor)
        self.save_every = save_every
        self._compiled = {}

    def program(self, n_cycles: int, steps: int):
        key = ("jit", n_cycles, steps)
        if key not in self._compiled:
            body = functools.partial(_predicted_cycles, n_cycles=n_cycles, steps=steps,
                                     save_every=self.save_every)
            # first_cycle is a per-part copy of the cycle counter (sharded like the rest)
            mapped = jax.shard_map(jax.vmap(body), mesh=self.runner.device_mesh,
                                   in_specs=(P(AXIS),) * 5, out_specs=(P(AXIS),) * 4,
                                   check_vma=False)
            self._compiled[key] = jax.jit(mapped)
        return self._compiled[key]

    def lowered_text(self, state, buffer, n_cycles: int, steps: int) -> str:
        """The compiled program's HLO text (to check that it has no collective)."""
        first = self._first(0)
        return self.program(n_cycles, steps).lower(self.runner.parts, self.predictor, state,
                                                   buffer, first).compile().as_text()

    def _first(self, cycle: int):
        return self.runner._put(np.full(self.runner.partition.n_parts, cycle, dtype=np.int32))

    def prepare(self, state, buffer, n_cycles: int, steps: int):
        """Compile (ahead of time, once) the program for ``n_cycles`` cycles of ``steps``."""
        key = ("compiled", n_cycles, steps)
        if key not in self._compiled:
            self._compiled[key] = self.program(n_cycles, steps).lower(
                self.runner.parts, self.predictor, state, buffer, self._first(0)).compile()
        return self._compiled[key]

    def run(self, state, buffer, first_cycle: int, n_cycles: int, steps: int):
        return self.prepare(state, buffer, n_cycles, steps)(
            self.runner.parts, self.predictor, state, buffer, self._first(first_cycle))


def simulate_sync_avoiding(problem, n_steps: int, *, partitions, surrogates, n_cri: int,
                           dt=None, mode: str = "preassembled", save_every: int = 1,
                           seed: int = 0, devices=None, cond: float | None = None,
                           progress: bool | None = None, cycles_per_chunk: int | None = None,
                           resync_tolerance: float | None = None):
    """Run paper Algorithm 3: synchronized up to ``n_cri``, then surrogate-predicted.

    Going beyond the paper, ``resync_tolerance`` turns the estimate es_hat (paper eq. 26:
    the mean disagreement of the parts' predictions at the shared nodes, which needs no
    reference solution) into a live monitor: after each compiled chunk of refill cycles,
    if es_hat at any saved step of the chunk exceeds the tolerance, the parts are brought
    back to one state (the mean over the parts at shared nodes), the solver runs
    synchronized for n_p n_s steps -- which refills every network's input history with
    synchronized values -- and prediction resumes.

    Args:
        problem: the problem.
        n_steps: total steps; steps n_cri + 1 .. n_steps are predicted.
        partitions: n_parts or a :class:`jaxsync.Partition` (the surrogates' partition).
        surrogates: a surrogate checkpoint (path or
            :class:`jaxsync.surrogate.SurrogateCheckpoint`), a :class:`SurrogatePredictor`
            or an :class:`OraclePredictor`.
        n_cri: last synchronized step; at least n_p n_s + 1.
        save_every: snapshot stride; must divide n_cri and n_s n_f.
        cond: load parameter for conditional surrogates.
        cycles_per_chunk: refill cycles per compiled call (default: about 20 000 steps;
            1 when ``resync_tolerance`` is given, so that the monitor acts every cycle).
        resync_tolerance: es_hat [cm] above which the run re-synchronizes (None: never).
            Needs ``save_every`` to divide n_p n_s, and a predictor that works from its
            input history (not an :class:`OraclePredictor`).

    Returns:
        :class:`jaxsync.Trajectory` with ``synchronized`` flags (True at the snapshots of
        synchronized steps, re-synchronized ones included) and, per part,
        ``predicted_shared_displacement`` (n_predicted_saved, 3 n_shared_p): the part's own
        predictions at the saved predicted steps. With a tolerance, ``parameters`` holds
        ``resynchronized_at`` (the steps at which re-synchronization started) and
        ``es_hat_trigger`` (the es_hat that triggered each) [cm].

    Raises:
        ProblemError: n_cri too small, save_every not dividing n_cri and n_s n_f (and n_p
            n_s with a tolerance), a tolerance that is not > 0 or with an oracle.
        CheckpointError: surrogates made for another partition.
        StabilityError: a prediction turned NaN/Inf (the message names the step and the
            part; ``error.trajectory`` keeps the snapshots saved before).
    """
    from .surrogate.checkpoint import SurrogateCheckpoint, check_compatible, load_checkpoint

    n_steps, n_cri, save_every = int(n_steps), int(n_cri), int(save_every)
    dt = problem.dt if dt is None else float(dt)
    if isinstance(surrogates, (str, bytes)) or hasattr(surrogates, "__fspath__"):
        surrogates = load_checkpoint(surrogates)
    system = build_system(problem, dt, mode)
    runner = DistributedRunner(problem, system, partitions, save_every=1, mode=mode, seed=seed,
                               devices=devices)
    partition = runner.partition
    n_dof, counts = shared_dof_layout(partition)
    if isinstance(surrogates, SurrogateCheckpoint):
        check_compatible(surrogates, [p.shared_nodes for p in partition.parts])
        predictor = SurrogatePredictor.from_checkpoint(surrogates, cond)
    else:
        predictor = surrogates
    n_s, n_p, n_f = predictor.n_s, predictor.n_past, predictor.n_future
    if isinstance(predictor, SurrogatePredictor) and predictor.arch.n_dof != n_dof:
        raise CheckpointError(f"the surrogates predict {predictor.arch.n_dof} dofs per part but this "
                              f"partition needs {n_dof}: retrain on this partition")
    history, cycle_steps = n_s * n_p, n_s * n_f
    if n_cri < history + 1:
        raise ProblemError(f"n_cri={n_cri} is too small: the first refill needs n_p * n_s + 1 = "
                           f"{history + 1} synchronized steps (n_p={n_p}, n_s={n_s})")
    if n_cri > n_steps:
        raise ProblemError(f"n_cri={n_cri} is beyond n_steps={n_steps}")
    if n_cri % save_every or cycle_steps % save_every or n_steps % save_every:
        raise ProblemError(f"save_every={save_every} must divide n_cri={n_cri}, n_steps={n_steps} "
                           f"and the steps per refill cycle n_s * n_f = {cycle_steps}")
    monitor = None
    if resync_tolerance is not None:
        try:
            tolerance_ok = float(resync_tolerance) > 0  # False for NaN; inf never triggers
        except (TypeError, ValueError):
            tolerance_ok = False
        if not tolerance_ok:
            raise ProblemError(f"resync_tolerance must be a tolerance > 0 [cm], got {resync_tolerance!r}")
        if isinstance(predictor, OraclePredictor):
            raise ProblemError("resync_tolerance needs a predictor that works from its input history; "
                               "an OraclePredictor replays fixed values")
        if history % save_every:
            raise ProblemError(f"with resync_tolerance, save_every={save_every} must also divide the "
                               f"re-synchronized steps n_p * n_s = {history}")
        monitor = _DisagreementMonitor(partition)
        cycles_per_chunk = cycles_per_chunk or 1

    # synchronized phase: every step kept (the refill history), thinned afterwards
    state0 = initial_state(problem, system)
    synced = drive(problem, runner, state0, n_cri, dt, 1, partition=partition, progress=progress,
                   label="synchronized")
    sync_disp = synced.displacement
    last = SolverState(jnp.asarray(sync_disp[-1]), jnp.asarray(sync_disp[-2]),
                       jnp.asarray(n_cri, dtype=jnp.int32))
    state = runner.from_global(last)
    buffer = np.zeros((partition.n_parts, history, n_dof))
    for p, part in enumerate(partition.parts):
        buffer[p, :, :counts[p]] = sync_disp[-history:, part.shared_nodes].reshape(history, -1)
    buffer = runner._put(buffer)

    online = _OnlineRunner(runner, predictor, save_every)
    n_predicted = n_steps - n_cri
    per_chunk = cycles_per_chunk or max(1, 20000 // cycle_steps)
    timeline = []  # in order: ("predicted", local displacement, predictions) / ("synchronized", global)
    resynced_at, triggers = [], []
    from tqdm import tqdm

    show = progress if progress is not None else n_predicted >= 20000
    bar = tqdm(total=n_predicted, disable=not show, unit="step", desc="predicted", dynamic_ncols=True)
    step_now, cycle = n_cri, 0
    chunk_times = []
    try:
        while step_now < n_steps:
            left = n_steps - step_now
            k, steps = (min(per_chunk, left // cycle_steps), cycle_steps) if left >= cycle_steps else (1, left)
            online.prepare(state, buffer, k, steps)  # compilation is not timed
            start = time.perf_counter()
            state, buffer, disp, pred = online.run(state, buffer, cycle, k, steps)
            disp, pred = _host(disp), _host(pred)  # (P, k, steps/save, ...)
            chunk_times.append((None, k * steps, time.perf_counter() - start))
            bad = ~np.isfinite(pred).all(axis=-1)  # (P, k, n_saved)
            if bad.any():
                p, c, j = (int(i[0]) for i in np.nonzero(bad))
                bad_step = step_now + c * steps + (j + 1) * save_every
                partial = _assemble(problem, partition, synced, timeline, counts, dt, save_every, n_cri)
                err = StabilityError(
                    f"the surrogate of part {p} predicted NaN/Inf for step {bad_step} "
                    f"(t = {bad_step * dt:.6g} s): the network diverged; retrain it or raise n_cri. "
                    f"The {partial.n_saved} snapshots saved before are kept (error.trajectory)")
                err.trajectory = partial
                raise err
            pred = pred.reshape(pred.shape[0], -1, pred.shape[-1])
            timeline.append(("predicted", disp.reshape(disp.shape[0], -1, *disp.shape[3:]), pred))
            bar.update(k * steps)
            cycle += k
            step_now += k * steps
            if monitor is not None and step_now < n_steps:
                es_hat = monitor.es_hat(pred, counts)
                if es_hat.max() > resync_tolerance:
                    # one state for all parts, then n_p n_s synchronized steps refill the history
                    resynced_at.append(step_now)
                    triggers.append(float(es_hat.max()))
                    length = min(history, n_steps - step_now)
                    merged = SolverState(_mean_over_parts(problem, partition, _host(state.displacement)),
                                         _mean_over_parts(problem, partition, _host(state.previous)), step_now)
                    segment = drive(problem, runner, merged, step_now + length, dt, 1,
                                    partition=partition, progress=False, label="resynchronized")
                    disp_sync = segment.displacement  # (length + 1, n_nodes, 3), from step_now
                    timeline.append(("synchronized", disp_sync[save_every::save_every]))
                    step_now += length
                    bar.update(length)
                    state = runner.from_global(SolverState(disp_sync[-1], disp_sync[-2], step_now))
                    if length == history:
                        refill = np.zeros((partition.n_parts, history, n_dof))
                        for p, part in enumerate(partition.parts):
                            refill[p, :, :counts[p]] = disp_sync[-history:, part.shared_nodes].reshape(history, -1)
                        buffer = runner._put(refill)
    finally:
        bar.close()
    traj = _assemble(problem, partition, synced, timeline, counts, dt, save_every, n_cri)
    if monitor is not None:
        traj = dataclasses.replace(traj, parameters={**traj.parameters, "resync_tolerance": resync_tolerance,
                                                     "resynchronized_at": resynced_at,
                                                     "es_hat_trigger": triggers})
    if chunk_times:
        traj = dataclasses.replace(traj, parameters={**traj.parameters, "us_per_step_predicted": us_per_step(chunk_times)})
    return traj


def _host(x) -> np.ndarray:
    from .distributed import _to_host

    return _to_host(x)


def _mean_over_parts(problem, partition, local) -> np.ndarray:
    """(n_nodes, 3) global field from per-part local fields (P, ..., n_local_max, 3): the
    mean over the parts that hold each node (they differ at shared nodes after prediction)."""
    local = np.asarray(local)
    total = np.zeros(local.shape[1:-2] + (problem.mesh.n_nodes, 3))
    count = np.zeros(problem.mesh.n_nodes)
    for p, part in enumerate(partition.parts):
        total[..., part.nodes, :] += local[p, ..., :part.n_local, :]
        count[part.nodes] += 1
    return total / count[:, None]


class _DisagreementMonitor:
    """es_hat (paper eq. 26) of the parts' own predictions, for the live re-synchronization."""

    def __init__(self, partition):
        from .metrics import shared_node_errors

        self._errors = shared_node_errors
        index = {int(node): k for k, node in enumerate(partition.shared_nodes)}
        self.columns = [np.array([index[int(n)] for n in part.shared_nodes], dtype=int)
                        for part in partition.parts]
        self.holds = np.zeros((partition.n_parts, len(partition.shared_nodes)), bool)
        for p, cols in enumerate(self.columns):
            self.holds[p, cols] = True

    def es_hat(self, pred, counts) -> np.ndarray:
        """(T,) es_hat of predictions (P, T, n_dof) [cm]."""
        n_parts, T = pred.shape[:2]
        by_node = np.zeros((n_parts, T, self.holds.shape[1], 3))
        for p, cols in enumerate(self.columns):
            by_node[p][:, cols] = pred[p, :, :counts[p]].reshape(T, -1, 3)
        return self._errors(np.zeros(by_node.shape[1:]), by_node, self.holds).es_hat


def _assemble(problem, partition, synced, timeline, counts, dt, save_every, n_cri):
    """The global trajectory: synchronized snapshots up to n_cri, then the segments of
    ``timeline`` in order -- predicted ones (mean over the parts that hold each node, with
    per-part predictions) and re-synchronized ones -- with per-snapshot flags."""
    from .trajectory import Trajectory

    pieces = [synced.displacement[::save_every]]
    flags = [np.ones(len(pieces[0]), bool)]
    preds = []
    for kind, values, *rest in timeline:
        if kind == "predicted":
            pieces.append(_mean_over_parts(problem, partition, np.asarray(values)))
            preds.append(rest[0])
        else:
            pieces.append(values)
        flags.append(np.full(len(pieces[-1]), kind == "synchronized"))
    pred = (np.concatenate(preds, axis=1) if preds
            else np.zeros((partition.n_parts, 0, max(counts.max(), 3))))
    displacement = np.concatenate(pieces)
    n_saved = len(displacement)
    synchronized = np.concatenate(flags)
    parts = []
    for p, part in enumerate(partition.parts):
        shared = displacement[:, part.shared_nodes].reshape(n_saved, -1)
        parts.append({"shared_nodes": part.shared_nodes, "elements": part.elements,
                      "shared_displacement": shared,
                      "predicted_shared_displacement": pred[p, :, :counts[p]]})
    return Trajectory(times=np.arange(n_saved) * save_every * dt, displacement=displacement,
                      mesh=problem.mesh, dt=dt, save_every=save_every,
                      parameters={**synced.parameters, "n_cri": n_cri}, parts=tuple(parts),
                      synchronized=synchronized)


def simulate_full_system(problem, reference, surrogates, *, n_cri: int, n_steps: int | None = None,
                         cond: float | None = None):
    """Full-system modeling (paper "Full system modeling"): one surrogate predicts every dof.

    The synchronized ``reference`` (saved at every step) supplies the first ``n_cri``
    steps; after that no solver step runs: refill cycles of the single surrogate,
    each consuming earlier predictions, produce all displacements. The network does not
    know the Dirichlet conditions; their predicted values are reported, not enforced.

    Args:
        problem: the problem (for its Dirichlet dofs).
        reference: :class:`jaxsync.Trajectory` saved at every step, at least n_cri + 1 long.
        surrogates: a one-replica checkpoint (path or object) over all 3 n_nodes dofs, a
            :class:`SurrogatePredictor` or an :class:`OraclePredictor` (one part).
        n_cri: last step taken from the reference (>= n_p n_s + 1).
        n_steps: total steps (default: the reference's length).

    Returns:
        :class:`jaxsync.Trajectory` (saved every step) with ``synchronized`` flags and
        ``parameters["dirichlet_max_abs_predicted"]``, the largest |predicted value| on the
        Dirichlet dofs, whose prescribed values the network does not enforce.
    """
    from .surrogate.checkpoint import SurrogateCheckpoint, load_checkpoint
    from .trajectory import Trajectory

    if reference.save_every != 1:
        raise ProblemError("full-system modeling needs the reference saved at every step")
    n_steps = reference.n_saved - 1 if n_steps is None else int(n_steps)
    if isinstance(surrogates, (str, bytes)) or hasattr(surrogates, "__fspath__"):
        surrogates = load_checkpoint(surrogates)
    n_dof = problem.mesh.n_dofs
    if isinstance(surrogates, SurrogateCheckpoint):
        if surrogates.n_parts != 1 or surrogates.dof_counts[0] != n_dof:
            raise CheckpointError(f"full-system modeling needs one surrogate over all {n_dof} dofs; "
                                  f"the checkpoint has {surrogates.n_parts} replicas with "
                                  f"{list(surrogates.dof_counts)} dofs")
        predictor = SurrogatePredictor.from_checkpoint(surrogates, cond)
    else:
        predictor = surrogates
    history, cycle_steps = predictor.n_s * predictor.n_past, predictor.n_s * predictor.n_future
    if n_cri < history + 1:
        raise ProblemError(f"n_cri={n_cri} is too small: the first refill needs n_p * n_s + 1 = "
                           f"{history + 1} known steps")
    if reference.n_saved < n_cri + 1:
        raise ProblemError(f"the reference holds {reference.n_saved} snapshots, fewer than n_cri + 1")
    known = np.asarray(reference.displacement[:n_cri + 1]).reshape(n_cri + 1, -1)
    n_cycles = -(-(n_steps - n_cri) // cycle_steps)
    one = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[0], predictor)

    @jax.jit
    def rollout(buffer):
        def cycle(buf, c):
            pred = one.predict(buf, c).astype(buf.dtype)
            return jnp.concatenate([buf, pred])[-history:], pred

        _, blocks = jax.lax.scan(cycle, buffer, jnp.arange(n_cycles))
        return blocks.reshape(-1, buffer.shape[1])

    start = time.perf_counter()
    predicted = np.asarray(rollout(jnp.asarray(known[-history:])))[:n_steps - n_cri]
    seconds = time.perf_counter() - start
    if not np.all(np.isfinite(predicted)):
        bad = n_cri + 1 + int(np.argmin(np.isfinite(predicted).all(axis=1)))
        raise StabilityError(f"the full-system surrogate predicted NaN/Inf for step {bad}; retrain it")
    displacement = np.concatenate([known, predicted]).reshape(n_steps + 1, -1, 3)
    fixed, values = problem.dirichlet_dofs()
    dirichlet_error = float(np.abs(predicted[:, fixed] - values).max()) if len(predicted) else 0.0
    return Trajectory(times=np.arange(n_steps + 1) * reference.dt, displacement=displacement,
                      mesh=problem.mesh, dt=reference.dt, save_every=1,
                      parameters={**reference.parameters, "n_cri": n_cri,
                                  "dirichlet_max_abs_predicted": dirichlet_error,
                                  "us_per_step_predicted": 1e6 * seconds / max(n_steps - n_cri, 1)},
                      synchronized=np.arange(n_steps + 1) <= n_cri)
