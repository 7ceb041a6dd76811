"""Training surrogates from trajectories: the one library function behind ``jaxsync train``
and ``jaxsync demo``.

:func:`train_surrogates` reads the per-part shared-dof histories of one or more
distributed runs of one partition (:func:`~jaxsync.surrogate.data.read_shared_histories`),
builds the sample-refill windows of every part, trains all replicas together
(:func:`~jaxsync.surrogate.train.train_replicas`; with ``model="linear"``, fits the linear
autoregressive baseline by least squares on the same windows instead,
:func:`~jaxsync.surrogate.linear.fit_linear`), measures sqrt(E_mse) on the first run
and returns a :class:`TrainedSurrogates`: the :class:`~jaxsync.surrogate.Surrogate` for the
solver, its checkpoint (with the partition's shared node ids), the loss history and
timings.  Given an output folder ``out`` it also writes there, each file atomically:

* the checkpoint (``surrogate.h5`` by default),
* ``loss_curves.png``, the per-part training and validation losses,
* ``train_summary.json`` (:meth:`TrainedSurrogates.summary`),
* while it trains, ``training_state.h5``, a resumable state rewritten every
  ``checkpoint_every`` epochs: the same call again continues from it and ends with the
  same parameters as an uninterrupted run; a state of other data or settings is refused.
  It is deleted once the results are written (LSTM only: a least-squares fit has no
  state to resume).
"""

from __future__ import annotations

import dataclasses
import os
import time
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import jax
import numpy as np

from jaxsync.errors import CheckpointError, ConfigError
from jaxsync.io import atomic_json, atomic_path
from jaxsync.options import LoadJumpWindows, SurrogateModel, ValidationSplit, check_option
from jaxsync.surrogate.architecture import architecture_to_dict
from jaxsync.surrogate.checkpoint import SurrogateCheckpoint, save_checkpoint
from jaxsync.surrogate.data import SharedHistories, build_dataset, read_shared_histories, stack_replicas
from jaxsync.surrogate.evaluate import RolloutErrors, RolloutWarning, e_mse, max_applications, rollout_errors
from jaxsync.surrogate.linear import DEFAULT_REGULARIZATION, LinearFitConfig, fit_linear
from jaxsync.surrogate.lstm import LSTMArchitecture, count_parameters
from jaxsync.surrogate.model import Surrogate
from jaxsync.surrogate.train import TrainConfig, TrainProgress, TrainResult, train_replicas
from jaxsync.trajectory import Trajectory

__all__ = ["train_surrogates", "TrainedSurrogates", "plot_loss_curves", "STATE_NAME", "SUMMARY_NAME",
           "LOSS_CURVES_NAME"]

STATE_NAME = "training_state.h5"
SUMMARY_NAME = "train_summary.json"
LOSS_CURVES_NAME = "loss_curves.png"

# what the checkpoint's metadata keeps of the summary
_METADATA_KEYS = ("model", "training", "sampling", "candidates", "load_parameters", "final_val_loss", "sqrt_e_mse",
                  "rollout_check")


