"""Sample-refill training data for the LSTM surrogates (paper sections 3-4, Algorithm 3).

A *history* is an array (n_steps, n_dof) of one part's shared-dof displacements saved at
every time step (step k is row k; units of the solver, cm in the paper).  From it:

1. only the first ``train_fraction`` (n_ts) of the steps feed training;
2. one snapshot every ``n_s`` steps is kept (:func:`subsample`);
3. windows of ``n_past`` inputs followed by ``n_future`` targets slide over the kept
   snapshots one snapshot at a time (:func:`make_windows`);
4. the windows are split 75/25 into training and validation, every 4th window held out
   (:func:`split_indices`; the paper's seeded random permutation is an option);
5. a per-dof normalization (mean, std) is fitted on the training windows and applied to
   everything; it is stored with the model.

With the load input, each window also carries the known load signals at its n_p + n_f
sample times (:mod:`jaxsync.fem`, recorded by the trajectory at the rows of
its shared histories), windowed, filtered and split exactly as the displacements, and
normalized by one scale per signal, the largest |u| over every recorded row of every run
(the loads are prescribed, so their range over the whole run is known beforehand; a
scale, not a mean and std, so that a signal that is constant in the training windows --
a load switched off later -- still normalizes to its true value).

Several runs (different initial conditions or loads, each with its scalar load parameter
for the conditional network) are combined by pooling their windows before the split.

Training data come from distributed trajectories (:func:`read_shared_histories`, through
:meth:`jaxsync.Trajectory.load`, the one trajectory reader); a partition's shared-dof
layout, padded to its largest part, is :func:`shared_dof_layout` (both exported by
:mod:`jaxsync.surrogate.training`).  The refill index sets that prediction uses are
:func:`jaxsync.surrogate.refill_index_sets`.

:class:`Sampling` holds these settings (and the seed of a training) as
:func:`jaxsync.surrogate.train_surrogates` and :func:`jaxsync.surrogate.grid_search` take
them.
"""

from __future__ import annotations

import dataclasses
import numbers
from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from jaxsync.errors import ConfigError
from jaxsync.options import LoadJumpWindows, ValidationSplit, check_option, choices

# re-exported: where they were defined before jaxsync.surrogate.training
from jaxsync.surrogate.training._histories import SharedHistories as SharedHistories
from jaxsync.surrogate.training._histories import read_shared_histories as read_shared_histories
from jaxsync.surrogate.training._histories import shared_dof_layout as shared_dof_layout

# ----------------------------------------------------------------------------- windows


def subsample(history: np.ndarray, n_s: int, offset: int = 0) -> np.ndarray:
    """Keep one snapshot every ``n_s`` steps, starting at step ``offset``.

    Args:
        history: (n_steps, n_dof) displacements at every step.

    Returns:
        (ceil((n_steps - offset) / n_s), n_dof) snapshots of steps offset, offset + n_s, ...
    """
    if n_s < 1:
        raise ConfigError(f"sampling stride n_s must be >= 1, got {n_s}")
    return np.asarray(history)[offset::n_s]


def make_windows(snapshots: np.ndarray, n_past: int, n_future: int) -> tuple[np.ndarray, np.ndarray]:
    """Sliding windows over consecutive snapshots (stride one snapshot).

    Args:
        snapshots: (n_snap, n_dof).
        n_past: n_p input snapshots.
        n_future: n_f target snapshots.

    Returns:
        ``(x (n_w, n_p, n_dof), y (n_w, n_f, n_dof))`` with n_w = n_snap - n_p - n_f + 1;
        window w has inputs snapshots w .. w + n_p - 1 and targets w + n_p .. w + n_p + n_f - 1.
    """
    snapshots = np.asarray(snapshots)
    length = n_past + n_future
    if snapshots.shape[0] < length:
        raise ConfigError(
            f"{snapshots.shape[0]} snapshots cannot make one window of n_p + n_f = {length}; "
            "use a longer run, a larger train fraction or a smaller n_s"
        )
    windows = np.lib.stride_tricks.sliding_window_view(snapshots, length, axis=0)  # (n_w, n_dof, L)
    windows = np.moveaxis(windows, -1, 1)
    return np.ascontiguousarray(windows[:, :n_past]), np.ascontiguousarray(windows[:, n_past:])


