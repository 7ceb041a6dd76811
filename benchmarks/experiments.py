"""The shared pieces of the benchmark scripts that run the paper's cantilever cases
(``paper_experiments.py``, ``bench_surrogates.py``, ``bench_finetune.py``): the experiment
matrix's settings, the cases' loads and targets, the errors of an online run against its
synchronized reference (on top of :mod:`jaxsync.metrics`), the run records and the
training wrapper.

Importing it starts no JAX backend: a script may set its device count afterwards, before
its first run.
"""

from __future__ import annotations

import dataclasses
import math
import os
import platform
import subprocess
import sys
import time
import warnings

import jax
import numpy as np

import jaxsync
from jaxsync.app.plots import tip_node
from jaxsync.metrics import l2_error, node_error
from jaxsync.surrogate import ArchitectureChoice, Sampling, TrainConfig, TrainingChecks, TrainingState, train_surrogates
from jaxsync.surrogate.training import RolloutWarning

# ----------------------------------------------------------------------------- cases

# the body force of the fixed-load cantilever cases [dyn/cm^3] (paper section 5.1)
BODY_FORCES = {"default": (0.0, 0.0, -0.5), "skewed": (0.0, -0.5, -0.5)}
# the paper's refined case: 6 parts on 6 processors
PAPER_REFINED_PARTS = 6
# targets (paper section 5.1), as fractions of the free end's largest |z|
TARGETS = {"fixed": {"tip_max": 0.02, "tip_final": 0.01}, "unseen": {"tip_max": 0.05},
           "full_system": {"tip_max": 0.02}}


def check_tip(mesh, parts) -> int:
    """The free-end node (:func:`jaxsync.app.plots.tip_node`), refused when ``parts``
    shares it: the free-end metrics need a node the solver computes."""
    tip = tip_node(mesh)
    if parts is not None and tip in set(np.asarray(parts.shared_nodes).tolist()):
        raise RuntimeError(f"the free-end node {tip} is shared by the partition: the metric needs a node the "
                           "solver computes; try another --seed")
    return tip