@dataclasses.dataclass(frozen=True)
class TrainedSurrogates:
    """The result of :func:`train_surrogates`.

    Attributes:
        surrogate: the trained replicas, ready for the solver (conditional networks carry
            the load parameter of the first trajectory).
        result: the optimization: losses per epoch and part, best epochs, early stop,
            seconds per epoch, compilation time (a linear surrogate's: the one
            least-squares solve, :func:`~jaxsync.surrogate.linear.fit_linear`).
        shared_nodes: per part, the global ids of its shared nodes (the partition).
        trajectories: absolute path of each trajectory (None for one given in memory).
        load_parameters: the load parameter of each run fed to a conditional network, or
            None (unconditional).
        train_fraction, val_fraction, seed, n_offsets, split: the sampling settings.
        candidates: with several candidates per part, which one each part kept and every
            candidate's validation loss (:func:`choose_candidates`); None for one, and
            for the linear surrogate (least squares has one solution).
        n_train_windows, n_val_windows: windows per part.
        n_excluded_windows: windows per part left out because they straddle a load jump.
        load_jump_windows: whether such windows were left out (``"exclude"``) or kept.
        checkpoint_every: epochs between writes of the resumable training state.
        train_seconds: wall time of the training call (compilation included).
        e_mse_applications: refill cycles N of ``sqrt_e_mse`` (None: not measured).
        sqrt_e_mse: per part, sqrt(E_mse) on the first trajectory [solver units].
        rollout: the offline accuracy check: every replica rolled out autonomously from
            step n_s n_p - 1 (where an online run starts predicting) to the end of the
            first trajectory, including the steps after ``train_fraction`` that no
            window was taken from (:func:`~jaxsync.surrogate.evaluate.rollout_errors`);
            None when not measured (shared histories thinned, or too short a run).
        rollout_tolerance: the largest ``rollout.relative`` accepted without a
            :class:`~jaxsync.surrogate.evaluate.RolloutWarning` (None: no check).
        files: the files written, by kind (``checkpoint``, ``loss_curves``, ``summary``);
            empty without ``out``.
    """

    surrogate: Surrogate
    result: TrainResult
    shared_nodes: tuple[np.ndarray, ...]
    trajectories: tuple[str | None, ...]
    load_parameters: tuple[float, ...] | None
    train_fraction: float
    val_fraction: float
    seed: int
    n_train_windows: int
    n_val_windows: int
    checkpoint_every: int
    train_seconds: float
    e_mse_applications: int | None
    sqrt_e_mse: tuple[float, ...] | None
    rollout: RolloutErrors | None = None
    rollout_tolerance: float | None = None
    n_offsets: int = 1
    split: ValidationSplit = "interleaved"
    candidates: dict | None = None
    files: dict[str, str] = dataclasses.field(default_factory=dict)
    n_excluded_windows: int = 0
    load_jump_windows: LoadJumpWindows = "keep"

    @property
    def model(self) -> SurrogateModel:
        """``"lstm"`` or ``"linear"``: the kind of the trained replicas."""
        return self.result.arch.kind

    @property
    def rollout_passed(self) -> bool | None:
        """Every replica's offline rollout error within ``rollout_tolerance`` of its
        shared amplitude (None: not checked)."""
        if self.rollout is None or self.rollout_tolerance is None:
            return None
        return bool(self.rollout.relative.max() <= self.rollout_tolerance)

    @property
    def checkpoint(self) -> SurrogateCheckpoint:
        """What is saved: the replicas with the partition's shared node ids and the
        training metadata (a part of :meth:`summary`)."""
        summary = self.summary()
        return SurrogateCheckpoint.from_result(self.result, self.surrogate.n_s, self.shared_nodes,
                                               metadata={k: summary[k] for k in _METADATA_KEYS})

    @property
    def final_val_loss(self) -> np.ndarray:
        """(n_parts,) validation MSE of the kept parameters (normalized units)."""
        return self.result.best_val_loss

    def summary(self) -> dict[str, Any]:
        """The content of ``train_summary.json`` (JSON-serializable).

        The keys are the same for both models; where epochs do not apply (the linear
        surrogate's least-squares fit) ``n_epochs_run``, ``seconds_per_epoch`` and the like
        are None, ``training`` gives the fit's settings and ``fit_seconds``, and
        ``loss_history`` has one row (the solve)."""
        result, arch = self.result, self.result.arch
        n_parts = len(result.dof_counts)
        iterative = self.model != "linear"
        if iterative:
            training = {**result.config.to_dict(), "n_epochs_run": result.n_epochs_run,
                        "stopped_early": result.stopped_epoch is not None,
                        "stopped_at_epoch": result.stopped_epoch,
                        "best_epoch": [int(e) for e in result.best_epoch],
                        "resumed_from_epoch": result.resumed_from, "checkpoint_every": self.checkpoint_every}
        else:
            training = {**result.config.to_dict(), "fit_seconds": result.seconds_per_epoch, "n_epochs_run": None,
                        "candidates": "not applicable: least squares has one solution (n_candidates ignored)"}
        out = {
            "model": self.model,
            "trajectories": list(self.trajectories),
            "load_parameters": None if self.load_parameters is None else list(self.load_parameters),
            "n_parts": n_parts,
            "dof_counts": list(result.dof_counts),
            "architecture": architecture_to_dict(arch),
            "parameters_per_replica_padded": count_parameters(result.params) // n_parts,
            "training": training,
            "sampling": {"n_s": self.surrogate.n_s, "n_offsets": self.n_offsets, "train_fraction": self.train_fraction,
                         "val_fraction": self.val_fraction, "split": self.split, "seed": self.seed,
                         "n_train_windows": self.n_train_windows, "n_val_windows": self.n_val_windows,
                         "n_excluded_windows": self.n_excluded_windows,
                         "load_jump_windows": self.load_jump_windows},
            "candidates": self.candidates,
            "initial_val_loss": result.initial_val_loss.tolist(),
            "final_train_loss": result.train_loss[-1].tolist(),
            "final_val_loss": result.best_val_loss.tolist(),
            "last_epoch_val_loss": result.val_loss[-1].tolist(),
            "n_epochs_run": result.n_epochs_run if iterative else None,
            "stopped_at_epoch": result.stopped_epoch,
            "seconds_per_epoch": result.seconds_per_epoch if iterative else None,
            "gradient_steps_per_second": (result.steps_per_epoch / result.seconds_per_epoch
                                          if iterative and result.seconds_per_epoch > 0 else None),
            "compile_seconds": result.compile_seconds,
            "train_seconds": self.train_seconds,
            "e_mse_applications": self.e_mse_applications,
            "sqrt_e_mse": None if self.sqrt_e_mse is None else list(self.sqrt_e_mse),
            "rollout_check": None if self.rollout is None else {
                **self.rollout.to_dict(), "tolerance": self.rollout_tolerance, "passed": self.rollout_passed},
        }
        if self.files:
            out.update(checkpoint=self.files["checkpoint"], loss_curves=self.files["loss_curves"])
        out["loss_history"] = {"train": result.train_loss.tolist(), "val": result.val_loss.tolist()}
        return out