SPLITS = choices(ValidationSplit)


def split_indices(n_windows: int, val_fraction: float, seed: int,
                  split: ValidationSplit = "interleaved") -> tuple[np.ndarray, np.ndarray]:
    """Seeded split of window indices into training and validation.

    Args:
        n_windows: windows to split.
        val_fraction: fraction held out.
        seed: picks the held-out windows (``random``) or their phase (``interleaved``).
        split: ``"interleaved"`` (default) holds out evenly spaced windows, every
            ``n_windows / n_val``-th from a phase set by ``seed`` (every 4th at the
            default 25 %), so every stretch of a run is trained on and validated on
            alike; ``"random"`` holds out a seeded random subset. A random subset can
            hold out half of a run's first windows -- the transient after the load ramp,
            where an online run starts predicting -- and the networks then never learn
            it: on the demo's cantilever one random split gave a 4.5 % free-end error
            where the interleaved one gives 1.2 % (same weights' seed).

    Returns:
        ``(train, val)`` sorted index arrays; ``len(val) = round(val_fraction * n_windows)``,
        at least one of each.
    """
    check_option("the train/validation split", split, ValidationSplit)
    if not 0.0 < val_fraction < 1.0:
        raise ConfigError(f"validation fraction must be in (0, 1), got {val_fraction}")
    if n_windows < 2:
        raise ConfigError(f"need at least 2 windows to split train/validation, got {n_windows}")
    n_val = min(max(int(round(val_fraction * n_windows)), 1), n_windows - 1)
    if split == "random":
        perm = np.random.default_rng(seed).permutation(n_windows)
        return np.sort(perm[n_val:]), np.sort(perm[:n_val])
    # n_val points spaced n_windows / n_val >= 1 apart, so distinct; the phase cycles
    # through the stride's positions with the seed (every 4th from seed % 4 at 25 %)
    stride = n_windows / n_val
    phases = max(int(round(stride)), 1)
    phase = ((seed % phases) + 0.5) / phases
    val = np.floor((np.arange(n_val) + phase) * stride).astype(np.int64)
    train = np.setdiff1d(np.arange(n_windows), val)
    return train, val


# ----------------------------------------------------------------------------- settings


def _is_integer(value) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


