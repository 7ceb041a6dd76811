"""train_surrogates: trajectories in, a trained Surrogate, its checkpoint and files out."""

import json

import jax
import numpy as np
import pytest

import jaxsync
from jaxsync.errors import CheckpointError, ConfigError
from jaxsync.surrogate import Surrogate, TrainConfig, TrainedSurrogates, load_checkpoint, train_surrogates
from jaxsync.surrogate.data import build_dataset, stack_replicas
from jaxsync.surrogate.evaluate import e_mse
from jaxsync.surrogate.train import train_replicas
from jaxsync.trajectory import PartHistory, Trajectory

NODES = (np.array([3, 8], np.int64), np.array([3, 8, 11], np.int64))


def oscillator_trajectory(n_steps=600, dt=0.05, save_every=1, load=None, nodes=NODES, synchronized=None):
    """A distributed trajectory (the real type and file format) whose parts' shared dofs are
    damped oscillators, one frequency per dof; the full field is not used by training."""
    t = np.arange(n_steps) * dt
    parts = []
    for p, ids in enumerate(nodes):
        freqs = 0.6 + 0.1 * np.arange(3 * ids.size) + 0.05 * p
        w = 2 * np.pi * freqs[None, :]
        disp = (1.0 if load is None else load) * np.exp(-0.02 * w * t[:, None]) * np.cos(w * t[:, None])
        parts.append(PartHistory(shared_nodes=np.asarray(ids, np.int64), elements=np.arange(2),
                                 shared_displacement=disp))
    mesh = jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1))
    return Trajectory(times=t * save_every, displacement=np.zeros((n_steps, mesh.n_nodes, 3)), mesh=mesh, dt=dt,
                      save_every=save_every, parameters={} if load is None else {"load_parameter": load},
                      parts=tuple(parts), synchronized=synchronized)


def write_trajectory(path, **kwargs):
    """:func:`oscillator_trajectory` saved to ``path`` with ``Trajectory.save``."""
    oscillator_trajectory(**kwargs).save(path)
    return path


SMALL = dict(n_s=2, n_past=6, n_future=5, n_hidden=6, n_layers=1,
             config=TrainConfig(batch_size=8, eta0=1e-2, gamma=0.95, n_epochs=12, epochs_per_call=6),
             progress=False)


def test_in_memory_training_equals_the_library_steps_and_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    traj = oscillator_trajectory(n_steps=300)
    trained = train_surrogates(traj, emse_applications=5, **SMALL)
    assert isinstance(trained, TrainedSurrogates) and trained.files == {} and not list(tmp_path.iterdir())
    assert trained.trajectories == (None,) and trained.load_parameters is None
    # the same as the steps it is made of: windows, train_replicas, E_mse
    data = stack_replicas([build_dataset([p.shared_displacement], 2, 6, 5, 0.5, 0.25, 0) for p in traj.parts])
    assert (trained.n_train_windows, trained.n_val_windows) == data.x_train.shape[1:2] + data.x_val.shape[1:2]
    result = train_replicas(data, trained.result.arch, SMALL["config"], jax.random.key(0), progress=False)
    for a, b in zip(jax.tree_util.tree_leaves(result.params), jax.tree_util.tree_leaves(trained.result.params)):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(result.val_loss, trained.result.val_loss)
    surrogate = trained.surrogate
    assert isinstance(surrogate, Surrogate) and surrogate.n_s == 2 and surrogate.dof_counts == (6, 9)
    histories = np.stack([np.pad(p.shared_displacement, ((0, 0), (0, 9 - p.shared_displacement.shape[1])))
                          for p in traj.parts])
    np.testing.assert_array_equal(trained.sqrt_e_mse, np.sqrt(e_mse(surrogate, histories, 5)))
    assert trained.e_mse_applications == 5
    # the checkpoint holds the partition and the metadata of the summary
    ckpt = trained.checkpoint
    assert [n.tolist() for n in ckpt.shared_nodes] == [n.tolist() for n in NODES]
    summary = trained.summary()
    assert ckpt.metadata["final_val_loss"] == summary["final_val_loss"] == trained.final_val_loss.tolist()
    assert ckpt.metadata["sampling"]["n_s"] == 2 and summary["training"]["n_epochs_run"] == 12
    json.dumps(summary)  # serializable


