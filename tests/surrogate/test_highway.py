"""The LSTM's linear highway: the least-squares affine map of the window (the linear model,
ARX with the load input) plus what the decoder learns on top."""

import argparse
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsync
from jaxpr_counts import dot_flops
from jaxsync.cli.train import add_train_parser
from jaxsync.errors import ConfigError
from jaxsync.surrogate import (
    ArchitectureChoice,
    LSTMArchitecture,
    Sampling,
    Surrogate,
    TrainConfig,
    TrainingChecks,
    load_surrogate,
    train_surrogates,
)
from jaxsync.surrogate.models import count_flops, forward, init_params, pad_params, param_shapes, unpad_params
from jaxsync.surrogate.training import rollout_errors

N_STEPS = 2400  # about four periods of the short beam's first bending mode
SAMPLING = Sampling(n_s=5, n_past=8, n_future=8, train_fraction=0.5)
UNCHECKED = TrainingChecks(rollout_tolerance=None, emse_applications=1)


def _network(n_dof=6, n_load=2, rank=7):
    return LSTMArchitecture(n_dof=n_dof, n_hidden=5, n_layers=1, n_past=4, n_future=3, n_load=n_load, highway=True,
                            highway_rank=rank, dtype="float64")


def _random_highway(arch, key):
    """Random (normal) highway parameters of ``arch``."""
    shapes = param_shapes(arch.highway_arch)
    keys = jax.random.split(key, len(shapes))
    return {name: jax.random.normal(k, shape, jnp.float64) for k, (name, shape) in zip(keys, sorted(shapes.items()))}


def test_with_a_zero_output_layer_the_network_is_its_linear_model():
    arch = _network()
    params = init_params(jax.random.key(0), arch)
    assert set(params["highway"]) == {"w_in", "w_out", "b", "w_load"}
    assert all(not np.any(w) for w in params["highway"].values())  # set by the fit, zero before
    params["highway"] = _random_highway(arch, jax.random.key(1))
    params["dense"] = jax.tree_util.tree_map(jnp.zeros_like, params["dense"])
    xs = jax.random.normal(jax.random.key(2), (4, 6), jnp.float64)
    loads = jax.random.normal(jax.random.key(3), (7, 2), jnp.float64)
    mask = jnp.array([1.0, 1, 1, 1, 0, 0])
    expected = forward(params["highway"], arch.highway_arch, xs, dof_mask=mask, loads=loads)
    np.testing.assert_array_equal(forward(params, arch, xs, dof_mask=mask, loads=loads), expected)
    # the decoder's output adds to it, and only the recurrent part gets gradients
    params["dense"] = jax.tree_util.tree_map(lambda w: w + 0.1, params["dense"])
    assert not np.allclose(forward(params, arch, xs, loads=loads),
                           forward(params["highway"], arch.highway_arch, xs, loads=loads))
    grads = jax.grad(lambda p: jnp.sum(forward(p, arch, xs, loads=loads) ** 2))(params)
    assert all(not np.any(g) for g in jax.tree_util.tree_leaves(grads["highway"]))
    assert np.any(grads["dense"]["w"]) and np.any(grads["decoder"]["w_h"])


def test_padding_keeps_a_replica_alone():
    """A replica of 4 dofs padded to 6 predicts on its 4 dofs what it predicts alone."""
    small = _network(n_dof=4)
    params = init_params(jax.random.key(0), small)
    params["highway"] = _random_highway(small, jax.random.key(1))
    padded = pad_params(params, small, 6)
    wide = dataclasses.replace(small, n_dof=6)
    assert jax.tree_util.tree_structure(padded) == jax.tree_util.tree_structure(init_params(
        jax.random.key(0), wide))
    xs = jax.random.normal(jax.random.key(2), (4, 4), jnp.float64)
    loads = jax.random.normal(jax.random.key(3), (7, 2), jnp.float64)
    alone = forward(params, small, xs, loads=loads)
    within = forward(padded, wide, jnp.pad(xs, ((0, 0), (0, 2))), dof_mask=jnp.array([1.0, 1, 1, 1, 0, 0]),
                          loads=loads)
    np.testing.assert_allclose(within[:, :4], alone, rtol=1e-12, atol=1e-12)
    assert not np.any(within[:, 4:])
    back = unpad_params(padded, wide, 4)
    for a, b in zip(jax.tree_util.tree_leaves(back), jax.tree_util.tree_leaves(params)):
        np.testing.assert_array_equal(a, b)


