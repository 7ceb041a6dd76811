"""The hand-written LSTM encoder-decoder against a NumPy transcription of the paper's equations."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxsync.errors import ConfigError
from jaxsync.surrogate.models import (
    LSTMArchitecture,
    count_parameters,
    encode,
    forward,
    init_params,
    lstm_cell,
    run_lstm,
)

# ----------------------------------------------------------------------------- NumPy reference


def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


def np_cell(cell, h, c, d):
    """Paper's LSTM equations, gates stacked (forget, input, candidate, output)."""
    w_d, w_h, b = (np.asarray(cell[k], np.float64) for k in ("w_d", "w_h", "b"))
    n = h.size
    W = {g: (w_d[k * n:(k + 1) * n], w_h[k * n:(k + 1) * n], b[k * n:(k + 1) * n]) for k, g in enumerate("figo")}
    f = _sigmoid(W["f"][0] @ d + W["f"][1] @ h + W["f"][2])
    i = _sigmoid(W["i"][0] @ d + W["i"][1] @ h + W["i"][2])
    g = np.tanh(W["g"][0] @ d + W["g"][1] @ h + W["g"][2])
    o = _sigmoid(W["o"][0] @ d + W["o"][1] @ h + W["o"][2])
    c_new = f * c + i * g
    return o * np.tanh(c_new), c_new


def np_run(cell, xs, n_hidden):
    h, c = np.zeros(n_hidden), np.zeros(n_hidden)
    hs = []
    for x in xs:
        h, c = np_cell(cell, h, c, x)
        hs.append(h)
    return np.array(hs), (h, c)


def np_forward(params, arch, xs, load=None):
    """Encoder: each layer runs forward over xs and backward over xs reversed; decoder
    starts from [fwd | bwd] final states and feeds back its own dense output."""
    layer_in = np.asarray(xs, np.float64)
    for layer in params["encoder"]:
        hs_f, (h_f, c_f) = np_run(layer["forward"], layer_in, arch.n_hidden)
        hs_b, (h_b, c_b) = np_run(layer["backward"], layer_in[::-1], arch.n_hidden)
        layer_in = np.concatenate([hs_f, hs_b[::-1]], axis=1)
    h, c = np.concatenate([h_f, h_b]), np.concatenate([c_f, c_b])
    w, b = np.asarray(params["dense"]["w"], np.float64), np.asarray(params["dense"]["b"], np.float64)
    y = np.asarray(xs[-1], np.float64)
    out = []
    for _ in range(arch.n_future):
        d = y if load is None else np.concatenate([y, np.full(arch.n_cond_repeat, load)])
        h, c = np_cell(params["decoder"], h, c, d)
        y = w @ h + b
        out.append(y)
    return np.array(out)


# ----------------------------------------------------------------------------- tests


@pytest.mark.parametrize("dtype, tol", [("float32", 1e-6), ("float64", 1e-13)])
def test_cell_matches_paper_equations(dtype, tol):
    arch = LSTMArchitecture(n_dof=5, n_hidden=7, n_layers=1, dtype=dtype)
    cell = init_params(jax.random.key(1), arch)["encoder"][0]["forward"]
    rng = np.random.default_rng(0)
    h, c, d = rng.normal(size=7), rng.normal(size=7), rng.normal(size=5)
    h_ref, c_ref = np_cell(cell, h, c, d)
    h_jax, c_jax = lstm_cell(cell, (jnp.asarray(h, dtype), jnp.asarray(c, dtype)), jnp.asarray(d, dtype))
    assert h_jax.dtype == jnp.dtype(dtype)
    np.testing.assert_allclose(np.asarray(h_jax), h_ref, rtol=0, atol=tol)
    np.testing.assert_allclose(np.asarray(c_jax), c_ref, rtol=0, atol=tol * 4)


def test_scan_runs_the_cell_in_order():
    arch = LSTMArchitecture(n_dof=3, n_hidden=6, n_layers=1, dtype="float64")
    cell = init_params(jax.random.key(2), arch)["encoder"][0]["forward"]
    xs = np.random.default_rng(1).normal(size=(9, 3))
    hs, (h, c) = run_lstm(cell, jnp.asarray(xs), (jnp.zeros(6), jnp.zeros(6)))
    hs_ref, (h_ref, c_ref) = np_run(cell, xs, 6)
    np.testing.assert_allclose(np.asarray(hs), hs_ref, atol=1e-13)
    np.testing.assert_allclose(np.asarray(c), c_ref, atol=1e-13)


def test_backward_direction_sees_reversed_sequence():
    arch = LSTMArchitecture(n_dof=4, n_hidden=5, n_layers=1, n_past=7, dtype="float64")
    params = init_params(jax.random.key(3), arch)
    xs = np.random.default_rng(2).normal(size=(7, 4))
    h0, c0 = encode(params, arch, jnp.asarray(xs))
    bwd = params["encoder"][0]["backward"]
    _, (h_rev, c_rev) = np_run(bwd, xs[::-1], 5)
    _, (h_fwd_order, _) = np_run(bwd, xs, 5)
    # Second half of the decoder state is the backward cell run over the reversed window.
    np.testing.assert_allclose(np.asarray(h0[5:]), h_rev, atol=1e-13)
    np.testing.assert_allclose(np.asarray(c0[5:]), c_rev, atol=1e-13)
    assert np.max(np.abs(h_fwd_order - h_rev)) > 1e-3  # direction matters for this input
    # First half: forward cell over the window in time order.
    _, (h_f, _) = np_run(params["encoder"][0]["forward"], xs, 5)
    np.testing.assert_allclose(np.asarray(h0[:5]), h_f, atol=1e-13)