def _read_runs(trajectories, allow_predicted: bool) -> tuple[list[SharedHistories], list[str | None]]:
    """The shared histories of every trajectory, all of one partition."""
    if isinstance(trajectories, (str, os.PathLike, Trajectory)):
        trajectories = [trajectories]
    if len(trajectories) == 0:
        raise ConfigError("train_surrogates needs at least one trajectory")
    names = [None if isinstance(t, Trajectory) else os.path.abspath(os.fspath(t)) for t in trajectories]
    runs = [read_shared_histories(t, allow_predicted=allow_predicted) for t in trajectories]
    first = runs[0]
    for k, run in enumerate(runs[1:], start=1):
        same = len(run.shared_nodes) == len(first.shared_nodes) and all(
            np.array_equal(a, b) for a, b in zip(run.shared_nodes, first.shared_nodes)
        )
        if not same:
            label = lambda i: names[i] or f"trajectory {i}"  # noqa: E731
            raise CheckpointError(
                f"{label(k)} belongs to another partition than {label(0)} (different shared nodes); "
                "train on runs of one partition"
            )
    return runs, names


def _load_parameters(runs, given, n_cond_repeat: int) -> list[float] | None:
    """The load parameter of each run for a conditional network (None: unconditional)."""
    if given is not None:
        if len(given) != len(runs):
            raise ConfigError(f"load_parameters (--load-parameter) got {len(given)} values for {len(runs)} "
                              "trajectories; give one each")
        loads = [float(v) for v in given]
    elif all(run.load_parameter is not None for run in runs):
        loads = [run.load_parameter for run in runs]
    else:
        loads = None
    if n_cond_repeat > 0 and loads is None:
        raise ConfigError(
            "n_cond_repeat > 0 (--cond-repeat) trains the conditional network, which needs a load parameter per "
            "trajectory: pass load_parameters (--load-parameter) or run the solver with a problem parameter "
            "'load_parameter'"
        )
    return loads if n_cond_repeat > 0 else None


