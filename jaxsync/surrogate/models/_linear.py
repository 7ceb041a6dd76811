"""Linear autoregressive surrogate: the baseline beside the LSTM.

The same protocol as the LSTM (:class:`~jaxsync.surrogate.models.SurrogateArchitecture`;
fitted in closed form) -- an architecture, ``init_params`` and
``forward(params, arch, xs, load_parameter, dof_mask)`` mapping a normalized window
of ``n_past`` snapshots (n_p, n_dof) to the next ``n_future`` (n_f, n_dof) -- so that
:class:`~jaxsync.surrogate.Surrogate`, the refill, the surrogate file and the online solver run
it unchanged.  The prediction is an affine map of the window::

    vec(y) = vec(x) W + b,     W (n_p n_dof, n_f n_dof),   b (n_f n_dof,)

each future snapshot predicted directly from the inputs (no feedback of predictions
inside a window), which is the affine predictor of least training MSE: the LSTM's loss,
on the LSTM's windows (:func:`~jaxsync.surrogate.training.build_dataset`,
:func:`~jaxsync.surrogate.training.stack_replicas`), minimized exactly.

Structure: W is stored factored, ``W = w_in w_out`` through the ``rank`` directions of
the training inputs that the fit uses (:func:`fit_linear`: the right singular vectors of
the centered inputs).  This is the ridge least-squares solution itself -- it lies in the
span of the training inputs -- less the directions its ridge suppresses below
:data:`~jaxsync.surrogate.training.FILTER_CUT` of their weight, and its size grows
with the number of windows at most, not with n_dof^2: a full W of the 11-part vessel
(n_dof = 2 310, n_p = n_f = 20) would hold 2.1e9 numbers per part.  Parameters, one
replica::

    {"w_in":  (n_p, n_dof, rank),     input directions (orthonormal columns)
     "w_out": (rank, n_f, n_dof),     their least-squares map to the outputs
     "b":     (n_f, n_dof)}           bias (the centering)

Replicas are padded like the LSTM's: zeros on padded dofs and on the rank columns a part
does not use, so a padded replica computes what it would alone and predicts 0 on padding.
The model is unconditional (no load parameter).

Load input (``n_load > 0``, ARX): the known load signals u (:mod:`jaxsync.fem`,
normalized by the surrogate's per-signal scale) at the window's n_p past and n_f future
sample times, ``loads`` (n_p + n_f, n_load), are further inputs of the same affine map::

    vec(y) = [vec(x), vec(u_past), vec(u_future)] W + b

fitted by the same least squares: the load columns are more input directions (the centered
inputs' SVD runs over the displacement and load columns together, with the same ridge and
rank cut). Their rows of ``w_in`` are stored apart, ``"w_load": (n_p + n_f, n_load, rank)``,
and their term added to the projection: a model whose ``w_load`` is zero computes bit for
bit what the model without load input computes, and ``n_load = 0`` is that model (no
``w_load``; surrogate files written before the load input load unchanged).
"""

from __future__ import annotations

import dataclasses
import functools
import time
from typing import TYPE_CHECKING, Any, ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from jaxsync.errors import ConfigError
from jaxsync.surrogate.models._protocol import (
    FitSettings,
    LeastSquaresFitted,
    PredictionCost,
    check_compute_dtype,
    check_loads,
)
from jaxsync.surrogate.training._data import ReplicaData
from jaxsync.surrogate.training._least_squares import (
    DEFAULT_REGULARIZATION,
    rollout_error,
    select_regularization,
    solve_least_squares,
)

if TYPE_CHECKING:  # fit_linear imports it: jaxsync.surrogate.training imports optax
    from jaxsync.surrogate.training._train import TrainResult

__all__ = ["LinearArchitecture", "LinearFitConfig", "init_params", "forward", "fit_linear", "fit_affine",
           "solve_least_squares", "param_shapes", "DEFAULT_REGULARIZATION"]

Params = dict[str, Any]

_DTYPES = ("float32", "float64")