def excluded_nodes(problem, parts) -> np.ndarray:
    """Shared nodes and constrained nodes: what the interior ("noise") metric leaves out."""
    fixed = np.unique(np.asarray(problem.dirichlet_dofs()[0]) // 3)
    shared = np.asarray(parts.shared_nodes) if parts is not None else np.zeros(0, np.int64)
    return np.union1d(fixed, shared).astype(np.int64)


# ----------------------------------------------------------------------------- settings


@dataclasses.dataclass(frozen=True)
class Settings:
    """The matrix's parameters, paper or reduced (``--reduced``). Training hyperparameters
    are the library's defaults (:class:`jaxsync.surrogate.TrainConfig`,
    :class:`jaxsync.surrogate.LSTMArchitecture`) except in reduced mode, where
    ``train_overrides`` makes the training a smoke test."""

    reduced: bool
    n_steps: int
    n_s: int
    save_every: int
    n_past: int
    n_future: int
    train_fraction: float
    n_parts: int
    sequence_variants: tuple
    training_fractions: tuple
    refined_divisions: tuple
    refined_parts: int
    refined_n_s: int
    refined_steps: int
    refined_save_every: int
    t_off: float
    n_runs: int
    n_cond_repeat: int
    ic_range: float
    load_range: tuple
    train_overrides: dict

    def to_dict(self) -> dict:
        return settings_record(self)


def settings_record(settings) -> dict:
    """A settings dataclass with ``train_overrides`` as JSON-ready values."""
    out = dataclasses.asdict(settings)
    out["train_overrides"] = {k: (v.to_dict() if hasattr(v, "to_dict") else v)
                              for k, v in settings.train_overrides.items()}
    return out


def paper_settings() -> Settings:
    # n_s: the library's default (train_surrogates); the full field every 50 steps, which
    # divides n_s = 150, n_cri and the paper's 1e5 steps
    n_s = Sampling.n_s
    return Settings(reduced=False, n_steps=100_000, n_s=n_s, save_every=math.gcd(n_s, 100_000),
                    n_past=20, n_future=20, train_fraction=0.5, n_parts=2,
                    sequence_variants=((5, 5), (20, 20), (50, 50), (20, 5)),
                    training_fractions=(0.2, 0.35, 0.5, 0.75), refined_divisions=(48, 4, 4),
                    refined_parts=PAPER_REFINED_PARTS, refined_n_s=350, refined_steps=500_000,
                    refined_save_every=1000, t_off=3.0, n_runs=10, n_cond_repeat=12, ic_range=0.25,
                    load_range=(0.3, 0.7), train_overrides={})


def reduced_settings(n_devices: int) -> Settings:
    """Seconds instead of hours: the tests' settings. Two variants each of the sequence
    length and training size cases (every distinct network shape costs a compilation);
    the refined case gets as many parts as there are devices, up to 6 (the tests emulate 2)."""
    return Settings(reduced=True, n_steps=3000, n_s=10, save_every=10, n_past=5, n_future=5, train_fraction=0.5,
                    n_parts=2, sequence_variants=((5, 5), (5, 2)), training_fractions=(0.25, 0.5),
                    refined_divisions=(12, 2, 2), refined_parts=max(1, min(PAPER_REFINED_PARTS, n_devices)),
                    refined_n_s=20, refined_steps=4000, refined_save_every=20, t_off=0.5, n_runs=3,
                    n_cond_repeat=12, ic_range=0.25, load_range=(0.3, 0.7),
                    # a smoke test: every distinct network shape costs a compilation, which
                    # dominates these runs (one encoder layer compiles about 30 % faster; the
                    # E_mse measure, about 1.4 s a training, is skipped)
                    train_overrides={"config": TrainConfig(n_epochs=2), "n_hidden": 8, "n_layers": 1,
                                     "emse_applications": 0})


# ----------------------------------------------------------------------------- metrics


def high_frequency_error(reference: np.ndarray, predicted: np.ndarray, excluded_nodes, window: int = 5) -> dict:
    """The fast part of the error at nodes neither shared nor constrained: the error minus
    its centred moving average over ``window`` saved snapshots, largest over nodes,
    components and snapshots, in cm and relative to the model's largest displacement."""
    diff = np.asarray(predicted, np.float64) - np.asarray(reference, np.float64)
    keep = np.setdiff1d(np.arange(diff.shape[1]), np.asarray(excluded_nodes, np.int64))
    diff = diff[:, keep]
    kernel = np.ones(window) / window
    smooth = np.apply_along_axis(lambda e: np.convolve(e, kernel, mode="same"), 0, diff)
    fast = np.abs(diff - smooth)[window:-window]  # the ends see the zero padding
    amplitude = float(np.linalg.norm(np.asarray(reference), axis=2).max())
    worst = float(fast.max()) if fast.size else 0.0
    return {"window_snapshots": window, "max_cm": worst, "relative": worst / amplitude if amplitude > 0 else None}


def run_metrics(reference: np.ndarray, predicted: np.ndarray, tip: int, excluded_nodes, *,
                final_relative_to: str = "final value", component: int = 2) -> dict:
    """Errors of a predicted run against its reference, both (n_saved, n_nodes, 3) at the
    same saved steps.

    tip_*: the free-end node's ``component`` (:func:`jaxsync.metrics.node_error`): largest
    |error| over the saved steps relative to the largest |reference| (the amplitude), and
    the final error relative to the final reference value (``final_relative_to="final
    value"``) or to the amplitude. l2_relative: sqrt(sum (u - u_ref)^2) / sqrt(sum u_ref^2)
    over all saved steps, nodes and components; l2_relative_final: the same at the last
    saved step. e_l2: the norm of the error field per saved step [cm]
    (:func:`jaxsync.metrics.l2_error`). interior_*: the largest error norm at any node
    neither shared nor constrained, relative to the largest displacement norm anywhere in
    the reference (the "noise" the predicted interface injects)."""
    reference, predicted = np.asarray(reference, np.float64), np.asarray(predicted, np.float64)
    if reference.shape != predicted.shape:
        raise ValueError(f"reference {reference.shape} and predicted {predicted.shape} differ in shape")
    diff = predicted - reference
    at_tip = node_error(reference, predicted, tip, component)
    z_ref, z = reference[:, tip, component], predicted[:, tip, component]
    final_scale = at_tip.amplitude if final_relative_to == "amplitude" else abs(float(z_ref[-1]))
    e_l2 = l2_error(reference, predicted)
    norm_ref = float(np.sqrt(np.square(reference).sum()))
    norm_ref_final = float(np.linalg.norm(reference[-1]))
    keep = np.setdiff1d(np.arange(reference.shape[1]), np.asarray(excluded_nodes, np.int64))
    node_norm = np.linalg.norm(diff[:, keep], axis=2)
    model_amplitude = float(np.linalg.norm(reference, axis=2).max())
    worst = np.unravel_index(int(np.argmax(node_norm)), node_norm.shape) if node_norm.size else (0, 0)
    return {
        "component": "xyz"[component], "n_saved": int(len(reference)),
        "tip_amplitude_cm": at_tip.amplitude, "tip_max_error_cm": at_tip.max_error,
        "tip_max_error_relative": at_tip.relative,
        "tip_final_reference_cm": float(z_ref[-1]), "tip_final_predicted_cm": float(z[-1]),
        "tip_final_error_cm": at_tip.final_error, "tip_final_relative_to": final_relative_to,
        "tip_final_error_relative": at_tip.final_error / final_scale if final_scale > 0 else None,
        "l2_relative": float(np.sqrt(np.square(diff).sum()) / norm_ref) if norm_ref > 0 else None,
        "l2_relative_final": float(np.linalg.norm(diff[-1]) / norm_ref_final) if norm_ref_final > 0 else None,
        "e_l2_max_cm": float(e_l2.max()), "e_l2_final_cm": float(e_l2[-1]),
        "model_amplitude_cm": model_amplitude,
        "interior_max_error_cm": float(node_norm.max()) if node_norm.size else 0.0,
        "interior_max_error_relative": (float(node_norm.max()) / model_amplitude
                                        if node_norm.size and model_amplitude > 0 else None),
        "interior_worst_node": int(keep[worst[1]]) if node_norm.size else None,
        "interior_worst_time_index": int(worst[0]) if node_norm.size else None,
    }


def targets(metrics: dict, kind: str) -> dict:
    """Which of the paper's targets of ``kind`` ("fixed", "unseen", "full_system") are met."""
    out = {"kind": kind}
    goal = TARGETS[kind]
    out["tip_max_within_percent"] = 100 * goal["tip_max"]
    out["tip_max_met"] = metrics["tip_max_error_relative"] is not None and \
        metrics["tip_max_error_relative"] <= goal["tip_max"]
    if "tip_final" in goal:
        out["tip_final_within_percent"] = 100 * goal["tip_final"]
        out["tip_final_met"] = metrics["tip_final_error_relative"] is not None and \
            metrics["tip_final_error_relative"] <= goal["tip_final"]
    out["met"] = bool(out["tip_max_met"] and out.get("tip_final_met", True))
    return out


# ----------------------------------------------------------------------------- records


def timed(fn, *args, **kwargs):
    """(fn(*args, **kwargs), its wall time [s])."""
    start = time.perf_counter()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - start


def run_stats(traj, seconds: float) -> dict:
    """The run statistics of a trajectory worth recording, with its wall time."""
    st = traj.stats
    keys = ("us_per_step", "us_per_step_synchronized", "us_per_step_predicted", "compile_seconds",
            "n_synchronized_steps", "n_predicted_steps", "n_cri", "load_jumps", "n_devices", "emulated",
            "dirichlet_max_abs_predicted")
    out = {"wall_seconds": seconds}
    out.update({k: getattr(st, k) for k in keys if getattr(st, k, None) is not None})
    if "load_jumps" in out:
        out["load_jumps"] = list(out["load_jumps"])
    return out


def machine() -> dict:
    """The machine, versions, commit and devices of this process."""
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=os.path.dirname(os.path.abspath(__file__)),
                                capture_output=True, text=True, timeout=10).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        commit = None
    devices = jax.devices()
    return {"platform": platform.platform(), "machine": platform.machine(), "cores": os.cpu_count(),
            "python": sys.version.split()[0], "jax": jax.__version__, "numpy": np.__version__,
            "jaxsync": jaxsync.__version__, "git_commit": commit, "load_average": os.getloadavg()[0],
            "n_devices": len(devices), "device_kind": devices[0].device_kind,
            "xla_flags": os.environ.get("XLA_FLAGS", "")}


