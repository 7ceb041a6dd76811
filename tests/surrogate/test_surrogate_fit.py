"""train_surrogates: trajectories in, a trained Surrogate, its checkpoint and files out."""

import dataclasses
import json

import jax
import numpy as np
import pytest

import jaxsync
from jaxsync.errors import CheckpointError, ConfigError
from jaxsync.io.trajectory import Trajectory
from jaxsync.surrogate import (
    ArchitectureChoice,
    Sampling,
    Surrogate,
    TrainConfig,
    TrainedSurrogates,
    TrainingChecks,
    TrainingState,
    load_surrogate,
    train_surrogates,
)
from jaxsync.surrogate.models import FitSettings
from jaxsync.surrogate.training import build_dataset, e_mse, stack_replicas
from oscillator_trajectories import NODES, oscillator_trajectory, write_trajectory

ARCH = ArchitectureChoice(n_hidden=6, n_layers=1)
SAMPLING = Sampling(n_s=2, n_past=6, n_future=5)
CONFIG = TrainConfig(batch_size=8, eta0=1e-2, gamma=0.95, n_epochs=12, epochs_per_call=6)
SMALL = dict(architecture=ARCH, sampling=SAMPLING, optimizer=CONFIG, progress=False)


def test_in_memory_training_equals_the_library_steps_and_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    traj = oscillator_trajectory(n_steps=300)
    trained = train_surrogates(traj, checks=TrainingChecks(emse_applications=5), **SMALL)
    assert isinstance(trained, TrainedSurrogates) and trained.files == {} and not list(tmp_path.iterdir())
    assert trained.trajectories == (None,) and trained.load_parameters is None
    # the same as the steps it is made of: windows (twice: two candidates per part by
    # default), the model's fit (train_replicas from the linear highway's least-squares
    # fit), the lower validation loss of each part's pair, E_mse
    datasets = [build_dataset([p.shared_displacement], 2, 6, 5, 0.5, 0.25, 0) for p in traj.parts]
    data = stack_replicas(datasets * 2)
    assert (trained.n_train_windows, trained.n_val_windows) == data.x_train.shape[1:2] + data.x_val.shape[1:2]
    assert trained.result.arch.highway
    both = trained.result.arch.fit(data, FitSettings(ARCH, CONFIG, jax.random.key(0)))
    losses = both.best_val_loss.reshape(2, 2)  # (candidate, part)
    chosen = np.argmin(losses, axis=0)
    assert trained.candidates == {"n_candidates": 2, "chosen": chosen.tolist(), "best_val_loss": losses.tolist()}
    keep = chosen * 2 + np.arange(2)
    for a, b in zip(jax.tree_util.tree_leaves(both.params), jax.tree_util.tree_leaves(trained.result.params)):
        np.testing.assert_array_equal(a[keep], b)
    np.testing.assert_array_equal(both.val_loss[:, keep], trained.result.val_loss)
    np.testing.assert_array_equal(trained.result.best_val_loss, losses.min(axis=0))
    surrogate = trained.surrogate
    assert isinstance(surrogate, Surrogate) and surrogate.n_s == 2 and surrogate.dof_counts == (6, 9)
    histories = np.stack([np.pad(p.shared_displacement, ((0, 0), (0, 9 - p.shared_displacement.shape[1])))
                          for p in traj.parts])
    np.testing.assert_array_equal(trained.sqrt_e_mse, np.sqrt(e_mse(surrogate, histories, 5)))
    assert trained.e_mse_applications == 5
    # the checkpoint holds the partition and the metadata of the summary
    ckpt = trained.saved
    assert [n.tolist() for n in ckpt.shared_nodes] == [n.tolist() for n in NODES]
    summary = trained.summary()
    assert ckpt.metadata["final_val_loss"] == summary["final_val_loss"] == trained.final_val_loss.tolist()
    assert ckpt.metadata["sampling"]["n_s"] == 2 and summary["training"]["n_epochs_run"] == 12
    json.dumps(summary)  # serializable


