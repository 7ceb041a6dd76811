"""Reduced-precision (bfloat16) surrogate inference (issue 14): float32 accumulation, close
to float32 within the stated bound, refused or flagged above it, run by the online solver."""

import dataclasses
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsync
from jaxsync.errors import ConfigError, InferencePrecisionError
from jaxsync.solve.coupling import simulate_sync_avoiding
from jaxsync.surrogate import (
    DEFAULT_BOUND,
    LinearArchitecture,
    LSTMArchitecture,
    ReducedPrecisionWarning,
    SavedSurrogate,
    Surrogate,
    TrainConfig,
    build_dataset,
    check_inference_precision,
    inference_deviation,
    reduced_precision,
    stack_replicas,
    surrogate_windows,
    train_replicas,
)
from jaxsync.surrogate.models import forward, init_replicas

N_P, N_F = 4, 3


def _lstm_surrogate(dtype="float32"):
    """Two initialized replicas (2 and 3 real dofs, width 3), a non-trivial normalization."""
    arch = LSTMArchitecture(n_dof=3, n_hidden=16, n_layers=2, n_past=N_P, n_future=N_F, dtype=dtype)
    params = jax.tree_util.tree_map(np.asarray, init_replicas(jax.random.key(4), arch, (2, 3)))
    return Surrogate(params=params, mean=np.array([[0.1, -0.2, 0.0], [0.0, 0.3, -0.1]]),
                     std=np.array([[0.5, 0.7, 1.0], [0.8, 0.6, 0.4]]),
                     dof_mask=np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 1.0]]), load_parameter=np.float32([0.0, 0.0]),
                     arch=arch, n_s=2)


def _histories(n_steps=200):
    t = np.arange(n_steps)[:, None] * 0.05
    return [np.cos(2 * np.pi * np.array([[0.3, 0.7]]) * t) * 0.5 + 0.1,
            np.sin(2 * np.pi * np.array([[0.2, 0.5, 0.4]]) * t) * 0.6]


def test_bfloat16_products_accumulate_in_float32():
    """Every matrix product of the bfloat16 forward takes bfloat16 operands and returns
    float32 (dot_general with preferred_element_type float32); the float32 forward has no
    bfloat16 at all, and both return the architecture's dtype."""
    s = _lstm_surrogate()
    params = jax.tree_util.tree_map(lambda x: x[0], s.params)
    x = jnp.ones((N_P, 3), jnp.float32)
    low = jax.make_jaxpr(lambda p, w: forward(p, s.arch, w, compute_dtype="bfloat16"))(params, x)
    full = jax.make_jaxpr(lambda p, w: forward(p, s.arch, w))(params, x)

    def dots(jaxpr):
        """(operand dtypes, result dtype) of every dot_general, nested jaxprs included."""
        found = []
        for eqn in jaxpr.eqns:
            if eqn.primitive.name == "dot_general":
                found.append(([v.aval.dtype for v in eqn.invars], eqn.outvars[0].aval.dtype))
            for value in eqn.params.values():
                for inner in value if isinstance(value, (list, tuple)) else [value]:
                    inner = getattr(inner, "jaxpr", inner)
                    if hasattr(inner, "eqns"):
                        found += dots(inner)
        return found

    low_dots, full_dots = dots(low.jaxpr), dots(full.jaxpr)
    assert len(low_dots) >= 5 and len(low_dots) == len(full_dots)
    for operands, out in low_dots:
        assert operands == [jnp.bfloat16, jnp.bfloat16] and out == jnp.float32
    assert all(jnp.bfloat16 not in operands for operands, _ in full_dots)
    assert forward(params, s.arch, x, compute_dtype="bfloat16").dtype == jnp.float32