@dataclasses.dataclass(frozen=True)
class Sampling:
    """How the training windows are taken from the trajectories (:func:`build_dataset`,
    for every part), and the seed of a training: the ``sampling`` of
    :func:`jaxsync.surrogate.train_surrogates` and :func:`jaxsync.surrogate.grid_search`.

    The defaults are those of ``jaxsync train`` and the cantilever demo.

    Attributes:
        n_s: sampling stride [steps]: one snapshot every n_s steps is kept. Default 150
            (the paper's published code; the paper's text uses 80): an input window then
            spans n_p n_s = 3 000 steps, 0.74 s on the paper's coarse cantilever, a third
            of its slowest period; on the skewed load that halved the free-end error of
            n_s = 80 (``benchmarks/paper_experiments.py``).
        n_past: n_p, snapshots in an input window (default 20, the paper's).
        n_future: n_f, snapshots a window predicts (default 20, the paper's).
        train_fraction: n_ts in (0, 1], the leading fraction of each run's steps that
            windows are taken from (default 0.5); the rest is seen only by the offline
            check.
        val_fraction: fraction in (0, 1) of the windows held out for validation
            (default 0.25).
        n_offsets: sampled sequences per run, starting at the evenly spaced steps
            k n_s / n_offsets, from 1 to n_s (default 1; at most the rows per n_s of
            thinned shared histories).
        split: which windows are held out (:func:`split_indices`): ``"interleaved"``
            (default; every 4th at 25 %, phase from ``seed``) or the paper's
            ``"random"``. A random split can hold out most of the transient where an
            online run starts predicting; on the demo's cantilever that, not the initial
            weights, made one seed 3x worse.
        load_jump_windows: ``"exclude"``: leave out the windows that straddle a load
            jump the trajectories record (an online run stays synchronized through a
            jump by default, so those windows teach a response it never predicts);
            ``"keep"``: train on them (needed to predict through a jump,
            ``load_jumps="predict"``). None (default) takes the model's rule
            (:meth:`for_model`): ``"exclude"`` for the linear model, whose least-squares
            fit they bend (cantilever with the load switched off: free end 27.6 % kept,
            2.45 % excluded), ``"keep"`` for the LSTM, which fits them without losing the
            rest (1.42 % kept, 2.54 % excluded, seed 0; through the jump 3.58 % against
            139 %).
        seed: integer >= 0 (default 0) seeding every random choice of a training: the
            train/validation split, the mini-batch order and the initial weights
            (``jax.random.key(seed)``).
    """

    n_s: int = 150
    n_past: int = 20  # LSTMArchitecture's defaults
    n_future: int = 20
    train_fraction: float = 0.5
    val_fraction: float = 0.25
    n_offsets: int = 1
    split: ValidationSplit = "interleaved"
    load_jump_windows: LoadJumpWindows | None = None
    seed: int = 0

    def __post_init__(self):
        for name, what in (("n_s", "steps between sampled snapshots"), ("n_past", "input snapshots n_p"),
                           ("n_future", "predicted snapshots n_f")):
            value = getattr(self, name)
            if not _is_integer(value) or value < 1:
                raise ConfigError(f"Sampling.{name} must be an integer >= 1 ({what}), got {value!r}")
        if not isinstance(self.train_fraction, numbers.Real) or not 0.0 < self.train_fraction <= 1.0:
            raise ConfigError(f"train fraction n_ts must be in (0, 1], got {self.train_fraction!r} "
                              "(Sampling.train_fraction, --train-fraction)")
        if not isinstance(self.val_fraction, numbers.Real) or not 0.0 < self.val_fraction < 1.0:
            raise ConfigError(f"validation fraction must be in (0, 1), got {self.val_fraction!r} "
                              "(Sampling.val_fraction, --val-fraction)")
        if not _is_integer(self.n_offsets) or not 1 <= self.n_offsets <= self.n_s:
            raise ConfigError(f"n_offsets must be an integer from 1 to n_s={self.n_s}, got {self.n_offsets!r} "
                              "(Sampling.n_offsets, --offsets)")
        check_option("split", self.split, ValidationSplit)
        if self.load_jump_windows is not None:
            check_option("load_jump_windows", self.load_jump_windows, LoadJumpWindows)
        if not _is_integer(self.seed) or self.seed < 0:
            raise ConfigError(f"Sampling.seed must be an integer >= 0, got {self.seed!r}")

    def for_model(self, model) -> "Sampling":
        """These settings with ``load_jump_windows`` decided for ``model`` when it is None:
        the model's own ``load_jump_windows`` (``"exclude"`` for the linear model, ``"keep"``
        for the LSTM; :mod:`jaxsync.surrogate.models`). ``model``: a surrogate model
        (class or instance), or its kind (:mod:`jaxsync.surrogate.models`)."""
        from jaxsync.surrogate.models._registry import surrogate_class

        rule = getattr(model, "load_jump_windows", None)
        if rule is None:
            rule = surrogate_class(model).load_jump_windows
        if self.load_jump_windows is not None:
            return self
        return dataclasses.replace(self, load_jump_windows=rule)


# ----------------------------------------------------------------------------- normalization


