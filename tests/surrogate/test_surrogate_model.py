"""The Surrogate pytree: one refill and rollouts against a step-by-step reference on the
refill index sets, construction, and its checkpoint round trip."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsync
from jaxsync.errors import CheckpointError, ConfigError
from jaxsync.surrogate import (
    LSTMArchitecture,
    SavedSurrogate,
    Surrogate,
    load_surrogate,
    refill_cycle,
    refill_index_sets,
    refill_rollout,
)
from jaxsync.surrogate.models import forward, init_replicas, replica_params
from jaxsync.surrogate.training import shared_dof_layout

N_S, N_P, N_F = 3, 4, 2


def _surrogate(q=0, dtype="float32", smooth=False):
    """Two replicas (2 and 3 real dofs, width 3) with a non-trivial normalization; the
    raw refill of the paper unless ``smooth``."""
    arch = LSTMArchitecture(n_dof=3, n_hidden=5, n_layers=1, n_past=N_P, n_future=N_F, n_cond_repeat=q,
                            dtype=dtype)
    params = jax.tree_util.tree_map(np.asarray, init_replicas(jax.random.key(9), arch, (2, 3)))
    mean = np.array([[0.1, -0.2, 0.0], [0.0, 0.3, -0.1]])
    std = np.array([[0.5, 0.7, 1.0], [0.8, 0.6, 0.4]])
    mask = np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 1.0]])
    return Surrogate(params=params, mean=mean, std=std, dof_mask=mask, load_parameter=np.float32([0.4, 0.4]),
                     arch=arch, n_s=N_S, smooth=smooth)


def _smoothed(raw, last, n_s):
    """The smooth refill, written independently: block means of n_s rows placed at the
    block centres (step offsets j n_s + (n_s + 1) / 2 after the known step), np.interp
    from the known value through them, the line through the last two continued after."""
    n_f = len(raw) // n_s
    t = np.arange(1, len(raw) + 1, dtype=float)
    knots_t = np.r_[0.0, n_s * np.arange(n_f) + (n_s + 1) / 2]
    knots_v = np.vstack([last, raw.reshape(n_f, n_s, -1).mean(axis=1)])
    out = np.empty_like(raw)
    for d in range(raw.shape[1]):
        out[:, d] = np.interp(t, knots_t, knots_v[:, d])
        slope = (knots_v[-1, d] - knots_v[-2, d]) / (knots_t[-1] - knots_t[-2])
        after = t > knots_t[-1]
        out[after, d] = knots_v[-1, d] + slope * (t[after] - knots_t[-1])
    return out


def _history(n_steps=60):
    t = np.arange(n_steps)[:, None] * 0.05
    part0 = np.cos(2 * np.pi * np.array([[1.0, 2.0]]) * t)
    part1 = np.sin(2 * np.pi * np.array([[0.5, 1.5, 1.0]]) * t)
    return np.stack([np.pad(part0, ((0, 0), (0, 1))), part1])


def _reference(surrogate, part, series, n, n_cycles):
    """Predictions of steps n + 1 .. by applying the network once per refill index set
    (paper Algorithm 3) in a Python loop, in float64 around the network, smoothed with
    :func:`_smoothed` when the surrogate smooths; ``series``: step -> known displacement."""
    s = surrogate
    params = replica_params(s.params, part)
    mean, std, mask = s.mean[part], s.std[part], s.dof_mask[part]
    load = jnp.float32(s.load_parameter[part]) if s.arch.conditional else None
    series = dict(series)
    for cycle in range(n_cycles):
        inputs, targets = refill_index_sets(n + cycle * N_S * N_F, N_S, N_P, N_F)
        new = {}
        for i in range(N_S):
            window = np.stack([series[k] for k in inputs[i]])
            z = jnp.asarray((window - mean) / std, s.arch.dtype)
            out = np.asarray(forward(params, s.arch, z, load, jnp.asarray(mask, jnp.float32)), np.float64)
            new.update(zip(targets[i].tolist(), out * std + mean))
        if surrogate.smooth:
            start = n + cycle * N_S * N_F
            steps = range(start + 1, start + 1 + N_S * N_F)
            smooth = _smoothed(np.stack([new[k] for k in steps]), series[start], N_S) * mask
            new = dict(zip(steps, smooth))
        series.update(new)  # the next cycle reads these predictions
    return np.stack([series[k] for k in range(n + 1, n + 1 + n_cycles * N_S * N_F)])


# the default run checks the rollout in the (0, False) and (0, True) cases, and that a load parameter reaches the
# output in test_surrogate_lstm.py::test_conditional_output_depends_on_load_parameter
@pytest.mark.parametrize("q, smooth", [(0, False), pytest.param(2, False, marks=pytest.mark.slow), (0, True)])
def test_predict_and_rollout_follow_the_refill_index_sets(q, smooth):
    surrogate, history = _surrogate(q, smooth=smooth), _history()
    n0 = N_S * N_P + 5  # the buffer holds steps n0 + 1 - n_s n_p .. n0
    buffers = history[:, n0 + 1 - N_S * N_P:n0 + 1]
    n_cycles = 3
    rolled = np.asarray(jax.jit(jax.vmap(lambda s, b: s.rollout(b, n0, n_cycles)))(surrogate, buffers))
    one = np.asarray(jax.vmap(lambda s, b: s.predict(b, n0))(surrogate, buffers))
    assert rolled.shape == (2, n_cycles * N_S * N_F, 3) and one.shape == (2, N_S * N_F, 3)
    for part in range(2):
        known = {k: history[part, k] for k in range(n0 + 1)}
        expected = _reference(surrogate, part, known, n0, n_cycles)
        np.testing.assert_allclose(rolled[part], expected, rtol=1e-5, atol=1e-6)
        # the first cycle is predict (eager here, compiled there: equal to round-off)
        np.testing.assert_allclose(one[part], rolled[part, :N_S * N_F], rtol=1e-12, atol=1e-15)
        assert np.all(rolled[part][:, surrogate.dof_mask[part] == 0] == 0)
        # part() is the one-part view that vmap gives each part
        alone = np.asarray(surrogate.part(part).rollout(buffers[part], n0, n_cycles))
        np.testing.assert_allclose(alone, rolled[part], rtol=1e-6, atol=1e-7)
    if q:  # the load parameter reaches the decoder
        other = dataclasses.replace(surrogate, load_parameter=np.float32([0.9, 0.9]))
        assert not np.allclose(np.asarray(other.part(0).predict(buffers[0], n0)), one[0])


def test_smooth_refill_removes_the_jitter_between_applications_and_keeps_lines():
    """Rows from application i carry an error e_i of their own (independent between
    applications): the raw rows jitter from step to step, the smoothed ones do not (the
    second difference vanishes inside each segment, a linear signal comes back exactly,
    the curve starts from the last known value), and the mean of the e_i is all that is
    left of them."""
    from jaxsync.surrogate import smooth_refill

    n_s, n_f = 6, 5
    t = np.arange(1, n_s * n_f + 1, dtype=float)
    line = 0.2 + 0.03 * t
    errors = np.random.default_rng(1).normal(0.0, 0.05, n_s)
    raw = (line + errors[(t.astype(int) - 1) % n_s])[:, None]
    out = np.asarray(smooth_refill(jnp.asarray(raw), jnp.array([0.2]), n_s))[:, 0]
    np.testing.assert_allclose(out, _smoothed(raw, np.array([0.2]), n_s)[:, 0], rtol=1e-12, atol=1e-14)
    exact = np.asarray(smooth_refill(jnp.asarray(line[:, None]), jnp.array([0.2]), n_s))[:, 0]
    np.testing.assert_allclose(exact, line, rtol=1e-12, atol=1e-14)
    after_first_centre = t > (n_s + 1) / 2
    np.testing.assert_allclose(out[after_first_centre], line[after_first_centre] + errors.mean(), atol=1e-12)
    assert np.abs(np.diff(raw[:, 0], 2)).max() > 0.05 and np.abs(np.diff(out[after_first_centre], 2)).max() < 1e-12
    with pytest.raises(ConfigError, match="not a multiple of n_s=7"):
        smooth_refill(jnp.asarray(raw), jnp.array([0.2]), 7)


def test_smooth_refill_from_a_few_applications_averages_those_applications_only():
    """refill_samples m < n_s: the smooth curve goes through the block means of the m
    evenly spaced applications floor((k + 1/2) n_s / m), computed here one application at
    a time on the refill index sets; buffer rows that only the other applications read do
    not change the prediction (they are never computed); None gives the exact block means
    of the raw refill."""
    from jaxsync.surrogate import DEFAULT_REFILL_SAMPLES, refill_applications, smooth_refill

    n_s, samples = 12, 4
    np.testing.assert_array_equal(refill_applications(n_s, samples), [1, 4, 7, 10])
    np.testing.assert_array_equal(refill_applications(n_s, None), np.arange(n_s))
    np.testing.assert_array_equal(refill_applications(n_s, 20), np.arange(n_s))
    for bad in (0, -3, 2.5, True, "4"):
        with pytest.raises(ConfigError, match="refill samples must be an integer >= 1"):
            refill_applications(n_s, bad)
    base = dataclasses.replace(_surrogate(), n_s=n_s, smooth=True)
    assert base.refill_samples == DEFAULT_REFILL_SAMPLES and base.refill_calls == n_s  # 16 >= 12: all of them
    surrogate = base.with_refill_samples(samples)
    assert surrogate.refill_calls == samples and dataclasses.replace(surrogate, smooth=False).refill_calls == n_s
    with pytest.raises(ConfigError, match="refill samples"):
        base.with_refill_samples(0)
    history = _history(80)
    n0 = n_s * N_P + 10
    buffer = history[1, n0 + 1 - n_s * N_P:n0 + 1]
    one = surrogate.part(1)
    out = np.asarray(one.predict(buffer, n0))
    # reference: each chosen application alone, on its own index set, in float64 around the network
    params, mean, std = replica_params(surrogate.params, 1), surrogate.mean[1], surrogate.std[1]
    inputs, _ = refill_index_sets(n0, n_s, N_P, N_F)
    apps = refill_applications(n_s, samples)
    outputs = []
    for i in apps:
        z = jnp.asarray((history[1, inputs[i]] - mean) / std, jnp.float32)
        outputs.append(np.asarray(forward(params, surrogate.arch, z, None, jnp.float32(surrogate.dof_mask[1])),
                                  np.float64) * std + mean)
    block_means = np.mean(outputs, axis=0)  # (n_f, n_dof)
    expected = _smoothed(np.repeat(block_means, n_s, axis=0), history[1, n0], n_s)
    np.testing.assert_allclose(out, expected, rtol=1e-5, atol=1e-6)
    # rows read only by an application that is not chosen (application 0: rows 0, n_s, 2 n_s, ...)
    other = buffer.copy()
    other[0::n_s] += 5.0
    np.testing.assert_array_equal(np.asarray(one.predict(other, n0)), out)
    chosen = buffer.copy()
    chosen[apps[0]::n_s] += 5.0
    assert np.abs(np.asarray(one.predict(chosen, n0)) - out).max() > 1e-3
    # all applications: the block means of the raw refill, smoothed
    every = base.with_refill_samples(None).part(1)
    raw = np.asarray(dataclasses.replace(every, smooth=False).predict(buffer, n0))
    np.testing.assert_allclose(np.asarray(every.predict(buffer, n0)),
                               np.asarray(smooth_refill(jnp.asarray(raw), jnp.asarray(buffer[-1]), n_s)),
                               rtol=1e-12, atol=1e-14)


def test_rollout_sizes_and_a_wrong_buffer():
    surrogate, history = _surrogate(), _history()
    buffer = history[0, :N_S * N_P]
    assert surrogate.part(0).rollout(buffer, N_S * N_P - 1, 2).dtype == jnp.float64
    with pytest.raises(ConfigError, match="refill buffer"):
        surrogate.part(0).predict(buffer[:-1], 0)
    assert (surrogate.history_steps, surrogate.cycle_steps) == (N_S * N_P, N_S * N_F)
    assert (surrogate.n_parts, surrogate.part(1).n_parts, surrogate.dof_counts) == (2, 1, (2, 3))


def test_save_and_load_round_trip_is_exact(tmp_path):
    surrogate = _surrogate(q=2, smooth=True)  # smoothing is not stored: a loaded surrogate smooths
    surrogate.save(tmp_path / "s.h5", metadata={"note": "test"})
    loaded = Surrogate.load(tmp_path / "s.h5", load_parameter=0.4)
    assert loaded.arch == surrogate.arch and loaded.n_s == N_S
    a, tree_a = jax.tree_util.tree_flatten(surrogate)
    b, tree_b = jax.tree_util.tree_flatten(loaded)
    assert tree_a == tree_b
    for x, y in zip(a, b):
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype and x.tobytes() == y.tobytes()
    ckpt = load_surrogate(tmp_path / "s.h5")
    assert ckpt.metadata == {"note": "test"} and ckpt.dof_counts == (2, 3) and ckpt.shared_nodes is None
    assert Surrogate.from_saved(ckpt, 0.4).dof_counts == (2, 3)
    with pytest.raises(CheckpointError, match="conditional on a load parameter"):
        Surrogate.from_saved(ckpt)
    with pytest.raises(CheckpointError, match="does not exist"):
        Surrogate.load(tmp_path / "missing.h5")


def test_initialized_replicas_fit_the_partition_and_save_with_its_nodes(tmp_path):
    problem = jaxsync.cantilever()
    part = jaxsync.partition(problem.mesh, 2, seed=0)
    n_dof, counts = shared_dof_layout(part)
    assert n_dof == max(3 * p.n_shared for p in part.parts) and list(counts) == [3 * p.n_shared for p in part.parts]
    surrogate = Surrogate.initialized(part, 4, n_hidden=6, n_layers=1, n_past=3, n_future=2, seed=1)
    assert surrogate.arch.n_dof == n_dof and surrogate.dof_counts == tuple(counts) and surrogate.n_s == 4
    assert surrogate.mean.dtype == np.float64 and surrogate.dof_mask.dtype == np.float64
    assert surrogate.load_parameter.dtype == np.float32
    again = Surrogate.initialized(part, 4, n_hidden=6, n_layers=1, n_past=3, n_future=2, seed=1)
    np.testing.assert_array_equal(again.params["dense"]["w"], surrogate.params["dense"]["w"])
    nodes = [p.shared_nodes for p in part.parts]
    surrogate.save(tmp_path / "s.h5", shared_nodes=nodes)
    ckpt = load_surrogate(tmp_path / "s.h5", shared_nodes_per_part=nodes)  # the partition check passes
    assert isinstance(ckpt, SavedSurrogate) and ckpt.n_parts == 2
    default = Surrogate.initialized(part, 80)
    assert (default.arch.n_hidden, default.arch.n_layers, default.n_past, default.n_future, default.arch.dtype) == (
        100, 2, 20, 20, "float32")


class _Replay:
    """A predictor that replays known values (the contract refill_rollout relies on:
    ``predict(buffer, step)`` for the steps after ``step``, sizes ``n_s``, ``n_future``)."""

    n_s, n_future = N_S, N_F

    def __init__(self, series):
        self.series = jnp.asarray(series)

    def predict(self, buffer, step):
        return jax.lax.dynamic_slice_in_dim(self.series, step + 1, N_S * N_F, axis=0)


def test_refill_cycles_of_any_predictor_move_the_buffer_on():
    series = _history(80)[1]
    n0 = N_S * N_P - 1
    replay = _Replay(series)
    pred, buffer = refill_cycle(replay, jnp.asarray(series[:n0 + 1]), n0)
    np.testing.assert_array_equal(pred, series[n0 + 1:n0 + 1 + N_S * N_F])
    np.testing.assert_array_equal(buffer, series[N_S * N_F:n0 + 1 + N_S * N_F])  # the last n_s n_p steps
    rolled = jax.jit(lambda b, s: refill_rollout(replay, b, s, 3))(series[:n0 + 1], jnp.int32(n0))
    np.testing.assert_array_equal(rolled, series[n0 + 1:n0 + 1 + 3 * N_S * N_F])