# the default run checks the float32 network; a float64 one goes through the same rounding
# (lstm._reduced, the bfloat16 products) and is the slow case
@pytest.mark.parametrize("dtype", ["float32", pytest.param("float64", marks=pytest.mark.slow)])
def test_bfloat16_predictions_are_close_to_full_precision_within_the_bound(dtype):
    """On an initialized LSTM (well conditioned, as trained ones are: the cantilever's
    measure 0.1 %) the bfloat16 forward moves the predictions by a few bfloat16
    roundings, above float32 round-off and below the stated bound; Surrogate.predict and
    rollout with inference_dtype agree with the float32 ones within the same bound,
    relative to the predicted signal."""
    s = _lstm_surrogate(dtype)
    windows = surrogate_windows(s, _histories())
    assert windows.shape == (2, 100 - N_P, N_P, 3)
    report = check_inference_precision(s, windows)
    assert report.passed and report.bound == DEFAULT_BOUND
    assert np.all(report.deviation > 1e-5) and report.worst < DEFAULT_BOUND
    assert report.to_dict()["passed"] is True and len(report.to_dict()["deviation"]) == 2

    low, again = reduced_precision(s, windows)
    assert low.inference_dtype == "bfloat16" and s.inference_dtype is None
    np.testing.assert_array_equal(again.deviation, report.deviation)
    history = np.pad(_histories()[1], ((0, 0), (0, 0)))
    buffer = history[-s.history_steps:]
    full_pred = np.asarray(s.part(1).predict(buffer, 199))
    low_pred = np.asarray(low.part(1).predict(buffer, 199))
    assert low_pred.dtype == full_pred.dtype == np.float64  # the dtype of the normalization
    signal = np.sqrt(np.mean(np.square(full_pred - s.mean[1])))
    assert 0 < np.sqrt(np.mean(np.square(low_pred - full_pred))) <= DEFAULT_BOUND * signal
    roll_full = np.asarray(s.part(1).rollout(buffer, 199, 2))
    roll_low = np.asarray(low.part(1).rollout(buffer, 199, 2))
    assert np.sqrt(np.mean(np.square(roll_low - roll_full))) <= DEFAULT_BOUND * signal


def _cancelling_linear_surrogate(gain=200.0):
    """One linear replica per part that predicts gain * (x[-1] - x[-2]) + x[-1] for each
    dof: an extrapolation from the difference of two nearly equal snapshots, which
    rounding to bfloat16 (2^-9 relative) destroys once gain * 2^-9 is not small."""
    n_dof, rank = 2, 2
    arch = LinearArchitecture(n_dof=n_dof, rank=rank, n_past=N_P, n_future=1)
    w_in = np.zeros((N_P, n_dof, rank))
    w_in[-1, :, :] = np.eye(n_dof)
    w_out_last = np.eye(n_dof)[:, None, :] * (1.0 + gain)
    w_in2 = np.zeros((N_P, n_dof, rank))
    w_in2[-2, :, :] = np.eye(n_dof)
    # the factored map W = w_in w_out must carry both snapshots: rank 2 n_dof
    arch = dataclasses.replace(arch, rank=2 * n_dof)
    w_in = np.concatenate([w_in, w_in2], axis=2)
    w_out = np.concatenate([w_out_last, -gain * np.eye(n_dof)[:, None, :]], axis=0)
    params = {"w_in": np.stack([w_in] * 2).astype(np.float32), "w_out": np.stack([w_out] * 2).astype(np.float32),
              "b": np.zeros((2, 1, n_dof), np.float32)}
    return Surrogate(params=params, mean=np.zeros((2, n_dof)), std=np.ones((2, n_dof)), dof_mask=np.ones((2, n_dof)),
                     load_parameter=np.float32([0.0, 0.0]), arch=arch, n_s=1)


