"""The surrogate-model protocol (jaxsync.surrogate.models.SurrogateArchitecture): models defined outside the
package -- the MLP of the guide docs/guides/extending-surrogates.md (its code block is
executed here) and a ridge-regularised linear model fitted in closed form, defined below --
are trained through the public entry point, saved and loaded, named on the command line,
run by the synchronization-avoiding solver and updated by online learning."""

import dataclasses
import json
import pathlib
import re
import sys
import types
import warnings
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsync
from jaxpr_counts import dot_flops
from jaxsync.cli import main
from jaxsync.errors import CheckpointError, ConfigError
from jaxsync.perf.roofline import surrogate_costs
from jaxsync.solve import ResyncTolerance, simulate_sync_avoiding
from jaxsync.surrogate import (
    ArchitectureChoice,
    FitSettings,
    LeastSquaresFitted,
    OnlineLearning,
    Sampling,
    Surrogate,
    TrainConfig,
    TrainingChecks,
    TrainResult,
    build_dataset,
    load_surrogate,
    register_surrogate,
    stack_replicas,
    surrogate_class,
    surrogate_kinds,
    train_surrogates,
    unregister_surrogate,
)
from jaxsync.surrogate.training import OnlineLearner

GUIDE = pathlib.Path(__file__).resolve().parents[2] / "docs" / "guides" / "extending-surrogates.md"
N_STEPS = 4000
N_S, N_P, N_F = 20, 10, 10
SAMPLING = Sampling(n_s=N_S, n_past=N_P, n_future=N_F)


def _guide_module():
    """The guide's first Python code block, executed as a module (it registers "mlp")."""
    blocks = re.findall(r"```python\n(.*?)```", GUIDE.read_text(), flags=re.S)
    assert blocks and "class WindowMLP" in blocks[0]
    module = types.ModuleType("extending_surrogates_guide")
    sys.modules[module.__name__] = module  # dataclasses look their module up
    exec(compile(blocks[0], str(GUIDE), "exec"), module.__dict__)
    return module


# ----------------------------------------------------------------------------- closed form


@dataclasses.dataclass(frozen=True)
class RidgeSettings:
    ridge: float

    def to_dict(self):
        return {"model": "ridge-test", "method": "ridge", "ridge": self.ridge}