def test_files_written_into_out_and_several_runs_with_load_parameters(tmp_path):
    paths = [write_trajectory(tmp_path / f"run{k}.h5", load=load, n_steps=300) for k, load in enumerate((1.0, 0.6))]
    out = tmp_path / "out"
    trained = train_surrogates(paths, **dict(SMALL, architecture=dataclasses.replace(ARCH, n_cond_repeat=2)),
                               checks=TrainingChecks(emse_applications=0), state=TrainingState(out, every=6))
    trained = trained.write(out)
    assert trained.load_parameters == (1.0, 0.6) and trained.sqrt_e_mse is None
    assert trained.surrogate.arch.conditional and float(trained.surrogate.load_parameter[0]) == 1.0
    assert sorted(p.name for p in out.iterdir()) == ["loss_curves.png", "surrogate.h5", "train_summary.json"]
    assert trained.files["surrogate"] == str((out / "surrogate.h5").resolve())
    saved = json.loads((out / "train_summary.json").read_text())
    assert saved == json.loads(json.dumps(trained.summary()))
    assert saved["trajectories"] == [str(p.resolve()) for p in paths] and saved["load_parameters"] == [1.0, 0.6]
    loaded = Surrogate.load(out / "surrogate.h5", load_parameter=1.0)
    for a, b in zip(jax.tree_util.tree_leaves(loaded), jax.tree_util.tree_leaves(trained.surrogate)):
        np.testing.assert_array_equal(a, b)
    assert load_surrogate(out / "surrogate.h5").metadata == trained.saved.metadata
    with pytest.raises(CheckpointError, match="conditional"):
        Surrogate.load(out / "surrogate.h5")


def test_unusable_trajectories_and_settings_are_refused(tmp_path):
    conditional = dict(SMALL, architecture=dataclasses.replace(ARCH, n_cond_repeat=2))
    with pytest.raises(CheckpointError, match="every 5 steps, which does not divide the sampling stride n_s=2"):
        train_surrogates(oscillator_trajectory(n_steps=300, save_every=5), **SMALL)
    with pytest.raises(ConfigError, match="load parameter"):
        train_surrogates(oscillator_trajectory(n_steps=300), **conditional)
    with pytest.raises(ConfigError, match="2 values for 1 trajectories"):
        train_surrogates(oscillator_trajectory(n_steps=300), load_parameters=[1, 2], **conditional)
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
    settings = dict(SMALL, sampling=dataclasses.replace(SAMPLING, n_s=4))
    a = train_surrogates(full, checks=TrainingChecks(emse_applications=0), **settings)
    b = train_surrogates(thin, checks=TrainingChecks(emse_applications=5), **settings)
    assert (a.n_train_windows, a.n_val_windows) == (b.n_train_windows, b.n_val_windows) and a.n_train_windows > 0
    for x, y in zip(jax.tree_util.tree_leaves(a.result.params), jax.tree_util.tree_leaves(b.result.params)):
        np.testing.assert_array_equal(x, y)
    assert b.sqrt_e_mse is None and b.e_mse_applications is None
    with pytest.raises(CheckpointError, match="every 2 steps, which does not divide the sampling stride n_s=3"):
        train_surrogates(thin, checks=TrainingChecks(emse_applications=0),
                         **dict(SMALL, sampling=dataclasses.replace(SAMPLING, n_s=3)))


