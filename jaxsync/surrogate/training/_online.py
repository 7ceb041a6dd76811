"""Learning while synchronized: surrogate updates from the steps a run recomputes.

When error control rejects a refill cycle, the host executor recomputes the steps from
its last synchronized point with the synchronized solver (:mod:`jaxsync.solve.executors`).
Those steps are exact shared-node values at the run's current state: the data the
surrogates lacked. :class:`OnlineLearning` turns them into sample-refill windows (the
windows of offline training, :mod:`jaxsync.surrogate.training`: n_p inputs n_s steps apart,
the next n_f samples as targets, with the load signals at the same steps), mixes in
windows replayed from the run's first synchronized stretch (the span the surrogates were
trained on, so that an update does not unlearn it) and takes full-batch Adam steps on all
replicas together, from their current weights, within a budget of update time. The
update is kept only where it lowers the error of what the run does with the surrogates
(per part): the refill rollout over the newest recomputed stretch, each part fed its own
predictions, against the recomputed values (a lower error one window ahead can still drift
cycle after cycle).

Each model learns the way it is fitted (its ``online_update``,
:mod:`jaxsync.surrogate.models`): a model trained by gradient (the LSTM encoder-decoder,
or a user's :class:`~jaxsync.surrogate.models.GradientFitted`) takes the Adam steps above
(:meth:`OnlineLearner.gradient_steps`); a model fitted in closed form (the linear
autoregressive model, :class:`~jaxsync.surrogate.models.LeastSquaresFitted`) corrects
its first fit: one solve on every window the run has synchronized -- each chained window
of the first stretch (one per stride, so that the fit's rollouts run over them) and the
recomputed ones, all weighed alike (its rank, the shape of its factors, stays as fitted).
A refit on the recomputed windows alone, a short stretch in which the loads hardly vary,
explains them and still drifts when fed its own predictions beyond them.

:func:`sample_refill_windows` cuts windows from rows of every step;
:class:`OnlineLearner` keeps a run's windows and updates the predictor.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxsync.errors import ConfigError
from jaxsync.surrogate.training._data import normalize
from jaxsync.surrogate.training._evaluate import rollout_parts

__all__ = ["OnlineLearning", "OnlineLearner", "UpdateReport", "sample_refill_windows"]


def _whole(value, name: str, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise ConfigError(f"OnlineLearning.{name} must be a whole number >= {low}, got {value!r}")
    return int(value)


def _positive(value, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) or not value > 0:
        raise ConfigError(f"OnlineLearning.{name} must be a number > 0, got {value!r}")
    return float(value)


@dataclasses.dataclass(frozen=True)
class OnlineLearning:
    """How a synchronization-avoiding run learns from the steps it recomputes.

    Attributes:
        iterations: Adam steps per update (full batch: the new windows and the replayed
            ones together).
        learning_rate: Adam's step size (on the normalized loss).
        budget_seconds: the most wall time all updates of one run may take together [s];
            an update stops early (after a whole block of ``iterations_per_call``) once
            it is spent, and none starts after.
        windows: the most windows kept from recomputed stretches (the newest; windows
            that start within one stride n_s of each other are thinned to
            ``starts_per_stride`` per stride).
        replay: windows of the first synchronized stretch mixed into every gradient
            update (evenly spread over it); a closed-form refit replays every chained
            window of that stretch (one per stride) instead; 0: none, for either.
        starts_per_stride: window starts per n_s steps taken from a recomputed stretch.
        new_weight: the share of a gradient update's loss carried by the new windows
            (the replayed ones carry the rest), 0 < new_weight <= 1; a closed-form refit
            weighs every window alike.
        iterations_per_call: Adam steps per compiled call (the budget is checked between
            calls).
        save_to: a surrogate file (``.h5``) the learned surrogates are written to after
            every update that changed them, atomically, with the run's shared nodes and
            the steps of the updates in its metadata (``online_learning``): a surrogate
            file like the trained one, to run or learn from again; None (default): kept
            in memory only.
    """

    iterations: int = 100
    learning_rate: float = 1e-3
    budget_seconds: float = 120.0
    windows: int = 256
    replay: int = 128
    starts_per_stride: int = 4
    new_weight: float = 0.5
    iterations_per_call: int = 10
    save_to: str | None = None

    def __post_init__(self):
        _whole(self.iterations, "iterations", 1)
        _positive(self.learning_rate, "learning_rate")
        _positive(self.budget_seconds, "budget_seconds")
        _whole(self.windows, "windows", 1)
        _whole(self.replay, "replay", 0)
        _whole(self.starts_per_stride, "starts_per_stride", 1)
        _whole(self.iterations_per_call, "iterations_per_call", 1)
        if not 0 < _positive(self.new_weight, "new_weight") <= 1:
            raise ConfigError(f"OnlineLearning.new_weight must be in (0, 1], got {self.new_weight!r}")
        if self.save_to is not None:
            if not isinstance(self.save_to, (str, os.PathLike)) or not os.fspath(self.save_to):
                raise ConfigError(f"OnlineLearning.save_to must be a file path, got {self.save_to!r}")
            folder = os.path.dirname(os.path.abspath(os.fspath(self.save_to)))
            if not os.path.isdir(folder):
                raise ConfigError(f"OnlineLearning.save_to={os.fspath(self.save_to)!r}: the folder {folder!r} does "
                                  "not exist; create it first")
            object.__setattr__(self, "save_to", os.fspath(self.save_to))

    @classmethod
    def parse(cls, value) -> "OnlineLearning | None":
        """None or False: no learning; True: the defaults; an :class:`OnlineLearning`: itself."""
        if value is None or value is False:
            return None
        if value is True:
            return cls()
        if isinstance(value, cls):
            return value
        raise ConfigError(f"learning={value!r}: give True (the defaults), "
                          "jaxsync.surrogate.OnlineLearning(...), or None/False (no learning)")


def sample_refill_windows(rows: np.ndarray, n_s: int, n_past: int, n_future: int, starts: np.ndarray):
    """Sample-refill windows cut from rows of consecutive steps.

    Window ``w`` ends its inputs at row ``c = starts[w]``: inputs rows ``c - n_s (n_p - 1),
    ..., c - n_s, c`` and targets rows ``c + n_s, ..., c + n_s n_f`` (the spacing of
    refill application ``i``'s N_p^i and N_f^i, :mod:`jaxsync.surrogate`).

    Args:
        rows: (..., n_rows, width) values at consecutive steps (leading axes kept, e.g.
            the parts).
        n_s, n_past, n_future: the refill geometry.
        starts: (n_w,) rows c, each with n_s (n_p - 1) <= c < n_rows - n_s n_f.

    Returns:
        ``(x (..., n_w, n_p, width), y (..., n_w, n_f, width))``.
    """
    starts = np.asarray(starts, np.int64)
    n_rows = rows.shape[-2]
    if starts.size and (starts.min() < n_s * (n_past - 1) or starts.max() >= n_rows - n_s * n_future):
        raise ConfigError(f"window starts must lie in [{n_s * (n_past - 1)}, {n_rows - n_s * n_future}) for "
                          f"{n_rows} rows, n_s={n_s}, n_p={n_past}, n_f={n_future}")
    past = starts[:, None] + n_s * (np.arange(n_past) - (n_past - 1))[None]
    future = starts[:, None] + n_s * np.arange(1, n_future + 1)[None]
    return np.take(rows, past, axis=-2), np.take(rows, future, axis=-2)


def window_starts(n_rows: int, n_s: int, n_past: int, n_future: int, per_stride: int, count: int | None = None):
    """Window starts (rows c) in ``n_rows`` rows: ``per_stride`` per n_s steps, the
    newest first kept; with ``count``, at most that many, evenly spread (newest kept)."""
    first, last = n_s * (n_past - 1), n_rows - n_s * n_future - 1
    if last < first:
        return np.zeros(0, np.int64)
    spacing = max(1, n_s // per_stride)
    starts = np.arange(last, first - 1, -spacing)[::-1]
    if count is not None and starts.size > count:
        pick = np.unique(np.round(np.linspace(0, starts.size - 1, count)).astype(np.int64))
        starts = starts[pick]
    return starts


@dataclasses.dataclass(frozen=True)
class UpdateReport:
    """One update of the surrogates.

    Attributes:
        step: the run's step it followed (the end of a recomputed stretch).
        n_new, n_replay: windows of recomputed stretches and of the first synchronized
            stretch the gradient update trained on (a closed-form refit fits every
            chained window of that stretch, :meth:`OnlineLearner.every_window`).
        iterations: Adam steps taken.
        loss_before, loss_after: (n_parts,) mean squared error on the new windows
            (normalized units) before and after (after: as kept).
        kept: (n_parts,) bool, the parts that took the update: those whose rollout error
            over the newest recomputed stretch fell (where it holds a whole refill cycle
            beyond the input history; else those whose ``loss`` fell); the others kept
            their weights.
        rollout_before, rollout_after: (n_parts,) that rollout's mean squared error [cm^2]
            before and after (after: as kept), or None where the stretch is too short.
        seconds: its wall time (compilation included) [s].
    """

    step: int
    n_new: int
    n_replay: int
    iterations: int
    loss_before: np.ndarray
    loss_after: np.ndarray
    seconds: float
    kept: np.ndarray | None = None
    rollout_before: np.ndarray | None = None
    rollout_after: np.ndarray | None = None


def _replica_loss(params, arch, x, y, u, weight, load_parameter, dof_mask):
    """Weighted mean squared error of one replica over its windows (normalized units)."""
    load = load_parameter if arch.conditional else None
    if u is None:
        pred = jax.vmap(lambda xs: arch.forward(params, xs, load, dof_mask))(x)
    else:
        pred = jax.vmap(lambda xs, us: arch.forward(params, xs, load, dof_mask, None, us))(x, u)
    sq = jnp.square(pred - y) * dof_mask[None, None]
    per_window = jnp.sum(sq, axis=(1, 2)) / (arch.n_future * jnp.maximum(jnp.sum(dof_mask), 1.0))
    return jnp.sum(weight * per_window) / jnp.sum(weight)


@functools.partial(jax.jit, static_argnames=("arch",))
def _losses(params, x, y, u, weight, load_parameter, dof_mask, *, arch):
    u_axis = None if u is None else 0
    return jax.vmap(_replica_loss, in_axes=(0, None, 0, 0, u_axis, None, 0, 0))(
        params, arch, x, y, u, weight, load_parameter, dof_mask)


@functools.partial(jax.jit, static_argnames=("arch", "optimizer", "n_iterations"))
def _adam_block(params, opt_state, x, y, u, weight, load_parameter, dof_mask, *, arch, optimizer, n_iterations):
    """``n_iterations`` full-batch steps of every replica. The loss is the sum of the
    replicas' losses, so each replica's gradient is its own, and Adam (elementwise) on the
    stacked parameters is Adam on each replica."""
    def total(stacked):
        return jnp.sum(_losses.__wrapped__(stacked, x, y, u, weight, load_parameter, dof_mask, arch=arch))

    def body(carry, _):
        p, state = carry
        with jax.numpy_dtype_promotion("standard"):  # optax's bias correction mixes float and int
            updates, state = optimizer.update(jax.grad(total)(p), state, p)
        return (optax.apply_updates(p, updates), state), None

    (params, opt_state), _ = jax.lax.scan(body, (params, opt_state), None, length=n_iterations)
    return params, opt_state


class OnlineLearner:
    """The windows of one run and the updates of its predictor.

    Args:
        settings: :class:`OnlineLearning`.
        predictor: the run's :class:`~jaxsync.surrogate.Surrogate` (stacked replicas,
            bound to the problem's load signals when it reads them).
        replay_rows: per part, (n_rows, 3 n_shared_p) the shared values of the first
            synchronized stretch at every step from step 0, or None (no replay).
        shared_nodes: per part, the global ids of its shared nodes, recorded in the file
            of ``settings.save_to`` (None: not recorded).
    """

    def __init__(self, settings: OnlineLearning, predictor, replay_rows=None, shared_nodes=None):
        if not hasattr(predictor, "params") or not hasattr(predictor, "arch"):
            raise ConfigError(f"online learning updates trained surrogates (jaxsync.surrogate.Surrogate); "
                              f"{type(predictor).__name__} has no weights to learn")
        self.settings, self.predictor = settings, predictor
        self.shared_nodes = shared_nodes
        self.n_s, self.n_past, self.n_future = predictor.n_s, predictor.n_past, predictor.n_future
        self.spent = 0.0
        self._optimizer = optax.adam(settings.learning_rate)  # one per run: its compiled steps are reused
        self.reports: list[UpdateReport] = []
        self._new: list[tuple] = []  # (x, y, u) normalized windows of recomputed stretches, oldest first
        self._stretch = None  # (rows per part, first step) of the newest recomputed stretch
        self._replay = self._replay_chained = None
        if replay_rows is not None and settings.replay:
            n_rows = len(replay_rows[0])
            starts = window_starts(n_rows, self.n_s, self.n_past, self.n_future, settings.starts_per_stride,
                                   settings.replay)
            if starts.size:
                self._replay = self._windows(replay_rows, 0, starts)
                # a closed-form refit corrects the first fit: every chained window of the stretch
                self._replay_chained = self._windows(replay_rows, 0,
                                                     window_starts(n_rows, self.n_s, self.n_past, self.n_future, 1))

    @property
    def exhausted(self) -> bool:
        """The run's budget of update time is spent."""
        return self.spent >= self.settings.budget_seconds

    def _windows(self, rows, first_step: int, starts: np.ndarray):
        """Normalized (x, y, u) windows (n_parts, n_w, ...) of ``rows``, per part (n_rows,
        width_p) values at consecutive steps from ``first_step`` (padded here to the
        replicas' width); u None without load input."""
        p = self.predictor
        width = p.n_dof
        mean, std = np.asarray(p.mean)[:, None, None], np.asarray(p.std)[:, None, None]
        cut = [sample_refill_windows(np.asarray(r), self.n_s, self.n_past, self.n_future, starts) for r in rows]
        pad = lambda a: np.pad(a, [(0, 0)] * (a.ndim - 1) + [(0, width - a.shape[-1])])  # noqa: E731
        x = np.stack([pad(xp) for xp, _ in cut])
        y = np.stack([pad(yp) for _, yp in cut])
        x, y = normalize(x, mean, std), normalize(y, mean, std)
        u = None
        if p.n_load:
            n_rows = len(rows[0])
            table = np.asarray(p.load_signals.at_steps(first_step, n_rows), np.float64)  # (n_rows, n_u)
            ux, uy = sample_refill_windows(table, self.n_s, self.n_past, self.n_future, starts)
            signals = np.concatenate([ux, uy], axis=1)  # (n_w, n_p + n_f, n_u)
            u = signals[None] / np.asarray(p.signal_scale)[:, None, None, :]
        return x, y, u

    def add_stretch(self, rows, first_step: int) -> int:
        """Keep the windows of recomputed rows (per part, (n_rows, 3 n_shared_p)) whose row 0
        is step ``first_step`` (the input history before the stretch included); returns
        how many were added."""
        s = self.settings
        starts = window_starts(len(rows[0]), self.n_s, self.n_past, self.n_future, s.starts_per_stride)
        if not starts.size:
            return 0
        starts = starts[-s.windows:]
        self._new.append(self._windows(rows, first_step, starts))
        self._stretch = ([np.asarray(r) for r in rows], int(first_step))  # the rollout that judges an update
        while sum(w[0].shape[1] for w in self._new[1:]) >= s.windows:
            del self._new[0]  # the newest windows are kept
        return int(starts.size)

    def gradient_steps(self, params, x, y, u, weight, q, mask, start: float):
        """Full-batch Adam steps on the stacked replicas ``params`` within the budget, the
        update started at ``start`` (``time.perf_counter()``): (params, steps taken). What
        a :class:`~jaxsync.surrogate.models.GradientFitted` model's ``online_update`` runs.

        Args:
            x, y, u: (n_parts, n_w, ...) normalized windows (``u`` None without load input).
            weight: (n_w,) window weights; q: the load parameter; mask: (n_parts, n_dof).
        """
        s = self.settings
        opt_state = self._optimizer.init(params)
        done = 0
        while done < s.iterations:
            block = min(s.iterations_per_call, s.iterations - done)
            params, opt_state = _adam_block(params, opt_state, x, y, u, weight, q, mask, arch=self.predictor.arch,
                                            optimizer=self._optimizer, n_iterations=block)
            done += block
            if self.spent + time.perf_counter() - start >= s.budget_seconds:
                break
        return params, done

    def rollout_error(self, predictor):
        """(n_parts,) mean squared error [cm^2] of ``predictor``'s refill rollout over the
        newest recomputed stretch (each part fed its own predictions from the first step
        with a whole input history, as a predicted run does, against the recomputed values:
        the truth), over as many whole cycles as the stretch holds; None when it holds
        none."""
        if self._stretch is None:
            return None
        rows, first = self._stretch
        history, cycle = self.n_s * self.n_past, self.n_s * self.n_future
        n_cycles = (len(rows[0]) - history) // cycle
        if n_cycles < 1:
            return None
        width = predictor.n_dof
        padded = np.stack([np.pad(r, [(0, 0), (0, width - r.shape[1])]) for r in rows])
        buffers = jnp.asarray(padded[:, :history])  # the solver's values, as a run feeds them
        predicted = np.asarray(rollout_parts(predictor, buffers, first + history - 1, n_cycles), np.float64)
        truth = padded[:, history:history + n_cycles * cycle]
        counts = np.array([r.shape[1] for r in rows])
        return np.square(predicted - truth).sum(axis=(1, 2)) / (predicted.shape[1] * counts)

    def every_window(self):
        """What a closed-form refit fits (a :class:`~jaxsync.surrogate.models.LeastSquaresFitted`
        model's ``online_update``, an LSTM's linear highway): the windows of the recomputed
        stretches kept so far and every chained window of the first synchronized stretch
        (one per stride, so that rollouts run over them; none with ``replay=0``), all
        weighed alike, in the replicas' dtype.

        Returns:
            ``(x, y, u, weight)``: (n_parts, n_w, n_p, D), (n_parts, n_w, n_f, D),
            (n_parts, n_w, n_p + n_f, L) or None, (n_w,) ones.
        """
        sets = list(self._new) + ([self._replay_chained] if self._replay_chained is not None else [])
        if not sets:
            raise ConfigError("no windows to refit on: add a recomputed stretch first (add_stretch)")
        dtype = np.dtype(self.predictor.arch.dtype)
        x, y, u = (None if sets[0][k] is None else np.concatenate([w[k] for w in sets], axis=1).astype(dtype)
                   for k in range(3))
        return x, y, u, np.ones(x.shape[1], dtype)

    def update(self, step: int):
        """Train on the windows kept so far; returns the updated predictor (the same
        object when nothing was learned) and records an :class:`UpdateReport`."""
        s = self.settings
        if not self._new or self.exhausted:
            return self.predictor
        start = time.perf_counter()
        p = self.predictor
        arch = p.arch
        dtype = jnp.dtype(arch.dtype)
        new = [None if parts[0] is None else np.concatenate(parts, axis=1)[:, -s.windows:]
               for parts in zip(*self._new)]
        n_new = new[0].shape[1]
        # a fixed number of window slots (the unused ones weigh 0): one compiled update per run
        new = [None if a is None else np.pad(a, [(0, 0), (0, s.windows - n_new)] + [(0, 0)] * (a.ndim - 2))
               for a in new]
        sets = [new]
        n_replay = 0
        if self._replay is not None:
            sets.append(list(self._replay))
            n_replay = self._replay[0].shape[1]
        x, y, u = (None if sets[0][k] is None else np.concatenate([w[k] for w in sets], axis=1) for k in range(3))
        slots = np.arange(s.windows) < n_new
        weight = np.concatenate([slots * ((s.new_weight if n_replay else 1.0) / n_new)]
                                + ([np.full(n_replay, (1.0 - s.new_weight) / n_replay)] if n_replay else []))
        cast = lambda a: None if a is None else jnp.asarray(a, dtype)  # noqa: E731
        x, y, u, weight = cast(x), cast(y), cast(u), cast(weight)
        only_new = jnp.concatenate([jnp.asarray(slots, dtype), jnp.zeros(n_replay, dtype)])
        q = jnp.asarray(np.asarray(p.load_parameter), dtype)
        mask = jnp.asarray(np.asarray(p.dof_mask), dtype)
        params = jax.tree_util.tree_map(lambda a: jnp.asarray(np.asarray(a)), p.params)
        before = np.asarray(_losses(params, x, y, u, only_new, q, mask, arch=arch))
        trained, done = arch.online_update(self, params, x, y, u, weight, q, mask, start)
        after = np.asarray(_losses(trained, x, y, u, only_new, q, mask, arch=arch))
        # judged by what the run does with it: fed its own predictions over the newest stretch
        # (a lower error one window ahead can still drift cycle after cycle)
        rollout_before = self.rollout_error(p)
        if rollout_before is None:  # a stretch too short for one cycle: the windows' error
            better = np.isfinite(after) & (after < before)
            rollout_after = None
        else:
            rollout_after = self.rollout_error(dataclasses.replace(p, params=trained))
            better = np.isfinite(rollout_after) & (rollout_after < rollout_before)
        keep = jnp.asarray(better)

        def choose(new_leaf, old_leaf):
            return jnp.where(keep.reshape((-1,) + (1,) * (new_leaf.ndim - 1)), new_leaf, old_leaf)

        params = jax.tree_util.tree_map(choose, trained, params)
        self.predictor = dataclasses.replace(p, params=params)
        seconds = time.perf_counter() - start
        self.spent += seconds
        self.reports.append(UpdateReport(step=int(step), n_new=n_new, n_replay=n_replay, iterations=done,
                                         loss_before=before, loss_after=np.where(better, after, before),
                                         seconds=seconds, kept=better,
                                         rollout_before=rollout_before,
                                         rollout_after=None if rollout_after is None
                                         else np.where(better, rollout_after, rollout_before)))
        if s.save_to is not None and np.any(better):
            self.save(s.save_to)
        return self.predictor

    def save(self, path) -> None:
        """Write the surrogates as learned so far to the surrogate file ``path`` (atomically;
        the run's shared nodes, and the steps and seconds of the updates in the metadata's
        ``online_learning``)."""
        changed = [r for r in self.reports if np.any(r.kept)]
        metadata = {"online_learning": {"updated_at": [r.step for r in changed],
                                        "seconds_updating": float(sum(r.seconds for r in self.reports)),
                                        "settings": {k: v for k, v in dataclasses.asdict(self.settings).items()
                                                     if k != "save_to"}}}
        self.predictor.save(path, shared_nodes=self.shared_nodes, metadata=metadata)
