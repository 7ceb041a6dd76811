"""Surrogates that know the load (issue 36, item 1): the known load signals as inputs of
the LSTM and of the linear model (ARX), recorded by the trajectories, fed online from the
problem's own time functions, recorded in the surrogate file and checked against the
problem a surrogate runs on."""

import argparse
import dataclasses
import json

import h5py
import jax
import numpy as np
import pytest

import jaxsync
from jaxsync.cli.train import add_train_parser
from jaxsync.errors import CheckpointError, ConfigError
from jaxsync.fem import LoadSignals, load_inputs_of
from jaxsync.solve.coupling import simulate_sync_avoiding
from jaxsync.surrogate import (
    ArchitectureChoice,
    LinearArchitecture,
    LSTMArchitecture,
    Sampling,
    Surrogate,
    TrainConfig,
    TrainingChecks,
    build_dataset,
    fit_linear,
    load_surrogate,
    stack_replicas,
    train_surrogates,
)
from jaxsync.surrogate.models import forward, init_params
from jaxsync.surrogate.training import rollout_errors

N_STEPS = 2400  # about four periods of the short beam's first bending mode
SAMPLING = Sampling(n_s=5, n_past=8, n_future=8, train_fraction=0.5)
UNCHECKED = TrainingChecks(rollout_tolerance=None, emse_applications=1)


def short_beam():
    """A 5 x 1 x 1 cm cantilever (5 cells, 2 parts): the paper's material, a bending
    period of about 600 steps."""
    return jaxsync.cantilever(jaxsync.box_beam(5.0, 1.0, 1.0, (5, 1, 1)))


def step_off_problem(t_off_fraction=0.7):
    """The load ramps on over 0.15 s (seen in training) and is switched off at 70 % of the
    run (out of sample)."""
    base = short_beam()
    return jaxsync.cantilever(base.mesh, t_ramp=0.15, t_off=t_off_fraction * N_STEPS * float(base.dt))


def pulsatile_problem(period=0.12, peak=1.0):
    """A pulse-like periodic body force (sharp rise, slower decay, rest), ramped in."""
    base = short_beam()
    pulse = jaxsync.Periodic(times=[0.0, 0.2 * period, 0.35 * period, 0.6 * period], values=[0.0, peak, 0.3, 0.0],
                             period=period)
    return dataclasses.replace(base, loads=(jaxsync.BodyForce((0.0, 0.0, -0.5), jaxsync.Ramp(0.05) * pulse),))


def padded_histories(reference):
    width = max(p.shared_displacement.shape[1] for p in reference.parts)
    return np.stack([np.pad(p.shared_displacement, ((0, 0), (0, width - p.shared_displacement.shape[1])))
                     for p in reference.parts])


