"""Sample-refill data: refill index sets, subsampling, windows, split, normalization,
and the shared histories of trajectories."""

import dataclasses

import h5py
import numpy as np
import pytest

import jaxsync
from jaxsync.errors import CheckpointError, ConfigError
from jaxsync.io.trajectory import PartHistory, Trajectory
from jaxsync.surrogate import (
    refill_index_sets,
    refill_input_steps,
    refill_scatter,
    refill_target_steps,
    refill_windows,
)
from jaxsync.surrogate.training import (
    Normalization,
    build_dataset,
    make_windows,
    read_shared_histories,
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


@pytest.mark.parametrize("split", ["interleaved", "random"])
def test_split_is_seeded_disjoint_and_75_25(split):
    train, val = split_indices(100, 0.25, seed=3, split=split)
    assert len(train) == 75 and len(val) == 25
    assert set(train) | set(val) == set(range(100)) and not set(train) & set(val)
    again = split_indices(100, 0.25, seed=3, split=split)
    np.testing.assert_array_equal(train, again[0])
    other = split_indices(100, 0.25, seed=4, split=split)
    assert not np.array_equal(val, other[1])
    with pytest.raises(ConfigError):
        split_indices(1, 0.25, 0, split=split)
    with pytest.raises(ConfigError):
        split_indices(10, 1.0, 0, split=split)


def test_interleaved_split_holds_out_every_4th_window_from_a_seeded_phase():
    for seed in range(6):  # the default: every 4th from seed % 4, the rest trained on
        train, val = split_indices(100, 0.25, seed)
        np.testing.assert_array_equal(val, np.arange(seed % 4, 100, 4))
        np.testing.assert_array_equal(train, np.setdiff1d(np.arange(100), val))
    for n_windows, fraction in [(37, 0.25), (101, 0.25), (10, 0.3), (23, 0.5), (7, 0.9)]:
        n_val = int(round(fraction * n_windows))
        for seed in range(4):
            train, val = split_indices(n_windows, fraction, seed)
            assert len(val) == n_val and len(np.unique(val)) == n_val
            assert np.array_equal(np.sort(np.concatenate([train, val])), np.arange(n_windows))
            # evenly spread: consecutive held-out windows are floor/ceil of n/n_val apart,
            # so no stretch of the run is left out of training or of validation
            gaps = np.diff(val)
            assert gaps.min() >= np.floor(n_windows / n_val) and gaps.max() <= np.ceil(n_windows / n_val)
    # the transient at a run's start: a random split can hold out most of it, the
    # interleaved one a quarter of any 8 consecutive windows
    worst_random = max(np.isin(np.arange(8), split_indices(100, 0.25, s, "random")[1]).sum() for s in range(50))
    assert worst_random >= 4
    assert all(np.isin(np.arange(8), split_indices(100, 0.25, s)[1]).sum() == 2 for s in range(50))
    with pytest.raises(ConfigError, match="split must be one of 'interleaved', 'random', got 'odd'"):
        split_indices(100, 0.25, 0, "odd")


def test_normalization_fit_apply_invert_and_constant_dof():
    rng = np.random.default_rng(0)
    data = np.column_stack([rng.normal(3.0, 2.0, 500), np.full(500, 7.0), rng.normal(-1e-3, 1e-4, 500)])
    norm = Normalization.fit(data)
    z = norm.apply(data)
    np.testing.assert_allclose(z[:, [0, 2]].mean(axis=0), 0.0, atol=1e-12)
    np.testing.assert_allclose(z[:, [0, 2]].std(axis=0), 1.0, atol=1e-12)
    assert norm.std[1] == 0.0 and np.all(z[:, 1] == 0.0)  # fixed dof: no 0/0
    np.testing.assert_allclose(norm.invert(z), data, rtol=1e-14, atol=1e-14)
    # whatever a network says for the fixed dof, it inverts to its constant (in cm, not 1 cm
    # per normalized unit); the moving dofs scale by their own spread
    wrong = z + 0.3
    back = norm.invert(wrong)
    assert np.all(back[:, 1] == 7.0)
    np.testing.assert_allclose(back[:, 0] - data[:, 0], 0.3 * data[:, 0].std(), rtol=1e-12)
    # JAX arrays (the refill's path) normalize the same way
    import jax.numpy as jnp

    from jaxsync.surrogate.training import normalize
    np.testing.assert_allclose(np.asarray(normalize(jnp.asarray(data), jnp.asarray(norm.mean)[None],
                                                    jnp.asarray(norm.std)[None])),
                               z, rtol=1e-12, atol=1e-12)


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
    loads = np.concatenate([ds.load_parameter_train, ds.load_parameter_val])
    for value, count in zip([0.3, 0.5, 0.7], per_run):
        assert np.sum(np.isclose(loads, value)) == count
    with pytest.raises(ConfigError, match="load parameters"):
        build_dataset(runs, 3, 5, 4, load_parameters=[0.3])
    with pytest.raises(ConfigError, match="run 1"):
        build_dataset([runs[0], _wave(300, 3)], 3, 5, 4)
    bad = runs[0].copy()
    bad[3, 1] = np.nan
    with pytest.raises(ConfigError, match="NaN"):
        build_dataset([bad], 3, 5, 4)


def test_windows_across_a_load_jump_are_left_out():
    history = _wave(400, 2)
    n_s, n_p, n_f = 3, 4, 2
    all_windows = build_dataset([history], n_s, n_p, n_f, train_fraction=1.0, n_offsets=3)
    cut = build_dataset([history], n_s, n_p, n_f, train_fraction=1.0, n_offsets=3, load_jumps=[[100.0, 250.5]])
    # by hand: offset k = 0, 1, 2; window w spans rows k + 3 w .. k + 3 (w + 5); a window is left
    # out when its first row <= J < its last row for some jump J
    expected_out, kept = 0, []
    for k in range(3):
        x, _ = make_windows(subsample(history, n_s, k), n_p, n_f)
        for w in range(x.shape[0]):
            first, last = k + n_s * w, k + n_s * (w + n_p + n_f - 1)
            out = any(first <= j < last for j in (100.0, 250.5))
            expected_out += out
            if not out:
                kept.append(x[w])
    total = all_windows.x_train.shape[0] + all_windows.x_val.shape[0]
    assert cut.n_excluded == expected_out > 0 and all_windows.n_excluded == 0
    assert cut.x_train.shape[0] + cut.x_val.shape[0] == total - expected_out
    # the kept windows, in order, split as any other set of windows
    kept = np.array(kept)
    train, val = split_indices(len(kept), 0.25, 0, "interleaved")
    np.testing.assert_allclose(cut.normalization.invert(cut.x_train.astype(np.float64)), kept[train], atol=1e-5)
    np.testing.assert_allclose(cut.normalization.invert(cut.x_val.astype(np.float64)), kept[val], atol=1e-5)
    with pytest.raises(ConfigError, match="every one of the .* windows straddles a load jump"):
        build_dataset([history[:40]], 3, 4, 2, train_fraction=1.0, load_jumps=[[1.0, 10.0, 20.0, 30.0]])
    with pytest.raises(ConfigError, match="one list per run"):
        build_dataset([history], 3, 4, 2, load_jumps=[[1.0], [2.0]])


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


def _trajectory(n=30, synchronized=None, load=None, save_every=1, distributed=True):
    """A small run of a 2-part box beam, the real type (saved with Trajectory.save)."""
    mesh = jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1))
    parts = jaxsync.partition(mesh, 2)
    disp = _wave(n, 3 * mesh.n_nodes).reshape(n, mesh.n_nodes, 3)
    histories = tuple(PartHistory(p.shared_nodes, p.elements, disp[:, p.shared_nodes].reshape(n, -1))
                      for p in parts.parts)
    traj = Trajectory(times=np.arange(n) * 1e-3 * save_every, displacement=disp, mesh=mesh, dt=1e-3,
                      save_every=save_every, parameters={} if load is None else {"load_parameter": load},
                      parts=histories if distributed else (), synchronized=synchronized)
    return traj, parts