@dataclasses.dataclass(frozen=True)
class Normalization:
    """Per-dof affine normalization ``z = (d - mean) / std``.

    Attributes:
        mean: (n_dof,) float64, solver units.
        std: (n_dof,) float64, solver units; 0 for dofs that never move (clamped ones):
            they normalize to 0 and invert to their constant, whatever a network says.
    """

    mean: np.ndarray
    std: np.ndarray

    @classmethod
    def fit(cls, snapshots: np.ndarray) -> "Normalization":
        """Fit on (..., n_dof) snapshots; constant dofs get std 0.

        A fixed std for them (1 solver unit, as before) would turn a network's small
        normalized error there into a displacement of that size whatever the problem's
        scale (0.4 cm on the cantilever's clamp in full-system modeling, whose motion is
        0.09 cm), and feed it back as the next input.
        """
        flat = np.asarray(snapshots, dtype=np.float64).reshape(-1, np.shape(snapshots)[-1])
        mean = flat.mean(axis=0)
        std = flat.std(axis=0)
        scale = max(float(np.max(std, initial=0.0)), float(np.max(np.abs(mean), initial=0.0)))
        # A dof whose spread is at round-off level relative to the data is treated as fixed.
        std = np.where(std > 1e-12 * scale, std, 0.0)
        return cls(mean=mean, std=std)

    def apply(self, values):
        return normalize(values, self.mean, self.std)

    def invert(self, values):
        return values * self.std + self.mean


def normalize(values, mean, std):
    """(values - mean) / std, and 0 where std is 0 (a fixed dof); NumPy or JAX arrays."""
    xp = np if isinstance(values, np.ndarray) and isinstance(std, np.ndarray) else jnp
    moving = std > 0
    return xp.where(moving, (values - mean) / xp.where(moving, std, 1.0), 0.0)


# ----------------------------------------------------------------------------- datasets


@dataclasses.dataclass(frozen=True)
class WindowDataset:
    """Normalized training/validation windows of one part.

    Attributes:
        x_train, y_train: (n_train, n_p, n_dof), (n_train, n_f, n_dof) float32.
        load_parameter_train: (n_train,) float32 load parameter of each window's run (0 if
            none).
        x_val, y_val, load_parameter_val: the validation counterparts.
        normalization: fitted on the training windows.
        n_excluded: windows left out because they straddle a load jump (``load_jumps`` of
            :func:`build_dataset`).
        signal_train, signal_val: (n_train|n_val, n_p + n_f, n_u) float32 normalized load
            signals of each window (load input), or None.
        signal_scale: (n_u,) float64 scale of each load signal (u / scale is what the
            model reads), or None.
    """

    x_train: np.ndarray
    y_train: np.ndarray
    load_parameter_train: np.ndarray
    x_val: np.ndarray
    y_val: np.ndarray
    load_parameter_val: np.ndarray
    normalization: Normalization
    n_excluded: int = 0
    signal_train: np.ndarray | None = None
    signal_val: np.ndarray | None = None
    signal_scale: np.ndarray | None = None

    @property
    def n_dof(self) -> int:
        return self.x_train.shape[-1]


def trained_rows(n_rows: int, train_fraction: float) -> int:
    """How many leading rows of a run's history (``n_rows`` rows) feed training: the
    first ``floor(train_fraction n_rows)``; the rest is never seen by the networks."""
    return int(np.floor(train_fraction * n_rows))