# ----------------------------------------------------------------------------- training


# the settings dataclasses of train_surrogates, by its keyword
_SETTINGS = {"architecture": ArchitectureChoice, "sampling": Sampling, "checks": TrainingChecks}


def training_arguments(flat: dict) -> dict:
    """train_surrogates' keyword arguments from flat setting names, the names the records
    keep: ``config`` (the optimizer, a TrainConfig) and any field of ArchitectureChoice
    (``model``, ``n_hidden``, ``n_cond_repeat``...; ``highway`` False unless given, the
    paper's network), Sampling (``n_s``, ``train_fraction``,
    ``seed``...) or TrainingChecks (``emse_applications``...), the library's defaults for
    the rest; any other name (``progress``...) is passed as it is."""
    out = dict(flat)
    out.setdefault("highway", False)  # the paper's network, unless a case names a highway
    if "config" in out:
        out["optimizer"] = out.pop("config")
    for keyword, cls in _SETTINGS.items():
        mine = {f.name: out.pop(f.name) for f in dataclasses.fields(cls) if f.name in out}
        if mine:
            out[keyword] = cls(**mine)
    return out


def train(trajectories, parameters: dict, *, overrides: dict | None = None, folder: str | None = None,
          progress: bool = True):
    """train_surrogates with a case's ``parameters`` and ``overrides`` (flat names, see
    :func:`training_arguments`; the library's defaults for the rest); ``overrides`` are
    the settings that are not the case's (:attr:`Settings.train_overrides`, the reduced
    smoke run's). With ``folder``, the training state, the surrogate file, the loss curves
    and ``train_summary.json`` are written there. The offline check's RolloutWarning is
    recorded, not raised.

    Returns:
        (the :class:`jaxsync.surrogate.TrainedSurrogates`, the training's record)
    """
    overrides = overrides or {}
    passed = {k: (v.to_dict() if hasattr(v, "to_dict") else v) for k, v in parameters.items()}
    n_runs = len(trajectories) if isinstance(trajectories, (list, tuple)) else 1
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        trained = train_surrogates(trajectories, progress=progress,
                                   **training_arguments({**parameters, **overrides}),
                                   state=None if folder is None else TrainingState(folder))
        if folder is not None:
            trained = trained.write(folder)
    rollout_warnings = [str(w.message) for w in caught if issubclass(w.category, RolloutWarning)]
    for w in caught:  # anything else goes on as usual
        if not issubclass(w.category, RolloutWarning):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    summary = trained.summary()
    summary.pop("loss_history", None)  # in train_summary.json
    record = {
        "case_parameters_passed": passed,
        "overrides_passed": sorted(overrides),
        "n_training_runs": n_runs,
        "train_seconds": trained.train_seconds, "n_epochs_run": trained.result.n_epochs_run,
        "rollout_relative": None if trained.rollout is None else trained.rollout.relative.tolist(),
        "rollout_passed": trained.rollout_passed,
        "rollout_warning": rollout_warnings[0] if rollout_warnings else None,
        "folder": None if folder is None else os.path.abspath(folder), "summary": summary,
    }
    return trained, record