def out_of_sample_error(trained, problem, reference):
    """RMS error of the autonomous rollout over the second half of the run (never trained
    on), relative to the largest shared displacement."""
    rollout = rollout_errors(trained.surrogate.for_problem(problem), padded_histories(reference),
                             start=N_STEPS // 2 - 1)
    return float(np.sqrt(rollout.mse.mean()) / rollout.amplitude.max())


@pytest.fixture(scope="module")
def step_off_run():
    problem = step_off_problem()
    return problem, jaxsync.simulate(problem, N_STEPS, partitions=2)


# ----------------------------------------------------------------------------- models


def _zero_load_path(params_with, params_without):
    """``params_with`` (a model with load input) carrying the weights of ``params_without``
    and zero load weights."""
    def merge(path, leaf):
        keys = [getattr(k, "key", getattr(k, "idx", None)) for k in path]
        if keys[-1] in ("w_u", "w_load"):
            return np.zeros_like(leaf)
        node = params_without
        for k in keys:
            node = node[k]
        return node
    return jax.tree_util.tree_map_with_path(merge, params_with)


@pytest.mark.parametrize("model", ["lstm", "linear"])
def test_a_zero_load_path_reproduces_the_load_blind_model_bit_for_bit(model):
    n_dof, n_p, n_f, n_load = 6, 4, 3, 2
    if model == "lstm":
        blind = LSTMArchitecture(n_dof=n_dof, n_hidden=5, n_layers=2, n_past=n_p, n_future=n_f)
    else:
        blind = LinearArchitecture(n_dof=n_dof, rank=7, n_past=n_p, n_future=n_f)
    aware = dataclasses.replace(blind, n_load=n_load)
    key = jax.random.key(3)
    if model == "lstm":
        params_blind = init_params(key, blind)
    else:  # zero-initialized: give the map random weights
        shapes = jax.eval_shape(init_params, key, blind)
        keys = jax.random.split(key, len(jax.tree_util.tree_leaves(shapes)))
        params_blind = jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(shapes), [
            jax.random.normal(k, s.shape, s.dtype) for k, s in zip(keys, jax.tree_util.tree_leaves(shapes))])
    params_aware = init_params(jax.random.key(4), aware)
    xs = jax.random.normal(jax.random.key(5), (n_p, n_dof), np.float32)
    loads = jax.random.normal(jax.random.key(6), (n_p + n_f, n_load), np.float32)
    out = forward(params_aware, aware, xs, loads=loads)
    assert out.shape == (n_f, n_dof) and out.dtype == np.float32
    zeroed = _zero_load_path(params_aware, params_blind)
    np.testing.assert_array_equal(np.asarray(forward(zeroed, aware, xs, loads=loads)),
                                  np.asarray(forward(params_blind, blind, xs)))
    # the load path is read: other loads, other predictions (with the trained weights)
    if model == "linear":
        params_aware = dict(zeroed, w_load=np.ones_like(zeroed["w_load"]))
    assert not np.allclose(forward(params_aware, aware, xs, loads=loads),
                           forward(params_aware, aware, xs, loads=2 * loads))
    with pytest.raises(ConfigError, match="takes 2 known load signal"):
        forward(params_aware, aware, xs)
    with pytest.raises(ConfigError, match=r"shape \(n_past \+ n_future, n_load\) = \(7, 2\)"):
        forward(params_aware, aware, xs, loads=loads[:n_p])
    with pytest.raises(ConfigError, match="trained without load input"):
        forward(params_blind, blind, xs, loads=loads)


def test_the_arx_fit_is_the_least_squares_solution_of_numpy():
    """The linear model with load input against numpy.linalg.lstsq on the design matrix
    [vec(x), vec(u_past), vec(u_future), 1] (float64, no regularization)."""
    rng = np.random.default_rng(0)
    n_steps, n_dof, n_u, n_s, n_p, n_f = 400, 4, 2, 2, 3, 2
    signal = np.stack([np.sin(0.05 * np.arange(n_steps)), np.where(np.arange(n_steps) < 250, 2.0, -0.5)], axis=1)
    # a damped rotation driven by the signals, with a little noise
    angle = 0.1
    rotation = 0.97 * np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    dynamics = np.kron(np.eye(2), rotation)
    forcing = rng.normal(size=(n_dof, n_u))
    history = np.zeros((n_steps, n_dof))
    for k in range(1, n_steps):
        history[k] = dynamics @ history[k - 1] + forcing @ signal[k - 1] + 0.01 * rng.normal(size=n_dof)
    dataset = build_dataset([history], n_s, n_p, n_f, train_fraction=1.0, signals=[signal])
    data = stack_replicas([dataset], load_inputs_of(short_beam()) * 2)
    data = dataclasses.replace(data, x_train=data.x_train.astype(np.float64), y_train=data.y_train.astype(np.float64),
                               signal_train=data.signal_train.astype(np.float64))
    result = fit_linear(data, ArchitectureChoice(model="linear", regularization=0.0).fit_config, "float64")
    assert result.arch.n_load == n_u and result.load_inputs == data.load_inputs
    np.testing.assert_array_equal(result.signal_scale, np.abs(signal).max(axis=0)[None])  # largest |u| of each
    x, y, u = data.x_train[0], data.y_train[0], data.signal_train[0]
    design = np.concatenate([x.reshape(len(x), -1), u.reshape(len(u), -1), np.ones((len(x), 1))], axis=1)
    coeffs, *_ = np.linalg.lstsq(design, y.reshape(len(y), -1), rcond=None)
    expected = (design @ coeffs).reshape(y.shape)
    params = jax.tree_util.tree_map(lambda a: a[0], result.params)
    got = np.stack([np.asarray(forward(params, result.arch, x[w], loads=u[w])) for w in range(len(x))])
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9 * np.abs(expected).max())
    # the load columns matter here: the fit without them is worse
    blind = fit_linear(dataclasses.replace(data, signal_train=None, signal_val=None, signal_scale=None,
                                           load_inputs=()), result.config, "float64")
    assert blind.train_loss[0, 0] > 10 * result.train_loss[0, 0]


