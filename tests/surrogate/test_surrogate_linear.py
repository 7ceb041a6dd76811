"""The linear autoregressive surrogate (issue 14): exact on an exactly linear recurrence,
the LSTM's checkpoint format and Surrogate interface, online in the solver, `--model linear`."""

import argparse
import dataclasses
import json

import h5py
import jax
import numpy as np
import pytest
from scipy.linalg import expm

import jaxsync
from jaxsync.cli.train import add_train_parser
from jaxsync.errors import CheckpointError, ConfigError
from jaxsync.io import array_checksum
from jaxsync.solve.coupling import simulate_sync_avoiding
from jaxsync.surrogate import (
    ArchitectureChoice,
    LinearArchitecture,
    LinearFitConfig,
    LSTMArchitecture,
    Sampling,
    SavedSurrogate,
    Surrogate,
    TrainingChecks,
    build_dataset,
    fit_linear,
    load_surrogate,
    save_surrogate,
    stack_replicas,
    train_surrogates,
)
from jaxsync.surrogate.models import architecture_from_dict, architecture_to_dict, forward, init_replicas
from jaxsync.surrogate.training import ReplicaData, RolloutWarning, make_windows, padding_mask, subsample
from oscillator_trajectories import NODES, write_trajectory

N_S, N_P, N_F = 3, 4, 5
COUNTS = (3, 5)  # part 0 is padded to part 1's width


def mixed_oscillators(n_steps, x0_seed, dt=0.05):
    """Per part, (n_steps, count) displacements H x(t) + c of three damped oscillators (state
    x in R^6, one run per initial state ``x0_seed``; H and c fixed): every sequence
    sampled n_s steps apart obeys x_{k+1} = F x_k with F = expm(A n_s dt), so a window of
    n_p >= 2 snapshots determines the next ones by an exact affine map that couples the
    dofs."""
    a = np.zeros((6, 6))
    for i, (sigma, omega) in enumerate([(0.02, 1.0), (0.05, 1.7), (0.03, 2.9)]):
        a[2 * i:2 * i + 2, 2 * i:2 * i + 2] = [[-sigma, omega], [-omega, -sigma]]
    step = expm(a * dt)
    x = [np.random.default_rng(x0_seed).normal(size=6)]
    for _ in range(n_steps - 1):
        x.append(step @ x[-1])
    x = np.array(x)
    rng = np.random.default_rng(0)
    return [x @ rng.normal(size=(c, 6)).T + rng.normal(size=c) for c in COUNTS]


def pad(history, width=max(COUNTS)):
    return np.pad(history, ((0, 0), (0, width - history.shape[1])))


def test_an_exact_linear_recurrence_is_recovered_to_round_off_in_float64():
    """float64 windows, plain least squares: the fitted map reproduces the recurrence on
    windows of runs it never saw, to float64 round-off."""
    train = mixed_oscillators(600, x0_seed=1)
    windows = [make_windows(subsample(h, N_S), N_P, N_F) for h in train]
    width = max(COUNTS)
    x = np.stack([pad(w[0].reshape(-1, COUNTS[p])).reshape(-1, N_P, width) for p, w in enumerate(windows)])
    y = np.stack([pad(w[1].reshape(-1, COUNTS[p])).reshape(-1, N_F, width) for p, w in enumerate(windows)])
    n = x.shape[1]
    data = ReplicaData(x_train=x, y_train=y, load_parameter_train=np.zeros((2, n)), x_val=x[:, :5], y_val=y[:, :5],
                       load_parameter_val=np.zeros((2, 5)), dof_mask=padding_mask(COUNTS, width),
                       dof_counts=COUNTS, mean=np.zeros((2, width)), std=np.ones((2, width)))
    result = fit_linear(data, LinearFitConfig(regularization=0.0), dtype="float64")
    assert result.arch == LinearArchitecture(n_dof=5, rank=result.arch.rank, n_past=N_P, n_future=N_F, dtype="float64")
    assert result.arch.rank <= 6  # the windows span the oscillators' state: a 6-dimensional affine set
    assert result.train_loss.shape == (1, 2) and result.train_loss.max() < 1e-24 and result.val_loss.max() < 1e-24
    assert result.initial_val_loss.min() > 1e-2
    # a run from another initial state; the NumPy reference is the recurrence itself
    test = mixed_oscillators(600, x0_seed=5)
    for p, count in enumerate(COUNTS):
        params = jax.tree_util.tree_map(lambda a: a[p], result.params)
        mask = padding_mask(COUNTS, width)[p]
        assert np.all(np.asarray(result.params["w_in"])[p, :, count:] == 0)  # padding untouched
        snaps = subsample(test[p], N_S)
        scale = np.abs(snaps).max()
        for k in (0, 37, 150):
            pred = np.asarray(forward(params, result.arch, pad(snaps[k:k + N_P]), None, mask))
            np.testing.assert_array_equal(pred[:, count:], 0.0)
            assert np.abs(pred[:, :count] - snaps[k + N_P:k + N_P + N_F]).max() <= 1e-11 * scale