def train_surrogates(
    trajectories,
    *,
    model: SurrogateModel = "lstm",
    n_s: int = 150,
    n_past: int = LSTMArchitecture.n_past,
    n_future: int = LSTMArchitecture.n_future,
    n_hidden: int = LSTMArchitecture.n_hidden,
    n_layers: int = LSTMArchitecture.n_layers,
    n_cond_repeat: int = LSTMArchitecture.n_cond_repeat,
    dtype: str = LSTMArchitecture.dtype,
    config: TrainConfig | None = None,
    regularization: float = DEFAULT_REGULARIZATION,
    train_fraction: float = 0.5,
    val_fraction: float = 0.25,
    n_offsets: int = 1,
    split: ValidationSplit = "interleaved",
    load_jump_windows: LoadJumpWindows | None = None,
    n_candidates: int = 2,
    load_parameters: Sequence[float] | None = None,
    allow_predicted: bool = False,
    seed: int = 0,
    emse_applications: int = 60,
    rollout_tolerance: float | None = 0.02,
    devices: int | None = None,
    out: str | os.PathLike | None = None,
    checkpoint_name: str = "surrogate.h5",
    checkpoint_every: int = 50,
    progress: bool = True,
    callback: Callable[[TrainProgress], None] | None = None,
) -> TrainedSurrogates:
    """Train one LSTM surrogate per part on distributed trajectories of one partition
    (or fit the linear baseline: ``model="linear"``).

    Args:
        trajectories: a :class:`jaxsync.Trajectory` or trajectory file, or a sequence of
            them (runs of one partition, e.g. different loads), with the shared nodes
            kept every step (``simulate(..., shared_every=1)``) or at any stride dividing
            ``n_s`` (e.g. ``save_every=n_s``: what training reads, and all a long run
            needs to keep).
        model: ``"lstm"`` (default), the encoder-decoder trained with optax, or
            ``"linear"``, the affine autoregressive baseline fitted by least squares on
            the same windows (:mod:`jaxsync.surrogate.linear`; unconditional: needs
            ``n_cond_repeat`` = 0). The LSTM-only settings (``n_hidden``, ``n_layers``,
            ``config``, ``n_candidates``, ``checkpoint_every``, ``devices``, ``progress``,
            ``callback``) are ignored by the linear fit.
        n_s, n_past, n_future: sampling stride and window lengths n_p, n_f. The default
            n_s = 150 (the paper's published code; the paper's text uses 80) makes an
            input window span n_p n_s = 3 000 steps, 0.74 s on the paper's coarse
            cantilever, a third of its slowest period: on the skewed load that halved
            the free-end error of n_s = 80 (``benchmarks/paper_experiments.py``).
        n_hidden, n_layers, n_cond_repeat, dtype: the architecture
            (:class:`~jaxsync.surrogate.lstm.LSTMArchitecture`, whose defaults these are;
            ``n_cond_repeat`` > 0 trains the conditional network).
        config: optimization settings (default :class:`~jaxsync.surrogate.train.TrainConfig`,
            the laptop schedule).
        regularization: relative ridge parameter of the linear fit
            (:class:`~jaxsync.surrogate.linear.LinearFitConfig`, whose default this is);
            ignored by the LSTM.
        train_fraction, val_fraction: leading fraction n_ts of each run used, fraction of
            windows held out for validation.
        n_offsets: sampled sequences per run, at evenly spaced starting steps within n_s
            (:func:`~jaxsync.surrogate.data.build_dataset`; at most the rows per n_s
            of thinned histories).
        split: which windows are held out for validation: ``"interleaved"`` (every
            4th at the default 25 %, phase from ``seed``) or the paper's ``"random"``
            (:func:`~jaxsync.surrogate.data.split_indices`). A random split can hold out
            most of the transient where an online run starts predicting; on the demo's
            cantilever that, not the initial weights, made one seed 3x worse.
        load_jump_windows: ``"exclude"``: leave out the windows that straddle a load jump
            the trajectories record (:func:`~jaxsync.surrogate.data.build_dataset`); an
            online run stays synchronized through a jump by default, so those windows teach
            a response it never predicts. ``"keep"``: train on them (needed to predict
            through a jump, ``load_jumps="predict"``). Default (None): ``"exclude"`` for the
            linear model, whose least-squares fit they bend (cantilever with the load
            switched off: free end 27.6 % kept, 2.45 % excluded), ``"keep"`` for the LSTM,
            which fits them without losing the rest (1.42 % kept, 2.54 % excluded, seed 0;
            through the jump 3.58 % against 139 %).
        n_candidates: networks trained per part from different initial weights (all in
            one compiled program, on the same windows); each part keeps the one with the
            lowest validation loss. Training an LSTM lands in basins of different quality:
            on the demo's cantilever one seed's pair reached a 5x higher validation loss
            and a 4.5 % free-end error where another's reached 1.3 %; choosing between two
            candidates costs less than twice the time, since the per-part work is small.
        load_parameters: the load parameter of each trajectory (default: their problem
            parameter ``load_parameter``); used with ``n_cond_repeat`` > 0.
        allow_predicted: accept synchronization-avoiding trajectories (refused by default).
        seed: seed of initialization, shuffling and the train/validation split.
        emse_applications: refill cycles N of sqrt(E_mse) on the first trajectory,
            clipped to what it holds; 0 skips it, and so do shared histories not kept at
            every step (the refill reads every step).
        rollout_tolerance: the offline check before any online run: every replica is
            rolled out without the truth from step n_s n_p - 1 (or, where a load of the run
            jumps, n_s n_p - 1 steps after the last jump: an online run stays synchronized
            through it) to the end of the first trajectory (its held-out steps after
            ``train_fraction`` included), and a
            :class:`~jaxsync.surrogate.evaluate.RolloutWarning` is issued when its
            largest error exceeds this fraction of the part's largest shared
            displacement (default 2 %, the accuracy the paper asks of the free end);
            None skips the check. Needs shared histories at every step.
        devices: local devices to spread the parts over (default: as many as divide the
            part count).
        out: output folder for the files listed in the module docstring (None: nothing
            is written).
        checkpoint_name: checkpoint file name inside ``out``.
        checkpoint_every: epochs between writes of the resumable training state in
            ``out`` (0: none).
        progress: show a progress bar.
        callback: given a :class:`~jaxsync.surrogate.train.TrainProgress` after every
            compiled chunk of epochs.

    Returns:
        :class:`TrainedSurrogates`.

    Raises:
        CheckpointError: unusable trajectories (not distributed, shared nodes kept at a
            stride that does not divide n_s, predicted, of different partitions) or a training state in
            ``out`` of other data or settings.
        ConfigError: unusable settings.
    """
    config = TrainConfig() if config is None else config
    check_option("model", model, SurrogateModel)
    if model == "linear":
        if n_cond_repeat > 0:
            raise ConfigError("the linear surrogate is unconditional: n_cond_repeat (--cond-repeat) must be 0; "
                              "train model='lstm' (--model lstm) for a conditional surrogate")
        fit_config = LinearFitConfig(regularization)  # checked before any data is read
    if isinstance(n_candidates, bool) or not isinstance(n_candidates, (int, np.integer)) or n_candidates < 1:
        raise ConfigError(f"n_candidates must be an integer >= 1 (networks trained per part), got {n_candidates!r}")
    if rollout_tolerance is not None and not rollout_tolerance > 0:
        raise ConfigError(f"rollout_tolerance must be > 0 (a fraction of the shared amplitude) or None, "
                          f"got {rollout_tolerance}")
    if load_jump_windows is None:
        load_jump_windows = "exclude" if model == "linear" else "keep"
    exclude_jumps = check_option("load_jump_windows", load_jump_windows, LoadJumpWindows) == "exclude"
    runs, names = _read_runs(trajectories, allow_predicted)
    loads = _load_parameters(runs, load_parameters, n_cond_repeat)
    n_parts = len(runs[0].histories)
    row_strides = {run.for_sampling(n_s) for run in runs}
    if len(row_strides) > 1:
        raise CheckpointError(f"the trajectories keep their shared nodes at different strides "
                              f"({sorted({run.stride for run in runs})} steps); train on runs saved alike")
    row_stride = row_strides.pop()
    datasets = [
        build_dataset([run.histories[p] for run in runs], row_stride, n_past, n_future, train_fraction,
                      val_fraction, seed, loads, n_offsets=n_offsets, split=split,
                      load_jumps=[[j / run.stride for j in run.load_jumps] if exclude_jumps else []
                                  for run in runs])
        for p in range(n_parts)
    ]
    state_path = None
    if out is not None:
        os.makedirs(out, exist_ok=True)
        state_path = os.path.join(out, STATE_NAME) if checkpoint_every and model == "lstm" else None
    if model == "linear":
        data = stack_replicas(datasets)
        started = time.perf_counter()
        result = fit_linear(data, fit_config, dtype)
        train_seconds = time.perf_counter() - started
        candidates = None
    else:
        # candidate c of part p is replica c n_parts + p: the same windows, its own initial weights
        data = stack_replicas(datasets * int(n_candidates))
        arch = LSTMArchitecture(n_dof=data.n_dof_max, n_hidden=n_hidden, n_layers=n_layers, n_past=n_past,
                                n_future=n_future, n_cond_repeat=n_cond_repeat, dtype=dtype)
        started = time.perf_counter()
        result = train_replicas(data, arch, config, jax.random.key(seed), progress=progress, devices=devices,
                                checkpoint=state_path, checkpoint_every=checkpoint_every, callback=callback)
        train_seconds = time.perf_counter() - started
        result, candidates = choose_candidates(result, n_parts, int(n_candidates))
    arch = result.arch

    load = None if loads is None else loads[0]
    surrogate = Surrogate.from_result(result, n_s, load)
    first = runs[0]
    n_app = min(emse_applications, max_applications(first.histories[0].shape[0], n_s, n_past, n_future))
    if first.stride != 1:  # the refill reads every step of its input history
        n_app = 0
    sqrt_e_mse = rollout = None
    histories = np.stack([np.pad(h, ((0, 0), (0, arch.n_dof - h.shape[1]))) for h in first.histories])
    if n_app > 0:
        sqrt_e_mse = tuple(float(v) for v in np.sqrt(e_mse(surrogate, histories, n_app)))
    # from where an online run starts predicting: n_s n_p - 1, or after the last load jump
    # (simulate_sync_avoiding stays synchronized through it by default)
    start = n_s * n_past - 1 + (first.last_load_jump or 0)
    if (rollout_tolerance is not None and first.stride == 1
            and max_applications(histories.shape[1], n_s, n_past, n_future, start) > 0):
        rollout = rollout_errors(surrogate, histories, start=start)
    if rollout is not None:
        worst = int(np.argmax(rollout.relative))
        if rollout.relative[worst] > rollout_tolerance:
            warnings.warn(RolloutWarning(
                f"the trained surrogates miss the offline check: rolled out without the truth over "
                f"{rollout.n_steps} steps of the first trajectory, part {worst}'s shared displacements are "
                f"off by up to {100 * rollout.relative[worst]:.2g} % of their amplitude (tolerance "
                f"{100 * rollout_tolerance:.2g} %); an online run would likely be as far off. "
                + ("Train longer (more epochs or patience), on more data" if model == "lstm" else
                   "Fit with another regularization, on more data")
                + " (train_fraction, more runs), or run online with error control (resync_tolerance)"),
                stacklevel=2)
    trained = TrainedSurrogates(
        surrogate=surrogate, result=result, shared_nodes=first.shared_nodes, trajectories=tuple(names),
        load_parameters=None if loads is None else tuple(loads), train_fraction=train_fraction,
        val_fraction=val_fraction, seed=seed, n_train_windows=int(data.x_train.shape[1]),
        n_val_windows=int(data.x_val.shape[1]), checkpoint_every=checkpoint_every, train_seconds=train_seconds,
        e_mse_applications=n_app if sqrt_e_mse is not None else None, sqrt_e_mse=sqrt_e_mse,
        rollout=rollout, rollout_tolerance=rollout_tolerance, n_offsets=n_offsets, split=split,
        candidates=candidates, n_excluded_windows=datasets[0].n_excluded, load_jump_windows=load_jump_windows,
    )
    if out is None:
        return trained
    files = {"checkpoint": os.path.abspath(os.path.join(out, checkpoint_name)),
             "loss_curves": os.path.abspath(os.path.join(out, LOSS_CURVES_NAME)),
             "summary": os.path.abspath(os.path.join(out, SUMMARY_NAME))}
    save_checkpoint(files["checkpoint"], trained.checkpoint)
    plot_loss_curves(result, files["loss_curves"])
    trained = dataclasses.replace(trained, files=files)
    atomic_json(files["summary"], trained.summary())
    if state_path is not None and os.path.exists(state_path):
        os.remove(state_path)  # everything it could resume is written
    return trained