# ----------------------------------------------------------------------------- out of sample


@pytest.mark.parametrize("case", ["step-off", "pulsatile"])
def test_the_linear_model_with_load_input_beats_the_load_blind_one_out_of_sample(case, step_off_run):
    """Trained on the first half of the run, rolled out autonomously over the second half.
    Measured: step-off 0.62 % against 41 % (66x), pulsatile 0.50 % against 17 % (33x) of the
    largest shared displacement; asserted: 10x and 2 %."""
    if case == "step-off":
        problem, reference = step_off_run
    else:
        problem = pulsatile_problem()
        reference = jaxsync.simulate(problem, N_STEPS, partitions=2)
    assert reference.load_signal.shape == (N_STEPS + 1, 1)
    errors = {}
    for load_input in (False, True):
        trained = train_surrogates(reference, architecture=ArchitectureChoice(model="linear", load_input=load_input),
                                   sampling=SAMPLING, checks=UNCHECKED, progress=False)
        assert trained.surrogate.n_load == (1 if load_input else 0)
        errors[load_input] = out_of_sample_error(trained, problem, reference)
    assert errors[True] <= 0.02
    assert errors[False] >= 10 * errors[True], errors


@pytest.mark.slow
def test_the_lstm_with_load_input_predicts_another_switch_off_time_better():
    """The LSTM (minutes): trained on the first half of a run whose load is switched off at
    30 % of it, rolled out over the second half of a run switched off at 70 % (n_H 32,
    5 sampled sequences per run, 1 500 epochs). Measured: 50 % without the load input,
    16.5 % with it (3.0x): the LSTM does NOT reach the linear model's 10x here (and on the
    first test's case, where training never sees the load switched off, it gains nothing:
    41 % and 40 %); asserted: 2x, the gain measured with a margin."""
    trained_on, runs_on = step_off_problem(0.3), step_off_problem(0.7)
    train_run = jaxsync.simulate(trained_on, N_STEPS, partitions=2)
    reference = jaxsync.simulate(runs_on, N_STEPS, partitions=2)
    errors = {}
    for load_input in (False, True):
        trained = train_surrogates(train_run, architecture=ArchitectureChoice(n_hidden=32, load_input=load_input),
                                   sampling=dataclasses.replace(SAMPLING, n_offsets=5), checks=UNCHECKED,
                                   optimizer=TrainConfig(n_epochs=1500, n_candidates=1, patience=None),
                                   progress=False)
        errors[load_input] = out_of_sample_error(trained, runs_on, reference)
    assert errors[False] >= 2 * errors[True], errors


# ----------------------------------------------------------------------------- files and problems