@jax.tree_util.register_static
@dataclasses.dataclass(frozen=True)
class RidgeARX(LeastSquaresFitted):
    """y = [vec(x), vec(u)] W + b, fitted by ridge regression (bias not penalised), per
    part on its real dofs, by an augmented least-squares solve."""

    kind: ClassVar[str] = "ridge-test"

    n_dof: int
    n_past: int = 20
    n_future: int = 20
    n_load: int = 0
    dtype: str = "float64"
    ridge: float = 1e-3

    @property
    def n_inputs(self):
        return self.n_past * self.n_dof + (self.n_past + self.n_future) * self.n_load

    def init(self, key):
        return {"w": jnp.zeros((self.n_inputs, self.n_future * self.n_dof), self.dtype),
                "b": jnp.zeros(self.n_future * self.n_dof, self.dtype)}

    def forward(self, params, xs, load_parameter=None, dof_mask=None, compute_dtype=None, loads=None):
        z = xs.reshape(-1) if loads is None else jnp.concatenate([xs.reshape(-1), loads.reshape(-1)])
        ys = (z.astype(self.dtype) @ params["w"] + params["b"]).reshape(self.n_future, self.n_dof)
        return ys if dof_mask is None else ys * dof_mask.astype(ys.dtype)[None]

    def _solve(self, x, y, signals, weight, counts):
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        params = {"w": np.zeros((len(counts), self.n_inputs, self.n_future * self.n_dof)),
                  "b": np.zeros((len(counts), self.n_future * self.n_dof))}
        root = np.sqrt(np.asarray(weight, np.float64))[:, None]
        n_w = x.shape[1]
        for p, c in enumerate(counts):
            inputs = x[p][:, :, :c].reshape(n_w, -1)
            if signals is not None:
                inputs = np.concatenate([inputs, np.asarray(signals[p], np.float64).reshape(n_w, -1)], axis=1)
            n_in = inputs.shape[1]
            design = np.concatenate([root * np.concatenate([inputs, np.ones((n_w, 1))], axis=1),
                                     np.sqrt(self.ridge) * np.eye(n_in, n_in + 1)])
            rhs = np.concatenate([root * y[p][:, :, :c].reshape(n_w, -1), np.zeros((n_in, self.n_future * c))])
            coef = np.linalg.lstsq(design, rhs, rcond=None)[0]
            # rows: input (t, d) at t n_dof + d (d < c), then the loads; columns: output (j, d) at j n_dof + d
            rows = np.concatenate([(np.arange(self.n_past)[:, None] * self.n_dof + np.arange(c)).ravel(),
                                   self.n_past * self.n_dof + np.arange(n_in - self.n_past * c)])
            cols = (np.arange(self.n_future)[:, None] * self.n_dof + np.arange(c)).ravel()
            params["w"][p][np.ix_(rows, cols)] = coef[:n_in]
            params["b"][p][cols] = coef[n_in]
        return {k: v.astype(self.dtype) for k, v in params.items()}

    def fit(self, data, settings):
        n_w = data.x_train.shape[1]
        params = self._solve(data.x_train, data.y_train, data.signal_train, np.ones(n_w), data.dof_counts)

        def losses(x, y, u):
            if x.shape[1] == 0:
                return np.full(data.n_parts, np.nan)
            ones = jnp.ones(x.shape[1], self.dtype)
            q = jnp.zeros(x.shape[:2], self.dtype)
            u = jnp.zeros(x.shape[:2] + (0,)) if u is None else jnp.asarray(u, self.dtype)
            return np.asarray(jax.vmap(self.loss, in_axes=(0, 0, 0, 0, None, 0, 0))(
                params, jnp.asarray(x, self.dtype), jnp.asarray(y, self.dtype), q, ones,
                jnp.asarray(data.dof_mask, self.dtype), u))

        val = losses(data.x_val, data.y_val, data.signal_val)
        return TrainResult(params=params, arch=self, config=RidgeSettings(self.ridge),
                           dof_counts=tuple(int(c) for c in data.dof_counts), mean=np.asarray(data.mean),
                           std=np.asarray(data.std),
                           train_loss=losses(data.x_train, data.y_train, data.signal_train)[None],
                           val_loss=val[None], initial_val_loss=val, seconds_per_epoch=0.0,
                           compile_seconds=0.0, steps_per_epoch=0, signal_scale=data.signal_scale,
                           load_inputs=data.load_inputs)

    def refit(self, params, x, y, signals, weight, dof_mask):
        counts = [int(c) for c in np.asarray(dof_mask).sum(axis=1)]
        return self._solve(x, y, signals, weight, counts)


# ----------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module", autouse=True)
def models():
    """The guide's MLP ("mlp", registered by the guide's code) and RidgeARX
    ("ridge-test"), registered for this module's tests only: other tests see the
    built-in kinds alone."""
    guide = _guide_module()
    register_surrogate(RidgeARX)
    yield guide.WindowMLP
    unregister_surrogate("mlp")
    unregister_surrogate("ridge-test")
    del sys.modules[guide.__name__]


@pytest.fixture(scope="module")
def problem():
    return jaxsync.cantilever()


@pytest.fixture(scope="module")
def partition(problem):
    return jaxsync.partition(problem.mesh, 2)


@pytest.fixture(scope="module")
def reference(problem, partition):
    return jaxsync.simulate(problem, N_STEPS, partitions=partition)


def _train(reference, model, **choice):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the offline rollout check of a brief training
        return train_surrogates(reference, architecture=ArchitectureChoice(model=model, **choice), sampling=SAMPLING,
                                optimizer=TrainConfig(n_epochs=150, eta0=3e-3, gamma=0.99, n_candidates=1),
                                checks=TrainingChecks(emse_applications=0, rollout_tolerance=None), progress=False)


@pytest.fixture(scope="module")
def mlp(reference):
    return _train(reference, "mlp", n_hidden=16)


@pytest.fixture(scope="module")
def ridge(reference):
    return _train(reference, "ridge-test", dtype="float64")


def _refill_rms(surrogate, reference, first, last, persistence=False):
    """RMS error [cm] of one refill per window at steps first .. last against the
    synchronized run, all parts (``persistence``: the last known value held instead)."""
    errors = []
    for c in range(first, last - N_S * N_F, N_S * N_F):
        for p in range(surrogate.n_parts):
            hist = reference.parts[p].shared_displacement
            truth = hist[c + 1:c + 1 + N_S * N_F]
            if persistence:
                pred = np.broadcast_to(hist[c], truth.shape)
            else:
                buffer = np.zeros((N_S * N_P, surrogate.n_dof))
                buffer[:, :hist.shape[1]] = hist[c - N_S * N_P + 1:c + 1]
                pred = np.asarray(surrogate.part(p).predict(buffer, c))[:, :hist.shape[1]]
            errors.append(pred - truth)
    return float(np.sqrt(np.mean(np.square(errors))))


