"""Sample-refill prediction (paper Algorithm 3): index sets, and the network applied to them.

At the current step ``n`` (the last step whose displacements are known), the network is
applied ``n_s`` times, ``i = 0 .. n_s - 1``, with

    N_p^i = { n + 1 + i - n_s (n_p - j) : j = 0 .. n_p - 1 }   (inputs)
    N_f^i = { n + 1 + i + n_s j         : j = 0 .. n_f - 1 }   (targets)

Inputs and targets are both spaced n_s steps apart, the last input lies one stride
before the first target, and the union of the N_f^i over i is exactly
n + 1 .. n + n_s n_f, each step once.  The inputs span the last n_s n_p steps
n + 1 - n_s n_p .. n, so refill needs n + 1 >= n_s n_p (steps counted from 0).  With
``buffer`` the rows of those last n_s n_p steps, :func:`refill_windows` gathers the
inputs of all applications by a reshape and :func:`refill_scatter` lays their outputs out
in step order (application i fills rows i, i + n_s, ... of the next n_s n_f steps).
:func:`refill_predict` does both around one batched call of the network (the n_s
applications are independent).

The smooth refill (:func:`smooth_refill`, what :class:`jaxsync.surrogate.Surrogate`
writes by default) keeps of the n_s applications only the mean of each block of n_s
consecutive steps, i.e. the mean over the applications of their prediction of target j.
:func:`refill_block_means` estimates those means from a few applications evenly spaced
through the block (:func:`refill_applications`: the midpoint rule over the application
index), which costs that many network calls per refill instead of n_s.

A refill *cycle* (:func:`refill_cycle`) predicts the next n_s n_f steps and moves the
buffer on by them; a rollout (:func:`refill_rollout`) runs cycles, each consuming the
previous predictions.  Both take any predictor of one part -- an object with
``predict(buffer, step) -> (n_s n_f, n_dof)`` and sizes ``n_s``, ``n_future``, such as
:class:`jaxsync.surrogate.Surrogate` -- so that the offline evaluation, full-system
modeling and the synchronization-avoiding solver step through cycles the same way.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxsync.errors import ConfigError
from jaxsync.surrogate.models._architecture import Architecture, forward
from jaxsync.surrogate.models._lstm import Params
from jaxsync.surrogate.training._data import normalize

__all__ = ["refill_input_steps", "refill_target_steps", "refill_index_sets", "refill_windows",
           "refill_scatter", "refill_predict", "refill_applications", "refill_block_means", "smooth_refill",
           "smooth_curve", "refill_cycle", "refill_rollout", "DEFAULT_REFILL_SAMPLES"]

#: Network applications a smooth refill evaluates per refill (:func:`refill_applications`):
#: the block means it keeps are averages over the application index, and 16 evenly spaced
#: applications estimate them by the midpoint rule, whose error is (1/16)^2 / 24 = 1.6e-4
#: of the predictions' second difference across a block (a smooth response) -- far below
#: the smoothing's own interpolation error, O((n_s dt)^2 u''). A refill then costs 16
#: network calls instead of n_s (the vessel demo's n_s = 1 000: 62 times fewer).
DEFAULT_REFILL_SAMPLES = 16


def refill_input_steps(n: int, n_s: int, n_past: int, i: int) -> np.ndarray:
    """N_p^i: steps whose snapshots are the inputs of refill application ``i``.

    ``N_p^i = { n + 1 + i - n_s (n_p - j) : j = 0 .. n_p - 1 }`` (increasing).

    Args:
        n: current step (last known).
        n_s: sampling stride.
        n_past: n_p, input snapshots per window.
        i: application index, 0 <= i < n_s.
    """
    _check_refill_args(n, n_s, n_past, 1, i)
    return n + 1 + i - n_s * (n_past - np.arange(n_past, dtype=np.int64))


def refill_target_steps(n: int, n_s: int, n_future: int, i: int) -> np.ndarray:
    """N_f^i: steps that refill application ``i`` predicts.

    ``N_f^i = { n + 1 + i + n_s j : j = 0 .. n_f - 1 }`` (increasing).
    """
    _check_refill_args(n, n_s, 1, n_future, i)
    return n + 1 + i + n_s * np.arange(n_future, dtype=np.int64)


def refill_index_sets(n: int, n_s: int, n_past: int, n_future: int) -> tuple[np.ndarray, np.ndarray]:
    """All refill index sets at step ``n``.

    Returns:
        ``(inputs (n_s, n_p), targets (n_s, n_f))``: row i is N_p^i, respectively N_f^i.
    """
    inputs = np.stack([refill_input_steps(n, n_s, n_past, i) for i in range(n_s)])
    targets = np.stack([refill_target_steps(n, n_s, n_future, i) for i in range(n_s)])
    return inputs, targets


def refill_windows(buffer, n_s: int, n_past: int):
    """Inputs of the n_s refill applications from the last n_s n_p steps.

    Args:
        buffer: (n_s n_p, ...) rows of steps n + 1 - n_s n_p .. n (NumPy or JAX array).

    Returns:
        (n_s, n_p, ...): entry [i, j] is row ``i + j n_s``, i.e. step N_p^i[j].
    """
    return buffer.reshape((n_past, n_s) + buffer.shape[1:]).swapaxes(0, 1)


def refill_scatter(predictions, n_s: int):
    """Lay the outputs of the n_s refill applications out in step order.

    Args:
        predictions: (n_s, n_f, ...), entry [i, j] predicting step N_f^i[j].

    Returns:
        (n_s n_f, ...): row k is step n + 1 + k; row ``i + j n_s`` is entry [i, j].
    """
    n_future = predictions.shape[1]
    return predictions.swapaxes(0, 1).reshape((n_future * n_s,) + predictions.shape[2:])


def _check_refill_args(n, n_s, n_past, n_future, i):
    if min(n_s, n_past, n_future) < 1:
        raise ConfigError(f"n_s, n_past, n_future must be >= 1, got {n_s}, {n_past}, {n_future}")
    if not 0 <= i < n_s:
        raise ConfigError(f"refill application index i must be in [0, n_s={n_s}), got {i}")
    if n + 1 < n_s * n_past:
        raise ConfigError(
            f"refill at step n={n} needs n + 1 >= n_s * n_p = {n_s * n_past} known steps; "
            "run more synchronized steps first"
        )


def _check_buffer(arch, buffer, n_s):
    if buffer.shape != (n_s * arch.n_past, arch.n_dof):
        raise ConfigError(f"refill buffer must have shape (n_s*n_p, n_dof) = {(n_s * arch.n_past, arch.n_dof)}, "
                          f"got {buffer.shape}")


def _network_outputs(params, arch, mean, std, buffer, n_s, load_parameter, dof_mask, compute_dtype, loads,
                     applications=None):
    """The normalized predictions (n_apps, n_f, n_dof) of refill applications
    ``applications`` (static indices; None: all n_s), in the network's dtype."""
    _check_buffer(arch, buffer, n_s)
    n_past = arch.n_past
    windows = refill_windows(buffer, n_s, n_past)  # (n_s, n_p, n_dof), rows N_p^i
    if applications is not None:  # chosen before normalizing: only their rows are read
        windows = windows[applications]
    windows = normalize(windows, mean[None, None], std[None, None]).astype(arch.dtype)  # every row alike
    if loads is None:
        return jax.vmap(lambda x: forward(params, arch, x, load_parameter, dof_mask, compute_dtype))(windows)
    expected = (n_s * (n_past + arch.n_future), arch.n_load)
    if tuple(loads.shape) != expected:
        raise ConfigError(f"refill load signals must have shape (n_s*(n_p+n_f), n_load) = {expected}, "
                          f"got {loads.shape}")
    signal_windows = refill_windows(loads, n_s, n_past + arch.n_future)  # (n_s, n_p + n_f, n_load)
    if applications is not None:
        signal_windows = signal_windows[applications]
    return jax.vmap(lambda x, u: forward(params, arch, x, load_parameter, dof_mask, compute_dtype, u))(
        windows, signal_windows)


