"""Surrogate files: bit-exact round trip, and a clear error for every bad file."""

import os

import h5py
import jax
import numpy as np
import pytest

from jaxsync.errors import CheckpointError
from jaxsync.io.surrogate_file import (
    FORMAT_VERSION,
    SavedSurrogate,
    check_compatible,
    load_surrogate,
    save_surrogate,
)
from jaxsync.surrogate.models import LSTMArchitecture, init_replicas

NODES = (np.array([4, 9, 17], np.int64), np.array([2, 4, 9, 30], np.int64))


def _checkpoint(q=2):
    arch = LSTMArchitecture(n_dof=12, n_hidden=5, n_layers=2, n_past=4, n_future=3, n_cond_repeat=q)
    params = jax.tree_util.tree_map(np.asarray, init_replicas(jax.random.key(0), arch, (9, 12)))
    rng = np.random.default_rng(1)
    mean = rng.normal(size=(2, 12))
    std = rng.uniform(0.5, 2.0, size=(2, 12))
    mean[0, 9:], std[0, 9:] = 0.0, 1.0
    return SavedSurrogate(arch=arch, params=params, mean=mean, std=std, dof_counts=(9, 12), n_s=80,
                          shared_nodes=NODES, metadata={"training": {"eta0": 5e-4}, "note": "test"})


@pytest.fixture
def saved(tmp_path):
    ckpt = _checkpoint()
    path = tmp_path / "surrogate.h5"
    save_surrogate(path, ckpt)
    return ckpt, path


def test_round_trip_is_bit_exact(saved):
    ckpt, path = saved
    loaded = load_surrogate(path, shared_nodes_per_part=NODES)
    assert loaded.arch == ckpt.arch and loaded.n_s == 80 and loaded.dof_counts == (9, 12)
    assert loaded.metadata == ckpt.metadata
    a_leaves, a_tree = jax.tree_util.tree_flatten(ckpt.params)
    b_leaves, b_tree = jax.tree_util.tree_flatten(loaded.params)
    assert a_tree == b_tree
    for a, b in zip(a_leaves, b_leaves):
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    for a, b in [(ckpt.mean, loaded.mean), (ckpt.std, loaded.std)] + list(zip(NODES, loaded.shared_nodes)):
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes()
    np.testing.assert_array_equal(loaded.dof_mask[0], [1] * 9 + [0] * 3)
    # Saving what was loaded reproduces the same file contents.
    again = path.with_name("again.h5")
    save_surrogate(again, loaded)
    with h5py.File(path) as f, h5py.File(again) as g:
        assert f.attrs["checksum_sha256"] == g.attrs["checksum_sha256"]


def test_checkpoint_for_another_partition_or_dof_count_is_rejected(saved):
    _, path = saved
    ckpt = load_surrogate(path)
    check_compatible(ckpt, NODES)  # the right partition passes
    with pytest.raises(CheckpointError, match="2 replicas but the partition has 3 parts"):
        check_compatible(ckpt, NODES + (np.array([1]),))
    with pytest.raises(CheckpointError, match="part 1: the saved replica predicts 12 shared dofs .* has 9"):
        check_compatible(ckpt, (NODES[0], NODES[1][:3]))
    with pytest.raises(CheckpointError, match="part 0: .*other shared nodes"):
        check_compatible(ckpt, (np.array([4, 9, 18]), NODES[1]))
    with pytest.raises(CheckpointError, match="other shared nodes"):
        load_surrogate(path, shared_nodes_per_part=(NODES[0], NODES[1][::-1]))
    no_nodes = SavedSurrogate(**{**ckpt.__dict__, "shared_nodes": None})
    with pytest.raises(CheckpointError, match="no shared node ids"):
        check_compatible(no_nodes, NODES)