def test_one_candidate_is_the_first_of_several_and_the_choice_is_by_validation_loss():
    """Candidate 0 of each part starts from the weights a single-candidate training uses
    (replica p's key) and sees the same batches: it is that training, to float32
    round-off; the part keeps the candidate of lower validation loss. Two candidates, the
    default (the program test_in_memory_training_equals_the_library_steps_and_writes_nothing
    compiled for the same data and settings)."""
    from jaxsync.surrogate.training import choose_candidates

    traj = oscillator_trajectory(n_steps=300)
    unchecked = TrainingChecks(emse_applications=0, rollout_tolerance=None)
    one = train_surrogates(traj, checks=unchecked, **dict(SMALL, optimizer=dataclasses.replace(CONFIG, n_candidates=1)))
    several = train_surrogates(traj, checks=unchecked,
                               **dict(SMALL, optimizer=dataclasses.replace(CONFIG, n_candidates=2)))
    assert one.candidates is None and one.summary()["candidates"] is None
    losses = np.asarray(several.candidates["best_val_loss"])
    assert losses.shape == (2, 2)
    np.testing.assert_allclose(losses[0], one.result.best_val_loss, rtol=1e-4)
    assert several.candidates["chosen"] == np.argmin(losses, axis=0).tolist()
    assert np.all(several.result.best_val_loss <= losses.min(axis=0))
    assert several.summary()["candidates"] == several.saved.metadata["candidates"] == several.candidates
    # the selection itself, on a constructed result: replica c * n_parts + p
    res = one.result
    fake = dataclasses.replace(res, params=jax.tree_util.tree_map(lambda a: np.concatenate([a, a + 1.0]), res.params),
                               dof_counts=res.dof_counts * 2, mean=np.concatenate([res.mean, res.mean + 1]),
                               std=np.concatenate([res.std, res.std]), train_loss=np.tile(res.train_loss, 2),
                               val_loss=np.concatenate([res.val_loss, res.val_loss * [[0.5, 2.0]]], axis=1),
                               initial_val_loss=np.tile(res.initial_val_loss, 2),
                               best_epoch=np.tile(res.best_epoch, 2))
    picked, info = choose_candidates(fake, 2, 2)
    assert info["chosen"] == [1, 0]  # part 0's second candidate has half the loss, part 1's twice
    leaf = jax.tree_util.tree_leaves(res.params)[0]
    np.testing.assert_array_equal(jax.tree_util.tree_leaves(picked.params)[0], np.stack([leaf[0] + 1.0, leaf[1]]))
    np.testing.assert_array_equal(picked.mean, [res.mean[0] + 1, res.mean[1]])
    with pytest.raises(ConfigError, match="n_candidates must be an integer >= 1"):
        train_surrogates(traj, **dict(SMALL, optimizer=dataclasses.replace(CONFIG, n_candidates=0)))


def test_offline_check_starts_after_the_last_load_jump(tmp_path):
    """A run whose load jumps at step 100 (``parameters["last_load_jump"]``, as simulate
    writes it, and through a file): the check rolls out from step 100 + n_s n_p - 1, where
    an online run, synchronized through the jump, starts predicting; its error there
    equals the rollout_errors of that start."""
    from jaxsync.surrogate.training import rollout_errors

    traj = oscillator_trajectory(n_steps=300)
    traj = Trajectory(times=traj.times, displacement=traj.displacement, mesh=traj.mesh, dt=traj.dt, save_every=1,
                      parameters={"last_load_jump": 100}, parts=traj.parts)
    traj.save(tmp_path / "jumped.h5")
    loose = TrainingChecks(emse_applications=0, rollout_tolerance=10.0)
    trained = train_surrogates(str(tmp_path / "jumped.h5"), checks=loose, **SMALL)
    start = 100 + 2 * 6 - 1
    assert trained.rollout.start == start and trained.summary()["rollout_check"]["start"] == start
    histories = np.stack([np.pad(p.shared_displacement, ((0, 0), (0, 9 - p.shared_displacement.shape[1])))
                          for p in traj.parts])
    again = rollout_errors(trained.surrogate, histories, start=start)
    np.testing.assert_allclose(trained.rollout.max_abs_error, again.max_abs_error, rtol=1e-12)
    # no jump: from n_s n_p - 1
    plain = train_surrogates(oscillator_trajectory(n_steps=300), checks=loose, **SMALL)
    assert plain.rollout.start == 2 * 6 - 1


def test_simulate_records_the_last_load_jump(tmp_path):
    """simulate (single device, distributed), ensemble and simulate_sync_avoiding store the
    last step where a load jumps, read from the schedule here; none without a jump."""
    problem = jaxsync.cantilever(t_off=40.5 * jaxsync.cantilever().dt)
    g = np.asarray(problem.loads[0].time(np.arange(101) * problem.dt))
    jump = int(np.argmax(np.abs(np.diff(g)))) + 1
    assert jump == 41
    single = jaxsync.simulate(problem, 100, save=10)
    assert single.parameters["last_load_jump"] == jump
    runs = jaxsync.ensemble([problem, problem.replace(loads=(jaxsync.BodyForce((0, 0, -0.3), problem.loads[0].time),))],
                            100, partitions=2, labels=[0.5, 0.3], save=jaxsync.SaveAt(10, 1))
    assert [r.parameters["last_load_jump"] for r in runs] == [jump, jump]
    runs[0].save(tmp_path / "r.h5")
    from jaxsync.surrogate.training import read_shared_histories
    assert read_shared_histories(str(tmp_path / "r.h5")).last_load_jump == jump
    assert "last_load_jump" not in jaxsync.simulate(jaxsync.cantilever(), 100, save=10).parameters
    # only jumps within the run count
    assert "last_load_jump" not in jaxsync.simulate(problem, 40, save=10).parameters


