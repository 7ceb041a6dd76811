"""Offline evaluation of trained surrogates: refill prediction, rollouts, E_mse, grid search.

Refill (Algorithm 3, index sets in :mod:`jaxsync.surrogate.data`): from the last
n_s n_p known steps the network is applied n_s times at once (vmap), application i
reading rows i, i + n_s, ... of that buffer and filling rows i, i + n_s, ... of the next
n_s n_f steps.  A rollout repeats this, each cycle consuming the previous predictions.

E_mse (paper section 4): starting at step n (default the first step where refill is
possible, n = n_s n_p - 1), run N refill cycles without ever looking at the truth and
average the squared error over the N n_s n_f predicted steps and the part's real dofs,
in solver units (cm^2 in the paper); its square root is reported.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import itertools
import json
import os
from collections.abc import Sequence
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxsync.errors import ConfigError
from jaxsync.trajectory import atomic_path
from jaxsync.surrogate.data import build_dataset, padding_mask, refill_scatter, refill_windows, stack_replicas
from jaxsync.surrogate.lstm import LSTMArchitecture, Params, forward
from jaxsync.surrogate.train import TrainConfig, TrainResult, train_replicas


def refill_predict(
    params: Params,
    arch: LSTMArchitecture,
    mean: jax.Array,
    std: jax.Array,
    buffer: jax.Array,
    n_s: int,
    cond: jax.Array | None = None,
    dof_mask: jax.Array | None = None,
) -> jax.Array:
    """Predict the next n_s n_f steps from the last n_s n_p steps (one replica, unbatched).

    Args:
        params: one replica's parameters.
        arch: architecture.
        mean, std: (n_dof,) normalization, solver units.
        buffer: (n_s n_p, n_dof) displacements of steps n + 1 - n_s n_p .. n, solver units.
        n_s: sampling stride the network was trained with.
        cond: load parameter (conditional networks).
        dof_mask: optional (n_dof,) padding mask.

    Returns:
        (n_s n_f, n_dof) predicted displacements of steps n + 1 .. n + n_s n_f, in the
        dtype of ``mean``.
    """
    n_p, n_dof = arch.n_past, arch.n_dof
    if buffer.shape != (n_s * n_p, n_dof):
        raise ConfigError(f"refill buffer must have shape (n_s*n_p, n_dof) = {(n_s * n_p, n_dof)}, got {buffer.shape}")
    z = ((buffer - mean) / std).astype(arch.dtype)
    windows = refill_windows(z, n_s, n_p)  # (n_s, n_p, n_dof), rows N_p^i
    pred = jax.vmap(lambda x: forward(params, arch, x, cond, dof_mask))(windows)  # (n_s, n_f, n_dof)
    return refill_scatter(pred, n_s).astype(mean.dtype) * std + mean


def rollout(
    params: Params,
    arch: LSTMArchitecture,
    mean: jax.Array,
    std: jax.Array,
    buffer: jax.Array,
    n_s: int,
    n_cycles: int,
    cond: jax.Array | None = None,
    dof_mask: jax.Array | None = None,
) -> jax.Array:
    """``n_cycles`` refill cycles, each consuming earlier predictions (one replica).

    Returns:
        (n_cycles n_s n_f, n_dof) predictions of steps n + 1 .. n + n_cycles n_s n_f.
    """
    keep = n_s * arch.n_past

    def cycle(buf, _):
        new = refill_predict(params, arch, mean, std, buf, n_s, cond, dof_mask)
        return jnp.concatenate([buf, new])[-keep:], new

    _, blocks = jax.lax.scan(cycle, buffer, None, length=n_cycles)
    return blocks.reshape(-1, arch.n_dof)


@partial(jax.jit, static_argnames=("arch", "n_s", "n_cycles"))
def rollout_replicas(params, arch, mean, std, buffer, n_s, n_cycles, cond=None, dof_mask=None):
    """:func:`rollout` for stacked replicas (leading part axis on every argument but
    ``arch``, ``n_s``, ``n_cycles``; ``cond`` is one scalar shared by all parts)."""
    fn = lambda p, m, s, b, k: rollout(p, arch, m, s, b, n_s, n_cycles, cond, k)  # noqa: E731
    mask = jnp.ones(mean.shape, mean.dtype) if dof_mask is None else dof_mask
    return jax.vmap(fn)(params, mean, std, buffer, mask)


def max_applications(n_steps: int, n_s: int, n_p: int, n_f: int, start: int | None = None) -> int:
    """Largest N such that N refill cycles from ``start`` stay within ``n_steps`` steps."""
    start = n_s * n_p - 1 if start is None else start
    return max((n_steps - 1 - start) // (n_s * n_f), 0)


def e_mse(
    params: Params,
    arch: LSTMArchitecture,
    mean: np.ndarray,
    std: np.ndarray,
    histories: np.ndarray,
    n_s: int,
    n_applications: int = 60,
    start: int | None = None,
    cond: float | None = None,
    dof_counts: Sequence[int] | None = None,
) -> np.ndarray:
    """E_mse of every replica (paper: N = 60 applications; report its square root).

    Args:
        params: stacked replica parameters.
        arch: architecture (padded n_dof).
        mean, std: (n_parts, n_dof) normalization.
        histories: (n_parts, n_steps, n_dof) true displacements at every step, padded
            with zeros; solver units.
        n_s: sampling stride.
        n_applications: N, refill cycles.
        start: current step n at which prediction starts (default n_s n_p - 1).
        cond: load parameter of this run (conditional networks).
        dof_counts: real dofs per part (default: all n_dof).

    Returns:
        (n_parts,) E_mse in squared solver units.
    """
    histories = np.asarray(histories)
    n_parts, n_steps, n_dof = histories.shape
    start = n_s * arch.n_past - 1 if start is None else int(start)
    if start + 1 < n_s * arch.n_past:
        raise ConfigError(f"E_mse start step {start} leaves fewer than n_s*n_p = {n_s * arch.n_past} known steps")
    available = max_applications(n_steps, n_s, arch.n_past, arch.n_future, start)
    if n_applications < 1 or n_applications > available:
        raise ConfigError(
            f"{n_applications} refill cycles from step {start} need {start + 1 + n_applications * n_s * arch.n_future} "
            f"steps but the history has {n_steps}; use at most {available} applications or a longer run"
        )
    counts = np.full(n_parts, n_dof) if dof_counts is None else np.asarray(dof_counts)
    mask = padding_mask(counts, n_dof)
    buffer = histories[:, start + 1 - n_s * arch.n_past:start + 1]
    pred = np.asarray(rollout_replicas(
        params, arch, jnp.asarray(mean), jnp.asarray(std), jnp.asarray(buffer), n_s, n_applications,
        None if cond is None else jnp.asarray(cond, arch.dtype), jnp.asarray(mask),
    ))
    truth = histories[:, start + 1:start + 1 + pred.shape[1]]
    sq = np.square(pred - truth) * mask[:, None, :]  # padded predictions are 0, truth padding 0
    return sq.sum(axis=(1, 2)) / (pred.shape[1] * counts)


# ----------------------------------------------------------------------------- grid search


@dataclasses.dataclass(frozen=True)
class GridPoint:
    """One trained combination.

    Attributes:
        batch_size, n_hidden, eta0: the hyperparameters (n_B, n_H, eta0).
        sqrt_e_mse: per part, sqrt(E_mse) in solver units.
        spread: max - min of sqrt_e_mse over the replicas.
        final_val_loss: per part, last validation MSE (normalized units).
    """

    batch_size: int
    n_hidden: int
    eta0: float
    sqrt_e_mse: tuple[float, ...]
    spread: float
    final_val_loss: tuple[float, ...]

    @property
    def worst(self) -> float:
        return max(self.sqrt_e_mse)


@dataclasses.dataclass(frozen=True)
class GridSearchResult:
    """Table of a grid search (paper Fig. 6) and the chosen combination: the one with
    the smallest worst-part sqrt(E_mse) (ties: smaller spread)."""

    points: tuple[GridPoint, ...]
    n_applications: int

    @property
    def best(self) -> GridPoint:
        return min(self.points, key=lambda p: (p.worst, p.spread))

    def to_csv(self) -> str:
        n_parts = len(self.points[0].sqrt_e_mse)
        out = io.StringIO()
        writer = csv.writer(out, lineterminator="\n")
        writer.writerow(["n_B", "n_H", "eta0"] + [f"sqrt_e_mse_part{p}" for p in range(n_parts)]
                        + ["spread", "chosen"])
        best = self.best
        for p in self.points:
            writer.writerow([p.batch_size, p.n_hidden, repr(p.eta0)] + [f"{v:.6e}" for v in p.sqrt_e_mse]
                            + [f"{p.spread:.6e}", int(p is best)])
        return out.getvalue()

    def to_dict(self) -> dict[str, Any]:
        return {
            "n_applications": self.n_applications,
            "points": [dataclasses.asdict(p) for p in self.points],
            "chosen": dataclasses.asdict(self.best),
        }

    def write(self, path: str | os.PathLike) -> None:
        """Write ``path`` (CSV table) and ``path`` with suffix .json, atomically."""
        path = os.fspath(path)
        stem = os.path.splitext(path)[0]
        for target, text in ((path, self.to_csv()), (stem + ".json", json.dumps(self.to_dict(), indent=2))):
            with atomic_path(target) as tmp:
                with open(tmp, "w") as fh:
                    fh.write(text)


def grid_search(
    runs_per_part: Sequence[Sequence[np.ndarray]],
    n_s: int,
    arch: LSTMArchitecture,
    config: TrainConfig,
    batch_sizes: Sequence[int],
    hidden_sizes: Sequence[int],
    learning_rates: Sequence[float],
    key: jax.Array,
    n_applications: int = 60,
    train_fraction: float = 0.5,
    val_fraction: float = 0.25,
    split_seed: int = 0,
    load_parameters: Sequence[float] | None = None,
    eval_run: int = 0,
    start: int | None = None,
    progress: bool = False,
) -> GridSearchResult:
    """Train every (n_B, n_H, eta0) combination for all parts and tabulate sqrt(E_mse).

    Args:
        runs_per_part: per part, its list of (n_steps, n_dof_p) histories (one per run).
        n_s: sampling stride.
        arch: base architecture (its n_hidden is replaced by the grid; n_dof is set to
            the largest part).
        config: base training configuration (batch_size and eta0 replaced by the grid).
        batch_sizes, hidden_sizes, learning_rates: the grid axes.
        key: PRNG key, the same for every combination.
        n_applications: N of E_mse.
        eval_run: which run's full history E_mse is measured on.
        start: E_mse start step.
        progress: show a progress bar per combination.

    Returns:
        A :class:`GridSearchResult`; use ``.write(path)`` for the table.
    """
    if arch.conditional and load_parameters is None:
        raise ConfigError("a conditional architecture (n_cond_repeat > 0) needs load_parameters, one per run")
    datasets = [
        build_dataset(runs, n_s, arch.n_past, arch.n_future, train_fraction, val_fraction, split_seed, load_parameters)
        for runs in runs_per_part
    ]
    data = stack_replicas(datasets)
    width = data.n_dof_max
    histories = np.stack([
        np.pad(np.asarray(runs[eval_run], np.float64), ((0, 0), (0, width - np.shape(runs[eval_run])[1])))
        for runs in runs_per_part
    ])
    cond = None if load_parameters is None else float(load_parameters[eval_run])
    points = []
    for n_b, n_h, eta0 in itertools.product(batch_sizes, hidden_sizes, learning_rates):
        combo_arch = dataclasses.replace(arch, n_dof=width, n_hidden=int(n_h))
        combo_config = dataclasses.replace(config, batch_size=int(n_b), eta0=float(eta0))
        result = train_replicas(data, combo_arch, combo_config, key, progress=progress,
                                description=f"n_B={n_b} n_H={n_h} eta0={eta0:g}")
        err = np.sqrt(evaluate_result(result, histories, n_s, n_applications, start, cond))
        points.append(GridPoint(
            batch_size=int(n_b), n_hidden=int(n_h), eta0=float(eta0),
            sqrt_e_mse=tuple(float(v) for v in err), spread=float(err.max() - err.min()),
            final_val_loss=tuple(float(v) for v in result.val_loss[-1]),
        ))
    return GridSearchResult(points=tuple(points), n_applications=n_applications)


def evaluate_result(
    result: TrainResult,
    histories: np.ndarray,
    n_s: int,
    n_applications: int = 60,
    start: int | None = None,
    cond: float | None = None,
) -> np.ndarray:
    """E_mse (n_parts,) of a :class:`TrainResult` on padded (n_parts, n_steps, n_dof) histories."""
    return e_mse(result.params, result.arch, result.mean, result.std, histories, n_s,
                 n_applications, start, cond, result.dof_counts)
