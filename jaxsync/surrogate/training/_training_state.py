"""The resumable state of a training run (one HDF5 file, written atomically).

:class:`TrainingState` says where (``<folder>/training_state.h5``) and how often (every
``every`` epochs) a training writes it: :func:`~jaxsync.surrogate.training.train_replicas`
and :func:`~jaxsync.surrogate.train_surrogates` take it as ``state=``.  The file holds the
whole state -- the carry of the compiled chunks (parameters, Adam state, best parameters,
best validation losses and epochs) as flat leaves, the loss history and the bookkeeping
(epochs done, stopped, timings) -- and a training started again with the same
:func:`training_fingerprint` (data, architecture, configuration, key, initial
parameters, state interval) resumes from it; anything else is refused with
:class:`~jaxsync.errors.CheckpointError` naming the difference.  A SHA-256 checksum over
arrays and attributes detects damaged files.

This is not the surrogate file of a trained surrogate (:mod:`jaxsync.io.surrogate_file`)
nor the solver's checkpoint: it holds optimizer state, and it is deleted once the
results are written (:meth:`jaxsync.surrogate.TrainedSurrogates.write`).
"""

from __future__ import annotations

import dataclasses
import json
import numbers
import os
from typing import Any

import h5py
import jax
import numpy as np

from jaxsync.errors import CheckpointError, ConfigError
from jaxsync.io import array_checksum, atomic_h5
from jaxsync.surrogate.training._data import ReplicaData

Params = Any  # a pytree of parameter arrays

__all__ = ["TrainingState", "STATE_NAME", "training_fingerprint", "save_training_state", "load_training_state"]

#: File name of the training state inside :attr:`TrainingState.folder`.
STATE_NAME = "training_state.h5"

_STATE_KIND = "jaxsync-training-state"
_STATE_VERSION = 1


@dataclasses.dataclass(frozen=True)
class TrainingState:
    """Where and how often a training writes its resumable state (the ``state`` of
    :func:`~jaxsync.surrogate.training.train_replicas` and
    :func:`~jaxsync.surrogate.train_surrogates`).

    The file ``<folder>/training_state.h5`` (:attr:`path`) is rewritten atomically every
    ``every`` epochs and at the end of the training; a training started again with the
    same data and settings continues from it and ends with the same parameters as an
    uninterrupted one (compiled chunks also end at the multiples of ``every``, so a
    multiple of ``TrainConfig.epochs_per_call`` compiles no second chunk length).

    Attributes:
        folder: folder of the state file, created if missing (``jaxsync train``: its
            output folder).
        every: epochs between writes, an integer >= 1 (default 50; ``jaxsync train
            --state-every``). For no state at all pass ``state=None``.
    """

    folder: str | os.PathLike
    every: int = 50

    def __post_init__(self):
        if not isinstance(self.folder, (str, os.PathLike)):
            raise ConfigError(f"TrainingState.folder must be a folder path, got {self.folder!r}")
        if isinstance(self.every, bool) or not isinstance(self.every, numbers.Integral) or self.every < 1:
            raise ConfigError(f"TrainingState.every must be an integer >= 1 (epochs between writes of the training "
                              f"state), got {self.every!r}; pass state=None for no training state")

    @property
    def path(self) -> str:
        """The state file, ``<folder>/training_state.h5``."""
        return os.path.join(os.fspath(self.folder), STATE_NAME)


def _digest(arrays) -> str:
    """sha256 over a sequence of arrays (dtype, shape and bytes of each)."""
    return array_checksum({f"{i:04d}": np.asarray(a) for i, a in enumerate(arrays)}, {})


def training_fingerprint(data: ReplicaData, arch, config, key: jax.Array,
                         init: Params | None = None, state_every: int | None = None) -> dict[str, Any]:
    """Everything that determines a training run, as a JSON-serializable dict
    (``config``: the :class:`~jaxsync.surrogate.training.TrainConfig`).

    A training state is resumed only by a run with the same fingerprint: same windows and
    normalization (hashed), architecture, configuration, key, initial parameters and
    state interval ``state_every`` (which sets where the compiled chunks end).
    """
    return {
        "data_sha256": _digest([data.x_train, data.y_train, data.load_parameter_train, data.x_val, data.y_val,
                                data.load_parameter_val, data.dof_mask, data.mean, data.std]
                               + ([] if data.signal_train is None else
                                  [data.signal_train, data.signal_val, data.signal_scale])),
        "architecture": arch.to_dict(),
        "config": config.to_dict(),
        "key": np.asarray(jax.random.key_data(key)).ravel().tolist(),
        "init_sha256": None if init is None else _digest(jax.tree_util.tree_leaves(init)),
        "state_every": state_every,
    }