# ----------------------------------------------------------------------------- tests


def test_the_registry_names_the_models_and_refuses_what_is_not_one(models):
    WindowMLP = models
    assert surrogate_kinds()[:2] == ("lstm", "linear") and {"mlp", "ridge-test"} <= set(surrogate_kinds())
    assert surrogate_class("mlp") is WindowMLP and surrogate_class("ridge-test") is RidgeARX
    # the model's own rule for windows across a load jump (the protocol's default: keep them)
    assert Sampling().for_model("ridge-test").load_jump_windows == "keep"
    assert Sampling().for_model(type("ExcludingRidge", (RidgeARX,), {"load_jump_windows": "exclude"})
                                ).load_jump_windows == "exclude"
    with pytest.raises(ConfigError, match="model must be one of 'lstm', 'linear'.*'mlp'.*got 'gru'"):
        ArchitectureChoice(model="gru")
    with pytest.raises(ConfigError, match="SurrogateArchitecture"):
        register_surrogate(type("NotAModel", (), {"kind": "nothing"}))

    @dataclasses.dataclass(frozen=True)
    class Other(WindowMLP):
        pass

    with pytest.raises(ConfigError, match="'mlp' is registered to"):
        register_surrogate(Other)
    with pytest.raises(ConfigError, match="built in"):
        register_surrogate(type("FakeLSTM", (WindowMLP,), {"kind": "lstm"}))
    # a conditional choice for a model that reads no load parameter is refused before any data are read
    with pytest.raises(ConfigError, match="mlp surrogate is unconditional"):
        ArchitectureChoice(model="mlp", n_cond_repeat=2)