def test_online_learning_refits_the_highway_by_least_squares():
    """An online update refits the highway on every window the run has synchronized (the
    learner's every_window; the linear model's refit, checked against numpy.linalg.lstsq on
    the real dofs) before the gradient steps, which get the refitted network and their own
    sample of windows."""
    arch = dataclasses.replace(_network(n_dof=3, n_load=1, rank=11), n_past=3, n_future=2)  # rank: 3 x 2 + 5 x 1
    rng = np.random.default_rng(0)
    x = rng.normal(size=(1, 40, 3, 3))
    y = np.einsum("pwtd,tdfe->pwfe", x, rng.normal(size=(3, 3, 2, 3))) + 0.1
    u = rng.normal(size=(1, 40, 5, 1))
    weight, mask = np.ones(40), np.array([[1.0, 1.0, 0.0]])
    x[..., 2], y[..., 2] = 0.0, 0.0  # the padded dof
    params = jax.tree_util.tree_map(lambda a: a[None], init_params(jax.random.key(0), arch))

    class Steps:  # the learner: every window for the refit; its gradient steps record what they get
        def every_window(self):
            return x, y, u, weight

        def gradient_steps(self, given, *args):
            self.given, self.args = given, args
            return given, 0

    steps = Steps()
    sample = (x[:, :4], y[:, :4], u[:, :4], weight[:4])  # the gradient update's windows
    updated, n = arch.online_update(steps, params, *sample, None, mask, 0.0)
    assert steps.args[0] is sample[0]
    assert updated is steps.given and n == 0
    one = jax.tree_util.tree_map(lambda a: a[0], updated["highway"])
    design = np.concatenate([x[0, :, :, :2].reshape(40, -1), u[0].reshape(40, -1), np.ones((40, 1))], axis=1)
    coeffs, *_ = np.linalg.lstsq(design, y[0, :, :, :2].reshape(40, -1), rcond=None)
    got = np.stack([np.asarray(forward(one, arch.highway_arch, x[0, w], loads=u[0, w]))[:, :2]
                    for w in range(40)])
    np.testing.assert_allclose(got.reshape(40, -1), design @ coeffs, rtol=0, atol=1e-6 * np.abs(y).max())
    for name in ("encoder", "decoder", "dense"):  # the recurrent part is the gradient steps' to change
        for a, b in zip(jax.tree_util.tree_leaves(updated[name]), jax.tree_util.tree_leaves(params[name])):
            np.testing.assert_array_equal(a, b)


def test_the_counted_cost_adds_the_highway_products_and_parameters():
    """prediction_cost of the network with a highway minus that of the same network
    without: the dot_generals the highway adds to forward's jaxpr, its 2 n_f n_dof
    additions (its bias and the sum with the decoder's output), and its parameters."""
    arch, n_s = _network(), 7
    plain = dataclasses.replace(arch, highway=False, highway_rank=0)
    params = {a: init_params(jax.random.key(0), a) for a in (arch, plain)}
    xs, loads = jnp.zeros((4, 6)), jnp.zeros((7, 2))
    dots = {a: dot_flops(jax.make_jaxpr(lambda p, a=a: forward(p, a, xs, loads=loads))(params[a]).jaxpr)
            for a in (arch, plain)}
    flops = {a: count_flops(a, n_s) for a in (arch, plain)}
    assert flops[arch]["matmul"] - flops[plain]["matmul"] == n_s * (dots[arch] - dots[plain]) > 0
    assert flops[arch]["bias"] - flops[plain]["bias"] == n_s * 2 * 3 * 6
    n_highway = sum(np.size(w) for w in params[arch]["highway"].values())
    cost = {a: a.prediction_cost(n_s) for a in (arch, plain)}
    assert cost[arch].bytes - cost[plain].bytes == 8 * n_highway


def test_bad_settings_are_refused():
    with pytest.raises(ConfigError, match="no linear highway.*model='lstm'"):
        ArchitectureChoice(model="linear", highway=True)
    with pytest.raises(ConfigError, match="highway_rank.*0 without a highway"):
        LSTMArchitecture(n_dof=3, highway_rank=2)
    with pytest.raises(ConfigError, match="highway must be True, False or None"):
        ArchitectureChoice(highway="yes")
    parser = argparse.ArgumentParser()
    add_train_parser(parser.add_subparsers(dest="command"))
    assert parser.parse_args(["train", "run.h5", "--highway"]).highway is True
    assert parser.parse_args(["train", "run.h5"]).highway is None  # the model's default
    assert parser.parse_args(["train", "run.h5", "--no-highway"]).highway is False
    assert ArchitectureChoice().lstm(4, 3, 2).highway and not ArchitectureChoice(highway=False).lstm(4, 3, 2).highway
    ArchitectureChoice(model="linear")  # the default does not apply to it


