"""Least squares of the linear surrogate and the linear highway (:mod:`jaxsync.surrogate.models`).

An affine map ``y ~ x W + b`` of flattened windows, W factored through input directions
(:func:`solve_least_squares`): the window's displacement columns ridge-penalized, the
known load signals' columns not (fitted first: what the loads explain is not spread over
the many displacement columns), and the ridge parameter chosen by what an online run
does with the map -- refill rollouts fed their own predictions over chained windows
(:func:`select_regularization`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["DEFAULT_REGULARIZATION", "REGULARIZATION_CHOICES", "ROLLOUT_SLACK", "FREE_REGULARIZATION",
           "solve_least_squares", "rollout_error", "select_regularization"]

#: Default ridge parameter, relative to the largest squared singular value of the centered
#: training inputs: lambda = 1e-8 s_max^2 (see :class:`LinearFitConfig`).
DEFAULT_REGULARIZATION = 1e-8


def solve_least_squares(x: np.ndarray, y: np.ndarray, regularization: float = DEFAULT_REGULARIZATION,
                        weight: np.ndarray | None = None, max_rank: int | None = None, n_free: int = 0):
    """Affine least squares ``y ~ x W + b``, W factored through the input directions.

    Minimizes sum_i w_i ||(x_i - x_mean) W - (y_i - y_mean)||^2 + lambda ||W_a||^2 (w_i = 1
    without ``weight``; the means weighted alike), W_a the rows of W of the first
    n_in - ``n_free`` input columns (the autoregressive ones: the window's displacements)
    and lambda = ``regularization`` s_max^2, s_max the largest singular value of those
    columns once the last ``n_free`` (the known load signals) are projected out.

    The free columns are penalized only lightly (:data:`FREE_REGULARIZATION`, relative
    to their own largest singular value; not at all when ``regularization`` is 0): the
    fit explains by them first what they can explain (Frisch-Waugh: every column and the
    targets are projected onto the complement of the free columns' span, the penalized
    rows W_a are fitted there, and the free rows W_f then by least squares on what W_a leaves). With a window
    of many more displacement columns than windows (the 11-part vessel: 20 x 231
    columns, 158 windows) the minimum-norm solution would otherwise spread a quasi-static
    response over the many displacement columns instead of the few load columns that
    cause it, and out of sample, fed its own predictions, that map drifts (the vessel:
    2.1 % of the amplitude after one refill cycle out of sample, 16 % over the second
    half; the load columns alone explain the response to 0.2 %).

    From the thin SVD of the projected, row-scaled displacement columns ``U diag(s) V^T``:
    W_a = V diag(s / (s^2 + lambda)) U^T (y - y_mean)_projected (rows scaled by
    sqrt(w_i)); singular values at or below ``eps * max(shape) * s_max`` (NumPy
    ``lstsq``'s rank cut) are dropped, so r = 0 is the minimum-norm solution, and with
    ``max_rank`` only the leading directions are kept (truncated SVD; the free columns'
    directions count first). Where the fit is overdetermined and ``regularization`` is 0
    it is the ordinary least-squares solution. The penalized directions the ridge keeps
    below :data:`FILTER_CUT` of their weight are dropped (every free direction is kept: a
    load signal of another waveform may move any of them), so that the prediction costs
    what the fit needs; this moves the fitted values by at most FILTER_CUT times the
    targets' (centred, weighted) norm (exactly so without free columns, whose light
    ridge adds its own small share otherwise).

    :func:`select_regularization` chooses lambda by the rollout error on the windows.

    Args:
        x: (n_windows, n_in) inputs; y: (n_windows, n_out) targets (any float dtype;
            solved in float64).
        regularization: relative ridge parameter r >= 0.
        weight: (n_windows,) window weights >= 0 (None: all 1).
        max_rank: the most input directions kept (None: all above the rank cut).
        n_free: the last ``n_free`` input columns are not penalized (0: none).

    Returns:
        ``(w_in (n_in, rank), w_out (rank, n_out), b (n_out,))`` float64 with
        W = w_in @ w_out; rank >= 0 is the number of directions kept.
    """
    return _LeastSquares(x, y, weight, n_free, max_rank).solution(regularization)


class _LeastSquares:
    """The factorization behind :func:`solve_least_squares`, computed once so that
    solutions for several ridge parameters cost one product each."""

    def __init__(self, x, y, weight, n_free: int, max_rank: int | None):
        x = np.asarray(x, np.float64)
        y = np.asarray(y, np.float64)
        w = np.ones(x.shape[0]) if weight is None else np.asarray(weight, np.float64)
        w = w / w.sum()
        self.n_in, self.n_out = x.shape[1], y.shape[1]
        self.x_mean, self.y_mean = w @ x, w @ y
        root = np.sqrt(w)[:, None]
        xc, yc = root * (x - self.x_mean), root * (y - self.y_mean)
        n_a = self.n_in - n_free
        eps = np.finfo(np.float64).eps
        # the free columns' orthonormal directions (in their columns' space and in rows)
        uf, sf, vtf = np.linalg.svd(xc[:, n_a:], full_matrices=False)
        keep_f = sf > eps * max(x.shape) * sf[0] if sf.size else np.zeros(0, bool)
        if max_rank is not None:
            keep_f &= np.arange(sf.size) < max_rank
        uf, sf, vtf = uf[:, keep_f], sf[keep_f], vtf[keep_f]
        xa = xc[:, :n_a] - uf @ (uf.T @ xc[:, :n_a])  # the penalized columns, free part projected out
        self.ya = yc - uf @ (uf.T @ yc)
        u, s, vt = np.linalg.svd(xa, full_matrices=False)
        # the rank cut relative to the columns before the projection: what the free
        # columns explain exactly leaves round-off, not directions to fit
        keep = s > eps * max(x.shape) * max(np.linalg.norm(xc[:, :n_a]), s[0] if s.size else 0.0)
        if max_rank is not None:
            keep &= np.arange(s.size) < max_rank - uf.shape[1]
        self.u, self.s, self.vt = u[:, keep], s[keep], vt[keep]
        self.xc_a, self.yc, self.n_a = xc[:, :n_a], yc, n_a
        self.uf, self.sf, self.vtf = uf, sf, vtf

    def kept_directions(self, regularization: float) -> int:
        """The number of leading penalized directions whose ridge filter factor s^2 / (s^2
        + lambda) is at least :data:`FILTER_CUT` (the singular values are decreasing)."""
        if not self.s.size:
            return 0
        lam = regularization * self.s[0] ** 2
        return int(np.count_nonzero(self.s ** 2 >= FILTER_CUT * (self.s ** 2 + lam)))

    def solution(self, regularization: float):
        """``(w_in, w_out, b)`` for the relative ridge parameter ``regularization``: every
        free direction and the penalized ones it does not suppress below
        :data:`FILTER_CUT`."""
        k = self.kept_directions(regularization)
        s, u, vt = self.s[:k], self.u[:, :k], self.vt[:k]
        r_a, r_f = k, self.sf.size
        w_in = np.zeros((self.n_in, r_a + r_f))
        w_in[:self.n_a, :r_a] = vt.T
        w_in[self.n_a:, r_a:] = self.vtf.T
        out_a = np.zeros((0, self.n_out))
        if r_a:
            # the ridge relative to the largest singular value of all the directions
            gain = s / (s * s + regularization * self.s[0] ** 2)
            out_a = gain[:, None] * (u.T @ self.ya)
        # the free rows: least squares on what the penalized ones leave
        rest = self.yc - (self.xc_a @ vt.T) @ out_a
        sf = self.sf
        free = FREE_REGULARIZATION if regularization > 0 else 0.0  # 0: the exact least squares
        gain_f = sf / (sf * sf + free * sf[0] ** 2) if r_f else sf
        out_f = gain_f[:, None] * (self.uf.T @ rest) if r_f else np.zeros((0, self.n_out))
        w_out = np.concatenate([out_a, out_f])
        if w_out.shape[0] == 0:  # constant inputs: predict the mean
            return np.zeros((self.n_in, 0)), np.zeros((0, self.n_out)), self.y_mean
        return w_in, w_out, self.y_mean - (self.x_mean @ w_in) @ w_out


REGULARIZATION_CHOICES = tuple(10.0 ** k for k in range(-8, 1))
"""The ridge parameters the fit chooses from (:func:`select_regularization`): 1e-8 ... 1,
those at or above the configured ``regularization``."""

FREE_REGULARIZATION = 1e-6
"""Ridge parameter of the load columns, relative to their own largest squared singular
value: it keeps directions the training windows hardly vary in (the kink at a ramp's end)
from gains that, out of sample, amplify the load (the short cantilever trained under a
constant load and switched off out of sample: 0 gives 960 % of the shared amplitude,
1e-6 0.63 %, 1e-3 2.6 %; the pulsatile beam 0.51, 0.51, 0.57 %)."""

ROLLOUT_SLACK = 2.0
"""The fit takes the strongest ridge whose rollout error is within this factor of the
smallest (:func:`select_regularization`): rollouts over the training windows are in
sample, and there a weaker ridge always looks a little better than it does out of sample
(the 11-part vessel: the smallest in-sample rollout error chose 1e-3 to 1e-1, 1.0 % of the
amplitude out of sample; within 2x of it, 1, 0.3 %)."""


FILTER_CUT = 1e-3
"""The fit drops the displacement directions that its ridge keeps below this fraction of
their least-squares weight (filter factor s^2 / (s^2 + lambda) < FILTER_CUT,
:func:`solve_least_squares`): together they move no in-sample prediction by more than
FILTER_CUT of the targets' norm, yet each costs as much at every prediction as a strong
one (2 (n_p + n_f) n_dof flops per window). The 4-part hyperelastic vessel under ridge 1:
about 16 of its 305 directions are kept, at the same rollout error to 0.1 %."""


def _chains(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(n_windows,) the index of the window whose inputs are the last n_p targets of each
    window (the window a refill cycle later), -1 where none is among them."""
    n_past = x.shape[1]
    if y.shape[1] < n_past:
        return np.full(x.shape[0], -1)
    index = {np.ascontiguousarray(x[j]).tobytes(): j for j in range(x.shape[0])}
    return np.array([index.get(np.ascontiguousarray(y[i, -n_past:]).tobytes(), -1) for i in range(x.shape[0])])


def rollout_error(fit, x, y, signals, cycles: int | None = None) -> float:
    """Mean squared error of refill rollouts over chained windows: from every window
    that has a successor a cycle later (:func:`_chains`), ``cycles`` cycles, each fed the
    previous cycle's predictions (what an online run does), compared with the windows'
    targets; nan where no window has a successor. ``cycles``: the most cycles of a
    rollout (None: as long as the chain of windows goes on).

    The rollouts run in the fit's rank-R coordinates z = inputs @ w_in: a cycle maps z
    to z G + c + (the next window's load columns) @ w_in with the (R, R) G, and the
    squared error |z w_out + b - y|^2 expands into (R, R) and (R,) products, so a cycle
    of A rollouts costs O(A R^2) instead of the O(A R (n_in + n_out)) of the full
    windows (the whole linear fit of benchmarks/untuned_vessel.py's 4-part vessel: 609 s
    to 120 s).

    Args:
        fit: ``(w_in, w_out, b)`` of flattened windows (:func:`solve_least_squares`).
        x: (n_windows, n_p, n_dof); y: (n_windows, n_f, n_dof); signals: (n_windows,
            n_p + n_f, n_load) or None.
    """
    w_in, w_out, b = (np.asarray(a, np.float64) for a in fit)
    following = _chains(x, y)
    active = np.flatnonzero(following >= 0)
    if active.size == 0:
        return float("nan")
    n_windows = x.shape[0]
    n_x = x[0].size  # the displacement columns of an input row; the load columns follow
    x_flat = np.asarray(x, np.float64).reshape(n_windows, n_x)
    targets = np.asarray(y, np.float64).reshape(n_windows, -1) - b
    w_x = w_in[:n_x]
    loads = np.zeros((n_windows, w_in.shape[1]))
    if signals is not None:
        loads = np.asarray(signals, np.float64).reshape(n_windows, -1) @ w_in[n_x:]
    # a cycle's prediction z w_out + b: its last n_p rows are the next input
    G = w_out[:, -n_x:] @ w_x
    c = b[-n_x:] @ w_x
    gram = w_out @ w_out.T
    cross = targets @ w_out.T  # (n_windows, R): w_out (y - b) of every window
    target_sq = np.einsum("ij,ij->i", targets, targets)
    z = x_flat[active] @ w_x + loads[active]
    sq, count = 0.0, 0
    for _ in range(n_windows if cycles is None else cycles):
        # |z w_out - (y - b)|^2 = z gram z - 2 z . w_out (y - b) + |y - b|^2
        sq += float(np.einsum("ij,ij->", z @ gram - 2.0 * cross[active], z) + target_sq[active].sum())
        count += active.size * targets.shape[1]
        nxt = following[active]
        more = nxt >= 0
        active, z = nxt[more], z[more] @ G + c + loads[nxt[more]]
        if active.size == 0:
            break
    return max(sq, 0.0) / count


def select_regularization(x, y, signals, regularization: float, weight=None, max_rank: int | None = None,
                          windows=None):
    """The least-squares fit (:func:`solve_least_squares`, load columns free) whose ridge
    parameter, from :data:`REGULARIZATION_CHOICES` at or above ``regularization`` (and
    ``regularization`` itself), is the strongest whose :func:`rollout_error` on
    ``windows`` (default: the fitted windows) is within :data:`ROLLOUT_SLACK` of the
    smallest: a fit that explains each window well can still drift
    when fed its own predictions, and that is what an online run does with it.

    Args:
        x: (n_windows, n_p, n_dof), y: (n_windows, n_f, n_dof), signals: (n_windows,
            n_p + n_f, n_load) or None: the fitted windows (one part, its real dofs).
        regularization: the smallest ridge parameter allowed; 0: none, and none chosen
            (the exact minimum-norm least squares, load columns unpenalized too).
        weight, max_rank: as in :func:`solve_least_squares`.
        windows: ``(x, y, signals)`` the rollouts run over (e.g. the training and the
            validation windows together, so that more windows have successors).

    Returns:
        ``((w_in, w_out, b), regularization chosen)``.
    """
    n = x.shape[0]
    flat = x.reshape(n, -1)
    n_free = 0
    if signals is not None:
        flat = np.concatenate([flat, signals.reshape(n, -1)], axis=1)
        n_free = signals[0].size
    solver = _LeastSquares(flat, y.reshape(n, -1), weight, n_free, max_rank)
    if regularization == 0:  # asked for the exact (minimum-norm) least squares
        return solver.solution(0.0), 0.0
    choices = [regularization] + [r for r in REGULARIZATION_CHOICES if r > regularization]
    xs, ys, us = (x, y, signals) if windows is None else windows
    fits, errors = [], []
    for r in choices:
        fits.append(solver.solution(r))
        errors.append(rollout_error(fits[-1], xs, ys, us))
        if not np.isfinite(errors[-1]):  # nothing to roll out over: the configured ridge
            return fits[0], regularization
    # the strongest ridge within ROLLOUT_SLACK of the best: in-sample rollouts favour the
    # weaker ridge that out of sample drifts more
    best = max(k for k, e in enumerate(errors) if e <= ROLLOUT_SLACK * min(errors))
    return fits[best], choices[best]