def test_truncated_file_is_rejected(saved):
    _, path = saved
    data = path.read_bytes()
    for keep in (len(data) // 2, len(data) - 100, 64):
        cut = path.with_name(f"cut{keep}.h5")
        cut.write_bytes(data[:keep])
        with pytest.raises(CheckpointError, match="truncated or not HDF5"):
            load_surrogate(cut)


def test_a_file_with_random_bytes_in_its_middle_is_rejected(saved):
    original, path = saved
    data = bytearray(path.read_bytes())
    rng = np.random.default_rng(0)
    refused = 0
    for start in range(0, len(data) - 512, max(512, len(data) // 16)):  # the header, metadata, datasets
        broken = data.copy()
        broken[start:start + 512] = rng.integers(0, 256, 512, dtype=np.uint8).tobytes()
        damaged = path.with_name(f"damaged{start}.h5")
        damaged.write_bytes(bytes(broken))
        try:
            loaded = load_surrogate(damaged)
        except CheckpointError as exc:  # never h5py's RuntimeError or OSError
            assert any(w in str(exc) for w in ("damaged", "checksum", "not a jaxsync surrogate", "format")), exc
            refused += 1
            continue
        # bytes HDF5 does not use (free space): the content is intact, to the bit
        for a, b in zip(jax.tree_util.tree_leaves(loaded.params), jax.tree_util.tree_leaves(original.params)):
            np.testing.assert_array_equal(a, b)
    assert refused >= 8


def test_wrong_checksum_is_rejected(saved, tmp_path):
    _, path = saved
    flipped = tmp_path / "flipped.h5"
    flipped.write_bytes(path.read_bytes())
    with h5py.File(flipped, "r+") as fh:
        w = fh["params/dense/w"]
        value = w[()]
        value[1, 0, 0] = np.nextafter(value[1, 0, 0], np.float32(1.0))  # one ulp
        w[...] = value
    with pytest.raises(CheckpointError, match="checksum mismatch"):
        load_surrogate(flipped)
    retagged = tmp_path / "retagged.h5"
    retagged.write_bytes(path.read_bytes())
    with h5py.File(retagged, "r+") as fh:
        fh.attrs["n_s"] = 40
    with pytest.raises(CheckpointError, match="checksum mismatch"):
        load_surrogate(retagged)
    nodes = tmp_path / "nodes.h5"
    nodes.write_bytes(path.read_bytes())
    with h5py.File(nodes, "r+") as fh:
        fh["shared_nodes/0"][0] = 5
    with pytest.raises(CheckpointError, match="checksum mismatch"):
        load_surrogate(nodes)


def test_other_files_are_rejected(saved, tmp_path):
    _, path = saved
    with pytest.raises(CheckpointError, match="does not exist"):
        load_surrogate(tmp_path / "missing.h5")
    text = tmp_path / "text.h5"
    text.write_text("not hdf5")
    with pytest.raises(CheckpointError, match="truncated or not HDF5"):
        load_surrogate(text)
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as fh:
        fh["times"] = np.arange(3.0)
    with pytest.raises(CheckpointError, match="not a jaxsync surrogate file"):
        load_surrogate(other)
    newer = tmp_path / "newer.h5"
    newer.write_bytes(path.read_bytes())
    with h5py.File(newer, "r+") as fh:
        fh.attrs["format_version"] = FORMAT_VERSION + 1
    with pytest.raises(CheckpointError, match=f"version {FORMAT_VERSION + 1}"):
        load_surrogate(newer)


def test_failed_write_keeps_the_previous_file(saved, monkeypatch):
    ckpt, path = saved
    before = path.read_bytes()

    def boom(self, name, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(h5py.Group, "create_dataset", boom)
    with pytest.raises(OSError, match="disk full"):
        save_surrogate(path, _checkpoint(q=0))
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert sorted(os.listdir(path.parent)) == ["surrogate.h5"]  # no temporary left behind
    load_surrogate(path, NODES)


def test_inconsistent_checkpoint_is_not_written(tmp_path):
    ckpt = _checkpoint()
    bad = SavedSurrogate(**{**ckpt.__dict__, "dof_counts": (9, 12, 3)})
    with pytest.raises(CheckpointError, match="expected"):
        save_surrogate(tmp_path / "bad.h5", bad)
    unserializable = SavedSurrogate(**{**ckpt.__dict__, "metadata": {"x": object()}})
    with pytest.raises(CheckpointError, match="JSON"):
        save_surrogate(tmp_path / "bad.h5", unserializable)
    assert not (tmp_path / "bad.h5").exists()