def test_the_closed_form_fit_is_the_ridge_solution_of_numpy():
    """The model's fit on padded replica windows equals the ridge normal equations solved
    by NumPy on each part's real dofs (bias not penalised)."""
    rng = np.random.default_rng(0)
    t = np.arange(300)[:, None]
    runs = [np.sin(0.05 * t * (1 + np.arange(w))) + 0.01 * rng.normal(size=(300, w)) for w in (4, 6)]
    datasets = [build_dataset([run], 2, 5, 3, train_fraction=0.8) for run in runs]
    data = stack_replicas(datasets)
    arch = RidgeARX(n_dof=6, n_past=5, n_future=3, ridge=0.1)
    result = arch.fit(data, FitSettings(architecture=ArchitectureChoice(), optimizer=None, key=None))
    for p, d in enumerate(datasets):
        c = runs[p].shape[1]
        x = np.asarray(d.x_train, np.float64).reshape(len(d.x_train), -1)
        y = np.asarray(d.y_train, np.float64).reshape(len(d.y_train), -1)
        a = np.concatenate([x, np.ones((len(x), 1))], axis=1)
        penalty = 0.1 * np.diag(np.r_[np.ones(x.shape[1]), 0.0])
        coef = np.linalg.solve(a.T @ a + penalty, a.T @ y)
        w = result.params["w"][p].reshape(5, 6, 3, 6)[:, :c, :, :c].reshape(5 * c, 3 * c)
        np.testing.assert_allclose(w, coef[:-1], rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(result.params["b"][p].reshape(3, 6)[:, :c].ravel(), coef[-1], rtol=1e-8,
                                   atol=1e-10)
        # nothing on padding
        assert not np.any(result.params["w"][p].reshape(5, 6, 3, 6)[:, c:]) and not np.any(
            result.params["b"][p].reshape(3, 6)[:, c:])
    # the loss of the fit is the MSE of its predictions, computed by NumPy
    pred = np.einsum("pwi,pio->pwo", np.asarray(data.x_train, np.float64).reshape(2, len(data.x_train[0]), -1),
                     result.params["w"]) + result.params["b"][:, None]
    sq = (pred.reshape(data.y_train.shape) - data.y_train) ** 2 * data.dof_mask[:, None, None]
    np.testing.assert_allclose(result.train_loss[0], sq.sum(axis=(1, 2, 3)) / (sq.shape[1] * 3 * data.dof_mask.sum(1)),
                               rtol=1e-6)


def test_the_gradient_model_trains_below_persistence_and_round_trips(models, mlp, reference, problem, tmp_path):
    """The MLP trained through train_surrogates predicts a refill with less than half the
    RMS error of holding the last value; its file names the model and loads back equal."""
    assert isinstance(mlp.result.arch, models) and mlp.model == "mlp" and mlp.result.arch.n_hidden == 16
    assert mlp.result.arch.n_load == mlp.surrogate.n_load > 0  # the cantilever records its load signals
    assert mlp.result.n_epochs_run > 1 and mlp.summary()["training"]["n_epochs_run"] == mlp.result.n_epochs_run
    surrogate = mlp.surrogate.for_problem(problem)
    trained_rms = _refill_rms(surrogate, reference, N_S * N_P, N_STEPS // 2)
    persistence_rms = _refill_rms(surrogate, reference, N_S * N_P, N_STEPS // 2, persistence=True)
    assert trained_rms < 0.5 * persistence_rms, (trained_rms, persistence_rms)

    written = mlp.write(tmp_path)
    saved = load_surrogate(written.files["surrogate"])
    assert saved.arch == mlp.result.arch and json.loads(
        json.dumps(saved.metadata))["model"] == "mlp"
    jax.tree_util.tree_map(np.testing.assert_array_equal, saved.params, mlp.result.params)
    loaded = Surrogate.load(written.files["surrogate"]).for_problem(problem)
    buffer = reference.parts[0].shared_displacement[:N_S * N_P]
    np.testing.assert_array_equal(loaded.part(0).predict(np.pad(buffer, ((0, 0), (0, loaded.n_dof - buffer.shape[1]))),
                                                         N_S * N_P - 1),
                                  surrogate.part(0).predict(np.pad(buffer, ((0, 0), (0, loaded.n_dof
                                                                                      - buffer.shape[1]))),
                                                            N_S * N_P - 1))
    # the roofline reads the model's own count
    cost = surrogate_costs(saved.arch, N_S)
    assert (cost.bytes, cost.flops) == tuple(saved.arch.prediction_cost(N_S))


def test_online_learning_takes_gradient_steps_or_refits(mlp, ridge, reference, problem):
    """The gradient-fitted model learns by Adam steps (as many as asked), the closed-form
    one by one refit; both lower the loss on the new windows."""
    rows = [p.shared_displacement[2400:3200] for p in reference.parts]
    for trained, iterations in ((mlp, 15), (ridge, 1)):
        learner = OnlineLearner(OnlineLearning(iterations=15, iterations_per_call=5, replay=0),
                                trained.surrogate.for_problem(problem))
        learner.add_stretch(rows, 2400)
        learner.update(3199)
        report = learner.reports[-1]
        assert report.iterations == iterations
        assert np.all(report.loss_after <= report.loss_before) and np.any(report.loss_after < report.loss_before)


def test_a_synchronization_avoiding_run_learns_with_the_user_model(mlp, reference, problem, partition, tmp_path):
    """The saved MLP drives a synchronization-avoiding run under error control (3e-3 cm,
    about 3 % of the amplitude) with learning: the run predicts steps, every rejected cycle
    is followed by an update by gradient steps, and the run stays within its tolerance of
    the synchronized run."""
    path = tmp_path / "mlp.h5"
    mlp.surrogate.save(path, shared_nodes=mlp.shared_nodes)
    tol = 3e-3
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        traj = simulate_sync_avoiding(
            problem, N_STEPS, partitions=partition, surrogates=load_surrogate(path), n_cri=2000,
            resync_tolerance=ResyncTolerance(absolute=tol, learning=OnlineLearning(iterations=20, budget_seconds=30)))
    st = traj.stats
    assert st.n_predicted_steps > 0 and st.n_resynchronizations >= 1
    assert len(st.surrogate_updated_at) == st.n_resynchronizations and st.seconds_updating > 0
    assert np.linalg.norm(traj.displacement - reference.displacement, axis=2).max() <= 1.2 * tol


def test_the_closed_form_model_trains_saves_and_loads(ridge, problem, tmp_path):
    assert isinstance(ridge.result.arch, RidgeARX) and ridge.result.steps_per_epoch == 0 and ridge.candidates is None
    assert ridge.summary()["training"]["method"] == "ridge" and ridge.summary()["n_epochs_run"] is None
    saved = load_surrogate(ridge.write(tmp_path).files["surrogate"])
    assert saved.arch == ridge.result.arch
    jax.tree_util.tree_map(np.testing.assert_array_equal, saved.params, ridge.result.params)


def test_the_command_line_trains_a_registered_model(models, reference, tmp_path, capsys):
    path = tmp_path / "run.h5"
    reference.save(path)
    out = tmp_path / "out"
    assert main(["train", str(path), "-o", str(out), "--model", "mlp", "--n-hidden", "8", "--n-s", str(N_S),
                 "--n-past", str(N_P), "--n-future", str(N_F), "--epochs", "3", "--candidates", "1",
                 "--emse-applications", "0", "--rollout-tolerance", "0", "--no-progress"]) == 0
    assert "3 epochs" in capsys.readouterr().out
    saved = load_surrogate(out / "surrogate.h5")
    assert saved.arch == models(n_dof=saved.arch.n_dof, n_past=N_P, n_future=N_F, n_load=saved.arch.n_load,
                                   n_hidden=8)
    assert json.loads((out / "train_summary.json").read_text())["architecture"]["kind"] == "mlp"


def test_a_file_of_an_unregistered_model_names_the_fix(ridge, tmp_path):
    path = tmp_path / "ridge.h5"
    ridge.surrogate.save(path)
    unregister_surrogate("ridge-test")
    try:
        with pytest.raises(CheckpointError, match="got 'ridge-test'.*register its model"):
            load_surrogate(path)
        with pytest.raises(ConfigError, match="built in"):
            unregister_surrogate("lstm")
    finally:
        register_surrogate(RidgeARX)
    assert load_surrogate(path).arch == ridge.result.arch


@pytest.mark.parametrize("name", ["linear", "mlp"])
def test_the_counted_cost_is_that_of_the_arrays_and_products(models, name):
    """prediction_cost against the model itself: the parameter bytes are those of the
    arrays init makes (each read once per prediction), the matrix-product flops those of
    the dot_generals in forward's jaxpr; the rest is the elementwise work the count names
    (biases, tanh and the persistence skip of the MLP) and the normalization 2 D (n_p + n_f)."""
    from jaxsync.surrogate import LinearArchitecture

    d, t, f, n_load, n_s = 5, 4, 3, 2, 7
    arch = (LinearArchitecture(n_dof=d, rank=6, n_past=t, n_future=f, n_load=n_load, dtype="float64")
            if name == "linear" else models(n_dof=d, n_past=t, n_future=f, n_load=n_load, n_hidden=9,
                                            dtype="float64"))
    params = arch.init(jax.random.key(0))
    n_params = sum(np.size(leaf) for leaf in jax.tree_util.tree_leaves(params))
    cost = arch.prediction_cost(n_s, masked=False, io_bytes_per_value=0)
    assert cost.bytes == 8 * n_params
    jaxpr = jax.make_jaxpr(lambda p, x, u: arch.forward(p, x, loads=u))(
        params, jnp.zeros((t, d)), jnp.zeros((t + f, n_load))).jaxpr
    elementwise = f * d if name == "linear" else 2 * 9 + 2 * f * d  # bias; b1, tanh, b2 and the skip
    assert cost.flops == n_s * (dot_flops(jaxpr) + elementwise + 2 * d * (t + f))
    masked = arch.prediction_cost(n_s, masked=True, io_bytes_per_value=8)
    assert masked.flops == cost.flops + n_s * f * d  # the mask
    assert masked.bytes == cost.bytes + 8 * (n_s * t * d + 2 * d + n_s * f * d + d)  # buffer, mean, std, output, mask


def test_untrained_replicas_of_a_registered_model(models, partition):
    """Surrogate.initialized makes any registered model: the guide's untrained MLP (zero
    output layer) is the persistence predictor, every predicted snapshot the last input
    one (zero on padding); a rank is refused for a model without one."""
    surrogate = Surrogate.initialized(partition, 3, model="mlp", n_hidden=4, n_past=4, n_future=2)
    assert isinstance(surrogate.arch, models) and surrogate.arch.n_hidden == 4
    mask = np.asarray(surrogate.dof_mask[1])
    xs = np.random.default_rng(0).normal(size=(4, surrogate.n_dof))
    params = jax.tree_util.tree_map(lambda a: a[1], surrogate.params)
    predicted = np.asarray(surrogate.arch.forward(params, jnp.asarray(xs, jnp.float32), dof_mask=jnp.asarray(mask)))
    np.testing.assert_allclose(predicted, np.broadcast_to(xs[-1] * mask, (2, surrogate.n_dof)), rtol=1e-6)
    with pytest.raises(ConfigError, match="leave rank out"):
        Surrogate.initialized(partition, 3, model="mlp", rank=2)