def last_trained_step(n_steps: int, stride: int, train_fraction: float) -> int:
    """The last time step whose displacements may feed training, for a run of ``n_steps``
    steps whose shared histories hold a row every ``stride`` steps from step 0 (rows
    ``0 .. n_steps // stride``): steps after it are out of sample for the networks."""
    return (trained_rows(n_steps // stride + 1, train_fraction) - 1) * stride


def build_dataset(
    runs: Sequence[np.ndarray],
    n_s: int,
    n_past: int,
    n_future: int,
    train_fraction: float = 0.5,
    val_fraction: float = 0.25,
    split_seed: int = 0,
    load_parameters: Sequence[float] | None = None,
    n_offsets: int = 1,
    split: ValidationSplit = "interleaved",
    load_jumps: Sequence[Sequence[float]] | None = None,
    signals: Sequence[np.ndarray] | None = None,
) -> WindowDataset:
    """Windows of one part from one or several runs.

    Args:
        runs: per run, the (n_steps, n_dof) history at every step (same n_dof for all).
        n_s: sampling stride (steps between kept snapshots).
        n_past, n_future: n_p and n_f.
        train_fraction: n_ts, the leading fraction of each run's steps that may be used.
        val_fraction: fraction of windows held out for validation (paper: 0.25).
        split_seed: seed of the train/validation split. Parts built with the same
            runs and seed get the same split (their windows are aligned in time).
        load_parameters: one scalar per run for the conditional network, or None.
        n_offsets: sampled sequences taken from each run, starting at the evenly spaced
            steps k n_s / n_offsets, k = 0 .. n_offsets - 1 (at most n_s). The online
            refill predicts all n_s interleaved sequences of a run; the paper trains on
            the one starting at step 0, and more offsets give the networks more of the
            same signal at other phases (n_offsets times the windows, the same run).
        split: ``"interleaved"`` or ``"random"`` (:func:`split_indices`), over the
            windows of all runs and offsets in order.
        load_jumps: per run, the load jumps (:func:`jaxsync.fem.load_jumps`) in rows
            of that run (the jump's step over the rows' stride). A window whose rows reach
            from r0 <= J to r1 > J mixes the response before a jump at J with the one after
            it, which no autonomous model can foresee (the online run stays synchronized
            through a jump and predicts only from a history after it): such windows are
            left out (counted in ``n_excluded``). None: none are.
        signals: per run, the (n_steps, n_u) known load signals at the rows of ``runs``
            (the load input; :func:`signal_scale` normalizes them), or None.

    Returns:
        The normalized :class:`WindowDataset`.
    """
    if len(runs) == 0:
        raise ConfigError("build_dataset needs at least one run")
    if load_parameters is not None and len(load_parameters) != len(runs):
        raise ConfigError(f"got {len(load_parameters)} load parameters for {len(runs)} runs; give one per run")
    if not 0.0 < train_fraction <= 1.0:
        raise ConfigError(f"train fraction n_ts must be in (0, 1], got {train_fraction}")
    if isinstance(n_offsets, bool) or not isinstance(n_offsets, (int, np.integer)) or not 1 <= n_offsets <= n_s:
        raise ConfigError(f"n_offsets must be an integer from 1 to n_s={n_s}, got {n_offsets!r}")
    if load_jumps is not None and len(load_jumps) != len(runs):
        raise ConfigError(f"got load jumps for {len(load_jumps)} runs and {len(runs)} runs; give one list per run")
    if signals is not None and len(signals) != len(runs):
        raise ConfigError(f"got load signals of {len(signals)} runs for {len(runs)} runs; give one per run")
    scale = None if signals is None else signal_scale(signals)
    n_dof = np.shape(runs[0])[-1]
    xs, ys, loads, us = [], [], [], []
    n_excluded = 0
    for r, run in enumerate(runs):
        run = np.asarray(run, dtype=np.float64)
        if run.ndim != 2 or run.shape[1] != n_dof:
            raise ConfigError(f"run {r} has shape {run.shape}; expected (n_steps, {n_dof})")
        if not np.all(np.isfinite(run)):
            raise ConfigError(f"run {r} holds NaN or Inf displacements; it cannot be used for training")
        n_used = trained_rows(run.shape[0], train_fraction)
        jumps = np.asarray([] if load_jumps is None else load_jumps[r], dtype=float)
        signal = None
        if signals is not None:
            signal = np.asarray(signals[r], np.float64)
            if signal.ndim != 2 or signal.shape != (run.shape[0], scale.size):
                raise ConfigError(f"run {r}: load signals of shape {signal.shape} for {run.shape[0]} rows; expected "
                                  f"({run.shape[0]}, {scale.size})")
        for k in range(n_offsets):
            offset = (k * n_s) // n_offsets
            x, y = make_windows(subsample(run[:n_used], n_s, offset), n_past, n_future)
            u = None
            if signal is not None:
                u_past, u_future = make_windows(subsample(signal[:n_used], n_s, offset), n_past, n_future)
                u = np.concatenate([u_past, u_future], axis=1) / scale
            if jumps.size:
                first = offset + n_s * np.arange(x.shape[0])  # rows of each window's first and last snapshot
                last = first + n_s * (n_past + n_future - 1)
                keep = ~np.any((first[:, None] <= jumps[None, :]) & (last[:, None] > jumps[None, :]), axis=1)
                n_excluded += int(np.count_nonzero(~keep))
                x, y = x[keep], y[keep]
                u = None if u is None else u[keep]
            us.append(u)
            xs.append(x)
            ys.append(y)
            loads.append(np.full(x.shape[0], 0.0 if load_parameters is None else load_parameters[r]))
    x, y, load = np.concatenate(xs), np.concatenate(ys), np.concatenate(loads)
    if x.shape[0] == 0 and n_excluded:
        raise ConfigError(f"every one of the {n_excluded} training windows straddles a load jump; train on "
                          f"a longer run, or with a smaller n_s (n_p + n_f snapshots every n_s steps must fit "
                          f"between the jumps)")
    train, val = split_indices(x.shape[0], val_fraction, split_seed, split)
    norm = Normalization.fit(np.concatenate([x[train], y[train]], axis=1))

    def prep(a):
        return norm.apply(a).astype(np.float32)

    u = None if signals is None else np.concatenate(us).astype(np.float32)
    return WindowDataset(
        x_train=prep(x[train]), y_train=prep(y[train]), load_parameter_train=load[train].astype(np.float32),
        x_val=prep(x[val]), y_val=prep(y[val]), load_parameter_val=load[val].astype(np.float32),
        normalization=norm, n_excluded=n_excluded,
        signal_train=None if u is None else u[train], signal_val=None if u is None else u[val], signal_scale=scale,
    )


def signal_scale(signals: Sequence[np.ndarray]) -> np.ndarray:
    """(n_u,) float64 scale of each load signal: the largest |u| over every row of every
    run (``signals``: per run, (n_rows, n_u)); 1 for a signal that is 0 throughout."""
    peak = np.max(np.abs(np.concatenate([np.asarray(u, np.float64) for u in signals])), axis=0, initial=0.0)
    return np.where(peak > 0, peak, 1.0)


@dataclasses.dataclass(frozen=True)
class ReplicaData:
    """Windows of all parts, padded to a common dof count and stacked on a leading part axis.

    Attributes:
        x_train, y_train: (n_parts, n_train, n_p|n_f, n_dof_max) float32, zero padding.
        load_parameter_train: (n_parts, n_train) float32.
        x_val, y_val, load_parameter_val: validation counterparts.
        dof_mask: (n_parts, n_dof_max) float32, 1 on real dofs.
        dof_counts: real dofs per part.
        mean, std: (n_parts, n_dof_max) float64 normalization (0 and 1 on padding).
        signal_train, signal_val: (n_parts, n_train|n_val, n_p + n_f, n_u) float32
            normalized load signals of the windows (the load input; the same for every
            part), or None.
        signal_scale: (n_parts, n_u) float64 scale of the load signals, or None.
        load_inputs: (n_u,) :class:`~jaxsync.fem.LoadInput` descriptions of
            the signals (empty without load input).
    """

    x_train: np.ndarray
    y_train: np.ndarray
    load_parameter_train: np.ndarray
    x_val: np.ndarray
    y_val: np.ndarray
    load_parameter_val: np.ndarray
    dof_mask: np.ndarray
    dof_counts: tuple[int, ...]
    mean: np.ndarray
    std: np.ndarray
    signal_train: np.ndarray | None = None
    signal_val: np.ndarray | None = None
    signal_scale: np.ndarray | None = None
    load_inputs: tuple = ()

    @property
    def n_load(self) -> int:
        """Load signals each window carries (0: no load input)."""
        return 0 if self.signal_train is None else int(self.signal_train.shape[-1])

    @property
    def n_parts(self) -> int:
        return len(self.dof_counts)

    @property
    def n_dof_max(self) -> int:
        return self.dof_mask.shape[1]


def padding_mask(dof_counts: Sequence[int], n_dof: int) -> np.ndarray:
    """(n_parts, n_dof) float32 mask, 1 on the first ``dof_counts[p]`` dofs of part p."""
    return (np.arange(n_dof)[None, :] < np.asarray(dof_counts)[:, None]).astype(np.float32)


def stack_replicas(datasets: Sequence[WindowDataset], load_inputs: Sequence = ()) -> ReplicaData:
    """Pad every part's windows to the largest dof count and stack them.

    All parts must have the same number of windows (true when they come from the same
    runs with the same sampling and split seed). ``load_inputs``: the descriptions of the
    windows' load signals (:class:`~jaxsync.fem.LoadInput`), if they carry any.
    """
    if len(datasets) == 0:
        raise ConfigError("stack_replicas needs at least one dataset")
    shapes = {(d.x_train.shape[:2], d.y_train.shape[:2], d.x_val.shape[:2]) for d in datasets}
    if len(shapes) != 1:
        raise ConfigError(
            f"parts have different window counts {sorted(shapes)}; build every part from the same runs, "
            "sampling and split seed"
        )
    counts = tuple(int(d.n_dof) for d in datasets)
    width = max(counts)

    def pad(a, fill=0.0):
        widths = [(0, 0)] * (a.ndim - 1) + [(0, width - a.shape[-1])]
        return np.pad(a, widths, constant_values=fill)

    return ReplicaData(
        x_train=np.stack([pad(d.x_train) for d in datasets]),
        y_train=np.stack([pad(d.y_train) for d in datasets]),
        load_parameter_train=np.stack([d.load_parameter_train for d in datasets]),
        x_val=np.stack([pad(d.x_val) for d in datasets]),
        y_val=np.stack([pad(d.y_val) for d in datasets]),
        load_parameter_val=np.stack([d.load_parameter_val for d in datasets]),
        dof_mask=padding_mask(counts, width),
        dof_counts=counts,
        mean=np.stack([pad(d.normalization.mean) for d in datasets]),
        std=np.stack([pad(d.normalization.std, 1.0) for d in datasets]),
        **_stacked_signals(datasets, tuple(load_inputs)),
    )


def _stacked_signals(datasets: Sequence[WindowDataset], load_inputs: tuple) -> dict:
    """The load-signal fields of :class:`ReplicaData` from every part's windows."""
    with_signals = {d.signal_train is not None for d in datasets}
    if with_signals != {True}:
        if True in with_signals:
            raise ConfigError("some parts' windows carry load signals and others do not; build every part with "
                              "the same signals")
        return {}
    if len(load_inputs) != datasets[0].signal_scale.size:
        raise ConfigError(f"{len(load_inputs)} load input descriptions for {datasets[0].signal_scale.size} load "
                          "signals; give one per signal")
    return {"signal_train": np.stack([d.signal_train for d in datasets]),
            "signal_val": np.stack([d.signal_val for d in datasets]),
            "signal_scale": np.stack([d.signal_scale for d in datasets]), "load_inputs": load_inputs}
