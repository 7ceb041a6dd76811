"""Surrogate files: a set of trained replicas as one HDF5 file (``surrogate.h5``), and
:class:`SavedSurrogate`, what such a file holds.

(Not to be confused with the solver's resumable checkpoints, :mod:`jaxsync.io.checkpoint`,
or the training state of :mod:`jaxsync.surrogate.training`.)

Layout (format ``jaxsync-lstm-surrogate``, version :data:`FORMAT_VERSION`; the name is
kept from before the linear surrogate, which the same format holds)::

    /params/<path>          stacked, padded parameters, e.g. params/encoder/0/forward/w_d
                            with shape (n_parts, 4 n_H, n_dof) (LSTM) or params/w_in with
                            shape (n_parts, n_p, n_dof, rank) (linear)
    /normalization/mean     (n_parts, n_dof) float64, solver units
    /normalization/std      (n_parts, n_dof) float64
    /dof_counts             (n_parts,) int64, real dofs of each part
    /shared_nodes/<p>       (n_shared_p,) int64 global node ids of part p (optional group)
    /load_inputs/scale      (n_parts, n_load) float64 scale of each known load signal
                            (load input only)
    attrs: format, format_version, architecture (JSON, with its ``kind``, "lstm" or
           "linear", and ``n_load`` when > 0; a file without ``kind`` holds an LSTM), n_s,
           metadata (JSON), load_inputs (JSON list, load input only: per signal its
           ``source`` "loads[i]"/"dirichlet[i]", ``kind``, time-function ``form`` and
           ``function`` in words, :class:`~jaxsync.fem.LoadInput`),
           checksum_sha256

A surrogate without load input writes exactly the file it wrote before the load input
existed, and such files (no ``n_load``, no ``load_inputs``) load as surrogates without it.

The checksum is SHA-256 over every dataset (name, dtype, shape, bytes; sorted by name)
and every other attribute (canonical JSON), so any change to stored values is detected.
Files are written under a temporary name and moved into place with ``os.replace``: a
failed write never clobbers an existing good surrogate file.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Sequence
from typing import Any

import h5py
import jax
import numpy as np

from jaxsync.errors import CheckpointError, ConfigError
from jaxsync.fem._load_signals import LoadInput
from jaxsync.io import array_checksum, atomic_h5
from jaxsync.surrogate.models._architecture import (
    Architecture,
    architecture_from_dict,
    architecture_to_dict,
    init_params,
)
from jaxsync.surrogate.models._lstm import Params
from jaxsync.surrogate.training._data import padding_mask
from jaxsync.surrogate.training._train import TrainResult

FORMAT_NAME = "jaxsync-lstm-surrogate"
FORMAT_VERSION = 1
_CHECKSUM_ATTR = "checksum_sha256"


@dataclasses.dataclass(frozen=True)
class SavedSurrogate:
    """Everything needed to run a set of trained replicas: what a surrogate file holds.

    Attributes:
        arch: architecture (:class:`~jaxsync.surrogate.models.LSTMArchitecture` or
            :class:`~jaxsync.surrogate.models.LinearArchitecture`); ``arch.n_dof`` is the
            padded width.
        params: stacked parameters (leading part axis), numpy arrays.
        mean, std: (n_parts, n_dof) normalization, solver units (padding: 0 and 1).
        dof_counts: real dofs per part.
        n_s: sampling stride the replicas were trained with.
        shared_nodes: per part, global ids of its shared nodes (dofs node-interleaved),
            or None for histories that are not tied to a partition.
        metadata: JSON-serializable extras (training configuration, losses...).
        signal_scale: (n_parts, n_load) float64 scale of the known load signals (load
            input), or None.
        load_inputs: (n_load,) :class:`~jaxsync.fem.LoadInput`: which load
            signals the replicas read (empty without load input).
    """

    arch: Architecture
    params: Params
    mean: np.ndarray
    std: np.ndarray
    dof_counts: tuple[int, ...]
    n_s: int
    shared_nodes: tuple[np.ndarray, ...] | None = None
    metadata: dict[str, Any] = dataclasses.field(default_factory=dict)
    signal_scale: np.ndarray | None = None
    load_inputs: tuple = ()

    @property
    def n_parts(self) -> int:
        return len(self.dof_counts)

    @property
    def dof_mask(self) -> np.ndarray:
        """(n_parts, n_dof) float32, 1 on real dofs."""
        return padding_mask(self.dof_counts, self.arch.n_dof)

    @classmethod
    def from_result(
        cls,
        result: TrainResult,
        n_s: int,
        shared_nodes: Sequence[np.ndarray] | None = None,
        metadata: dict[str, Any] | None = None,
    ) -> "SavedSurrogate":
        """The saved form of the replicas returned by :func:`~jaxsync.surrogate.training.train_replicas`."""
        return cls(
            arch=result.arch, params=result.params, mean=result.mean, std=result.std,
            dof_counts=result.dof_counts, n_s=int(n_s),
            shared_nodes=None if shared_nodes is None else tuple(np.asarray(n, np.int64) for n in shared_nodes),
            metadata={"training": result.config.to_dict(), **(metadata or {})},
            signal_scale=result.signal_scale, load_inputs=tuple(result.load_inputs),
        )


def _param_paths(arch: Architecture):
    """(path string, shape, dtype) of every parameter leaf of one replica, in tree order."""
    template = jax.eval_shape(init_params, jax.random.key(0), arch)
    leaves, treedef = jax.tree_util.tree_flatten_with_path(template)
    paths = []
    for keypath, leaf in leaves:
        parts = [str(getattr(k, "key", getattr(k, "idx", k))) for k in keypath]
        paths.append(("/".join(parts), leaf.shape, leaf.dtype))
    return paths, treedef


def _checksum(datasets: dict[str, np.ndarray], attrs: dict[str, Any]) -> str:
    return array_checksum(datasets, {k: v for k, v in attrs.items() if k != _CHECKSUM_ATTR})


def _to_datasets(saved: SavedSurrogate) -> dict[str, np.ndarray]:
    paths, _ = _param_paths(saved.arch)
    leaves = jax.tree_util.tree_leaves(saved.params)
    if len(leaves) != len(paths):
        raise CheckpointError(
            f"parameters have {len(leaves)} arrays but the architecture expects {len(paths)}; "
            "save the parameters that train_replicas returned for this architecture"
        )
    datasets = {}
    for (path, shape, dtype), leaf in zip(paths, leaves):
        leaf = np.asarray(leaf)
        if leaf.shape != (saved.n_parts,) + tuple(shape) or leaf.dtype != dtype:
            raise CheckpointError(
                f"parameter {path} has shape {leaf.shape} {leaf.dtype}; expected "
                f"{(saved.n_parts,) + tuple(shape)} {dtype} for {saved.n_parts} parts"
            )
        datasets[f"params/{path}"] = leaf
    datasets["normalization/mean"] = np.asarray(saved.mean, np.float64)
    datasets["normalization/std"] = np.asarray(saved.std, np.float64)
    datasets["dof_counts"] = np.asarray(saved.dof_counts, np.int64)
    if saved.shared_nodes is not None:
        if len(saved.shared_nodes) != saved.n_parts:
            raise CheckpointError(f"{len(saved.shared_nodes)} shared-node lists for {saved.n_parts} parts")
        for p, nodes in enumerate(saved.shared_nodes):
            datasets[f"shared_nodes/{p}"] = np.asarray(nodes, np.int64)
    n_load = getattr(saved.arch, "n_load", 0)
    if n_load:
        scale = None if saved.signal_scale is None else np.asarray(saved.signal_scale, np.float64)
        if scale is None or scale.shape != (saved.n_parts, n_load) or len(saved.load_inputs) != n_load:
            raise CheckpointError(f"the replicas read {n_load} load signals but come with a signal scale of shape "
                                  f"{None if scale is None else scale.shape} and {len(saved.load_inputs)} load input "
                                  f"descriptions; expected ({saved.n_parts}, {n_load}) and {n_load}")
        datasets["load_inputs/scale"] = scale
    return datasets


def save_surrogate(path: str | os.PathLike, saved: SavedSurrogate) -> None:
    """Write ``saved`` to ``path`` atomically (:func:`jaxsync.io.atomic_h5`)."""
    path = os.fspath(path)
    datasets = _to_datasets(saved)
    if saved.mean.shape != (saved.n_parts, saved.arch.n_dof) or saved.std.shape != saved.mean.shape:
        raise CheckpointError(
            f"normalization has shapes {saved.mean.shape}, {saved.std.shape}; "
            f"expected {(saved.n_parts, saved.arch.n_dof)}"
        )
    try:
        metadata = json.dumps(saved.metadata, sort_keys=True)
    except TypeError as err:
        raise CheckpointError(f"surrogate metadata must be JSON-serializable: {err}") from err
    attrs = {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "architecture": json.dumps(architecture_to_dict(saved.arch), sort_keys=True),
        "n_s": int(saved.n_s),
        "metadata": metadata,
    }
    if getattr(saved.arch, "n_load", 0):
        attrs["load_inputs"] = json.dumps([i.to_dict() for i in saved.load_inputs], sort_keys=True)
    attrs[_CHECKSUM_ATTR] = _checksum(datasets, attrs)
    with atomic_h5(path) as fh:
        for name, array in datasets.items():
            fh.create_dataset(name, data=array)
        for name, value in attrs.items():
            fh.attrs[name] = value


def _read(path: str) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    datasets: dict[str, np.ndarray] = {}

    def visit(name, obj):
        if isinstance(obj, h5py.Dataset):
            datasets[name] = obj[()]

    if os.path.isdir(path):
        inside = os.path.join(path, "surrogate.h5")
        hint = f" such as {inside}" if os.path.isfile(inside) else ""
        raise CheckpointError(f"surrogate file {path!r} is a folder; give a .h5 file{hint}")
    try:
        with h5py.File(path, "r") as fh:
            attrs = {k: (v.item() if isinstance(v, np.generic) else v) for k, v in fh.attrs.items()}
            attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in attrs.items()}
            fh.visititems(visit)
    except FileNotFoundError as err:
        raise CheckpointError(f"surrogate file {path} does not exist; train one with `jaxsync train`") from err
    except Exception as err:  # noqa: BLE001 - h5py raises OSError, KeyError, ValueError or RuntimeError
        raise CheckpointError(
            f"surrogate file {path} cannot be read ({' '.join(str(err).split())}); the file is damaged, "
            "truncated or not HDF5: "
            "restore it or retrain with `jaxsync train`"
        ) from err
    return datasets, attrs


def load_surrogate(
    path: str | os.PathLike, shared_nodes_per_part: Sequence[np.ndarray] | None = None
) -> SavedSurrogate:
    """Read and verify a surrogate file.

    Args:
        path: file written by :func:`save_surrogate`.
        shared_nodes_per_part: if given, also run :func:`check_compatible` against it.

    Raises:
        CheckpointError: unreadable or truncated file, another format or a newer version,
            checksum mismatch, inconsistent contents, or (with ``shared_nodes_per_part``)
            a surrogate made for another partition.
    """
    path = os.fspath(path)
    datasets, attrs = _read(path)
    if attrs.get("format") != FORMAT_NAME:
        raise CheckpointError(f"{path} is not a jaxsync surrogate file (format={attrs.get('format')!r})")
    version = attrs.get("format_version")
    if version != FORMAT_VERSION:
        raise CheckpointError(
            f"{path} has surrogate file format version {version}; this jaxsync reads version {FORMAT_VERSION}: "
            "retrain with this version or use the jaxsync that wrote it"
        )
    stored = attrs.get(_CHECKSUM_ATTR)
    actual = _checksum(datasets, attrs)
    if stored != actual:
        raise CheckpointError(
            f"checksum mismatch in {path} (stored {stored}, computed {actual}): the file was modified or "
            "corrupted; restore it or retrain with `jaxsync train`"
        )
    try:
        arch = architecture_from_dict(json.loads(attrs["architecture"]))
        metadata = json.loads(attrs["metadata"])
        n_s = int(attrs["n_s"])
        dof_counts = tuple(int(c) for c in datasets["dof_counts"])
        mean, std = datasets["normalization/mean"], datasets["normalization/std"]
        signal_scale, load_inputs = None, ()
        if getattr(arch, "n_load", 0):
            signal_scale = datasets["load_inputs/scale"]
            load_inputs = tuple(LoadInput.from_dict(d) for d in json.loads(attrs["load_inputs"]))
            if signal_scale.shape != (len(dof_counts), arch.n_load) or len(load_inputs) != arch.n_load:
                raise ValueError(f"load inputs of shape {signal_scale.shape} and {len(load_inputs)} descriptions for "
                                 f"n_load={arch.n_load}")
    except ConfigError as err:
        raise CheckpointError(f"surrogate file {path} holds an architecture this jaxsync does not know ({err}); "
                              "register its model (jaxsync.surrogate.register_surrogate), use the jaxsync that "
                              "wrote it or retrain with `jaxsync train`") from err
    except (KeyError, ValueError, TypeError) as err:
        raise CheckpointError(f"surrogate file {path} is incomplete ({err!r}); retrain with `jaxsync train`") from err
    paths, treedef = _param_paths(arch)
    leaves = []
    for name, shape, dtype in paths:
        leaf = datasets.get(f"params/{name}")
        if leaf is None or leaf.shape != (len(dof_counts),) + tuple(shape) or leaf.dtype != dtype:
            raise CheckpointError(
                f"surrogate file {path}: parameter {name} is missing or has the wrong shape/dtype for its architecture"
            )
        leaves.append(leaf)
    shared = None
    if any(name.startswith("shared_nodes/") for name in datasets):
        try:
            shared = tuple(datasets[f"shared_nodes/{p}"] for p in range(len(dof_counts)))
        except KeyError as err:
            raise CheckpointError(f"surrogate file {path} lacks shared node ids of a part ({err})") from err
    saved = SavedSurrogate(
        arch=arch, params=jax.tree_util.tree_unflatten(treedef, leaves), mean=mean, std=std,
        dof_counts=dof_counts, n_s=n_s, shared_nodes=shared, metadata=metadata,
        signal_scale=signal_scale, load_inputs=load_inputs,
    )
    if shared_nodes_per_part is not None:
        check_compatible(saved, shared_nodes_per_part)
    return saved


def check_compatible(
    saved: SavedSurrogate, shared_nodes_per_part: Sequence[np.ndarray], dofs_per_node: int = 3
) -> None:
    """Check that ``saved`` was trained for this partition.

    Args:
        saved: a loaded surrogate file.
        shared_nodes_per_part: per part, the global ids of its shared nodes, in the order
            its shared dofs are laid out (node-interleaved).
        dofs_per_node: dofs per shared node (3 for the displacement field).

    Raises:
        CheckpointError: different number of parts, a part with a different shared-dof
            count, different node ids, or a surrogate file without node ids.
    """
    n_parts = len(shared_nodes_per_part)
    if saved.n_parts != n_parts:
        raise CheckpointError(
            f"the surrogate file holds {saved.n_parts} replicas but the partition has {n_parts} parts; "
            "retrain the surrogates on a trajectory of this partition"
        )
    for p, nodes in enumerate(shared_nodes_per_part):
        nodes = np.asarray(nodes, np.int64)
        if saved.dof_counts[p] != dofs_per_node * nodes.size:
            raise CheckpointError(
                f"part {p}: the saved replica predicts {saved.dof_counts[p]} shared dofs but the partition "
                f"has {dofs_per_node * nodes.size} ({nodes.size} shared nodes); retrain on this partition"
            )
    if saved.shared_nodes is None:
        raise CheckpointError(
            "the surrogate file stores no shared node ids, so it cannot be matched to a partition; "
            "train it from a trajectory file with `jaxsync train`"
        )
    for p, nodes in enumerate(shared_nodes_per_part):
        if not np.array_equal(np.asarray(nodes, np.int64), saved.shared_nodes[p]):
            raise CheckpointError(
                f"part {p}: the surrogate was trained for other shared nodes than this partition has "
                "(different partition or numbering); retrain on this partition"
            )