def test_a_surrogate_file_records_its_load_inputs_and_runs_only_on_loads_of_the_same_form(tmp_path, step_off_run):
    problem, reference = step_off_run
    trained = train_surrogates(reference, architecture=ArchitectureChoice(model="linear"), sampling=SAMPLING,
                               checks=UNCHECKED, progress=False)  # the load input is the default
    assert trained.surrogate.n_load == 1 and trained.summary()["load_inputs"] == [
        {"source": "loads[0]", "kind": "BodyForce", "form": "StepOff(Ramp)",
         "function": f"StepOff(t_off={0.7 * N_STEPS * float(problem.dt):g} s, inner=Ramp(t_end=0.15 s))"}]
    trained.write(tmp_path / "out")
    path = tmp_path / "out" / "surrogate.h5"
    with h5py.File(path) as f:
        assert json.loads(f.attrs["load_inputs"]) == trained.summary()["load_inputs"]
        assert json.loads(f.attrs["architecture"])["n_load"] == 1
        np.testing.assert_array_equal(f["load_inputs/scale"][()], [[1.0], [1.0]])
    saved = load_surrogate(path)
    assert saved.load_inputs == trained.result.load_inputs
    partition = jaxsync.partition(problem.mesh, 2)
    # other loads are refused, naming the difference
    other_count = dataclasses.replace(problem, loads=problem.loads * 2)
    with pytest.raises(CheckpointError, match=r"take 1 load signal.*this problem has 2.*retrain"):
        simulate_sync_avoiding(other_count, 800, partitions=partition, surrogates=saved, n_cri=400)
    other_form = pulsatile_problem()
    with pytest.raises(CheckpointError, match=r"loads\[0\] a BodyForce of time function form StepOff\(Ramp\).*"
                                              r"form Product\(Ramp, Periodic\)"):
        simulate_sync_avoiding(other_form, 800, partitions=partition, surrogates=saved, n_cri=400)
    with pytest.raises(ConfigError, match="bind them to the problem"):
        Surrogate.from_saved(saved).part(0).predict(np.zeros((40, saved.arch.n_dof)), 39)
    # the same form with another switch-off time runs, online and through the jump: measured 4.3 % of the
    # amplitude at worst (the load-blind surrogates of the same run: 166 %)
    moved = step_off_problem(0.6)
    truth = jaxsync.simulate(moved, N_STEPS, partitions=partition)
    amplitude = np.abs(truth.displacement).max()
    errors = {}
    for load_input, surrogates in ((True, saved), (False, None)):
        if surrogates is None:
            surrogates = train_surrogates(reference, architecture=ArchitectureChoice(model="linear", load_input=False),
                                          sampling=SAMPLING, checks=UNCHECKED, progress=False).saved
        online = simulate_sync_avoiding(moved, N_STEPS, partitions=partition, surrogates=surrogates,
                                        n_cri=N_STEPS // 2, load_jumps="predict")
        errors[load_input] = np.abs(online.displacement - truth.displacement).max() / amplitude
    assert errors[True] <= 0.05 and errors[False] >= 10 * errors[True], errors


def test_surrogates_and_trajectories_without_load_inputs_load_and_run_as_before(tmp_path, step_off_run):
    """A load-blind surrogate file stores exactly what files did before the load input (no
    n_load, no load_inputs) and predicts as the surrogate in memory; a trajectory file
    without load signals (written before they were recorded) trains the load-blind model
    by default and refuses load_input=True, naming the fix."""
    problem, reference = step_off_run
    blind = train_surrogates(reference, architecture=ArchitectureChoice(model="linear", load_input=False),
                             sampling=SAMPLING, checks=UNCHECKED, progress=False)
    blind.write(tmp_path / "blind")
    with h5py.File(tmp_path / "blind" / "surrogate.h5") as f:
        assert "load_inputs" not in f.attrs and "load_inputs" not in f
        assert "n_load" not in json.loads(f.attrs["architecture"])
    loaded = Surrogate.load(tmp_path / "blind" / "surrogate.h5")
    assert loaded.n_load == 0 and loaded.for_problem(pulsatile_problem()) is loaded  # no loads to check
    buffer = padded_histories(reference)[0, 1000 - 40 + 1:1001]
    np.testing.assert_array_equal(loaded.part(0).predict(buffer, 1000), blind.surrogate.part(0).predict(buffer, 1000))
    # a trajectory file written before the load signals were recorded
    reference.save(tmp_path / "run.h5")
    with h5py.File(tmp_path / "run.h5", "r+") as f:
        del f["load_signal"]
        del f.attrs["load_inputs"]
    old = jaxsync.Trajectory.load(tmp_path / "run.h5")
    assert old.load_signal is None and old.load_inputs == ()
    trained = train_surrogates(tmp_path / "run.h5", architecture=ArchitectureChoice(model="linear"),
                               sampling=SAMPLING, checks=UNCHECKED, progress=False)
    assert trained.surrogate.n_load == 0
    with pytest.raises(ConfigError, match=r"load_input=True.*records no load signals.*jaxsync simulate"):
        train_surrogates(tmp_path / "run.h5", architecture=ArchitectureChoice(model="linear", load_input=True),
                         sampling=SAMPLING, checks=UNCHECKED, progress=False)


def test_jaxsync_train_takes_the_load_input_by_default_and_leaves_it_out_on_request(tmp_path, step_off_run, capsys):
    _, reference = step_off_run
    reference.save(tmp_path / "run.h5")
    parser = argparse.ArgumentParser(prog="jaxsync")
    add_train_parser(parser.add_subparsers(dest="command", required=True))
    common = ["--model", "linear", "--n-s", "5", "--n-past", "8", "--n-future", "8", "--rollout-tolerance", "100",
              "--no-progress"]
    for flag, n_load in ((None, 1), ("--no-load-input", 0), ("--load-input", 1)):
        out = tmp_path / str(flag)
        flags = [flag] if flag else []
        args = parser.parse_args(["train", str(tmp_path / "run.h5"), "-o", str(out)] + common + flags)
        assert args.func(args) == 0
        assert load_surrogate(out / "surrogate.h5").arch.n_load == n_load
        summary = json.loads((out / "train_summary.json").read_text())
        assert len(summary["load_inputs"]) == n_load
        printed = capsys.readouterr().out
        assert ("load input: 1 known load signal(s): loads[0] BodyForce with StepOff" in printed) == bool(n_load)


def test_the_load_signals_of_a_problem_at_its_steps():
    problem = step_off_problem()
    dt = float(problem.dt)
    signals = LoadSignals.of(problem, dt)
    expected = np.asarray(jax.vmap(problem.loads[0].time)(np.arange(10, 15) * dt))
    np.testing.assert_array_equal(np.asarray(signals.at_steps(10, 5))[:, 0], expected)
    assert signals == LoadSignals.of(step_off_problem(), dt) and signals != LoadSignals.of(step_off_problem(0.6), dt)
    # a prescribed motion with a time function is a signal too, after the loads
    moving = dataclasses.replace(problem, dirichlet=problem.dirichlet + (
        jaxsync.Dirichlet("x1", (0.0, 0.0, 0.01), components=(2,), time=jaxsync.Ramp(0.1)),))
    assert [i.signature for i in load_inputs_of(moving)] == [
        ("loads[0]", "BodyForce", "StepOff(Ramp)"), ("dirichlet[1]", "Dirichlet", "Ramp")]


def test_an_lstm_with_load_input_trains_saves_and_runs_online(tmp_path, step_off_run):
    """The LSTM's path end to end (a few epochs: the plumbing, not the accuracy): its load
    weights are trained and stored, the file round-trips exactly, and it runs online."""
    problem, reference = step_off_run
    trained = train_surrogates(reference, architecture=ArchitectureChoice(n_hidden=4, n_layers=1), sampling=SAMPLING,
                               checks=UNCHECKED, optimizer=TrainConfig(n_epochs=3, n_candidates=1), progress=False)
    arch = trained.result.arch
    assert isinstance(arch, LSTMArchitecture) and arch.n_load == 1
    params = trained.result.params
    assert params["decoder"]["w_u"].shape == (2, 4 * 2 * 4, 1)
    assert params["encoder"][0]["forward"]["w_u"].shape == (2, 4 * 4, 1)
    trained.write(tmp_path)
    saved = load_surrogate(tmp_path / "surrogate.h5")
    assert saved.arch == arch
    for a, b in zip(jax.tree_util.tree_leaves(saved.params), jax.tree_util.tree_leaves(params)):
        np.testing.assert_array_equal(a, b)
    online = simulate_sync_avoiding(problem, 400, partitions=jaxsync.partition(problem.mesh, 2), surrogates=saved,
                                    n_cri=200)
    assert online.stats.n_predicted_steps == 200 and np.all(np.isfinite(online.displacement))


def test_the_reduced_precision_check_reads_the_windows_load_signals(step_off_run):
    from jaxsync.surrogate import reduced_precision, surrogate_signal_windows, surrogate_windows

    problem, reference = step_off_run
    trained = train_surrogates(reference, architecture=ArchitectureChoice(model="linear"), sampling=SAMPLING,
                               checks=UNCHECKED, progress=False)
    surrogate = trained.surrogate.for_problem(problem)
    histories = [p.shared_displacement for p in reference.parts]
    windows = surrogate_windows(surrogate, histories, max_windows=50)
    signals = surrogate_signal_windows(surrogate, len(histories[0]), max_windows=50)
    assert signals.shape == (2, windows.shape[1], 16, 1)
    # window w of the first: the recorded signal at steps 5 (w' + j), j = 0 .. 15, w' the window kept
    n_windows = len(range(0, N_STEPS + 1, 5)) - 8
    kept = np.unique(np.linspace(0, n_windows - 1, 50).round().astype(np.int64))
    rows = 5 * (kept[:, None] + np.arange(16)[None, :])
    np.testing.assert_allclose(signals[0, :, :, 0], np.asarray(reference.load_signal)[np.minimum(rows, N_STEPS), 0],
                               rtol=1e-6)
    reduced, report = reduced_precision(surrogate, windows, signals=signals)
    assert report.passed and reduced.inference_dtype == "bfloat16"
    with pytest.raises(ConfigError, match="pass the windows' signals"):
        reduced_precision(surrogate, windows)
