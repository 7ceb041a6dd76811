"""Sample-refill data: subsampling, windows, split, normalization, refill index sets, files."""

import h5py
import numpy as np
import pytest

from jaxsync.errors import CheckpointError, ConfigError
from jaxsync.trajectory import PartHistory
from jaxsync.surrogate.data import (
    Normalization,
    build_dataset,
    make_windows,
    read_shared_histories,
    refill_index_sets,
    refill_input_steps,
    refill_scatter,
    refill_target_steps,
    refill_windows,
    split_indices,
    stack_replicas,
    subsample,
)

REFILL_CASES = [(1599, 80, 20, 20), (9, 1, 10, 10), (47, 4, 6, 3), (100, 7, 3, 5), (29, 3, 5, 9), (5, 2, 3, 1)]


@pytest.mark.parametrize("n, n_s, n_p, n_f", REFILL_CASES)
def test_refill_index_sets_follow_algorithm_3(n, n_s, n_p, n_f):
    inputs, targets = refill_index_sets(n, n_s, n_p, n_f)
    assert inputs.shape == (n_s, n_p) and targets.shape == (n_s, n_f)
    for i in range(n_s):
        # Inputs: n_p snapshots, stride n_s, first one at n - n_s (n_p - 1) + i - (n_s - 1).
        first = n - n_s * (n_p - 1) + i - (n_s - 1)
        assert list(inputs[i]) == [first + n_s * j for j in range(n_p)]
        assert list(refill_input_steps(n, n_s, n_p, i)) == list(inputs[i])
        # Targets: the first is one stride after the last input, then every n_s steps.
        assert list(targets[i]) == [inputs[i][-1] + n_s * (j + 1) for j in range(n_f)]
        assert list(refill_target_steps(n, n_s, n_f, i)) == list(targets[i])
    # Every one of the next n_s n_f steps is filled exactly once, and no earlier one.
    assert sorted(targets.ravel().tolist()) == list(range(n + 1, n + 1 + n_s * n_f))
    # Inputs are known steps: within the last n_s n_p steps.
    assert inputs.min() == n + 1 - n_s * n_p and inputs.max() == n


@pytest.mark.parametrize("n, n_s, n_p, n_f", REFILL_CASES)
def test_refill_gather_and_scatter_follow_the_index_sets(n, n_s, n_p, n_f):
    inputs, targets = refill_index_sets(n, n_s, n_p, n_f)
    steps = np.arange(n + 1 - n_s * n_p, n + 1)  # the buffer holds these steps, in order
    np.testing.assert_array_equal(refill_windows(steps, n_s, n_p), inputs)
    # Application i "predicts" its target step numbers; scattering must put them in order.
    np.testing.assert_array_equal(refill_scatter(targets, n_s), np.arange(n + 1, n + 1 + n_s * n_f))
    # Works with trailing dof axes too.
    buffer = np.stack([steps, -steps], axis=1)
    np.testing.assert_array_equal(refill_windows(buffer, n_s, n_p)[..., 1], -inputs)


def test_refill_rejects_too_short_history_and_bad_index():
    with pytest.raises(ConfigError, match="n_s \\* n_p"):
        refill_index_sets(10, 4, 3, 2)
    with pytest.raises(ConfigError, match="application index"):
        refill_input_steps(100, 4, 3, 4)


def test_subsample_and_windows():
    history = np.arange(50.0)[:, None] * np.array([1.0, -1.0])
    snaps = subsample(history, 4)
    np.testing.assert_array_equal(snaps[:, 0], np.arange(0, 50, 4))
    np.testing.assert_array_equal(subsample(history, 4, offset=1)[:, 0], np.arange(1, 50, 4))
    x, y = make_windows(snaps, 3, 2)
    assert x.shape == (13 - 5 + 1, 3, 2) and y.shape == (9, 2, 2)
    for w in range(9):
        np.testing.assert_array_equal(x[w, :, 0], snaps[w:w + 3, 0])
        np.testing.assert_array_equal(y[w, :, 0], snaps[w + 3:w + 5, 0])
    with pytest.raises(ConfigError, match="cannot make one window"):
        make_windows(snaps[:4], 3, 2)
    with pytest.raises(ConfigError, match="n_s"):
        subsample(history, 0)