@pytest.mark.parametrize("q", [0, 3])
def test_forward_matches_reference_and_feeds_back_its_output(q):
    arch = LSTMArchitecture(n_dof=4, n_hidden=6, n_layers=2, n_past=5, n_future=6, n_cond_repeat=q)
    params = init_params(jax.random.key(4), arch)
    xs = np.random.default_rng(3).normal(size=(5, 4)).astype(np.float32)
    load = 0.37 if q else None
    out = forward(params, arch, jnp.asarray(xs), None if load is None else jnp.float32(load))
    assert out.shape == (6, 4) and out.dtype == jnp.float32
    ref = np_forward(params, arch, xs, load)
    np.testing.assert_allclose(np.asarray(out), ref, atol=1e-5)

    # Feedback: step t of the decoder consumed the prediction of step t-1.  Replay the
    # decoder in NumPy from the encoder state, feeding jax's own outputs as inputs.
    h, c = (np.asarray(a, np.float64) for a in encode(params, arch, jnp.asarray(xs)))
    w, b = np.asarray(params["dense"]["w"], np.float64), np.asarray(params["dense"]["b"], np.float64)
    inputs = np.concatenate([xs[-1:], np.asarray(out[:-1])])
    for t in range(arch.n_future):
        d = inputs[t] if q == 0 else np.concatenate([inputs[t], np.full(q, load)])
        h, c = np_cell(params["decoder"], h, c, d)
        np.testing.assert_allclose(w @ h + b, np.asarray(out[t]), atol=1e-5)
    # A decoder that reused the last input instead of its own output would differ.
    h, c = (np.asarray(a, np.float64) for a in encode(params, arch, jnp.asarray(xs)))
    stale = []
    for t in range(arch.n_future):
        d = xs[-1] if q == 0 else np.concatenate([xs[-1], np.full(q, load)])
        h, c = np_cell(params["decoder"], h, c, d)
        stale.append(w @ h + b)
    assert np.max(np.abs(np.array(stale) - np.asarray(out))) > 1e-4


def test_conditional_output_depends_on_load_parameter():
    arch = LSTMArchitecture(n_dof=3, n_hidden=4, n_layers=1, n_past=4, n_future=3, n_cond_repeat=12)
    params = init_params(jax.random.key(5), arch)
    xs = jnp.ones((4, 3), jnp.float32)
    a, b = forward(params, arch, xs, jnp.float32(0.3)), forward(params, arch, xs, jnp.float32(0.7))
    assert float(jnp.max(jnp.abs(a - b))) > 1e-4
    with pytest.raises(ConfigError, match="conditional"):
        forward(params, arch, xs)


def test_parameter_shapes_dtype_and_initialization_bounds():
    arch = LSTMArchitecture(n_dof=6, n_hidden=8, n_layers=3, n_cond_repeat=2)
    params = init_params(jax.random.key(6), arch)
    assert len(params["encoder"]) == 3
    assert params["encoder"][0]["forward"]["w_d"].shape == (32, 6)
    assert params["encoder"][1]["backward"]["w_d"].shape == (32, 16)
    assert params["decoder"]["w_d"].shape == (64, 8) and params["decoder"]["w_h"].shape == (64, 16)
    assert params["dense"]["w"].shape == (6, 16)
    for leaf in jax.tree_util.tree_leaves(params["encoder"]):
        assert leaf.dtype == jnp.float32 and float(jnp.max(jnp.abs(leaf))) <= 1 / np.sqrt(8)
    for leaf in jax.tree_util.tree_leaves([params["decoder"], params["dense"]]):
        assert leaf.dtype == jnp.float32 and float(jnp.max(jnp.abs(leaf))) <= 1 / np.sqrt(16)
    def cell_size(n_in, n_h):
        return 4 * n_h * n_in + 4 * n_h * n_h + 4 * n_h

    expected = (2 * cell_size(6, 8) + 2 * 2 * cell_size(16, 8)  # encoder: layer 0, layers 1-2
                + cell_size(6 + 2, 16) + 6 * 16 + 6)  # decoder (dofs + q inputs), dense
    assert count_parameters(params) == expected
    # Same key, same parameters; another key, others.
    again = init_params(jax.random.key(6), arch)
    leaves = zip(jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(again))
    assert all(np.array_equal(a, b) for a, b in leaves)
    other = init_params(jax.random.key(7), arch)
    assert not np.array_equal(params["dense"]["w"], other["dense"]["w"])


@pytest.mark.parametrize("field, value", [("n_dof", 0), ("n_hidden", -1), ("n_layers", 0), ("n_cond_repeat", -2),
                                          ("dtype", "float16")])
def test_architecture_rejects_bad_values(field, value):
    kwargs = {"n_dof": 3, field: value}
    with pytest.raises(ConfigError, match=field if field != "dtype" else "dtype"):
        LSTMArchitecture(**kwargs)


def test_forward_rejects_wrong_window_width():
    arch = LSTMArchitecture(n_dof=3, n_hidden=4, n_layers=1, n_past=4, n_future=2)
    params = init_params(jax.random.key(0), arch)
    with pytest.raises(ConfigError, match="shape"):
        forward(params, arch, jnp.zeros((4, 5), jnp.float32))