def refill_predict(
    params: Params,
    arch: Architecture,
    mean: jax.Array,
    std: jax.Array,
    buffer: jax.Array,
    n_s: int,
    load_parameter: jax.Array | None = None,
    dof_mask: jax.Array | None = None,
    compute_dtype: str | None = None,
    loads: jax.Array | None = None,
) -> jax.Array:
    """Predict the next n_s n_f steps from the last n_s n_p steps (one replica, unbatched).

    Args:
        params: one replica's parameters.
        arch: architecture (LSTM or linear: :mod:`jaxsync.surrogate.models`).
        mean, std: (n_dof,) normalization, solver units.
        buffer: (n_s n_p, n_dof) displacements of steps n + 1 - n_s n_p .. n, solver units.
        n_s: sampling stride the network was trained with.
        load_parameter: scalar load parameter (conditional networks).
        dof_mask: optional (n_dof,) padding mask.
        compute_dtype: None or ``"bfloat16"``, the network's reduced-precision inference
            (:func:`~jaxsync.surrogate.models.forward`); the normalization stays in
            the dtypes of ``buffer`` and ``mean``.
        loads: a model with load input: (n_s (n_p + n_f), n_load) its normalized load
            signals at steps n + 1 - n_s n_p .. n + n_s n_f (the buffer's steps, then the
            predicted ones); application i reads rows i, i + n_s, ... (its N_p^i, then its
            N_f^i). None otherwise.

    Returns:
        (n_s n_f, n_dof) predicted displacements of steps n + 1 .. n + n_s n_f, in the
        dtype of ``mean``.
    """
    pred = _network_outputs(params, arch, mean, std, buffer, n_s, load_parameter, dof_mask, compute_dtype, loads)
    return refill_scatter(pred, n_s).astype(mean.dtype) * std[None] + mean[None]