def test_split_is_seeded_disjoint_and_75_25():
    train, val = split_indices(100, 0.25, seed=3)
    assert len(train) == 75 and len(val) == 25
    assert set(train) | set(val) == set(range(100)) and not set(train) & set(val)
    again = split_indices(100, 0.25, seed=3)
    np.testing.assert_array_equal(train, again[0])
    other = split_indices(100, 0.25, seed=4)
    assert not np.array_equal(val, other[1])
    with pytest.raises(ConfigError):
        split_indices(1, 0.25, 0)
    with pytest.raises(ConfigError):
        split_indices(10, 1.0, 0)


def test_normalization_fit_apply_invert_and_constant_dof():
    rng = np.random.default_rng(0)
    data = np.column_stack([rng.normal(3.0, 2.0, 500), np.full(500, 7.0), rng.normal(-1e-3, 1e-4, 500)])
    norm = Normalization.fit(data)
    z = norm.apply(data)
    np.testing.assert_allclose(z[:, [0, 2]].mean(axis=0), 0.0, atol=1e-12)
    np.testing.assert_allclose(z[:, [0, 2]].std(axis=0), 1.0, atol=1e-12)
    assert norm.std[1] == 1.0 and np.all(z[:, 1] == 0.0)  # fixed dof: no 0/0
    np.testing.assert_allclose(norm.invert(z), data, rtol=1e-14, atol=1e-14)


def _wave(n_steps, n_dof, phase=0.0):
    t = np.arange(n_steps)[:, None]
    return np.sin(0.05 * t * (1 + np.arange(n_dof)) + phase) + 0.1 * np.arange(n_dof)


def test_build_dataset_uses_leading_fraction_and_fits_normalization_on_training_windows():
    history = _wave(400, 3)
    history[200:] += 100.0  # anything beyond n_ts = 0.5 must never reach the dataset
    ds = build_dataset([history], n_s=2, n_past=4, n_future=3, train_fraction=0.5, split_seed=1)
    snaps = history[:200:2]
    x, y = make_windows(snaps, 4, 3)
    n_w = x.shape[0]
    assert ds.x_train.shape[0] + ds.x_val.shape[0] == n_w
    assert ds.x_val.shape[0] == round(0.25 * n_w)
    assert ds.x_train.dtype == np.float32 and ds.y_val.dtype == np.float32
    train, val = split_indices(n_w, 0.25, 1)
    expected = Normalization.fit(np.concatenate([x[train], y[train]], axis=1))
    np.testing.assert_allclose(ds.normalization.mean, expected.mean)
    np.testing.assert_allclose(ds.normalization.std, expected.std)
    np.testing.assert_allclose(ds.x_val, expected.apply(x[val]), atol=1e-6)
    np.testing.assert_allclose(ds.y_train, expected.apply(y[train]), atol=1e-6)
    assert np.max(np.abs(ds.normalization.invert(ds.x_train.astype(np.float64)))) < 2.0


def test_several_runs_pool_their_windows_with_load_parameters():
    runs = [_wave(300, 2), _wave(300, 2, phase=1.0), _wave(200, 2, phase=2.0)]
    ds = build_dataset(runs, n_s=3, n_past=5, n_future=4, train_fraction=1.0, split_seed=0,
                       load_parameters=[0.3, 0.5, 0.7])
    per_run = [make_windows(subsample(r, 3), 5, 4)[0].shape[0] for r in runs]
    total = ds.x_train.shape[0] + ds.x_val.shape[0]
    assert total == sum(per_run)
    conds = np.concatenate([ds.cond_train, ds.cond_val])
    for value, count in zip([0.3, 0.5, 0.7], per_run):
        assert np.sum(np.isclose(conds, value)) == count
    with pytest.raises(ConfigError, match="load parameters"):
        build_dataset(runs, 3, 5, 4, load_parameters=[0.3])
    with pytest.raises(ConfigError, match="run 1"):
        build_dataset([runs[0], _wave(300, 3)], 3, 5, 4)
    bad = runs[0].copy()
    bad[3, 1] = np.nan
    with pytest.raises(ConfigError, match="NaN"):
        build_dataset([bad], 3, 5, 4)


