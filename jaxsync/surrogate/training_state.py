"""The resumable state of a training run (one HDF5 file, written atomically).

:func:`~jaxsync.surrogate.train.train_replicas` with ``checkpoint=path`` writes its whole
state -- the carry of its compiled chunks (parameters, Adam state, best parameters,
best validation losses and epochs) as flat leaves, the loss history and the bookkeeping
(epochs done, stopped, timings) -- and resumes from it.  A state is resumed only by a
run with the same :func:`training_fingerprint` (data, architecture, configuration, key,
initial parameters, checkpoint interval); anything else is refused with
:class:`~jaxsync.errors.CheckpointError` naming the difference.  A SHA-256 checksum over
arrays and attributes detects damaged files.

This is not the checkpoint of a trained surrogate (:mod:`jaxsync.surrogate.checkpoint`):
it holds optimizer state, and it is deleted once the results are written.
"""

from __future__ import annotations

import json
from typing import Any

import h5py
import jax
import numpy as np

from jaxsync.errors import CheckpointError
from jaxsync.io import array_checksum, atomic_h5
from jaxsync.surrogate.data import ReplicaData
from jaxsync.surrogate.lstm import LSTMArchitecture, Params

__all__ = ["training_fingerprint", "save_training_state", "load_training_state"]

_STATE_KIND = "jaxsync-training-state"
_STATE_VERSION = 1


def _digest(arrays) -> str:
    """sha256 over a sequence of arrays (dtype, shape and bytes of each)."""
    return array_checksum({f"{i:04d}": np.asarray(a) for i, a in enumerate(arrays)}, {})


def training_fingerprint(data: ReplicaData, arch: LSTMArchitecture, config, key: jax.Array,
                         init: Params | None = None, checkpoint_every: int | None = None) -> dict[str, Any]:
    """Everything that determines a training run, as a JSON-serializable dict
    (``config``: the :class:`~jaxsync.surrogate.train.TrainConfig`).

    A training checkpoint is resumed only by a run with the same fingerprint: same
    windows and normalization (hashed), architecture, configuration, key, initial
    parameters and checkpoint interval (which sets where the compiled chunks end).
    """
    return {
        "data_sha256": _digest([data.x_train, data.y_train, data.load_parameter_train, data.x_val, data.y_val,
                                data.load_parameter_val, data.dof_mask, data.mean, data.std]),
        "architecture": arch.to_dict(),
        "config": config.to_dict(),
        "key": np.asarray(jax.random.key_data(key)).ravel().tolist(),
        "init_sha256": None if init is None else _digest(jax.tree_util.tree_leaves(init)),
        "checkpoint_every": checkpoint_every,
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
    try:
        with h5py.File(path, "r") as f:
            attrs = {k: (v.item() if hasattr(v, "item") else v) for k, v in f.attrs.items() if k != "checksum"}
            attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in attrs.items()}
            stored_sum = f.attrs.get("checksum")
            arrays = {}
            f.visititems(lambda name, obj: arrays.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    except Exception as exc:
        raise CheckpointError(f"cannot read training checkpoint {path} ({exc}); {fix}") from exc
    if attrs.get("kind") != _STATE_KIND:
        raise CheckpointError(f"{path} is not a jaxsync training checkpoint; {fix}")
    if int(attrs.get("version", -1)) != _STATE_VERSION:
        raise CheckpointError(f"training checkpoint {path} has version {attrs.get('version')}, this jaxsync "
                              f"reads {_STATE_VERSION}; {fix}")
    if stored_sum is None or str(stored_sum.decode() if isinstance(stored_sum, bytes) else stored_sum) != \
            array_checksum(arrays, attrs):
        raise CheckpointError(f"training checkpoint {path} fails its checksum (damaged or altered); {fix}")
    stored = json.loads(attrs["fingerprint"])
    if stored != fingerprint:
        diffs = "; ".join(_fingerprint_differences(stored, fingerprint))
        raise CheckpointError(
            f"training checkpoint {path} was written by a run with other data or settings ({diffs}); "
            f"rerun with the same arguments to resume, or {fix}"
        )
    leaves, treedef = jax.tree_util.tree_flatten(template)
    loaded = [arrays.get(f"state/{i:04d}") for i in range(len(leaves))]
    for i, (a, b) in enumerate(zip(loaded, leaves)):
        if a is None or a.shape != b.shape or a.dtype != b.dtype:
            raise CheckpointError(f"training checkpoint {path}: state array {i} does not fit this run; {fix}")
    history = {k[len("history/"):]: v for k, v in arrays.items() if k.startswith("history/")}
    return jax.tree_util.tree_unflatten(treedef, loaded), history, json.loads(attrs["info"])
