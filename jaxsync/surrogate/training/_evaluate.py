"""Offline evaluation of trained surrogates: rollout errors, E_mse and the grid search.

E_mse (paper section 4): starting at step n (default the first step where refill is
possible, n = n_s n_p - 1), run N refill cycles without ever looking at the truth
(:meth:`jaxsync.surrogate.Surrogate.rollout`) and average the squared error over the
N n_s n_f predicted steps and the part's real dofs, in solver units (cm^2 in the paper);
its square root is reported.

:class:`TrainingChecks` holds what :func:`jaxsync.surrogate.train_surrogates` measures after
training (sqrt(E_mse) and the offline rollout check).
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import io
import itertools
import math
import numbers
import os
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxsync.errors import ConfigError
from jaxsync.io import atomic_json, atomic_path
from jaxsync.surrogate._model import Surrogate
from jaxsync.surrogate.models._architecture import ArchitectureChoice
from jaxsync.surrogate.models._protocol import GradientFitted
from jaxsync.surrogate.training._data import Sampling, build_dataset, padding_mask, stack_replicas
from jaxsync.surrogate.training._train import TrainConfig, train_replicas

__all__ = ["max_applications", "rollout_errors", "RolloutErrors", "RolloutWarning", "e_mse", "TrainingChecks",
           "GridPoint", "GridSearchResult", "grid_search"]


def max_applications(n_steps: int, n_s: int, n_past: int, n_future: int, start: int | None = None) -> int:
    """Largest N such that N refill cycles from ``start`` stay within ``n_steps`` steps."""
    start = n_s * n_past - 1 if start is None else start
    return max((n_steps - 1 - start) // (n_s * n_future), 0)


@functools.partial(jax.jit, static_argnames="n_cycles")
def rollout_parts(surrogate: Surrogate, buffers, step0, n_cycles: int):
    """:meth:`Surrogate.rollout` of every part, one compiled call: (n_parts, n_cycles n_s
    n_f, n_dof) from buffers (n_parts, n_s n_p, n_dof)."""
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
    pred = np.asarray(rollout_parts(surrogate, jnp.asarray(buffer), start, n_applications))
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


@dataclasses.dataclass(frozen=True)
class TrainingChecks:
    """What :func:`jaxsync.surrogate.train_surrogates` measures on the trained replicas
    (its ``checks``), on the first trajectory. The defaults are ``jaxsync train``'s.

    Attributes:
        emse_applications: refill cycles N of sqrt(E_mse) (:func:`e_mse`; paper: N = 60,
            the default), clipped to what the trajectory holds; 0 skips it, and so do
            shared histories not kept at every step (the refill reads every step).
        rollout_tolerance: the offline check before any online run: every replica is
            rolled out without the truth from step n_s n_p - 1 (or, where a load of the
            run jumps, n_s n_p - 1 steps after the last jump: an online run stays
            synchronized through it) to the end of the trajectory (its held-out steps
            after ``train_fraction`` included, :func:`rollout_errors`), and a
            :class:`RolloutWarning` is issued when its largest error exceeds this
            fraction of the part's largest shared displacement. Default 0.02 (2 %, the
            accuracy the paper asks of the free end); None skips the check. Needs shared
            histories at every step.
    """

    emse_applications: int = 60
    rollout_tolerance: float | None = 0.02

    def __post_init__(self):
        n = self.emse_applications
        if isinstance(n, bool) or not isinstance(n, numbers.Integral) or n < 0:
            raise ConfigError(f"emse_applications must be an integer >= 0 (refill cycles of E_mse; 0 skips it), "
                              f"got {n!r}")
        tol = self.rollout_tolerance
        if tol is not None and (isinstance(tol, bool) or not isinstance(tol, numbers.Real)
                                or not math.isfinite(tol) or not tol > 0):
            raise ConfigError(f"rollout_tolerance must be > 0 (a fraction of the shared amplitude) or None, "
                              f"got {tol}")


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
    batch_sizes: Sequence[int],
    hidden_sizes: Sequence[int],
    learning_rates: Sequence[float],
    *,
    architecture: ArchitectureChoice = ArchitectureChoice(),
    sampling: Sampling = Sampling(),
    optimizer: TrainConfig = TrainConfig(),
    n_applications: int = TrainingChecks.emse_applications,
    load_parameters: Sequence[float] | None = None,
    eval_run: int = 0,
    start: int | None = None,
    progress: bool = False,
) -> GridSearchResult:
    """Train every (n_B, n_H, eta0) combination for all parts and tabulate sqrt(E_mse)
    (paper Fig. 6).

    Every combination trains one LSTM per part (no candidates) from the same key,
    ``jax.random.key(sampling.seed)``, on the same windows.

    Args:
        runs_per_part: per part, its list of (n_steps, n_dof_p) histories at every step
            (one per run) [solver units, cm in the paper].
        batch_sizes, hidden_sizes, learning_rates: the grid axes n_B, n_H, eta0.
        architecture: the LSTM's other settings (its ``n_hidden`` is replaced by the grid;
            n_dof is the largest part's); ``model`` must be trained by gradient and have
            an ``n_hidden`` (``"lstm"``, or a registered
            :class:`~jaxsync.surrogate.models.GradientFitted` model).
        sampling: the windows (n_s, n_p, n_f, train/validation fractions, offsets, split)
            and the seed of the split, the mini-batch order and the initial weights;
            ``load_jump_windows`` does not apply (the histories record no load jumps).
        optimizer: the schedule (its ``batch_size`` and ``eta0`` are replaced by the grid;
            ``n_candidates`` does not apply).
        n_applications: refill cycles N of E_mse (default 60, as
            :class:`TrainingChecks`); at most what the evaluated run holds.
        load_parameters: one per run, for a conditional architecture
            (``n_cond_repeat`` > 0).
        eval_run: which run's full history E_mse is measured on.
        start: E_mse start step (default n_s n_p - 1).
        progress: show a progress bar per combination.

    Returns:
        A :class:`GridSearchResult`; use ``.write(path)`` for the table.

    Raises:
        ConfigError: a linear architecture, a conditional one without load parameters,
            too short runs.
    """
    model = architecture.model_class
    if not (issubclass(model, GradientFitted) and "n_hidden" in {f.name for f in dataclasses.fields(model)}):
        raise ConfigError(f"grid_search trains models by gradient over n_B, n_H and eta0 (the LSTM, or a registered "
                          f"GradientFitted model with an n_hidden); got architecture model {architecture.model!r}: "
                          "use ArchitectureChoice(model='lstm')")
    if architecture.n_cond_repeat > 0 and load_parameters is None:
        raise ConfigError("a conditional architecture (n_cond_repeat > 0) needs load_parameters, one per run")
    s = sampling
    datasets = [
        build_dataset(runs, s.n_s, s.n_past, s.n_future, s.train_fraction, s.val_fraction, s.seed, load_parameters,
                      n_offsets=s.n_offsets, split=s.split)
        for runs in runs_per_part
    ]
    data = stack_replicas(datasets)
    width = data.n_dof_max
    histories = np.stack([
        np.pad(np.asarray(runs[eval_run], np.float64), ((0, 0), (0, width - np.shape(runs[eval_run])[1])))
        for runs in runs_per_part
    ])
    load_parameter = None if load_parameters is None else float(load_parameters[eval_run])
    key = jax.random.key(s.seed)
    points = []
    for n_b, n_h, eta0 in itertools.product(batch_sizes, hidden_sizes, learning_rates):
        combo_arch = model.from_choice(dataclasses.replace(architecture, n_hidden=int(n_h)), width, s.n_past,
                                       s.n_future, 0)
        combo_config = dataclasses.replace(optimizer, batch_size=int(n_b), eta0=float(eta0))
        result = train_replicas(data, combo_arch, combo_config, key, progress=progress,
                                description=f"n_B={n_b} n_H={n_h} eta0={eta0:g}")
        err = np.sqrt(e_mse(Surrogate.from_result(result, s.n_s, load_parameter), histories, n_applications, start))
        points.append(GridPoint(
            batch_size=int(n_b), n_hidden=int(n_h), eta0=float(eta0),
            sqrt_e_mse=tuple(float(v) for v in err), spread=float(err.max() - err.min()),
            final_val_loss=tuple(float(v) for v in result.val_loss[-1]),
        ))
    return GridSearchResult(points=tuple(points), n_applications=n_applications)
