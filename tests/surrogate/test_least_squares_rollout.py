"""The ridge selection's rollout error (:func:`jaxsync.surrogate.training.rollout_error`,
computed in the fit's rank-R coordinates) equals refill rollouts of the full windows,
written here directly: every chained window fed the previous cycle's prediction."""

import numpy as np
import pytest

from jaxsync.surrogate.training import rollout_error, select_regularization

N_PAST, N_FUTURE, N_DOF = 4, 6, 5


def windows(n_windows, seed, n_load=2, n_past=N_PAST, n_future=N_FUTURE):
    """Windows at every sample of a random series: window i's successor a cycle later is
    i + n_future; the load signal is a smooth function of time."""
    rng = np.random.default_rng(seed)
    series = np.cumsum(rng.normal(size=(n_windows + n_past + n_future, N_DOF)), axis=0) * 0.1
    load = np.sin(0.1 * np.arange(len(series))[:, None] * np.arange(1, n_load + 1))
    start = np.arange(n_windows)
    x = np.stack([series[i:i + n_past] for i in start])
    y = np.stack([series[i + n_past:i + n_past + n_future] for i in start])
    u = np.stack([load[i:i + n_past + n_future] for i in start]) if n_load else None
    return x, y, u


def direct_rollout_error(fit, x, y, u, cycles=None):
    """The reference: full-window rollouts, one start window at a time."""
    w_in, w_out, b = fit
    n_past = x.shape[1]
    successor = {}
    for i in range(len(x)):
        for j in range(len(x)):
            if np.array_equal(x[j], y[i, -n_past:]):
                successor[i] = j
    sq, count = 0.0, 0
    for start in successor:
        window, current = start, x[start]
        for _ in range(len(x) if cycles is None else cycles):
            inputs = current.ravel() if u is None else np.concatenate([current.ravel(), u[window].ravel()])
            prediction = ((inputs @ w_in) @ w_out + b).reshape(y[window].shape)
            sq += np.square(prediction - y[window]).sum()
            count += prediction.size
            if window not in successor:
                break
            window, current = successor[window], prediction[-n_past:]
    return sq / count


@pytest.mark.parametrize("n_load", [0, 2])
@pytest.mark.parametrize("cycles", [None, 3])
def test_rollout_error_equals_full_window_rollouts(n_load, cycles):
    x, y, u = windows(40, seed=n_load, n_load=n_load)
    n_in, n_out = x[0].size + (0 if u is None else u[0].size), y[0].size
    rng = np.random.default_rng(7)
    for rank in (3, n_in):  # a low-rank fit and a full one
        fit = (rng.normal(size=(n_in, rank)) / np.sqrt(n_in), rng.normal(size=(rank, n_out)) / np.sqrt(rank),
               rng.normal(size=n_out))
        expected = direct_rollout_error(fit, x, y, u, cycles)
        assert rollout_error(fit, x, y, u, cycles) == pytest.approx(expected, rel=1e-10)


@pytest.mark.parametrize("seed", range(4))
def test_a_good_fit_has_a_rollout_error_at_round_off_of_the_targets(seed):
    # a fit that reproduces the windows exactly (the series is a linear recurrence): the
    # expanded squared error must leave no more than round-off of the targets' square
    rng = np.random.default_rng(seed)
    A = np.linalg.qr(rng.normal(size=(N_DOF, N_DOF)))[0] * 0.99
    series = [rng.normal(size=N_DOF)]
    for _ in range(60):
        series.append(series[-1] @ A)
    series = np.array(series)
    x = np.stack([series[i:i + 1] for i in range(50)])
    y = np.stack([series[i + 1:i + 3] for i in range(50)])
    w = np.concatenate([A, A @ A], axis=1)  # x_last -> (x_last A, x_last A^2)
    fit = (w, np.eye(w.shape[1]), np.zeros(w.shape[1]))
    error = rollout_error(fit, x, y, None)
    assert 0.0 <= error < 1e-14 * np.mean(np.square(y))
    # and a fit off by 1e-6 shows as an error of that size, not round-off
    off = (w * (1 + 1e-6), np.eye(w.shape[1]), np.zeros(w.shape[1]))
    expected = direct_rollout_error(off, x, y, None)
    assert expected > 1e-13 * np.mean(np.square(y))
    assert rollout_error(off, x, y, None) == pytest.approx(expected, abs=1e-14 * np.mean(np.square(y)))


def test_no_chained_window_gives_nan_and_selection_keeps_the_configured_ridge():
    x, y, u = windows(5, seed=1, n_future=2)  # n_f < n_p: no window is another's successor
    assert np.isnan(rollout_error((np.ones((x[0].size + u[0].size, 1)), np.ones((1, y[0].size)),
                                   np.zeros(y[0].size)), x, y, u))
    _, chosen = select_regularization(x, y, u, 1e-4)
    assert chosen == 1e-4