def _out_of_sample_error(surrogate, problem, reference):
    """RMS error of the autonomous rollout over the second half (never trained on),
    relative to the largest shared displacement."""
    width = max(p.shared_displacement.shape[1] for p in reference.parts)
    histories = np.stack([np.pad(p.shared_displacement, ((0, 0), (0, width - p.shared_displacement.shape[1])))
                          for p in reference.parts])
    rollout = rollout_errors(surrogate.for_problem(problem), histories, start=N_STEPS // 2 - 1)
    return float(np.sqrt(rollout.mse.mean()) / rollout.amplitude.max())


@pytest.fixture(scope="module")
def step_off():
    """A 5 x 1 x 1 cm cantilever (2 parts) whose load ramps on and is switched off at 70 %
    of the run (out of sample)."""
    base = jaxsync.cantilever(jaxsync.box_beam(5.0, 1.0, 1.0, (5, 1, 1)))
    problem = jaxsync.cantilever(base.mesh, t_ramp=0.15, t_off=0.7 * N_STEPS * float(base.dt))
    return problem, jaxsync.simulate(problem, N_STEPS, partitions=2)


def _train(reference, choice, epochs=60):
    return train_surrogates(reference, architecture=choice, sampling=SAMPLING, checks=UNCHECKED, progress=False,
                            optimizer=TrainConfig(n_epochs=epochs, n_candidates=1))


def test_the_network_with_a_highway_predicts_as_well_as_its_linear_model(step_off, tmp_path):
    """Trained on the first half of the step-off run (the network 10 epochs, one compiled
    call: the slow test trains 150), rolled out over the second half. Measured: the linear
    model (ARX) 0.634 %, the LSTM with a highway 0.636 % after 10 epochs (0.636 % after 60;
    the plain LSTM of the same size 35 %, the slow test); asserted: within 5 % of the linear
    model and below 2 %. The file keeps the highway."""
    problem, reference = step_off
    arx = _train(reference, ArchitectureChoice(model="linear"))
    network = _train(reference, ArchitectureChoice(n_hidden=16, n_layers=1, highway=True), epochs=10)
    arch = network.surrogate.arch
    assert arch.highway and arch.highway_rank == arx.surrogate.arch.rank
    errors = {name: _out_of_sample_error(t.surrogate, problem, reference)
              for name, t in (("linear", arx), ("highway", network))}
    assert errors["highway"] <= min(1.05 * errors["linear"], 0.02), errors
    network.write(tmp_path / "out")
    saved = load_surrogate(tmp_path / "out" / "surrogate.h5")
    assert saved.arch == arch
    assert _out_of_sample_error(Surrogate.from_saved(saved), problem, reference) == errors["highway"]


@pytest.mark.slow
@pytest.mark.parametrize("case", ["step-off", "pulsatile"])
def test_the_highway_turns_the_lstm_from_worse_to_as_good_as_the_linear_model(case, step_off):
    """The table of the surrogates guide: the linear model, the plain LSTM and the LSTM with
    a highway (n_H 16, one layer, 150 epochs) on the step-off and on a pulsatile load.
    Measured: step-off 0.62 %, 35 %, 0.62 %; pulsatile 0.51 %, 4.7 %, 0.51 %; asserted:
    the highway within 5 % of the linear model, the plain LSTM at least 5x worse."""
    if case == "step-off":
        problem, reference = step_off
    else:
        base = step_off[0]
        period = 0.12
        pulse = jaxsync.Periodic(times=[0.0, 0.2 * period, 0.35 * period, 0.6 * period], values=[0.0, 1.0, 0.3, 0.0],
                                 period=period)
        problem = dataclasses.replace(base, loads=(jaxsync.BodyForce((0.0, 0.0, -0.5), jaxsync.Ramp(0.05) * pulse),))
        reference = jaxsync.simulate(problem, N_STEPS, partitions=2)
    errors = {}
    for name, choice in (("linear", ArchitectureChoice(model="linear")),
                         ("plain", ArchitectureChoice(n_hidden=16, n_layers=1, highway=False)),
                         ("highway", ArchitectureChoice(n_hidden=16, n_layers=1, highway=True))):
        errors[name] = _out_of_sample_error(_train(reference, choice, epochs=150).surrogate, problem, reference)
    assert errors["highway"] <= 1.05 * errors["linear"], errors
    assert errors["plain"] >= 5 * errors["highway"], errors