def refill_applications(n_s: int, samples: int | None) -> np.ndarray:
    """The refill applications a smooth refill evaluates: every one of the n_s
    (``samples`` None or >= n_s), or ``samples`` evenly spaced through them, the
    midpoints ``floor((k + 1/2) n_s / samples)``, k = 0 .. samples - 1 (the midpoint
    rule for the mean over the application index).

    Raises:
        ConfigError: ``samples`` is not None or an integer >= 1."""
    if samples is not None and (isinstance(samples, bool) or not isinstance(samples, (int, np.integer))
                                or samples < 1):
        raise ConfigError(f"refill samples must be an integer >= 1 (network applications per smooth refill) or "
                          f"None (all n_s), got {samples!r}")
    if samples is None or samples >= n_s:
        return np.arange(n_s)
    return np.floor((np.arange(samples) + 0.5) * n_s / samples).astype(np.int64)


def refill_block_means(
    params: Params,
    arch: Architecture,
    mean: jax.Array,
    std: jax.Array,
    buffer: jax.Array,
    n_s: int,
    load_parameter: jax.Array | None = None,
    dof_mask: jax.Array | None = None,
    compute_dtype: str | None = None,
    loads: jax.Array | None = None,
    samples: int | None = DEFAULT_REFILL_SAMPLES,
) -> jax.Array:
    """The means the smooth refill keeps: for each of the n_f blocks of n_s steps that
    a refill predicts, the mean over the refill applications of their prediction of it,
    estimated from the applications of :func:`refill_applications` (``samples`` network
    calls; None: all n_s, the exact block means of :func:`refill_predict`'s rows).

    Arguments as :func:`refill_predict`, and ``samples``.

    Returns:
        (n_f, n_dof) block means [solver units], in the dtype of ``mean``; block j
        covers steps n + 1 + j n_s .. n + (j + 1) n_s.
    """
    applications = refill_applications(n_s, samples)
    pred = _network_outputs(params, arch, mean, std, buffer, n_s, load_parameter, dof_mask, compute_dtype, loads,
                            None if len(applications) == n_s else applications)
    return pred.astype(mean.dtype).mean(axis=0) * std[None] + mean[None]


