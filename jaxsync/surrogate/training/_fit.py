"""Training surrogates from trajectories: the one library function behind ``jaxsync train``
and ``jaxsync demo``.

:func:`train_surrogates` reads the per-part shared-dof histories of one or more
distributed runs of one partition (:func:`~jaxsync.surrogate.training.read_shared_histories`),
builds the sample-refill windows of every part, fits all replicas together the model's own
way (its ``fit``, :mod:`jaxsync.surrogate.models`: the LSTM and other gradient-fitted
models by :func:`~jaxsync.surrogate.training.train_replicas`; with
``ArchitectureChoice(model="linear")``, the linear autoregressive baseline by least
squares on the same windows instead, :func:`~jaxsync.surrogate.models.fit_linear`),
measures sqrt(E_mse) and the offline rollout on the first run and returns a
:class:`TrainedSurrogates`: the :class:`~jaxsync.surrogate.Surrogate` for the solver, its
surrogate file's content (with the partition's shared node ids), the loss history and
timings.  It writes nothing, except the resumable training state when asked
(``state=TrainingState(folder, every)``: ``<folder>/training_state.h5``, rewritten every
``every`` epochs; the same call again continues from it and ends with the same parameters
as an uninterrupted run; a state of other data or settings is refused; LSTM only, a
least-squares fit has no state to resume).

Its settings come in frozen dataclasses, each with the defaults of ``jaxsync train``:

==========================  ============================================================
``architecture``            :class:`~jaxsync.surrogate.models.ArchitectureChoice`:
                            model (LSTM or linear), n_H, k, q, dtype, ridge r
``sampling``                :class:`~jaxsync.surrogate.training.Sampling`: n_s, n_p, n_f,
                            fractions, offsets, split, load-jump windows, seed
``optimizer``               :class:`~jaxsync.surrogate.training.TrainConfig`: the schedule,
                            early stopping, candidates per part
``checks``                  :class:`~jaxsync.surrogate.training.TrainingChecks`: E_mse
                            cycles, offline rollout tolerance
``state``                   :class:`~jaxsync.surrogate.training.TrainingState`, or
                            None: where and how often the resumable state is written
==========================  ============================================================

:meth:`TrainedSurrogates.write` writes the results into a folder, each file atomically:

* the surrogate file (``surrogate.h5`` by default, :data:`SURROGATE_NAME`),
* ``loss_curves.png``, the per-part training and validation losses,
* ``train_summary.json`` (:meth:`TrainedSurrogates.summary`),

and then deletes the training state, which has nothing left to resume.
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
from jaxsync.fem._load_signals import RecordedLoadSignals
from jaxsync.io import atomic_json, atomic_path
from jaxsync.io.surrogate_file import SavedSurrogate, save_surrogate
from jaxsync.io.trajectory import Trajectory
from jaxsync.surrogate._model import Surrogate
from jaxsync.surrogate.models._architecture import ArchitectureChoice, architecture_to_dict
from jaxsync.surrogate.models._protocol import FitSettings
from jaxsync.surrogate.models._replicas import count_parameters
from jaxsync.surrogate.training._data import Sampling, build_dataset, stack_replicas
from jaxsync.surrogate.training._evaluate import (
    RolloutErrors,
    RolloutWarning,
    TrainingChecks,
    e_mse,
    max_applications,
    rollout_errors,
)
from jaxsync.surrogate.training._histories import SharedHistories, read_shared_histories
from jaxsync.surrogate.training._train import TrainConfig, TrainProgress, TrainResult
from jaxsync.surrogate.training._training_state import STATE_NAME, TrainingState

__all__ = ["train_surrogates", "TrainedSurrogates", "plot_loss_curves", "choose_candidates", "SURROGATE_NAME",
           "STATE_NAME", "SUMMARY_NAME", "LOSS_CURVES_NAME"]

#: Default name of the surrogate file that :meth:`TrainedSurrogates.write` writes.
SURROGATE_NAME = "surrogate.h5"
SUMMARY_NAME = "train_summary.json"
LOSS_CURVES_NAME = "loss_curves.png"

# what the surrogate file's metadata keeps of the summary
_METADATA_KEYS = ("model", "training", "sampling", "candidates", "load_parameters", "final_val_loss", "sqrt_e_mse",
                  "rollout_check", "shared_amplitude_cm")


@dataclasses.dataclass(frozen=True)
class TrainedSurrogates:
    """The result of :func:`train_surrogates`.

    Attributes:
        surrogate: the trained replicas, ready for the solver (conditional networks carry
            the load parameter of the first trajectory).
        result: the optimization: losses per epoch and part, best epochs, early stop,
            seconds per epoch, compilation time (a linear surrogate's: the one
            least-squares solve, :func:`~jaxsync.surrogate.models.fit_linear`).
        shared_nodes: per part, the global ids of its shared nodes (the partition).
        trajectories: absolute path of each trajectory (None for one given in memory).
        load_parameters: the load parameter of each run fed to a conditional network, or
            None (unconditional).
        sampling: the sampling settings used, ``load_jump_windows`` decided for the model
            (:meth:`~jaxsync.surrogate.training.Sampling.for_model`).
        checks: the checks asked for (:class:`~jaxsync.surrogate.training.TrainingChecks`).
        n_train_windows, n_val_windows: windows per part.
        n_excluded_windows: windows per part left out because they straddle a load jump.
        state: where the resumable training state was written
            (:class:`~jaxsync.surrogate.training.TrainingState`); None when none was
            (not asked for, or the linear model).
        train_seconds: wall time of the training call (compilation included) [s].
        e_mse_applications: refill cycles N of ``sqrt_e_mse`` (None: not measured).
        sqrt_e_mse: per part, sqrt(E_mse) on the first trajectory [solver units, cm].
        rollout: the offline accuracy check: every replica rolled out autonomously from
            step n_s n_p - 1 (where an online run starts predicting) to the end of the
            first trajectory, including the steps after ``train_fraction`` that no
            window was taken from (:func:`~jaxsync.surrogate.training.rollout_errors`);
            None when not measured (shared histories thinned, or too short a run).
        candidates: with several candidates per part, which one each part kept and every
            candidate's validation loss (:func:`choose_candidates`); None for one, and
            for the linear surrogate (least squares has one solution).
        files: the files written by :meth:`write`, by kind (``surrogate``: the surrogate
            file, ``loss_curves``, ``summary``); empty before.
        shared_amplitude: the largest |displacement| component at the shared nodes [cm]
            (solver units) in the steps training could read (the first ``train_fraction``
            of every run, :func:`training_amplitude`): what a relative error-control
            tolerance of a run of these surrogates refers to (``jaxsync predict``); None
            when not known.
    """

    surrogate: Surrogate
    result: TrainResult
    shared_nodes: tuple[np.ndarray, ...]
    trajectories: tuple[str | None, ...]
    load_parameters: tuple[float, ...] | None
    sampling: Sampling
    checks: TrainingChecks
    n_train_windows: int
    n_val_windows: int
    train_seconds: float
    e_mse_applications: int | None
    sqrt_e_mse: tuple[float, ...] | None
    rollout: RolloutErrors | None = None
    n_excluded_windows: int = 0
    state: TrainingState | None = None
    candidates: dict | None = None
    files: dict[str, str] = dataclasses.field(default_factory=dict)
    shared_amplitude: float | None = None

    @property
    def model(self) -> str:
        """``"lstm"``, ``"linear"`` or a registered model's kind: the kind of the trained replicas."""
        return self.result.arch.kind

    @property
    def rollout_tolerance(self) -> float | None:
        """The largest ``rollout.relative`` accepted without a
        :class:`~jaxsync.surrogate.training.RolloutWarning` (None: no check)."""
        return self.checks.rollout_tolerance

    @property
    def rollout_passed(self) -> bool | None:
        """Every replica's offline rollout error within ``rollout_tolerance`` of its
        shared amplitude (None: not checked)."""
        if self.rollout is None or self.rollout_tolerance is None:
            return None
        return bool(self.rollout.relative.max() <= self.rollout_tolerance)

    @property
    def state_every(self) -> int:
        """Epochs between writes of the resumable training state (0: none was written)."""
        return 0 if self.state is None else int(self.state.every)

    @property
    def saved(self) -> SavedSurrogate:
        """What the surrogate file holds: the replicas with the partition's shared node
        ids and the training metadata (a part of :meth:`summary`)."""
        summary = self.summary()
        return SavedSurrogate.from_result(self.result, self.surrogate.n_s, self.shared_nodes,
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
        fields = arch.summary_fields(result, self.state_every)  # how the model was fitted
        s = self.sampling
        out = {
            "model": self.model,
            "trajectories": list(self.trajectories),
            "load_parameters": None if self.load_parameters is None else list(self.load_parameters),
            "load_inputs": [i.to_dict() for i in result.load_inputs],
            "n_parts": n_parts,
            "dof_counts": list(result.dof_counts),
            "architecture": architecture_to_dict(arch),
            "parameters_per_replica_padded": count_parameters(result.params) // n_parts,
            "training": fields["training"],
            "sampling": {"n_s": self.surrogate.n_s, "n_offsets": s.n_offsets, "train_fraction": s.train_fraction,
                         "val_fraction": s.val_fraction, "split": s.split, "seed": s.seed,
                         "n_train_windows": self.n_train_windows, "n_val_windows": self.n_val_windows,
                         "n_excluded_windows": self.n_excluded_windows,
                         "load_jump_windows": s.load_jump_windows},
            "candidates": self.candidates,
            "initial_val_loss": result.initial_val_loss.tolist(),
            "final_train_loss": result.train_loss[-1].tolist(),
            "final_val_loss": result.best_val_loss.tolist(),
            "last_epoch_val_loss": result.val_loss[-1].tolist(),
            "n_epochs_run": fields["n_epochs_run"],
            "stopped_at_epoch": result.stopped_epoch,
            "seconds_per_epoch": fields["seconds_per_epoch"],
            "gradient_steps_per_second": fields["gradient_steps_per_second"],
            "compile_seconds": result.compile_seconds,
            "train_seconds": self.train_seconds,
            "e_mse_applications": self.e_mse_applications,
            "sqrt_e_mse": None if self.sqrt_e_mse is None else list(self.sqrt_e_mse),
            "shared_amplitude_cm": self.shared_amplitude,
            "rollout_check": None if self.rollout is None else {
                **self.rollout.to_dict(), "tolerance": self.rollout_tolerance, "passed": self.rollout_passed},
        }
        if self.files:
            out.update(surrogate=self.files["surrogate"], loss_curves=self.files["loss_curves"])
        out["loss_history"] = {"train": result.train_loss.tolist(), "val": result.val_loss.tolist()}
        return out

    def write(self, out: str | os.PathLike, surrogate_name: str = SURROGATE_NAME) -> TrainedSurrogates:
        """Write the results into the folder ``out`` (created if missing), each file
        atomically (a failure leaves the earlier files of those names intact): the
        surrogate file ``surrogate_name``, ``loss_curves.png`` and ``train_summary.json``
        (:meth:`summary`, with the paths written). Then the training state
        (:attr:`state`), which has nothing left to resume, is deleted.

        Returns:
            These results with :attr:`files` set (what the summary file holds).
        """
        os.makedirs(out, exist_ok=True)
        files = {"surrogate": os.path.abspath(os.path.join(out, surrogate_name)),
                 "loss_curves": os.path.abspath(os.path.join(out, LOSS_CURVES_NAME)),
                 "summary": os.path.abspath(os.path.join(out, SUMMARY_NAME))}
        save_surrogate(files["surrogate"], self.saved)
        plot_loss_curves(self.result, files["loss_curves"])
        written = dataclasses.replace(self, files=files)
        atomic_json(files["summary"], written.summary())
        if self.state is not None and os.path.exists(self.state.path):
            os.remove(self.state.path)  # everything it could resume is written
        return written


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


def _load_signals(runs, load_input: bool | None) -> tuple[list[np.ndarray] | None, tuple]:
    """The per-run load signals the windows carry and their descriptions, decided by
    ``load_input`` (:class:`~jaxsync.surrogate.models.ArchitectureChoice`): None:
    when every run records signals (and there is at least one); True: required; False:
    none."""
    recorded = [run.load_signal is not None and run.load_signal.shape[1] > 0 for run in runs]
    if load_input is False or (load_input is None and not all(recorded)):
        return None, ()
    if not all(recorded):
        missing = [k for k, ok in enumerate(recorded) if not ok]
        raise ConfigError(
            f"load_input=True (--load-input) but trajectory {', '.join(map(str, missing))} records no load signals "
            "(a run without time-dependent loads, or a file written before jaxsync recorded them): rerun the solver "
            "(jaxsync simulate) to record them, or train without the load input (load_input=False, --no-load-input)")
    first = runs[0].load_inputs
    for k, run in enumerate(runs[1:], start=1):
        if [i.signature for i in run.load_inputs] != [i.signature for i in first]:
            raise ConfigError(
                f"trajectory {k} has the loads {'; '.join(map(str, run.load_inputs))} but trajectory 0 has "
                f"{'; '.join(map(str, first))}: a surrogate with load input is trained on runs whose loads have the "
                "same count, kinds and time-function forms; train on such runs, or without the load input "
                "(load_input=False)")
    return [run.load_signal for run in runs], tuple(first)


def train_surrogates(
    trajectories,
    *,
    architecture: ArchitectureChoice = ArchitectureChoice(),
    sampling: Sampling = Sampling(),
    optimizer: TrainConfig = TrainConfig(),
    checks: TrainingChecks = TrainingChecks(),
    load_parameters: Sequence[float] | None = None,
    allow_predicted: bool = False,
    state: TrainingState | None = None,
    devices: int | None = None,
    progress: bool = True,
    callback: Callable[[TrainProgress], None] | None = None,
) -> TrainedSurrogates:
    """Train one LSTM surrogate per part on distributed trajectories of one partition
    (or fit the linear baseline: ``architecture=ArchitectureChoice(model="linear")``, or
    any registered model: ``ArchitectureChoice(model=kind)``, fitted by its own ``fit``,
    :mod:`jaxsync.surrogate.models`).

    Computes only: write the results with :meth:`TrainedSurrogates.write`.

    Args:
        trajectories: a :class:`jaxsync.Trajectory` or trajectory file, or a sequence of
            them (runs of one partition, e.g. different loads), with the shared nodes
            kept every step (``simulate(..., shared_every=1)``) or at any stride dividing
            ``sampling.n_s`` (e.g. ``save_every=n_s``: what training reads, and all a long
            run needs to keep). Displacements in solver units (cm in the paper).
        architecture: the model and its size
            (:class:`~jaxsync.surrogate.models.ArchitectureChoice`; default: the
            LSTM with n_H = 50, k = 2, unconditional, float32). ``n_cond_repeat`` > 0
            trains the conditional network. The linear model is fitted by least squares
            with ``architecture.regularization``. ``architecture.load_input`` (default
            None: on when every trajectory records its load signals, as every run of
            ``jaxsync simulate`` does) feeds both models the known load signals (the
            time functions of the problem's loads and prescribed motions over the past and
            the predicted window, :mod:`jaxsync.fem`); trajectory files
            written before those were recorded train the load-blind model, and
            ``load_input=True`` refuses them. The LSTM-only settings (``n_hidden``,
            ``n_layers``, ``optimizer``, ``state``, ``devices``, ``progress``,
            ``callback``) do not apply to it.
        sampling: the windows and the seed (:class:`~jaxsync.surrogate.training.Sampling`;
            default n_s = 150, n_p = n_f = 20, the first half of each run, 25 %
            interleaved validation windows, seed 0). Its ``load_jump_windows`` None takes
            the model's rule: windows across a recorded load jump are left out for the
            linear model and kept for the LSTM.
        optimizer: the schedule and the candidates per part
            (:class:`~jaxsync.surrogate.training.TrainConfig`; default the laptop schedule:
            n_B = 10, eta0 = 2e-3, gamma = 0.995, 800 epochs, early stop after 200, the
            better of 2 candidates per part). LSTM only.
        checks: the measures after training, on the first trajectory
            (:class:`~jaxsync.surrogate.training.TrainingChecks`; default sqrt(E_mse) over
            60 refill cycles and the offline rollout check at 2 % of each part's shared
            amplitude, warning with
            :class:`~jaxsync.surrogate.training.RolloutWarning` above it).
        load_parameters: the load parameter of each trajectory (default: their problem
            parameter ``load_parameter``); used with ``architecture.n_cond_repeat`` > 0.
        allow_predicted: accept synchronization-avoiding trajectories (refused by default).
        state: where and how often to write the resumable training state
            (:class:`~jaxsync.surrogate.training.TrainingState`; None, the default:
            none). The same call again resumes from it; :meth:`TrainedSurrogates.write`
            deletes it. LSTM only.
        devices: local devices to spread the parts over (default: as many as divide the
            part count).
        progress: show a progress bar.
        callback: given a :class:`~jaxsync.surrogate.training._train.TrainProgress` after every
            compiled chunk of epochs.

    Returns:
        :class:`TrainedSurrogates` (nothing written but the training state).

    Raises:
        CheckpointError: unusable trajectories (not distributed, shared nodes kept at a
            stride that does not divide n_s, predicted, of different partitions) or a
            training state in ``state.folder`` of other data or settings.
        ConfigError: unusable settings.
    """
    for name, value, cls in (("architecture", architecture, ArchitectureChoice), ("sampling", sampling, Sampling),
                             ("optimizer", optimizer, TrainConfig), ("checks", checks, TrainingChecks)):
        if not isinstance(value, cls):
            raise ConfigError(f"{name} must be a jaxsync.surrogate.{cls.__name__}, got {value!r}")
    if state is not None and not isinstance(state, TrainingState):
        raise ConfigError(f"state must be a jaxsync.surrogate.TrainingState(folder, every) or None, got {state!r}")
    model = architecture.model_class
    sampling = sampling.for_model(model)
    n_s, n_past, n_future = sampling.n_s, sampling.n_past, sampling.n_future
    exclude_jumps = sampling.load_jump_windows == "exclude"
    runs, names = _read_runs(trajectories, allow_predicted)
    loads = _load_parameters(runs, load_parameters, architecture.n_cond_repeat)
    signals, load_inputs = _load_signals(runs, architecture.load_input)
    n_parts = len(runs[0].histories)
    row_strides = {run.for_sampling(n_s) for run in runs}
    if len(row_strides) > 1:
        raise CheckpointError(f"the trajectories keep their shared nodes at different strides "
                              f"({sorted({run.stride for run in runs})} steps); train on runs saved alike")
    row_stride = row_strides.pop()
    datasets = [
        build_dataset([run.histories[p] for run in runs], row_stride, n_past, n_future, sampling.train_fraction,
                      sampling.val_fraction, sampling.seed, loads, n_offsets=sampling.n_offsets, split=sampling.split,
                      load_jumps=[[j / run.stride for j in run.load_jumps] if exclude_jumps else []
                                  for run in runs], signals=signals)
        for p in range(n_parts)
    ]
    if not model.resumes_training:
        state = None  # e.g. a least-squares fit: no state to resume
    # candidate c of part p is replica c n_parts + p: the same windows, its own initial weights
    n_candidates = model.candidates_per_part(optimizer)
    data = stack_replicas(datasets * n_candidates, load_inputs)
    arch = model.from_choice(architecture, data.n_dof_max, n_past, n_future, data.n_load)
    started = time.perf_counter()
    result = arch.fit(data, FitSettings(architecture=architecture, optimizer=optimizer,
                                        key=jax.random.key(sampling.seed), progress=progress, devices=devices,
                                        state=state, callback=callback))
    train_seconds = time.perf_counter() - started
    result, candidates = choose_candidates(result, n_parts, n_candidates)
    arch = result.arch

    load = None if loads is None else loads[0]
    surrogate = Surrogate.from_result(result, n_s, load)
    first = runs[0]
    # the offline checks read the first run's recorded load signals (kept every step there)
    checked = surrogate if signals is None or first.stride != 1 else surrogate.with_load_signals(
        RecordedLoadSignals(first.load_signal, load_inputs))
    n_app = min(checks.emse_applications, max_applications(first.histories[0].shape[0], n_s, n_past, n_future))
    if first.stride != 1:  # the refill reads every step of its input history
        n_app = 0
    sqrt_e_mse = rollout = None
    histories = np.stack([np.pad(h, ((0, 0), (0, arch.n_dof - h.shape[1]))) for h in first.histories])
    if n_app > 0:
        sqrt_e_mse = tuple(float(v) for v in np.sqrt(e_mse(checked, histories, n_app)))
    # from where an online run starts predicting: n_s n_p - 1, or after the last load jump
    # (simulate_sync_avoiding stays synchronized through it by default)
    start = n_s * n_past - 1 + (first.last_load_jump or 0)
    tolerance = checks.rollout_tolerance
    if (tolerance is not None and first.stride == 1
            and max_applications(histories.shape[1], n_s, n_past, n_future, start) > 0):
        rollout = rollout_errors(checked, histories, start=start)
    if rollout is not None:
        worst = int(np.argmax(rollout.relative))
        if rollout.relative[worst] > tolerance:
            warnings.warn(RolloutWarning(
                f"the trained surrogates miss the offline check: rolled out without the truth over "
                f"{rollout.n_steps} steps of the first trajectory, part {worst}'s shared displacements are "
                f"off by up to {100 * rollout.relative[worst]:.2g} % of their amplitude (tolerance "
                f"{100 * tolerance:.2g} %); an online run would likely be as far off. "
                + arch.accuracy_advice
                + " (train_fraction, more runs), or run online with error control (resync_tolerance)"),
                stacklevel=2)
    return TrainedSurrogates(
        surrogate=surrogate, result=result, shared_nodes=first.shared_nodes, trajectories=tuple(names),
        load_parameters=None if loads is None else tuple(loads), sampling=sampling, checks=checks,
        n_train_windows=int(data.x_train.shape[1]), n_val_windows=int(data.x_val.shape[1]),
        train_seconds=train_seconds, e_mse_applications=n_app if sqrt_e_mse is not None else None,
        sqrt_e_mse=sqrt_e_mse, rollout=rollout, n_excluded_windows=datasets[0].n_excluded, state=state,
        candidates=candidates, shared_amplitude=training_amplitude(runs, sampling.train_fraction),
    )


def training_amplitude(runs, train_fraction: float) -> float:
    """The largest |displacement| component at the shared nodes [cm] over the rows of
    every run and part that training may read: the first ``trained_rows(n_rows,
    train_fraction)`` of each part's history (:func:`jaxsync.surrogate.training._data.trained_rows`,
    the rule :func:`~jaxsync.surrogate.training.build_dataset` samples by). ``runs``:
    :class:`~jaxsync.surrogate.training.SharedHistories`."""
    from ._data import trained_rows

    return max(float(np.abs(h[:trained_rows(h.shape[0], train_fraction)]).max(initial=0.0))
               for run in runs for h in run.histories)


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
        best_epoch=None if result.best_epoch is None else np.asarray(result.best_epoch)[keep],
        signal_scale=None if result.signal_scale is None else np.asarray(result.signal_scale)[keep])
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
    what = result.arch.display_name or result.arch.kind
    ax.set_title(f"Training of {result.train_loss.shape[1]} {what} replicas (one per part)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize="small")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