def test_offline_rollout_check_measures_the_autonomous_rollout_and_warns_above_its_tolerance():
    """The rollout check against a rollout written here: one predict per refill cycle, each
    fed the predictions before it, never the truth after step n_s n_p - 1."""
    from jaxsync.surrogate.training import RolloutWarning

    traj = oscillator_trajectory(n_steps=300)
    with pytest.warns(RolloutWarning, match="offline check"):  # 12 epochs of a tiny network: far off
        trained = train_surrogates(traj, checks=TrainingChecks(emse_applications=0, rollout_tolerance=1e-3), **SMALL)
    surrogate, check = trained.surrogate, trained.rollout
    n_s, n_p, n_f = 2, 6, 5
    start = n_s * n_p - 1
    assert check.start == start and check.n_steps == (300 - 1 - start) // (n_s * n_f) * n_s * n_f
    for p, part in enumerate(traj.parts):
        truth = np.pad(part.shared_displacement, ((0, 0), (0, 9 - part.shared_displacement.shape[1])))
        one = jax.tree_util.tree_map(lambda a: a[p], surrogate)  # one part's replica
        buffer, predicted = truth[:start + 1][-n_s * n_p:], []
        while len(predicted) * n_s * n_f < check.n_steps:
            block = np.asarray(one.predict(buffer, start + len(predicted) * n_s * n_f))
            predicted.append(block)
            buffer = np.concatenate([buffer, block])[-n_s * n_p:]
        error = np.abs(np.concatenate(predicted) - truth[start + 1:start + 1 + check.n_steps])
        real = part.shared_displacement.shape[1]
        assert check.max_abs_error[p] == pytest.approx(error[:, :real].max(), rel=1e-5)
        assert check.amplitude[p] == np.abs(part.shared_displacement).max()
        assert check.mse[p] == pytest.approx(np.mean(np.square(error[:, :real])), rel=1e-5)
    assert trained.rollout_passed is False
    summary = trained.summary()["rollout_check"]
    assert summary["passed"] is False and summary["tolerance"] == 1e-3
    assert summary["relative"] == pytest.approx((check.max_abs_error / check.amplitude).tolist())

    # within a generous tolerance: no warning; None: not checked
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", RolloutWarning)
        loose = train_surrogates(traj, checks=TrainingChecks(emse_applications=0, rollout_tolerance=10.0), **SMALL)
    assert loose.rollout_passed is True
    unchecked = train_surrogates(traj, checks=TrainingChecks(emse_applications=0, rollout_tolerance=None), **SMALL)
    assert unchecked.rollout is None and unchecked.summary()["rollout_check"] is None
    with pytest.raises(ConfigError, match="rollout_tolerance must be > 0"):
        train_surrogates(traj, checks=TrainingChecks(rollout_tolerance=0.0), **SMALL)


def test_more_sampling_offsets_take_the_sequences_at_those_phases():
    history = np.arange(40.0)[:, None] * np.array([[1.0, -2.0]])  # step index per row
    one = build_dataset([history], 4, 2, 1, train_fraction=1.0, val_fraction=0.2, n_offsets=1)
    four = build_dataset([history], 4, 2, 1, train_fraction=1.0, val_fraction=0.2, n_offsets=4)
    two = build_dataset([history], 4, 2, 1, train_fraction=1.0, val_fraction=0.2, n_offsets=2)

    def windows(data):  # back to step indices, as a set of (inputs, target) tuples
        x = data.normalization.invert(np.concatenate([data.x_train, data.x_val]))[..., 0]
        y = data.normalization.invert(np.concatenate([data.y_train, data.y_val]))[..., 0]
        return {tuple(np.round(np.concatenate([a, b])).astype(int)) for a, b in zip(x, y)}

    expected = {offset: {(s, s + 4, s + 8) for s in range(offset, 40 - 8, 4)} for offset in range(4)}
    assert windows(one) == expected[0]
    assert windows(two) == expected[0] | expected[2]
    assert windows(four) == set().union(*expected.values())
    assert four.x_train.shape[0] + four.x_val.shape[0] == sum(len(w) for w in expected.values())
    with pytest.raises(ConfigError, match="n_offsets must be an integer from 1 to n_s=4"):
        build_dataset([history], 4, 2, 1, n_offsets=5)


