"""The linear surrogate's fit for the rollout (jaxsync.surrogate.training.select_regularization): load
columns fitted first, the ridge of the displacement columns chosen by refill rollouts.

The case is the pulsatile vessel's, reduced to what decides it: many shared dofs and few
windows (more displacement columns than windows), a response that is quasi-static in
the known load, d(t) = s u(t), plus a small ringing above the sampling's Nyquist
frequency (the wall's weakly damped modes, aliased by the n_s stride). The reference is
the true history; the previous fit (one minimum-norm least squares over every column,
ridge 1e-8) is computed here with numpy.linalg.lstsq."""

import numpy as np

from jaxsync.surrogate.models import fit_linear
from jaxsync.surrogate.training import (
    build_dataset,
    rollout_error,
    select_regularization,
    solve_least_squares,
    stack_replicas,
)

N_ROWS, N_DOF, N_P, N_MODES = 400, 90, 10, 300


def pulsatile_history(seed=0):
    """(history (N_ROWS, N_DOF), load signal (N_ROWS, 1)): a ramped pulse of a period
    incommensurate with the sampling, the quasi-static response of random shapes, and a
    ringing of 0.3 % of the amplitude at frequencies above the sampling's Nyquist."""
    rng = np.random.default_rng(seed)
    t = np.arange(N_ROWS, dtype=float)
    period = 37.3
    phase = (t % period) / period
    pulse = 1.0 + 0.5 * np.interp(phase, [0.0, 0.25, 0.45, 0.6, 1.0], [0.0, 1.0, 0.6, 0.7, 0.0])
    u = np.minimum(t / 40.0, 1.0) * pulse
    shape = rng.normal(size=N_DOF)
    # many modes (more than windows: no autoregression of the window can follow them),
    # at frequencies above the sampling's Nyquist (radians per row above pi), aliased
    frequencies = rng.uniform(3.5, 30.0, size=N_MODES)
    modes = rng.normal(size=(N_MODES, N_DOF))
    ringing = np.sin(np.outer(t, frequencies) + rng.uniform(0, 2 * np.pi, N_MODES)) @ modes
    history = np.outer(u, shape)
    history += 0.003 * np.abs(history).max() * ringing / np.abs(ringing).max()
    return history, u[:, None]


def rollout(fit, history, signal, scale, norm, start):
    """Refill cycles of the fitted map (flattened, normalized windows) from row ``start``,
    each fed the previous predictions: the rows start .. end, in solver units."""
    w_in, w_out, b = fit
    mean, std = norm.mean, norm.std
    buffer = (history[start - N_P:start] - mean) / std
    rows = []
    for row in range(start, N_ROWS - N_P + 1, N_P):
        inputs = np.concatenate([buffer.ravel(), (signal[row - N_P:row + N_P] / scale).ravel()])
        buffer = ((inputs @ w_in) @ w_out + b).reshape(N_P, N_DOF)
        rows.append(buffer * std + mean)
    return np.concatenate(rows)


def test_the_fit_for_the_rollout_keeps_the_pulsatile_response_within_1_percent_where_the_old_fit_drifts():
    history, signal = pulsatile_history()
    dataset = build_dataset([history], 1, N_P, N_P, train_fraction=0.5, signals=[signal])
    x, y, u = (np.asarray(a, np.float64) for a in (dataset.x_train, dataset.y_train, dataset.signal_train))
    n = x.shape[0]
    assert n * 4 < N_P * N_DOF  # far fewer windows than displacement columns: the vessel's case
    flat = np.concatenate([x.reshape(n, -1), u.reshape(n, -1)], axis=1)
    # the previous fit: minimum norm over all columns (ridge 1e-8 of s_max^2 is below the
    # smallest kept singular value here), from numpy
    design = np.concatenate([flat - flat.mean(0)], axis=1)
    coeffs = np.linalg.lstsq(design, y.reshape(n, -1) - y.reshape(n, -1).mean(0), rcond=None)[0]
    old = (coeffs, np.eye(coeffs.shape[1]), y.reshape(n, -1).mean(0) - flat.mean(0) @ coeffs)
    windows = (np.concatenate([x, np.asarray(dataset.x_val, np.float64)]),
               np.concatenate([y, np.asarray(dataset.y_val, np.float64)]),
               np.concatenate([u, np.asarray(dataset.signal_val, np.float64)]))
    new, chosen = select_regularization(x, y, u, 1e-8, windows=windows)
    start = N_ROWS // 2
    amplitude = np.abs(history).max()
    errors = {}
    for name, fit in (("old", old), ("new", new)):
        predicted = rollout(fit, history, signal, dataset.signal_scale, dataset.normalization, start)
        errors[name] = np.abs(predicted - history[start:start + len(predicted)]).max() / amplitude
    assert errors["new"] < 0.01 < errors["old"], (errors, chosen)
    # the rollout over the windows says the same: the chosen ridge drifts less than 1e-8
    loose = solve_least_squares(flat, y.reshape(n, -1), 1e-8, n_free=u[0].size)
    assert rollout_error(new, *windows) < rollout_error(loose, *windows)