@jax.tree_util.register_static
@dataclasses.dataclass(frozen=True)
class LinearArchitecture(LeastSquaresFitted):
    """Shape of one linear autoregressive surrogate (static: it never carries arrays): a
    surrogate model fitted in closed form (:mod:`jaxsync.surrogate.models`).

    Attributes:
        n_dof: degrees of freedom per snapshot; for replicas the padded width.
        rank: inner width of the factored map W = w_in w_out (the input directions the
            least-squares fit uses; at most min(training windows, n_p n_dof)); set by
            :func:`fit_linear`, padded to the largest over the parts.
        n_past: n_p, snapshots in an input window.
        n_future: n_f, snapshots predicted.
        dtype: "float32" (default, as the LSTM) or "float64" for parameters and computation.
        n_load: number of known load signals fed in (ARX, module docstring); 0 (default):
            none.
    """

    kind: ClassVar[str] = "linear"
    # windows across a load jump bend the least-squares fit (Sampling.load_jump_windows)
    load_jump_windows: ClassVar[str] = "exclude"

    n_dof: int
    rank: int
    n_past: int = 20
    n_future: int = 20
    dtype: str = "float32"
    n_load: int = 0

    def __post_init__(self):
        if isinstance(self.n_load, bool) or not isinstance(self.n_load, (int, np.integer)) or self.n_load < 0:
            raise ConfigError(f"LinearArchitecture.n_load must be an integer >= 0 (load signals), got {self.n_load!r}")
        for name in ("n_dof", "rank", "n_past", "n_future"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ConfigError(f"LinearArchitecture.{name} must be a positive integer, got {value!r}")
        if self.dtype not in _DTYPES:
            raise ConfigError(f"LinearArchitecture.dtype must be one of {_DTYPES}, got {self.dtype!r}")

    @property
    def conditional(self) -> bool:
        """Always False: the linear surrogate takes no load parameter."""
        return False

    @property
    def n_cond_repeat(self) -> int:
        """0: no copies of a load parameter (the LSTM's q)."""
        return 0

    @classmethod
    def from_choice(cls, choice, n_dof: int, n_past: int, n_future: int, n_load: int) -> "LinearArchitecture":
        """The model for the data's windows, of the largest rank a fit can give (n_p n_dof +
        (n_p + n_f) n_load input directions; :meth:`fit` returns the rank it used)."""
        return cls(n_dof=n_dof, rank=n_past * n_dof + (n_past + n_future) * n_load, n_past=n_past,
                   n_future=n_future, dtype=choice.dtype, n_load=n_load)

    def init(self, key: jax.Array) -> Params:
        """:func:`init_params`: zero parameters."""
        return init_params(key, self)

    def forward(self, params: Params, xs: jax.Array, load_parameter=None, dof_mask=None,
                compute_dtype: str | None = None, loads=None) -> jax.Array:
        """:func:`forward` of this model."""
        return forward(params, self, xs, load_parameter, dof_mask, compute_dtype=compute_dtype, loads=loads)

    def fit(self, data: ReplicaData, settings: FitSettings) -> "TrainResult":
        """:func:`fit_linear` with the choice's ``regularization`` (the rank is the fit's)."""
        return fit_linear(data, LinearFitConfig(settings.architecture.regularization), self.dtype)

    def refit(self, params, x, y, signals, weight, dof_mask) -> Params:
        """:func:`refit` with the default regularization (what online learning runs)."""
        return refit(params, self, x, y, signals, weight, dof_mask)

    def fit_description(self, result) -> str:
        return f"linear, least-squares fit of rank {result.arch.rank} in {result.seconds_per_epoch:.2f} s"

    def prediction_cost(self, n_s: int, masked: bool = True, io_bytes_per_value: int = 8) -> PredictionCost:
        """Bytes and flops of one refill prediction (n_s windows), with D = n_dof, T = n_p,
        F = n_f, R = rank, L = n_load: per window 2 T D R (projection) + 2 (T + F) L R (load
        projection) + 2 R F D (map to the outputs) + F D (bias) + F D (mask, when given) +
        2 D (T + F) (normalization) flops; the parameters (T D R + (T + F) L R + R F D + F D
        values of ``dtype``) read once for all n_s windows, plus the input buffer n_s T D,
        mean and std 2 D, mask D and output n_s F D values of ``io_bytes_per_value``."""
        d, t, f, r, u = self.n_dof, self.n_past, self.n_future, self.rank, self.n_load
        per_window = (2 * t * d * r + 2 * (t + f) * u * r + 2 * r * f * d + f * d + (f * d if masked else 0)
                      + 2 * d * (t + f))
        params = t * d * r + (t + f) * u * r + r * f * d + f * d
        io = n_s * t * d + 2 * d + n_s * f * d + (d if masked else 0)
        return PredictionCost(float(np.dtype(self.dtype).itemsize * params + io_bytes_per_value * io),
                              float(n_s * per_window))


@dataclasses.dataclass(frozen=True)
class LinearFitConfig:
    """Settings of the least-squares fit (the ``config`` of its
    :class:`~jaxsync.surrogate.training.TrainResult`).

    Attributes:
        regularization: the smallest ridge parameter r the fit may use, relative:
            lambda = r s_max^2 with s_max the largest singular value of the centered
            training inputs, so r does not depend on the number of windows or dofs.  The
            fit minimizes ||X W - Y||^2 + lambda ||W_x||^2 (bias and load columns not
            penalized; :func:`~jaxsync.surrogate.training.solve_least_squares`), with
            r chosen from r, 1e-8 ... 1 by refill rollouts over the training and
            validation windows
            (:func:`~jaxsync.surrogate.training.select_regularization`); r = 0 is
            the exact least squares (no ridge, none chosen).  Default 1e-8: the
            windows are float32 (relative round-off ~6e-8), so the inputs have
            directions of singular value ~1e-7 s_max that are round-off only; unpenalized
            (r = 0) their gain would be ~1e7 / s_max, amplifying that noise in every
            prediction and making autoregressive rollouts unstable, while r = 1e-8 caps
            it at ~10 / s_max.  Directions above 1e-4 s_max (components above ~1e-4 of the
            data's largest, far below the 2 % offline tolerance) keep more than half their
            gain, and above 1e-3 s_max more than 99 %.  Measured on the coarse
            cantilever (2 parts, n_s = 5, n_p = n_f = 4, fitted on 400 synchronized
            steps, online from step 40): r = 0 diverges, r = 1e-10, 1e-8, 1e-6 reach
            4.5, 2.7, 3.6 % of the amplitude (on a 1 200-step rollout 1e-10 did best,
            2.0 against 2.8 %: the best value depends on the data).  r = 0 is the plain
            minimum-norm least-squares solution (what an exactly linear recurrence in
            float64 needs to be recovered to round-off).
    """

    regularization: float = DEFAULT_REGULARIZATION

    def __post_init__(self):
        r = self.regularization
        if isinstance(r, bool) or not isinstance(r, (int, float, np.floating)) or not np.isfinite(r) or r < 0:
            raise ConfigError(f"regularization must be a finite number >= 0 (relative ridge parameter), got {r!r}")

    def to_dict(self) -> dict[str, Any]:
        return {"model": LinearArchitecture.kind, "method": "least_squares",
                "regularization": float(self.regularization)}


# ----------------------------------------------------------------------------- model


def param_shapes(arch: LinearArchitecture) -> dict[str, tuple[int, ...]]:
    """The parameters' shapes by name: ``w_in`` (n_p, n_dof, rank), ``w_out`` (rank, n_f,
    n_dof), ``b`` (n_f, n_dof) and, with load input, ``w_load`` (n_p + n_f, n_load, rank)."""
    shapes = {"w_in": (arch.n_past, arch.n_dof, arch.rank), "w_out": (arch.rank, arch.n_future, arch.n_dof),
              "b": (arch.n_future, arch.n_dof)}
    if arch.n_load:
        shapes["w_load"] = (arch.n_past + arch.n_future, arch.n_load, arch.rank)
    return shapes


@functools.partial(jax.jit, static_argnames="arch")
def init_params(key: jax.Array, arch: LinearArchitecture) -> Params:
    """Zero parameters (the map that predicts the training mean; normalized 0).

    Args:
        key: unused (the signature of :func:`jaxsync.surrogate.models._lstm.init_params`).
        arch: the architecture.

    Returns:
        The parameter pytree (module docstring), dtype ``arch.dtype``.
    """
    del key
    return {name: jnp.zeros(shape, jnp.dtype(arch.dtype)) for name, shape in param_shapes(arch).items()}


@functools.partial(jax.jit, static_argnames=("arch", "compute_dtype"))
def forward(
    params: Params,
    arch: LinearArchitecture,
    xs: jax.Array,
    load_parameter: jax.Array | None = None,
    dof_mask: jax.Array | None = None,
    compute_dtype: str | None = None,
    loads: jax.Array | None = None,
) -> jax.Array:
    """Predict the next ``n_future`` snapshots from ``n_past`` snapshots (unbatched).

    Args:
        params: one replica's parameters.
        arch: architecture.
        xs: normalized window (n_p, n_dof).
        load_parameter: must be None (the linear surrogate is unconditional).
        dof_mask: optional (n_dof,) padding mask; padded outputs are set to 0.
        compute_dtype: None (``arch.dtype`` throughout) or ``"bfloat16"``: parameters and
            window rounded to bfloat16, products accumulated in float32 (as the LSTM's,
            :mod:`jaxsync.surrogate.models`).
        loads: (n_p + n_f, n_load) normalized load signals at the window's sample times
            (past, then future), required when ``arch.n_load > 0``, None otherwise.

    Returns:
        Normalized predictions (n_f, n_dof), dtype ``arch.dtype``.
    """
    if xs.ndim != 2 or xs.shape != (arch.n_past, arch.n_dof):
        raise ConfigError(f"input window must have shape (n_past, n_dof) = {(arch.n_past, arch.n_dof)}, "
                          f"got {xs.shape}")
    if load_parameter is not None:
        raise ConfigError("the linear surrogate is unconditional: it takes no load parameter")
    check_compute_dtype(compute_dtype)
    loads = check_loads(arch, loads)
    xs = xs.astype(arch.dtype)
    if compute_dtype is None:
        coeffs = jnp.einsum("pd,pdr->r", xs, params["w_in"])
        if loads is not None:
            coeffs = coeffs + jnp.einsum("tu,tur->r", loads, params["w_load"])
        ys = jnp.einsum("r,rfd->fd", coeffs, params["w_out"]) + params["b"]
    else:
        low = lambda x: x.astype(compute_dtype)  # noqa: E731
        coeffs = jnp.einsum("pd,pdr->r", low(xs), low(params["w_in"]), preferred_element_type=jnp.float32)
        if loads is not None:
            coeffs = coeffs + jnp.einsum("tu,tur->r", low(loads), low(params["w_load"]),
                                         preferred_element_type=jnp.float32)
        ys = jnp.einsum("r,rfd->fd", low(coeffs), low(params["w_out"]), preferred_element_type=jnp.float32)
        ys = (ys + low(params["b"]).astype(jnp.float32)).astype(arch.dtype)
    if dof_mask is not None:
        ys = ys * dof_mask.astype(ys.dtype)[None]
    return ys


# ----------------------------------------------------------------------------- fit


def _fit_parts(x, y, signals, dof_counts, regularization: float, weight=None, max_rank: int | None = None,
               validation=None, select: bool = True):
    """One least-squares fit per part, on its real dofs, its ridge parameter chosen by
    rollouts (:func:`select_regularization`): ``([(w_in, w_out, b), ...], [r, ...])``.

    ``x`` (n_parts, n_windows, n_p, n_dof), ``y`` (n_parts, n_windows, n_f, n_dof) and
    ``signals`` (n_parts, n_windows, n_p + n_f, n_load) or None, normalized;
    ``validation``: ``(x, y, signals)`` more windows of the same layout that the rollouts
    may run over beside these; ``select`` False: no ridge chosen and no column left free
    (the plain ridge least squares of every column at ``regularization``: what an online
    refit on a run's few new windows does, where rollouts cannot choose)."""
    fits, chosen = [], []
    for p, count in enumerate(dof_counts):
        xp = np.asarray(x[p, :, :, :count], np.float64)
        yp = np.asarray(y[p, :, :, :count], np.float64)
        up = None if signals is None else np.asarray(signals[p], np.float64)
        windows = None
        if validation is not None and validation[0].shape[1]:
            vx, vy, vu = validation
            windows = (np.concatenate([xp, np.asarray(vx[p, :, :, :count], np.float64)]),
                       np.concatenate([yp, np.asarray(vy[p, :, :, :count], np.float64)]),
                       None if up is None else np.concatenate([up, np.asarray(vu[p], np.float64)]))
        if select:
            fit, r = select_regularization(xp, yp, up, regularization, weight, max_rank, windows)
        else:
            flat = xp.reshape(len(xp), -1) if up is None else np.concatenate(
                [xp.reshape(len(xp), -1), up.reshape(len(up), -1)], axis=1)
            fit, r = solve_least_squares(flat, yp.reshape(len(yp), -1), regularization, weight, max_rank), \
                regularization
        fits.append(fit)
        chosen.append(r)
    return fits, chosen


def _packed(fits, dof_counts, arch: "LinearArchitecture") -> Params:
    """The stacked, padded parameters (NumPy, ``arch.dtype``) of per-part fits of rank up
    to ``arch.rank``."""
    n_past, n_future, n_load = arch.n_past, arch.n_future, arch.n_load
    params = {name: np.zeros((len(fits),) + shape) for name, shape in param_shapes(arch).items()}
    for p, (count, (w_in, w_out, b)) in enumerate(zip(dof_counts, fits)):
        r = w_in.shape[1]
        if n_load:
            params["w_load"][p, :, :, :r] = w_in[n_past * count:].reshape(n_past + n_future, n_load, r)
            w_in = w_in[:n_past * count]
        params["w_in"][p, :, :count, :r] = w_in.reshape(n_past, count, r)
        params["w_out"][p, :r, :, :count] = w_out.reshape(r, n_future, count)
        params["b"][p, :, :count] = b.reshape(n_future, count)
    return {name: value.astype(arch.dtype) for name, value in params.items()}


def refit(params: Params, arch: "LinearArchitecture", x, y, signals, weight, dof_mask,
          regularization: float = DEFAULT_REGULARIZATION) -> Params:
    """The replicas fitted again by least squares on weighted windows, their rank (the
    shape of their factors) kept: a fit of higher rank is truncated to ``arch.rank``
    input directions. What online learning (:mod:`jaxsync.surrogate.training`) does to a
    linear surrogate: one exact solve in place of gradient steps.

    Args:
        params: the stacked replicas (their shapes are kept; the values are not used).
        arch: their architecture.
        x, y, signals: (n_parts, n_windows, ...) normalized windows as in training
            (``signals`` None without load input).
        weight: (n_windows,) window weights >= 0.
        dof_mask: (n_parts, n_dof) 1 on real dofs.
    """
    counts = [int(c) for c in np.asarray(dof_mask).sum(axis=1)]
    x, y = np.asarray(x), np.asarray(y)
    signals = None if signals is None else np.asarray(signals)
    weight = np.asarray(weight, np.float64)
    used = weight > 0  # unused window slots (zero weight) would also chain in the rollouts
    x, y, weight = x[:, used], y[:, used], weight[used]
    signals = None if signals is None else signals[:, used]
    fits, _ = _fit_parts(x, y, signals, counts, regularization, weight, max_rank=arch.rank)
    # a refit on a run's few new windows can explain them better one step ahead and still
    # drift when fed its own predictions: each part keeps its old map unless the new one
    # rolls out better over the windows it was fitted on (rollout_error over the chained ones)
    old = _unpacked(params, counts, arch)
    for p, count in enumerate(counts):
        xp, yp = x[p][..., :count].astype(np.float64), y[p][..., :count].astype(np.float64)
        up = None if signals is None else signals[p].astype(np.float64)
        before, after = rollout_error(old[p], xp, yp, up), rollout_error(fits[p], xp, yp, up)
        if np.isfinite(before) and not after < before:
            fits[p] = old[p]
    return _packed(fits, counts, arch)


def _unpacked(params: Params, dof_counts, arch: "LinearArchitecture") -> list:
    """The per-part fits ``[(w_in, w_out, b), ...]`` of flattened windows (float64) that
    :func:`_packed` stacked: the inverse of :func:`_packed` (rank padded to ``arch.rank``)."""
    n_past, n_future, n_load = arch.n_past, arch.n_future, arch.n_load
    fits = []
    for p, count in enumerate(dof_counts):
        r = arch.rank
        w_in = np.asarray(params["w_in"][p], np.float64)[:, :count, :r].reshape(n_past * count, r)
        if n_load:
            w_load = np.asarray(params["w_load"][p], np.float64)[..., :r].reshape((n_past + n_future) * n_load, r)
            w_in = np.concatenate([w_in, w_load])
        w_out = np.asarray(params["w_out"][p], np.float64)[:r, :, :count].reshape(r, n_future * count)
        b = np.asarray(params["b"][p], np.float64)[:, :count].reshape(n_future * count)
        fits.append((w_in, w_out, b))
    return fits


def _masked_mse(params: Params, arch: LinearArchitecture, x, y, dof_mask, u=None) -> np.ndarray:
    """(n_parts,) MSE of the stacked replicas over windows, steps and real dofs
    (normalized units; the LSTM's :func:`~jaxsync.surrogate.training.masked_mse`); ``u``
    (n_parts, n_windows, n_p + n_f, n_load) the windows' load signals (load input only)."""
    if x.shape[1] == 0:  # no windows (e.g. no validation split)
        return np.full(x.shape[0], np.nan)
    u_axis = None if u is None else 0
    per_window = jax.vmap(lambda p, xs, m, us: forward(p, arch, xs, None, m, loads=us), in_axes=(None, 0, None, u_axis))
    pred = np.asarray(jax.vmap(per_window, in_axes=(0, 0, 0, u_axis))(
        params, x, dof_mask, None if u is None else jnp.asarray(u, arch.dtype)), np.float64)
    mask = np.asarray(dof_mask, np.float64)[:, None, None, :]
    sq = np.square(pred - np.asarray(y, np.float64)) * mask
    return sq.sum(axis=(1, 2, 3)) / (x.shape[1] * arch.n_future * mask.sum(axis=(1, 2, 3)))


def fit_affine(data: ReplicaData, regularization: float = DEFAULT_REGULARIZATION,
               dtype: str = "float32") -> tuple[LinearArchitecture, Params]:
    """The least-squares affine map of every replica's training windows (ARX with the
    windows' load signals): ``(arch, stacked params)``, the rank the largest any part
    needs. What :func:`fit_linear` fits, and the LSTM's linear highway starts from
    (:mod:`jaxsync.surrogate.models`).

    Raises:
        ConfigError: no training windows."""
    n_parts, n_windows, n_past, n_dof = data.x_train.shape
    n_future = data.y_train.shape[2]
    if n_windows == 0:
        raise ConfigError("no training windows: use a longer run, a larger train fraction or a smaller n_s")
    signals = data.signal_train
    n_load = 0 if signals is None else signals.shape[-1]
    validation = (data.x_val, data.y_val, data.signal_val)
    fits, _ = _fit_parts(data.x_train, data.y_train, signals, data.dof_counts, regularization,
                         validation=validation)
    rank = max(1, max(w_in.shape[1] for w_in, _, _ in fits))
    arch = LinearArchitecture(n_dof=n_dof, rank=rank, n_past=n_past, n_future=n_future, dtype=dtype, n_load=n_load)
    return arch, _packed(fits, data.dof_counts, arch)


def fit_linear(data: ReplicaData, config: LinearFitConfig | None = None, dtype: str = "float32") -> TrainResult:
    """Fit one linear surrogate per part by least squares on the training windows.

    Each part is solved alone on its real dofs (:func:`solve_least_squares` with inputs
    the flattened (n_p, n_dof_p) windows, targets the flattened (n_f, n_dof_p) ones), then
    zero-padded and stacked like the LSTM's replicas. With the windows' load signals
    (``data.signal_train``, the load input), the flattened (n_p + n_f, n_load) signals are
    appended to each input row (ARX, module docstring) and the model takes ``n_load`` of
    them.

    Args:
        data: the normalized windows of all parts
            (:func:`~jaxsync.surrogate.training.stack_replicas`; float32 from
            :func:`~jaxsync.surrogate.training.build_dataset`, or float64 for an exact fit).
        config: the regularization (default :class:`LinearFitConfig`).
        dtype: dtype of the stored parameters and of prediction.

    Returns:
        A :class:`~jaxsync.surrogate.training.TrainResult` of one "epoch" (the solve):
        ``train_loss`` and ``val_loss`` (1, n_parts) MSE in normalized units,
        ``initial_val_loss`` that of the zero map (the training mean), ``seconds_per_epoch``
        the solve's wall time, ``steps_per_epoch`` 0 (no gradient steps), ``config`` the
        :class:`LinearFitConfig`.
    """
    from jaxsync.surrogate.training._train import TrainResult

    config = LinearFitConfig() if config is None else config
    if dtype not in _DTYPES:
        raise ConfigError(f"dtype must be one of {_DTYPES}, got {dtype!r}")
    if np.any(np.asarray(data.load_parameter_train) != 0):
        raise ConfigError("the linear surrogate is unconditional: it cannot use load parameters; "
                          "train the LSTM (model='lstm', n_cond_repeat > 0) for a conditional surrogate")
    started = time.perf_counter()
    arch, params = fit_affine(data, config.regularization, dtype)
    seconds = time.perf_counter() - started
    mask = data.dof_mask
    zero = {name: np.zeros_like(value) for name, value in params.items()}
    return TrainResult(
        params=params, arch=arch, config=config, dof_counts=tuple(int(c) for c in data.dof_counts),
        mean=np.asarray(data.mean), std=np.asarray(data.std),
        train_loss=_masked_mse(params, arch, data.x_train, data.y_train, mask, data.signal_train)[None],
        val_loss=_masked_mse(params, arch, data.x_val, data.y_val, mask, data.signal_val)[None],
        initial_val_loss=_masked_mse(zero, arch, data.x_val, data.y_val, mask, data.signal_val),
        seconds_per_epoch=seconds, compile_seconds=0.0, steps_per_epoch=0,
        signal_scale=data.signal_scale, load_inputs=data.load_inputs,
    )