def test_a_network_that_amplifies_rounding_is_refused_or_flagged():
    """A smooth signal near 1 (snapshot differences ~1e-3, bfloat16 spacing 2^-7 there)
    through a map with gain 200 on those differences: the bfloat16 deviation is tens of %,
    far above the bound. Refused by default, flagged (ReducedPrecisionWarning, failed
    report) on request; the full-precision network is untouched either way."""
    s = _cancelling_linear_surrogate()
    t = np.arange(80)[:, None] * 0.01
    histories = [1.0 + 0.05 * np.sin(t * np.array([[1.0, 1.3]])), 1.0 + 0.05 * np.cos(t * np.array([[0.7, 1.1]]))]
    windows = surrogate_windows(s, histories)
    relative, max_abs = inference_deviation(s, windows)
    assert np.all(relative > 10 * DEFAULT_BOUND) and np.all(max_abs > 0.01)
    with pytest.raises(InferencePrecisionError, match="above the bound 1 %"):
        check_inference_precision(s, windows)
    with pytest.raises(InferencePrecisionError):
        reduced_precision(s, windows)
    with pytest.warns(ReducedPrecisionWarning, match="bfloat16 inference deviates"):
        report = check_inference_precision(s, windows, on_excess="warn")
    assert not report.passed and report.worst > 10 * DEFAULT_BOUND
    # with no gain the same map is an identity on x[-1]: well within the bound
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert check_inference_precision(_cancelling_linear_surrogate(gain=0.0), windows).passed


def test_bad_arguments_are_refused():
    s = _lstm_surrogate()
    windows = surrogate_windows(s, _histories())
    with pytest.raises(ConfigError, match="bfloat16"):
        s.with_inference_dtype("float16")
    with pytest.raises(ConfigError, match="bfloat16"):
        check_inference_precision(s, windows, dtype="float16")
    with pytest.raises(ConfigError, match="on_excess"):
        check_inference_precision(s, windows, on_excess="ignore")
    with pytest.raises(ConfigError, match="bound"):
        check_inference_precision(s, windows, bound=0.0)
    with pytest.raises(ConfigError, match="windows must be"):
        check_inference_precision(s, windows[:1])
    assert s.with_inference_dtype(None) == s


def test_the_online_solver_runs_with_bfloat16_inference():
    """tests/solve/test_syncavoid.py's sizes and tiny trained replicas: the bfloat16 surrogate
    drives simulate_sync_avoiding unchanged; its shared values are its own offline rollout
    (as for any surrogate), and the run stays within a few bfloat16 roundings' worth of
    the float32 online run (1 % of the amplitude), while differing from it."""
    n_s, n_p, n_f, n_cri, n_steps = 5, 4, 4, 40, 400
    problem = jaxsync.cantilever()
    partition = jaxsync.partition(problem.mesh, 2)
    reference = jaxsync.simulate(problem, n_steps, partitions=partition)
    data = stack_replicas([build_dataset([part.shared_displacement], n_s, n_p, n_f, train_fraction=1.0)
                           for part in reference.parts])
    arch = LSTMArchitecture(n_dof=data.n_dof_max, n_hidden=8, n_layers=1, n_past=n_p, n_future=n_f)
    result = train_replicas(data, arch, TrainConfig(n_epochs=3), jax.random.key(0), progress=False)
    ckpt = SavedSurrogate.from_result(result, n_s, [p.shared_nodes for p in partition.parts])
    full = Surrogate.from_saved(ckpt)
    windows = surrogate_windows(full, [p.shared_displacement for p in reference.parts])
    low, report = reduced_precision(full, windows)
    assert report.passed
    online = simulate_sync_avoiding(problem, n_steps, partitions=partition, surrogates=low, n_cri=n_cri)
    online_full = simulate_sync_avoiding(problem, n_steps, partitions=partition, surrogates=full, n_cri=n_cri)
    assert np.all(np.isfinite(online.displacement))
    np.testing.assert_array_equal(online.displacement[:n_cri + 1], reference.displacement[:n_cri + 1])
    amplitude = np.abs(reference.displacement).max()
    difference = np.abs(online.displacement - online_full.displacement).max()
    assert 0 < difference <= 0.01 * amplitude
    n_cycles = -(-(n_steps - n_cri) // (n_s * n_f))
    for p, part in enumerate(reference.parts):
        count = part.shared_displacement.shape[1]
        history = np.pad(part.shared_displacement, ((0, 0), (0, low.n_dof - count)))
        rollout = np.asarray(low.part(p).rollout(history[n_cri + 1 - n_s * n_p:n_cri + 1], n_cri, n_cycles))
        predicted = online.parts[p].predicted_shared_displacement
        assert np.abs(predicted - rollout[:n_steps - n_cri, :count]).max() <= 1e-6 * amplitude