def test_load_columns_are_fitted_first_and_an_overdetermined_fit_is_ordinary_least_squares():
    """n_free moves no prediction where the fit is overdetermined and unregularized (numpy
    lstsq), and on
    an underdetermined one it puts on the load columns what they explain: the fitted map
    of a purely quasi-static history d = s u is the load's (zero displacement weights)."""
    rng = np.random.default_rng(1)
    x, y = rng.normal(size=(60, 8)), rng.normal(size=(60, 5))
    design = np.concatenate([x, np.ones((60, 1))], axis=1)
    expected = design @ np.linalg.lstsq(design, y, rcond=None)[0]
    for n_free in (0, 3):
        w_in, w_out, b = solve_least_squares(x, y, 0.0, n_free=n_free)
        np.testing.assert_allclose((x @ w_in) @ w_out + b, expected, atol=1e-10)
    u = rng.normal(size=(20, 2))
    shape = rng.normal(size=(2, 50))
    d = u @ shape  # 50 "displacement" columns exactly explained by 2 load columns
    w_in, w_out, b = solve_least_squares(np.concatenate([d, u], 1), d, 1e-8, n_free=2)
    weights = w_in @ w_out
    assert np.abs(weights[:50]).max() < 1e-8 * np.abs(weights[50:]).max()
    np.testing.assert_allclose(weights[50:], shape, atol=1e-5 * np.abs(shape).max())  # the light ridge


def test_fit_linear_takes_the_rollout_fit():
    """fit_linear on the pulsatile history: its parameters predict what
    select_regularization's fit predicts (same windows, same choice)."""
    history, signal = pulsatile_history()
    dataset = build_dataset([history], 1, N_P, N_P, train_fraction=0.5, signals=[signal])
    data = stack_replicas([dataset], load_inputs=("pressure",))
    result = fit_linear(data, dtype="float64")
    x, y, u = (np.asarray(a[0], np.float64) for a in (data.x_train, data.y_train, data.signal_train))
    windows = tuple(np.concatenate([a, np.asarray(b[0], np.float64)]) for a, b in
                    ((x, data.x_val), (y, data.y_val), (u, data.signal_val)))
    (w_in, w_out, b), _ = select_regularization(x, y, u, 1e-8, windows=windows)
    flat = np.concatenate([x.reshape(len(x), -1), u.reshape(len(u), -1)], axis=1)
    expected = ((flat @ w_in) @ w_out + b).reshape(y.shape)
    p = result.params
    coeffs = np.einsum("wpd,pdr->wr", x, p["w_in"][0]) + np.einsum("wtu,tur->wr", u, p["w_load"][0])
    got = np.einsum("wr,rfd->wfd", coeffs, p["w_out"][0]) + p["b"][0]
    np.testing.assert_allclose(got, expected, atol=1e-9 * np.abs(expected).max())


def test_directions_the_ridge_suppresses_are_dropped_and_move_the_fit_by_at_most_the_cut():
    """Against the ridge solution of the normal equations (numpy): with a ridge strong
    enough to suppress most directions, the fit keeps only those of filter factor >=
    FILTER_CUT, its fitted values are within FILTER_CUT of the targets' norm of the full
    ridge's, and the directions it keeps are exactly those; without a ridge nothing is
    dropped (numpy lstsq)."""
    from jaxsync.surrogate.training import FILTER_CUT

    rng = np.random.default_rng(3)
    n, n_in, n_out = 120, 60, 7
    # input columns of singular values spread over six decades
    q1, _ = np.linalg.qr(rng.normal(size=(n, n_in)))
    q2, _ = np.linalg.qr(rng.normal(size=(n_in, n_in)))
    sv = np.logspace(0, -6, n_in)
    x = (q1 * sv) @ q2.T + rng.normal(size=n_in)
    y = rng.normal(size=(n, n_out)) + x @ rng.normal(size=(n_in, n_out))
    xc, yc = x - x.mean(0), y - y.mean(0)
    s = np.linalg.svd(xc, compute_uv=False)
    for relative in (1e-2, 1e-4):
        lam = relative * s[0] ** 2
        ridge = np.linalg.solve(xc.T @ xc + lam * np.eye(n_in), xc.T @ yc)
        w_in, w_out, b = solve_least_squares(x, y, relative)
        expected_rank = np.count_nonzero(s ** 2 >= FILTER_CUT * (s ** 2 + lam))
        assert w_in.shape[1] == expected_rank < n_in
        moved = np.linalg.norm((x @ w_in) @ w_out + b - (xc @ ridge + y.mean(0)))
        assert 0 < moved <= FILTER_CUT * np.linalg.norm(yc)
    w_in, w_out, b = solve_least_squares(x, y, 0.0)
    design = np.concatenate([x, np.ones((n, 1))], axis=1)
    np.testing.assert_allclose((x @ w_in) @ w_out + b, design @ np.linalg.lstsq(design, y, rcond=None)[0],
                               atol=1e-6 * np.abs(y).max())