def test_the_same_recurrence_through_the_training_windows_and_the_refill():
    """The LSTM's windows (build_dataset: float32, normalized) and the refill in solver units:
    one prediction and a 4-cycle rollout follow the recurrence to float32 round-off."""
    data = stack_replicas([build_dataset([h], N_S, N_P, N_F, train_fraction=1.0) for h in mixed_oscillators(900, 1)])
    result = fit_linear(data)  # default regularization, float32 parameters
    assert result.config == LinearFitConfig() and result.arch.dtype == "float32"
    assert np.all(result.val_loss < 1e-10) and np.all(result.initial_val_loss > 0.5)
    surrogate = dataclasses.replace(Surrogate.from_result(result, N_S), smooth=False)  # the raw refill
    test = mixed_oscillators(900, x0_seed=7)
    step = 300
    for p, count in enumerate(COUNTS):
        truth = pad(test[p])
        scale = np.abs(truth).max()
        buffer = truth[step + 1 - N_S * N_P:step + 1]
        one = np.asarray(surrogate.part(p).predict(buffer, step))
        assert one.shape == (N_S * N_F, 5)
        assert np.abs(one - truth[step + 1:step + 1 + N_S * N_F]).max() <= 1e-6 * scale
        rolled = np.asarray(surrogate.part(p).rollout(buffer, step, 4))
        assert np.abs(rolled - truth[step + 1:step + 1 + 4 * N_S * N_F]).max() <= 1e-5 * scale


def _linear_checkpoint():
    data = stack_replicas([build_dataset([h], N_S, N_P, N_F) for h in mixed_oscillators(300, 1)])
    result = fit_linear(data)
    return SavedSurrogate.from_result(result, N_S, (np.array([1]), np.array([1, 4])), metadata={"note": "x"})


def test_linear_checkpoint_round_trip_is_exact(tmp_path):
    ckpt = _linear_checkpoint()
    path = tmp_path / "linear.h5"
    save_surrogate(path, ckpt)
    with h5py.File(path) as f:
        assert json.loads(f.attrs["architecture"])["kind"] == "linear"
    loaded = load_surrogate(path)
    assert loaded.arch == ckpt.arch and isinstance(loaded.arch, LinearArchitecture)
    assert loaded.metadata == ckpt.metadata and loaded.metadata["training"]["model"] == "linear"
    for name in ("w_in", "w_out", "b"):
        assert loaded.params[name].dtype == ckpt.params[name].dtype
        assert loaded.params[name].tobytes() == ckpt.params[name].tobytes()
    # the Surrogate of the file predicts what the one in memory does
    buffer = pad(mixed_oscillators(300, 3)[0])[:N_S * N_P]
    a, b = Surrogate.from_saved(ckpt).part(0), Surrogate.load(path).part(0)
    np.testing.assert_array_equal(a.predict(buffer, N_S * N_P - 1), b.predict(buffer, N_S * N_P - 1))
    assert architecture_from_dict(architecture_to_dict(ckpt.arch)) == ckpt.arch


def _rewrite_architecture(path, values):
    """Store ``values`` as the file's architecture, with the checksum of what it then holds."""
    with h5py.File(path, "r+") as f:
        f.attrs["architecture"] = json.dumps(values, sort_keys=True)
        datasets = {}
        f.visititems(lambda name, obj: datasets.update({name: obj[()]}) if isinstance(obj, h5py.Dataset) else None)
        attrs = {k: (v.item() if isinstance(v, np.generic) else v) for k, v in f.attrs.items()}
        del attrs["checksum_sha256"]
        f.attrs["checksum_sha256"] = array_checksum(datasets, attrs)