def test_the_conditional_decoder_uses_its_load_parameter():
    """Trained on two runs told apart by their load parameter (30 epochs, one compiled
    call), each run's refills are closer to that run given its own parameter than given the
    other's: measured 0.74 and 0.78 of the error given the other's (asserted: 0.9)."""
    runs = [oscillator_trajectory(n_steps=400, load=load) for load in (1.0, 0.6)]
    config = TrainConfig(batch_size=8, eta0=1e-2, gamma=0.99, n_epochs=30, epochs_per_call=30, patience=None)
    trained = train_surrogates(runs, **dict(SMALL, optimizer=config,
                                            architecture=dataclasses.replace(ARCH, n_cond_repeat=4),
                                            sampling=dataclasses.replace(SAMPLING, train_fraction=1.0)),
                               checks=TrainingChecks(emse_applications=0, rollout_tolerance=None))
    result = trained.result
    n_s, n_p, n_f = 2, 6, 5

    def refill_error(run, load):
        surrogate = Surrogate.from_result(result, n_s, load)
        errors = []
        for p, part in enumerate(run.parts):
            truth = np.pad(part.shared_displacement, ((0, 0), (0, 9 - part.shared_displacement.shape[1])))
            one = jax.tree_util.tree_map(lambda a: a[p], surrogate)
            for step in range(n_s * n_p - 1, 400 - n_s * n_f - 1, 17):
                pred = np.asarray(one.predict(truth[step + 1 - n_s * n_p:step + 1], step))
                errors.append(np.mean(np.square(pred - truth[step + 1:step + 1 + n_s * n_f])))
        return float(np.mean(errors))

    for run, own, other in ((runs[0], 1.0, 0.6), (runs[1], 0.6, 1.0)):
        assert refill_error(run, own) < 0.9 * refill_error(run, other)


def test_the_shared_amplitude_of_the_trained_steps_is_recorded_and_a_percentage_tolerance_refers_to_it(tmp_path):
    """The surrogates record the largest shared displacement in the rows training read
    (the first half here, of a response that keeps growing after it: not the whole run's),
    in the summary and the surrogate file; ``jaxsync predict`` holds a percentage tolerance
    to it, and to the trajectory's own amplitude for a file that does not record one."""
    from types import SimpleNamespace

    from jaxsync.cli.predict import trained_amplitude

    traj = oscillator_trajectory(n_steps=301)
    ramp = np.exp(np.linspace(0.0, 4.0, 301))[:, None]  # the amplitude grows through the run
    traj = dataclasses.replace(traj, parts=tuple(
        dataclasses.replace(p, shared_displacement=ramp * p.shared_displacement) for p in traj.parts))
    trained = train_surrogates(traj, architecture=ArchitectureChoice(model="linear"), sampling=SAMPLING,
                               checks=TrainingChecks(emse_applications=0, rollout_tolerance=None), progress=False)
    first_half = max(np.abs(p.shared_displacement[:150]).max() for p in traj.parts)  # floor(0.5 * 301) rows
    whole = max(np.abs(p.shared_displacement).max() for p in traj.parts)
    assert whole > 1.5 * first_half
    assert trained.shared_amplitude == trained.summary()["shared_amplitude_cm"] == first_half
    path = tmp_path / "surrogate.h5"
    trained.write(tmp_path)
    saved = load_surrogate(path)
    assert saved.metadata["shared_amplitude_cm"] == first_half
    assert trained_amplitude(saved, traj) == first_half
    older = dataclasses.replace(saved, metadata={k: v for k, v in saved.metadata.items() if k != "shared_amplitude_cm"})
    assert trained_amplitude(older, traj) == whole
    at_rest = SimpleNamespace(parts=[SimpleNamespace(shared_displacement=np.zeros((3, 6)))])
    assert trained_amplitude(SimpleNamespace(metadata={}), at_rest) is None