def _saved_trajectory(path, **kwargs):
    traj, parts = _trajectory(**kwargs)
    traj.save(path)
    return traj, parts


def test_read_shared_histories_of_a_trajectory_and_of_its_file(tmp_path):
    traj, parts = _saved_trajectory(tmp_path / "run.h5", load=0.4)
    for source in (tmp_path / "run.h5", str(tmp_path / "run.h5"), traj):
        hist = read_shared_histories(source)
        assert hist.load_parameter == 0.4 and hist.synchronized is None and hist.n_predicted == 0
        assert hist.dt == 1e-3
        for p, part in enumerate(parts.parts):
            np.testing.assert_array_equal(hist.shared_nodes[p], part.shared_nodes)
            assert hist.shared_nodes[p].dtype == np.int64 and hist.histories[p].dtype == np.float64
            np.testing.assert_array_equal(hist.histories[p],
                                          traj.displacement[:, part.shared_nodes].reshape(30, -1))
    assert read_shared_histories(_trajectory()[0]).load_parameter is None


def test_read_shared_histories_refuses_predicted_runs_unless_allowed(tmp_path):
    flags = np.arange(30) < 12
    _saved_trajectory(tmp_path / "online.h5", synchronized=flags)
    with pytest.raises(CheckpointError, match="synchronization-avoiding run: 18 of its 30 snapshots"):
        read_shared_histories(tmp_path / "online.h5")
    hist = read_shared_histories(tmp_path / "online.h5", allow_predicted=True)
    assert hist.n_predicted == 18 and hist.synchronized.dtype == bool
    _saved_trajectory(tmp_path / "synced.h5", synchronized=np.ones(30, bool))
    assert read_shared_histories(tmp_path / "synced.h5").n_predicted == 0