def test_an_lstm_checkpoint_written_before_the_linear_model_still_loads(tmp_path):
    """Files written before this change store the architecture without a 'kind': an LSTM."""
    arch = LSTMArchitecture(n_dof=4, n_hidden=3, n_layers=1, n_past=N_P, n_future=N_F)
    params = jax.tree_util.tree_map(np.asarray, init_replicas(jax.random.key(0), arch, (4,)))
    ckpt = SavedSurrogate(arch=arch, params=params, mean=np.zeros((1, 4)), std=np.ones((1, 4)),
                          dof_counts=(4,), n_s=N_S)
    path = tmp_path / "old.h5"
    save_surrogate(path, ckpt)
    with h5py.File(path) as f:
        assert json.loads(f.attrs["architecture"]) == {"kind": "lstm", **arch.to_dict()}
    _rewrite_architecture(path, arch.to_dict())  # what the earlier version wrote
    loaded = load_surrogate(path)
    assert loaded.arch == arch and isinstance(loaded.arch, LSTMArchitecture)
    # an unknown kind is refused with a message that names the fix
    _rewrite_architecture(path, {"kind": "gru", **arch.to_dict()})
    with pytest.raises(CheckpointError, match="architecture kind must be one of 'lstm', 'linear'.*retrain"):
        load_surrogate(path)
    with pytest.raises(ConfigError, match="kind 'linear' given to LSTMArchitecture"):
        LSTMArchitecture.from_dict({"kind": "linear", **arch.to_dict()})