def choose_candidates(result: TrainResult, n_parts: int, n_candidates: int) -> tuple[TrainResult, dict | None]:
    """Keep, per part, the candidate with the lowest validation loss.

    Args:
        result: replicas ordered candidate-major (replica c n_parts + p: candidate c of
            part p).
        n_parts, n_candidates: the layout.

    Returns:
        (the result of the chosen replicas, one per part; None for one candidate, else a
        dict with ``n_candidates``, ``chosen`` (per part, the candidate kept) and
        ``best_val_loss`` (n_candidates lists of n_parts values)).
    """
    if n_candidates == 1:
        return result, None
    losses = np.asarray(result.best_val_loss).reshape(n_candidates, n_parts)
    chosen = np.argmin(np.where(np.isfinite(losses), losses, np.inf), axis=0)
    keep = chosen * n_parts + np.arange(n_parts)
    picked = dataclasses.replace(
        result, params=jax.tree_util.tree_map(lambda a: np.asarray(a)[keep], result.params),
        dof_counts=tuple(result.dof_counts[k] for k in keep), mean=np.asarray(result.mean)[keep],
        std=np.asarray(result.std)[keep], train_loss=result.train_loss[:, keep], val_loss=result.val_loss[:, keep],
        initial_val_loss=np.asarray(result.initial_val_loss)[keep],
        best_epoch=None if result.best_epoch is None else np.asarray(result.best_epoch)[keep])
    return picked, {"n_candidates": n_candidates, "chosen": [int(c) for c in chosen],
                    "best_val_loss": losses.tolist()}