def smooth_refill(pred, last, n_s: int):
    """The refill's predictions as one smooth curve that starts at the last known value.

    Consecutive steps of a refill come from different applications (row k from
    application k mod n_s), whose errors are independent: written into the solver step
    after step, they jitter, and the jitter excites the structure's high frequencies,
    which the weak damping hardly removes. Here each block of n_s consecutive rows (every
    application once) is replaced by its mean, and the curve of :func:`smooth_curve` is
    drawn through those means.

    Args:
        pred: (n_s n_f, n_dof) predictions of steps n + 1 .. n + n_s n_f (step order).
        last: (n_dof,) the displacement at step n.
        n_s: sampling stride.

    Returns:
        (n_s n_f, n_dof), the dtype of ``pred``.
    """
    length = pred.shape[0]
    n_f = length // n_s
    if n_f * n_s != length:
        raise ConfigError(f"smooth_refill: {length} predicted rows are not a multiple of n_s={n_s}")
    return smooth_curve(pred.reshape((n_f, n_s) + pred.shape[1:]).mean(axis=1), last, n_s)


def smooth_curve(means, last, n_s: int):
    """The curve through a refill's block means: each mean is placed at its block's
    centre, and the steps in between are interpolated linearly from ``last`` (the known
    value at the step before the cycle) through the means; after the last block's centre
    the last segment is extrapolated. The curve is continuous from cycle to cycle and has
    no step-to-step jitter; for a smooth signal it differs from the exact values by
    O((n_s dt)^2 d'') (the resolution at which the networks see the signal anyway).

    Args:
        means: (n_f, n_dof) block means (:func:`refill_block_means`); block j covers steps
            n + 1 + j n_s .. n + (j + 1) n_s.
        last: (n_dof,) the displacement at step n.
        n_s: sampling stride.

    Returns:
        (n_s n_f, n_dof) values of steps n + 1 .. n + n_s n_f, the dtype of ``means``.
    """
    n_f = means.shape[0]
    length = n_f * n_s
    knots = np.concatenate([[0.0], n_s * np.arange(n_f) + 0.5 * (n_s + 1)])  # step offsets after n
    values = jnp.concatenate([jnp.asarray(last, means.dtype)[None], means])
    t = np.arange(1, length + 1, dtype=np.float64)
    segment = np.clip(np.searchsorted(knots, t, side="right") - 1, 0, n_f - 1)  # the last one extrapolates
    weight = ((t - knots[segment]) / (knots[segment + 1] - knots[segment])).astype(np.float64)
    weight = jnp.asarray(weight, means.dtype).reshape((-1,) + (1,) * (means.ndim - 1))
    return values[segment] + weight * (values[segment + 1] - values[segment])


def refill_cycle(predictor, buffer, step):
    """One refill cycle of ONE part: ``(predictions, buffer moved on)``.

    Args:
        predictor: a one-part predictor (``predict(buffer, step)``).
        buffer: (n_s n_p, n_dof) displacements of steps step + 1 - n_s n_p .. step.
        step: the last known step.

    Returns:
        The (n_s n_f, n_dof) predictions of steps step + 1 .. step + n_s n_f in the dtype
        of ``buffer``, and the buffer of the last n_s n_p of all those steps.
    """
    pred = predictor.predict(buffer, step).astype(buffer.dtype)
    return pred, jnp.concatenate([buffer, pred])[-buffer.shape[0]:]


def refill_rollout(predictor, buffer, step0, n_cycles: int):
    """``n_cycles`` refill cycles of ONE part, each consuming the predictions of the ones
    before (the truth is never looked at again).

    Args:
        predictor: a one-part predictor (``predict(buffer, step)``, ``n_s``, ``n_future``).
        buffer: (n_s n_p, n_dof) displacements of steps step0 + 1 - n_s n_p .. step0.
        step0: the last known step (a Python or JAX integer).
        n_cycles: refill cycles (static).

    Returns:
        (n_cycles n_s n_f, n_dof) predictions of steps step0 + 1 .. step0 +
        n_cycles n_s n_f, in the dtype of ``buffer``.
    """
    buffer = jnp.asarray(buffer)
    steps = predictor.n_s * predictor.n_future

    def cycle(buf, c):
        pred, buf = refill_cycle(predictor, buf, step0 + c * steps)
        return buf, pred

    _, blocks = jax.lax.scan(cycle, buffer, jnp.arange(n_cycles, dtype=jnp.result_type(step0)))
    return blocks.reshape(-1, buffer.shape[1])