def test_a_linear_surrogate_runs_online_and_its_shared_values_are_its_offline_rollout():
    """Oracle-style: fitted on a synchronized cantilever run, the linear surrogate drives
    simulate_sync_avoiding through the Surrogate interface.

    Bound (derived, not tuned): after n_cri the solver overwrites each part's shared dofs
    with that part's refill, and the refill reads a buffer of the part's own earlier
    predictions (refill_cycle, as Surrogate.rollout does), starting from the synchronized
    buffer, which equals the reference. So the online shared values of part p ARE the
    offline autonomous rollout of part p from the reference at n_cri, and their error
    against the synchronized run equals that rollout's error, measured from the reference
    alone: equal to float32 round-off (1e-6 of the amplitude). That error is the
    surrogate's; on this run it is 2.7 % (3.6 % at regularization 1e-6, 4.5 % at 1e-10,
    and the run blows up without regularization), checked here at 4 %."""
    n_s, n_p, n_f, n_cri, n_steps = 5, 4, 4, 40, 400  # tests/solve/test_syncavoid.py's sizes
    problem = jaxsync.cantilever()
    partition = jaxsync.partition(problem.mesh, 2)
    reference = jaxsync.simulate(problem, n_steps, partitions=partition)
    data = stack_replicas([build_dataset([part.shared_displacement], n_s, n_p, n_f, train_fraction=1.0)
                           for part in reference.parts])
    surrogate = Surrogate.from_result(fit_linear(data), n_s)
    online = simulate_sync_avoiding(problem, n_steps, partitions=partition, surrogates=surrogate, n_cri=n_cri)
    np.testing.assert_array_equal(online.displacement[:n_cri + 1], reference.displacement[:n_cri + 1])
    amplitude = np.abs(reference.displacement).max()
    n_cycles = -(-(n_steps - n_cri) // (n_s * n_f))
    for p, part in enumerate(reference.parts):
        count = part.shared_displacement.shape[1]
        history = np.pad(part.shared_displacement, ((0, 0), (0, surrogate.n_dof - count)))
        rollout = np.asarray(surrogate.part(p).rollout(history[n_cri + 1 - n_s * n_p:n_cri + 1], n_cri, n_cycles))
        rollout = rollout[:n_steps - n_cri, :count]
        predicted = online.parts[p].predicted_shared_displacement
        assert np.abs(predicted - rollout).max() <= 1e-6 * amplitude
        rollout_error = np.abs(rollout - part.shared_displacement[n_cri + 1:]).max()
        online_error = np.abs(predicted - reference.parts[p].shared_displacement[n_cri + 1:]).max()
        assert abs(online_error - rollout_error) <= 1e-6 * amplitude
        assert rollout_error <= 0.04 * amplitude


def _parser():
    parser = argparse.ArgumentParser(prog="jaxsync")
    add_train_parser(parser.add_subparsers(dest="command", required=True))
    return parser


def test_jaxsync_train_model_linear_writes_checkpoint_and_summary(tmp_path, capsys):
    """On test_surrogate_fit's oscillators (one damped oscillator per dof: an exact order-2
    recurrence of the sampled snapshots) the fit is exact (validation MSE ~1e-14), yet the
    offline check warns: the Surrogate's default smooth refill interpolates between block
    means, an O((n_s dt omega)^2) error per cycle at 13 steps per period, which 58 cycles
    of rollout accumulate to ~18 % (the raw refill stays within 1e-6: see
    test_the_same_recurrence_through_the_training_windows_and_the_refill)."""
    path = write_trajectory(tmp_path / "run.h5")
    out = tmp_path / "out"
    args = _parser().parse_args(["train", str(path), "-o", str(out), "--model", "linear", "--n-s", "2",
                                 "--n-past", "6", "--n-future", "5", "--emse-applications", "5", "--no-progress"])
    with pytest.warns(RolloutWarning, match="Fit with another regularization"):
        assert args.func(args) == 0
    ckpt = load_surrogate(out / "surrogate.h5", shared_nodes_per_part=NODES)
    assert isinstance(ckpt.arch, LinearArchitecture) and ckpt.arch.n_dof == 9 and ckpt.dof_counts == (6, 9)
    assert ckpt.metadata["model"] == "linear" and ckpt.metadata["training"]["regularization"] == 1e-8
    summary = json.loads((out / "train_summary.json").read_text())
    assert summary["model"] == "linear" and summary["architecture"]["kind"] == "linear"
    assert summary["candidates"] is None and "not applicable" in summary["training"]["candidates"]
    assert summary["n_epochs_run"] is None and summary["training"]["fit_seconds"] > 0
    assert len(summary["loss_history"]["val"]) == 1 and summary["final_val_loss"] == ckpt.metadata["final_val_loss"]
    assert max(summary["final_val_loss"]) < 1e-10 and len(summary["rollout_check"]["relative"]) == 2
    assert len(summary["sqrt_e_mse"]) == 2
    assert (out / "loss_curves.png").read_bytes()[:4] == b"\x89PNG" and not (out / "training_state.h5").exists()
    assert "(linear, least-squares fit of rank" in capsys.readouterr().out
    # the surrogate of the file is the one train_surrogates returns in memory
    trained = train_surrogates(path, architecture=ArchitectureChoice(model="linear"),
                               sampling=Sampling(n_s=2, n_past=6, n_future=5),
                               checks=TrainingChecks(emse_applications=0, rollout_tolerance=None))
    assert trained.model == "linear" and trained.saved.arch == ckpt.arch


def test_a_bad_model_is_refused(tmp_path, capsys):
    with pytest.raises(SystemExit):
        _parser().parse_args(["train", "run.h5", "--model", "gru"])
    assert "invalid choice: 'gru' (choose from 'lstm', 'linear')" in capsys.readouterr().err
    path = write_trajectory(tmp_path / "run.h5")
    with pytest.raises(ConfigError, match="model must be one of 'lstm', 'linear', got 'gru'"):
        train_surrogates(path, architecture=ArchitectureChoice(model="gru"))
    with pytest.raises(ConfigError, match="linear surrogate is unconditional.*--model lstm"):
        train_surrogates(path, architecture=ArchitectureChoice(model="linear", n_cond_repeat=2))
    with pytest.raises(ConfigError, match="regularization must be a finite number >= 0"):
        train_surrogates(path, architecture=ArchitectureChoice(model="linear", regularization=-1.0))


def test_initialized_linear_replicas_for_timing_have_the_widest_rank_and_predict_the_mean():
    from jaxsync.surrogate import Surrogate
    from jaxsync.surrogate.training import shared_dof_layout

    part = jaxsync.partition(jaxsync.cantilever().mesh, 2)
    n_dof, _ = shared_dof_layout(part)
    surrogate = Surrogate.initialized(part, 4, n_past=3, n_future=5, model="linear")
    assert (surrogate.arch.kind, surrogate.arch.rank) == ("linear", 3 * n_dof)
    assert surrogate.params["w_in"].shape == (2, 3, n_dof, 3 * n_dof)
    # zero weights and unit normalization about 0: the networks predict 0, the training
    # mean, so a history at rest stays at rest (the smooth refill starts from the history)
    history = np.random.default_rng(0).standard_normal((2, 4 * 3, n_dof))
    pred = np.asarray(jax.vmap(lambda s, h: s.predict(h, 0))(surrogate, history))
    assert pred.shape == (2, 4 * 5, n_dof) and np.all(np.isfinite(pred))
    rest = np.asarray(jax.vmap(lambda s, h: s.predict(h, 0))(surrogate, np.zeros_like(history)))
    assert np.all(rest == 0.0)
    assert Surrogate.initialized(part, 4, model="linear", rank=7).arch.rank == 7
    with pytest.raises(ConfigError, match="lstm"):
        Surrogate.initialized(part, 4, model="gru")


def test_training_leaves_out_the_windows_across_a_recorded_load_jump(tmp_path):
    """A run whose load switches off records its jumps; training takes no window across
    them (counted in the summary) and the fit equals a fit on the kept windows alone."""
    from jaxsync.surrogate import train_surrogates
    from jaxsync.surrogate.training import read_shared_histories

    problem = jaxsync.cantilever()
    t_off = 150.5 * float(problem.dt)
    problem = dataclasses.replace(problem, loads=(jaxsync.BodyForce(
        problem.loads[0].vector, jaxsync.StepOff(t_off, problem.loads[0].time)),))
    reference = jaxsync.simulate(problem, 400, partitions=2)
    assert reference.parameters["load_jumps"] == [151] and reference.parameters["last_load_jump"] == 151
    reference.save(tmp_path / "run.h5")
    histories = read_shared_histories(tmp_path / "run.h5")
    assert histories.load_jumps == (151,)
    linear, windows = ArchitectureChoice(model="linear"), Sampling(n_s=5, n_past=4, n_future=4, train_fraction=1.0)
    unchecked = TrainingChecks(rollout_tolerance=None)
    trained = train_surrogates(tmp_path / "run.h5", architecture=linear, sampling=windows, checks=unchecked)
    kept = [build_dataset([h], 5, 4, 4, train_fraction=1.0, load_jumps=[[151.0]]) for h in histories.histories]
    assert trained.n_excluded_windows == kept[0].n_excluded == 7  # windows of 8 snapshots 5 steps apart
    sampling = trained.summary()["sampling"]
    assert (sampling["n_excluded_windows"], sampling["load_jump_windows"]) == (7, "exclude")
    assert trained.n_train_windows == kept[0].x_train.shape[0]
    # kept on request (the LSTM's default): every window, as without a jump
    every = train_surrogates(tmp_path / "run.h5", architecture=linear, checks=unchecked,
                             sampling=dataclasses.replace(windows, load_jump_windows="keep"))
    assert every.n_excluded_windows == 0 and every.n_train_windows > trained.n_train_windows
    with pytest.raises(ConfigError, match="load_jump_windows must be one of 'exclude', 'keep'"):
        train_surrogates(tmp_path / "run.h5", architecture=linear, sampling=Sampling(load_jump_windows="drop"))
    # from the command line
    args = _parser().parse_args(["train", str(tmp_path / "run.h5"), "-o", str(tmp_path / "cli"), "--model", "linear",
                                 "--n-s", "5", "--n-past", "4", "--n-future", "4", "--train-fraction", "1",
                                 "--load-jump-windows", "keep", "--rollout-tolerance", "100", "--no-progress"])
    assert args.func(args) == 0
    sampling = json.loads((tmp_path / "cli" / "train_summary.json").read_text())["sampling"]
    assert (sampling["n_excluded_windows"], sampling["load_jump_windows"]) == (0, "keep")