def plot_loss_curves(result: TrainResult, path: str | os.PathLike) -> None:
    """Write the per-part training and validation loss curves to a PNG (atomically), with
    each part's best epoch (the parameters kept) and the early stop marked."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    fig = Figure(figsize=(7, 4.5))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    epochs = np.arange(1, result.train_loss.shape[0] + 1)
    best = result.best_epoch
    marker = "o" if epochs.size == 1 else None  # one row (a least-squares fit): points, not lines
    for p in range(result.train_loss.shape[1]):
        line, = ax.semilogy(epochs, result.train_loss[:, p], marker=marker, label=f"part {p} train")
        ax.semilogy(epochs, result.val_loss[:, p], "--", marker="s" if marker else None, color=line.get_color(),
                    label=f"part {p} validation")
        if best is not None:
            ax.semilogy([best[p]], [result.val_loss[best[p] - 1, p]], "o", color=line.get_color(), mfc="none",
                        label=f"part {p} best epoch ({best[p]}, kept)")
    if result.stopped_epoch is not None:
        ax.axvline(result.stopped_epoch, color="0.3", ls=":", lw=1.0,
                   label=f"early stop (epoch {result.stopped_epoch})")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("epoch" if marker is None else "least-squares solve")
    ax.set_ylabel("MSE of normalized displacements [-]")
    what = "LSTM" if result.arch.kind == "lstm" else result.arch.kind
    ax.set_title(f"Training of {result.train_loss.shape[1]} {what} replicas (one per part)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize="small")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
