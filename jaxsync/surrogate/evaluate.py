"""Offline evaluation of trained surrogates: rollout errors, E_mse and the grid search.

E_mse (paper section 4): starting at step n (default the first step where refill is
possible, n = n_s n_p - 1), run N refill cycles without ever looking at the truth
(:meth:`jaxsync.surrogate.Surrogate.rollout`) and average the squared error over the
N n_s n_f predicted steps and the part's real dofs, in solver units (cm^2 in the paper);
its square root is reported.
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import io
import itertools
import os
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxsync.errors import ConfigError
from jaxsync.io import atomic_json, atomic_path
from jaxsync.surrogate.data import build_dataset, padding_mask, stack_replicas
from jaxsync.surrogate.lstm import LSTMArchitecture
from jaxsync.surrogate.model import Surrogate
from jaxsync.surrogate.train import TrainConfig, train_replicas

__all__ = ["max_applications", "rollout_errors", "RolloutErrors", "RolloutWarning", "e_mse", "GridPoint",
           "GridSearchResult", "grid_search"]


def max_applications(n_steps: int, n_s: int, n_past: int, n_future: int, start: int | None = None) -> int:
    """Largest N such that N refill cycles from ``start`` stay within ``n_steps`` steps."""
    start = n_s * n_past - 1 if start is None else start
    return max((n_steps - 1 - start) // (n_s * n_future), 0)


@functools.partial(jax.jit, static_argnames="n_cycles")
def _rollout_parts(surrogate: Surrogate, buffers, step0, n_cycles: int):
    """:meth:`Surrogate.rollout` of every part (buffers (n_parts, n_s n_p, n_dof))."""
    return jax.vmap(lambda one, buffer: one.rollout(buffer, step0, n_cycles))(surrogate, buffers)


class RolloutWarning(UserWarning):
    """Trained surrogates whose offline rollout misses the accuracy asked for: the online
    run would likely miss it too (the shared dofs of a predicted run ARE this rollout)."""


@dataclasses.dataclass(frozen=True)
class RolloutErrors:
    """Errors of an autonomous rollout of every replica against the true histories.

    Attributes:
        start: step n at which prediction starts; the predicted steps are n+1 .. n +
            n_steps.
        n_steps: predicted steps compared.
        mse: (n_parts,) mean squared error over the predicted steps and the part's real
            dofs [cm^2] (E_mse).
        max_abs_error: (n_parts,) largest absolute error at any predicted step and dof [cm].
        amplitude: (n_parts,) largest absolute true displacement of the part's shared dofs
            over the whole history given [cm].
    """

    start: int
    n_steps: int
    mse: np.ndarray
    max_abs_error: np.ndarray
    amplitude: np.ndarray

    @property
    def relative(self) -> np.ndarray:
        """(n_parts,) ``max_abs_error / amplitude``: the offline accuracy check."""
        return self.max_abs_error / np.where(self.amplitude > 0, self.amplitude, 1.0)

    def to_dict(self) -> dict[str, Any]:
        return {"start": self.start, "n_steps": self.n_steps, "sqrt_mse": np.sqrt(self.mse).tolist(),
                "max_abs_error": self.max_abs_error.tolist(), "amplitude": self.amplitude.tolist(),
                "relative": self.relative.tolist()}


def rollout_errors(
    surrogate: Surrogate,
    histories: np.ndarray,
    n_applications: int | None = None,
    start: int | None = None,
) -> RolloutErrors:
    """Run N refill cycles of every replica without looking at the truth after ``start``
    (:meth:`Surrogate.rollout`, what a predicted run does at its shared dofs) and compare.

    Args:
        surrogate: the replicas (with the load parameter of this run, for conditional
            networks).
        histories: (n_parts, n_steps, n_dof) true displacements at every step, padded
            with zeros to the surrogate's width; solver units.
        n_applications: N, refill cycles (default: as many as the history holds).
        start: current step n at which prediction starts (default n_s n_p - 1, the
            earliest possible: the online run's n_cri - 1).

    Returns:
        :class:`RolloutErrors`.
    """
    histories = np.asarray(histories)
    n_s, n_past, n_future = surrogate.n_s, surrogate.n_past, surrogate.n_future
    if histories.ndim != 3 or histories.shape[0] != surrogate.n_parts or histories.shape[2] != surrogate.n_dof:
        raise ConfigError(f"histories must have shape (n_parts, n_steps, n_dof) = ({surrogate.n_parts}, n_steps, "
                          f"{surrogate.n_dof}) for these replicas, got {histories.shape}")
    n_steps, n_dof = histories.shape[1:]
    start = n_s * n_past - 1 if start is None else int(start)
    if start + 1 < n_s * n_past:
        raise ConfigError(f"rollout start step {start} leaves fewer than n_s*n_p = {n_s * n_past} known steps")
    available = max_applications(n_steps, n_s, n_past, n_future, start)
    n_applications = available if n_applications is None else n_applications
    if n_applications < 1 or n_applications > available:
        raise ConfigError(
            f"{n_applications} refill cycles from step {start} need {start + 1 + n_applications * n_s * n_future} "
            f"steps but the history has {n_steps}; use at most {available} applications or a longer run"
        )
    counts = np.asarray(surrogate.dof_counts)
    mask = padding_mask(counts, n_dof)
    buffer = histories[:, start + 1 - n_s * n_past:start + 1]
    pred = np.asarray(_rollout_parts(surrogate, jnp.asarray(buffer), start, n_applications))
    truth = histories[:, start + 1:start + 1 + pred.shape[1]]
    error = np.abs(pred - truth) * mask[:, None, :]  # padded predictions are 0, truth padding 0
    return RolloutErrors(start=start, n_steps=int(pred.shape[1]),
                         mse=np.square(error).sum(axis=(1, 2)) / (pred.shape[1] * counts),
                         max_abs_error=error.max(axis=(1, 2)),
                         amplitude=np.abs(histories * mask[:, None, :]).max(axis=(1, 2)))


def e_mse(
    surrogate: Surrogate,
    histories: np.ndarray,
    n_applications: int = 60,
    start: int | None = None,
) -> np.ndarray:
    """E_mse of every replica (paper: N = 60 applications; report its square root): the
    ``mse`` of :func:`rollout_errors`.

    Args:
        surrogate: the replicas (with the load parameter of this run, for conditional
            networks).
        histories: (n_parts, n_steps, n_dof) true displacements at every step, padded
            with zeros to the surrogate's width; solver units.
        n_applications: N, refill cycles.
        start: current step n at which prediction starts (default n_s n_p - 1).

    Returns:
        (n_parts,) E_mse in squared solver units, over each part's real dofs.
    """
    return rollout_errors(surrogate, histories, n_applications, start).mse


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
        with atomic_path(path) as tmp:
            with open(tmp, "w") as fh:
                fh.write(self.to_csv())
        atomic_json(os.path.splitext(path)[0] + ".json", self.to_dict())


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
    load_parameter = None if load_parameters is None else float(load_parameters[eval_run])
    points = []
    for n_b, n_h, eta0 in itertools.product(batch_sizes, hidden_sizes, learning_rates):
        combo_arch = dataclasses.replace(arch, n_dof=width, n_hidden=int(n_h))
        combo_config = dataclasses.replace(config, batch_size=int(n_b), eta0=float(eta0))
        result = train_replicas(data, combo_arch, combo_config, key, progress=progress,
                                description=f"n_B={n_b} n_H={n_h} eta0={eta0:g}")
        err = np.sqrt(e_mse(Surrogate.from_result(result, n_s, load_parameter), histories, n_applications, start))
        points.append(GridPoint(
            batch_size=int(n_b), n_hidden=int(n_h), eta0=float(eta0),
            sqrt_e_mse=tuple(float(v) for v in err), spread=float(err.max() - err.min()),
            final_val_loss=tuple(float(v) for v in result.val_loss[-1]),
        ))
    return GridSearchResult(points=tuple(points), n_applications=n_applications)