def test_stack_replicas_pads_and_masks():
    a = build_dataset([_wave(300, 2)], 2, 4, 3, split_seed=5)
    b = build_dataset([_wave(300, 5, 0.3)], 2, 4, 3, split_seed=5)
    data = stack_replicas([a, b])
    assert data.dof_counts == (2, 5) and data.n_dof_max == 5 and data.n_parts == 2
    np.testing.assert_array_equal(data.dof_mask, [[1, 1, 0, 0, 0], [1, 1, 1, 1, 1]])
    np.testing.assert_array_equal(data.x_train[0, :, :, :2], a.x_train)
    assert np.all(data.x_train[0, :, :, 2:] == 0) and np.all(data.y_val[0, :, :, 2:] == 0)
    np.testing.assert_array_equal(data.x_val[1], b.x_val)
    np.testing.assert_array_equal(data.std[0], [*a.normalization.std, 1, 1, 1])
    short = build_dataset([_wave(200, 2)], 2, 4, 3)
    with pytest.raises(ConfigError, match="window counts"):
        stack_replicas([a, short])


def _write_trajectory(path, save_every=1, n_steps=40, counts=(2, 3)):
    with h5py.File(path, "w") as fh:
        fh.attrs.update(format="jaxsync-trajectory", format_version=1, n_parts=len(counts), dt=1e-3,
                        save_every=save_every)
        fh["times"] = np.arange(n_steps) * 1e-3 * save_every
        for p, n in enumerate(counts):
            fh[f"parts/{p}/shared_nodes"] = np.arange(n, dtype=np.int64) + 10 * p
            fh[f"parts/{p}/shared_displacement"] = _wave(n_steps, 3 * n, phase=p)


def test_read_shared_histories(tmp_path):
    path = tmp_path / "traj.h5"
    _write_trajectory(path)
    hist = read_shared_histories(path)
    assert [h.shape for h in hist.histories] == [(40, 6), (40, 9)]
    np.testing.assert_array_equal(hist.shared_nodes[1], [10, 11, 12])
    assert hist.dt == 1e-3 and hist.load_parameter is None


def test_read_shared_histories_errors(tmp_path):
    path = tmp_path / "every2.h5"
    _write_trajectory(path, save_every=2)
    with pytest.raises(CheckpointError, match="shared_every=1"):
        read_shared_histories(path)
    with pytest.raises(CheckpointError, match="does not exist"):
        read_shared_histories(tmp_path / "missing.h5")
    broken = tmp_path / "broken.h5"
    _write_trajectory(broken)
    with h5py.File(broken, "r+") as fh:
        del fh["parts/1/shared_nodes"]
    with pytest.raises(CheckpointError, match="part 1"):
        read_shared_histories(broken)
    mismatch = tmp_path / "mismatch.h5"
    _write_trajectory(mismatch)
    with h5py.File(mismatch, "r+") as fh:
        del fh["parts/0/shared_displacement"]
        fh["parts/0/shared_displacement"] = np.zeros((40, 5))
    with pytest.raises(CheckpointError, match="expected \\(n_saved, 6\\)"):
        read_shared_histories(mismatch)
    noattr = tmp_path / "noattr.h5"
    _write_trajectory(noattr)
    with h5py.File(noattr, "r+") as fh:
        del fh.attrs["save_every"]
    with pytest.raises(CheckpointError, match="save_every"):
        read_shared_histories(noattr)


def _saved_trajectory(path, synchronized=None, load=None):
    """A small distributed run written by Trajectory.save (the real file format)."""
    import dataclasses

    import jaxsync

    mesh = jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1))
    parts = jaxsync.partition(mesh, 2)
    n = 30
    disp = _wave(n, 3 * mesh.n_nodes).reshape(n, mesh.n_nodes, 3)
    traj = jaxsync.Trajectory(times=np.arange(n) * 1e-3, displacement=disp, mesh=mesh, dt=1e-3,
                              parameters={} if load is None else {"load_parameter": load},
                              parts=tuple(PartHistory(p.shared_nodes, p.elements,
                                                      disp[:, p.shared_nodes].reshape(n, -1))
                                          for p in parts.parts))
    if synchronized is not None:
        traj = dataclasses.replace(traj, synchronized=synchronized)
    traj.save(path)
    return traj, parts