def test_files_written_into_out_and_several_runs_with_load_parameters(tmp_path):
    paths = [write_trajectory(tmp_path / f"run{k}.h5", load=load, n_steps=300) for k, load in enumerate((1.0, 0.6))]
    out = tmp_path / "out"
    trained = train_surrogates(paths, n_cond_repeat=2, emse_applications=0, out=out, checkpoint_every=6, **SMALL)
    assert trained.load_parameters == (1.0, 0.6) and trained.sqrt_e_mse is None
    assert trained.surrogate.arch.conditional and float(trained.surrogate.load_parameter[0]) == 1.0
    assert sorted(p.name for p in out.iterdir()) == ["loss_curves.png", "surrogate.h5", "train_summary.json"]
    assert trained.files["checkpoint"] == str((out / "surrogate.h5").resolve())
    saved = json.loads((out / "train_summary.json").read_text())
    assert saved == json.loads(json.dumps(trained.summary()))
    assert saved["trajectories"] == [str(p.resolve()) for p in paths] and saved["load_parameters"] == [1.0, 0.6]
    loaded = Surrogate.load(out / "surrogate.h5", load_parameter=1.0)
    for a, b in zip(jax.tree_util.tree_leaves(loaded), jax.tree_util.tree_leaves(trained.surrogate)):
        np.testing.assert_array_equal(a, b)
    assert load_checkpoint(out / "surrogate.h5").metadata == trained.checkpoint.metadata
    with pytest.raises(CheckpointError, match="conditional"):
        Surrogate.load(out / "surrogate.h5")


def test_unusable_trajectories_and_settings_are_refused(tmp_path):
    with pytest.raises(CheckpointError, match="every 5 steps, which does not divide the sampling stride n_s=2"):
        train_surrogates(oscillator_trajectory(n_steps=300, save_every=5), **SMALL)
    with pytest.raises(ConfigError, match="load parameter"):
        train_surrogates(oscillator_trajectory(n_steps=300), n_cond_repeat=2, **SMALL)
    with pytest.raises(ConfigError, match="2 values for 1 trajectories"):
        train_surrogates(oscillator_trajectory(n_steps=300), n_cond_repeat=2, load_parameters=[1, 2], **SMALL)
    other = oscillator_trajectory(n_steps=300, nodes=(np.array([3, 8]), np.array([3, 9, 11])))
    with pytest.raises(CheckpointError, match="trajectory 1 belongs to another partition than trajectory 0"):
        train_surrogates([oscillator_trajectory(n_steps=300), other], **SMALL)
    with pytest.raises(ConfigError, match="at least one trajectory"):
        train_surrogates([], **SMALL)


def test_shared_histories_thinned_to_a_divisor_of_n_s_train_the_same_replicas():
    """Training samples every n_s steps, so a run that kept its shared nodes only every
    s steps (s dividing n_s; the memory a long run needs) gives the same windows and the
    same parameters as one that kept every step; a stride that does not divide n_s is
    refused. E_mse, which reads every step, is skipped on the thinned run."""
    import dataclasses

    full = oscillator_trajectory(n_steps=600)
    thin = dataclasses.replace(
        full, shared_every=2,
        parts=tuple(dataclasses.replace(p, shared_displacement=p.shared_displacement[::2]) for p in full.parts))
    settings = dict(SMALL, n_s=4)
    a = train_surrogates(full, emse_applications=0, **settings)
    b = train_surrogates(thin, emse_applications=5, **settings)
    assert (a.n_train_windows, a.n_val_windows) == (b.n_train_windows, b.n_val_windows) and a.n_train_windows > 0
    for x, y in zip(jax.tree_util.tree_leaves(a.result.params), jax.tree_util.tree_leaves(b.result.params)):
        np.testing.assert_array_equal(x, y)
    assert b.sqrt_e_mse is None and b.e_mse_applications is None
    with pytest.raises(CheckpointError, match="every 2 steps, which does not divide the sampling stride n_s=3"):
        train_surrogates(thin, emse_applications=0, **dict(SMALL, n_s=3))