def test_read_shared_histories_errors(tmp_path):
    with pytest.raises(CheckpointError, match="not a distributed run"):
        read_shared_histories(_trajectory(distributed=False)[0])
    with pytest.raises(CheckpointError, match="7 flags for 30 saved steps"):
        read_shared_histories(_trajectory(synchronized=np.ones(7, bool))[0])
    traj, _ = _trajectory()
    bad = dataclasses.replace(traj.parts[1], shared_displacement=traj.parts[1].shared_displacement[:, :-1])
    with pytest.raises(CheckpointError, match=f"part 1 has shared_displacement .* expected \\(n_saved, "
                                              f"{3 * traj.parts[1].n_shared}\\)"):
        read_shared_histories(dataclasses.replace(traj, parts=(traj.parts[0], bad)))
    short = dataclasses.replace(traj.parts[1], shared_displacement=traj.parts[1].shared_displacement[:-1])
    with pytest.raises(CheckpointError, match="different numbers of steps"):
        read_shared_histories(dataclasses.replace(traj, parts=(traj.parts[0], short)))


def test_read_shared_histories_reads_through_trajectory_load(tmp_path):
    """The one reader: every file Trajectory.load refuses is refused, with its message."""
    with pytest.raises(CheckpointError, match="does not exist"):
        read_shared_histories(tmp_path / "missing.h5")
    damaged = {
        "foreign": (lambda fh: fh.attrs.__delitem__("format"), "not a jaxsync trajectory"),
        "newer": (lambda fh: fh.attrs.__setitem__("format_version", 99), "format version 99.*upgrade"),
        "broken": (lambda fh: fh.__delitem__("parts/1/shared_nodes"), "cannot read trajectory"),
    }
    for name, (damage, message) in damaged.items():
        path = tmp_path / f"{name}.h5"
        _saved_trajectory(path)
        with h5py.File(path, "r+") as fh:
            damage(fh)
        with pytest.raises(CheckpointError, match=message):
            read_shared_histories(path)
        with pytest.raises(CheckpointError, match=message):
            Trajectory.load(path)


def test_shared_history_every_step_with_a_thinned_full_field(tmp_path):
    """simulate(save_every=50, shared_every=1): the full field every 50 steps, each part's
    shared nodes every step (the training data), equal to a run saved at every step."""
    import jaxsync

    problem = jaxsync.cantilever()
    parts = jaxsync.partition(problem.mesh, 2)
    every = jaxsync.simulate(problem, 300, partitions=parts)
    thin = jaxsync.simulate(problem, 300, partitions=parts, save=jaxsync.SaveAt(50, 1))
    assert thin.n_saved == 7 and thin.shared_stride == 1
    np.testing.assert_array_equal(thin.displacement, every.displacement[::50])
    for a, b in zip(thin.parts, every.parts):
        np.testing.assert_array_equal(a.shared_displacement, b.shared_displacement)
    thin.save(tmp_path / "thin.h5")
    runs = read_shared_histories(tmp_path / "thin.h5")
    for got, part in zip(runs.histories, every.parts):
        np.testing.assert_array_equal(got, part.shared_displacement)
    # a thinned shared history is read with its stride: the rows of every 50th step
    jaxsync.simulate(problem, 300, partitions=parts, save=50).save(tmp_path / "coarse.h5")
    coarse = read_shared_histories(tmp_path / "coarse.h5")
    assert coarse.stride == 50 and coarse.for_sampling(100) == 2
    for got, part in zip(coarse.histories, every.parts):
        np.testing.assert_array_equal(got, part.shared_displacement[::50])
    # a stride that does not divide n_s is refused, with the fix named
    with pytest.raises(CheckpointError, match="does not divide the sampling stride n_s=80.*shared_every"):
        coarse.for_sampling(80)
    with pytest.raises(jaxsync.ProblemError, match="divisor"):
        jaxsync.simulate(problem, 300, partitions=parts, save=jaxsync.SaveAt(50, 3))


def test_a_one_part_run_is_refused_for_training_with_the_fix(tmp_path, capsys):
    """``jaxsync simulate --parts 1 --shared-every 1`` then ``jaxsync train``: a clear error
    (no shared nodes, nothing to predict: use 2 parts or more), not a numpy reshape error."""
    from jaxsync.cli import main
    from jaxsync.surrogate.training import train_surrogates

    problem = jaxsync.cantilever()
    run = jaxsync.simulate(problem, 100, partitions=jaxsync.partition(problem.mesh, 1), save=jaxsync.SaveAt(50, 1))
    run.save(tmp_path / "s1.h5")
    with pytest.raises(CheckpointError, match="1 part and so no shared nodes.*--parts n, n >= 2"):
        read_shared_histories(tmp_path / "s1.h5")
    with pytest.raises(CheckpointError, match="nothing for a surrogate to predict"):
        train_surrogates(run, architecture=jaxsync.surrogate.ArchitectureChoice(model="linear"),
                         sampling=jaxsync.surrogate.Sampling(n_s=10, n_past=5, n_future=5))
    capsys.readouterr()
    code = main(["train", str(tmp_path / "s1.h5"), "-o", str(tmp_path / "sur"), "--model", "linear", "--n-s", "10",
                 "--n-past", "5", "--n-future", "5", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and err.startswith("error: ") and "--parts" in err, err
    assert not (tmp_path / "sur").exists()