def _fingerprint_differences(stored: dict, current: dict) -> list[str]:
    out = []
    for name in sorted(set(stored) | set(current)):
        a, b = stored.get(name), current.get(name)
        if a == b:
            continue
        if isinstance(a, dict) and isinstance(b, dict):
            out += [f"{name}.{k}: {a.get(k)!r} there, {b.get(k)!r} here"
                    for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]
        elif name.endswith("sha256"):
            out.append(f"{name[:-len('_sha256')]} differ")
        else:
            out.append(f"{name}: {a!r} there, {b!r} here")
    return out


def save_training_state(path, fingerprint: dict, state, history: dict[str, np.ndarray],
                        info: dict[str, Any]) -> None:
    """Write the training state atomically (HDF5): the chunk carry as flat leaves, the
    loss history and the bookkeeping in ``info`` (epochs done, stopped, timings)."""
    arrays = {f"state/{i:04d}": np.asarray(leaf) for i, leaf in enumerate(jax.tree_util.tree_leaves(state))}
    arrays.update({f"history/{k}": np.asarray(v) for k, v in history.items()})
    attrs = {"kind": _STATE_KIND, "version": _STATE_VERSION, "fingerprint": json.dumps(fingerprint, sort_keys=True),
             "info": json.dumps(info, sort_keys=True)}
    with atomic_h5(path) as f:
        for name, value in attrs.items():
            f.attrs[name] = value
        f.attrs["checksum"] = array_checksum(arrays, attrs)
        for name, array in arrays.items():
            f[name] = array


def load_training_state(path, fingerprint: dict, template):
    """Read a state written by :func:`save_training_state` for a run with ``fingerprint``;
    ``template`` is the chunk carry of this run (tree structure, shapes and dtypes)."""
    fix = "delete it to start over, or write to another output folder"
    if os.path.isdir(path):
        raise CheckpointError(f"training state {os.fspath(path)!r} is a folder; give a .h5 file, or {fix}")
    try:
        with h5py.File(path, "r") as f:
            attrs = {k: (v.item() if hasattr(v, "item") else v) for k, v in f.attrs.items() if k != "checksum"}
            attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in attrs.items()}
            stored_sum = f.attrs.get("checksum")
            arrays = {}
            f.visititems(lambda name, obj: arrays.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    except Exception as exc:
        raise CheckpointError(f"cannot read the training state {path} ({' '.join(str(exc).split())}); {fix}") from exc
    if attrs.get("kind") != _STATE_KIND:
        raise CheckpointError(f"{path} is not a jaxsync training state; {fix}")
    if int(attrs.get("version", -1)) != _STATE_VERSION:
        raise CheckpointError(f"training state {path} has version {attrs.get('version')}, this jaxsync "
                              f"reads {_STATE_VERSION}; {fix}")
    if stored_sum is None or str(stored_sum.decode() if isinstance(stored_sum, bytes) else stored_sum) != \
            array_checksum(arrays, attrs):
        raise CheckpointError(f"training state {path} fails its checksum (damaged or altered); {fix}")
    stored = json.loads(attrs["fingerprint"])
    if stored != fingerprint:
        diffs = "; ".join(_fingerprint_differences(stored, fingerprint))
        raise CheckpointError(
            f"training state {path} was written by a run with other data or settings ({diffs}); "
            f"rerun with the same arguments to resume, or {fix}"
        )
    leaves, treedef = jax.tree_util.tree_flatten(template)
    loaded = [arrays.get(f"state/{i:04d}") for i in range(len(leaves))]
    for i, (a, b) in enumerate(zip(loaded, leaves)):
        if a is None or a.shape != b.shape or a.dtype != b.dtype:
            raise CheckpointError(f"training state {path}: state array {i} does not fit this run; {fix}")
    history = {k[len("history/"):]: v for k, v in arrays.items() if k.startswith("history/")}
    return jax.tree_util.tree_unflatten(treedef, loaded), history, json.loads(attrs["info"])