def test_read_shared_histories_of_a_saved_trajectory(tmp_path):
    traj, parts = _saved_trajectory(tmp_path / "run.h5", load=0.4)
    hist = read_shared_histories(tmp_path / "run.h5")
    assert hist.load_parameter == 0.4 and hist.synchronized is None and hist.n_predicted == 0
    for p, part in enumerate(parts.parts):
        np.testing.assert_array_equal(hist.shared_nodes[p], part.shared_nodes)
        np.testing.assert_array_equal(hist.histories[p],
                                      traj.displacement[:, part.shared_nodes].reshape(30, -1))


def test_read_shared_histories_refuses_predicted_runs_unless_allowed(tmp_path):
    flags = np.arange(30) < 12
    _saved_trajectory(tmp_path / "online.h5", synchronized=flags)
    with pytest.raises(CheckpointError, match="synchronization-avoiding run: 18 of its 30 snapshots"):
        read_shared_histories(tmp_path / "online.h5")
    hist = read_shared_histories(tmp_path / "online.h5", allow_predicted=True)
    assert hist.n_predicted == 18 and hist.synchronized.dtype == bool
    _saved_trajectory(tmp_path / "synced.h5", synchronized=np.ones(30, bool))
    assert read_shared_histories(tmp_path / "synced.h5").n_predicted == 0


def test_read_shared_histories_checks_the_format_like_trajectory_load(tmp_path):
    import jaxsync

    foreign = tmp_path / "foreign.h5"
    _write_trajectory(foreign)
    with h5py.File(foreign, "r+") as fh:
        del fh.attrs["format"]
    newer = tmp_path / "newer.h5"
    _write_trajectory(newer)
    with h5py.File(newer, "r+") as fh:
        fh.attrs["format_version"] = 99
    for path, message in ((foreign, "not a jaxsync trajectory"), (newer, "format version 99.*upgrade")):
        with pytest.raises(CheckpointError, match=message):
            read_shared_histories(path)
        with pytest.raises(CheckpointError):  # the same files Trajectory.load refuses
            jaxsync.Trajectory.load(path)
    single = tmp_path / "single.h5"
    _write_trajectory(single)
    with h5py.File(single, "r+") as fh:
        del fh.attrs["n_parts"]
    with pytest.raises(CheckpointError, match="not a distributed run"):
        read_shared_histories(single)
    short = tmp_path / "short.h5"
    _write_trajectory(short)
    with h5py.File(short, "r+") as fh:
        fh["synchronized"] = np.ones(7, bool)
    with pytest.raises(CheckpointError, match="7 flags for 40 saved steps"):
        read_shared_histories(short)


def test_shared_history_every_step_with_a_thinned_full_field(tmp_path):
    """simulate(save_every=50, shared_every=1): the full field every 50 steps, each part's
    shared nodes every step (the training data), equal to a run saved at every step."""
    import jaxsync

    problem = jaxsync.cantilever()
    parts = jaxsync.partition(problem.mesh, 2)
    every = jaxsync.simulate(problem, 300, partitions=parts)
    thin = jaxsync.simulate(problem, 300, partitions=parts, save_every=50, shared_every=1)
    assert thin.n_saved == 7 and thin.shared_stride == 1
    np.testing.assert_array_equal(thin.displacement, every.displacement[::50])
    for a, b in zip(thin.parts, every.parts):
        np.testing.assert_array_equal(a.shared_displacement, b.shared_displacement)
    thin.save(tmp_path / "thin.h5")
    runs = read_shared_histories(tmp_path / "thin.h5")
    for got, part in zip(runs.histories, every.parts):
        np.testing.assert_array_equal(got, part.shared_displacement)
    # a thinned shared history is refused for training, with the fix named
    jaxsync.simulate(problem, 300, partitions=parts, save_every=50).save(tmp_path / "coarse.h5")
    with pytest.raises(CheckpointError, match="shared_every=1"):
        read_shared_histories(tmp_path / "coarse.h5")
    with pytest.raises(jaxsync.ProblemError, match="divisor"):
        jaxsync.simulate(problem, 300, partitions=parts, save_every=50, shared_every=3)
