"""Reduced-precision inference of the surrogates, and the check that it keeps accuracy.

:meth:`Surrogate.with_inference_dtype("bfloat16") <jaxsync.surrogate.Surrogate.with_inference_dtype>`
runs the networks with bfloat16 weights and activations and float32 accumulation
(:mod:`jaxsync.surrogate.models`). bfloat16 keeps 8 significant bits: every weight, input
and hidden state is rounded by up to 2^-9 = 0.2 % of itself, so the predictions move.
How far depends on the trained network, so it is measured here on windows of the
network's own inputs, against the same network in full precision:

    deviation_p = RMS(f_low(x) - f(x)) / RMS(f(x))

over part p's windows x and real (unpadded) dofs, in normalized units (each dof divided
by its training standard deviation), f the network in ``arch.dtype``, f_low in the
reduced dtype. :func:`check_inference_precision` refuses (:class:`~jaxsync.errors.InferencePrecisionError`)
or flags (:class:`ReducedPrecisionWarning`) a deviation above the bound;
:func:`reduced_precision` checks, then returns the reduced surrogate.

The bound, :data:`DEFAULT_BOUND` = 1 %. Rounding the operands of one matrix product to
bfloat16 with float32 accumulation perturbs its result by about u = 2^-9 relative (the
rounding errors of the n terms of a dot product have random signs: their sum grows like
sqrt(n) while the product itself grows like n for correlated terms, and like sqrt(n) for
uncorrelated ones, so the relative error stays near u). A well-conditioned network adds
a few such perturbations per layer and per recurrent step, and the recurrent map of a
trained LSTM is contracting (the forget gate is below 1), so they do not compound: a
deviation of a few u, up to 1 %, is what bfloat16 may cost a network that is insensitive
to its inputs' last digits (the trained LSTMs of the default and skewed cantilever cases
measure 0.1 %, ten times below the bound; ``benchmarks/bench_surrogates.py``). A
larger deviation means the network amplifies rounding -- predicting from small
differences of nearly equal inputs, or a recurrence near instability -- and then the
bfloat16 error is no longer small next to the surrogate's own one: the networks this
package trains err online by 1-2 % of the amplitude (the paper's target for the free end
is 2 %), so a 1 % per-refill deviation already spends half of that budget before the
rollout compounds it. The bound is a gate on one refill; the online accuracy is measured
by the benchmark.

Measured (``benchmarks/bench_surrogates.py``, 1e5 steps, 2 parts, the experiments' trained
LSTMs): bfloat16 inference leaves the online errors where they were (free end 1.48 %
against 1.46 % of its amplitude in the default case, 1.40 % against 1.37 % in the skewed
one) but saves little on a CPU, whose XLA backend has no faster bfloat16 products (t_d
5-15 % lower); the saving it is for is on accelerators with bfloat16 matrix units.
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import Literal, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxsync.errors import ConfigError, InferencePrecisionError
from jaxsync.surrogate._model import Surrogate
from jaxsync.surrogate.models._architecture import forward
from jaxsync.surrogate.models._protocol import check_compute_dtype
from jaxsync.surrogate.training._data import make_windows, normalize, subsample

__all__ = ["DEFAULT_BOUND", "ReducedPrecisionWarning", "InferencePrecisionReport", "surrogate_windows",
           "surrogate_signal_windows",
           "inference_deviation", "check_inference_precision", "reduced_precision"]

#: Largest accepted relative deviation of reduced-precision inference from full precision,
#: per part, in normalized units (module docstring: about 5 bfloat16 roundings, 2^-9 each).
DEFAULT_BOUND = 0.01


class ReducedPrecisionWarning(UserWarning):
    """Reduced-precision inference deviates from full precision by more than the bound
    (:func:`check_inference_precision` with ``on_excess="warn"``)."""


@dataclasses.dataclass(frozen=True)
class InferencePrecisionReport:
    """What :func:`check_inference_precision` measured.

    Attributes:
        dtype: the reduced compute dtype ("bfloat16").
        bound: the largest accepted relative deviation.
        deviation: (n_parts,) RMS(f_low - f) / RMS(f) per part (module docstring).
        max_abs: (n_parts,) largest |f_low - f| per part, normalized units.
        n_windows: windows per part the measure used.
    """

    dtype: str
    bound: float
    deviation: np.ndarray
    max_abs: np.ndarray
    n_windows: int

    @property
    def worst(self) -> float:
        return float(np.max(self.deviation))

    @property
    def passed(self) -> bool:
        return bool(self.worst <= self.bound)

    def to_dict(self) -> dict:
        return {"dtype": self.dtype, "bound": float(self.bound), "deviation": [float(v) for v in self.deviation],
                "max_abs": [float(v) for v in self.max_abs], "n_windows": int(self.n_windows),
                "worst": self.worst, "passed": self.passed}


def surrogate_windows(surrogate: Surrogate, histories: Sequence[np.ndarray], *, offset: int = 0,
                      max_windows: int | None = None) -> np.ndarray:
    """The surrogate's input windows from shared-dof histories, normalized as it normalizes.

    Args:
        surrogate: the replicas (n_parts of them).
        histories: per part, (n_steps, count) shared displacements at every step [solver
            units] (e.g. ``trajectory.parts[p].shared_displacement`` of a synchronized run).
        offset: first step sampled (then every n_s-th).
        max_windows: keep at most this many windows, evenly spread (default all).

    Returns:
        (n_parts, n_windows, n_p, n_dof) float32 windows, zero on padded dofs.
    """
    if len(histories) != surrogate.n_parts:
        raise ConfigError(f"{len(histories)} histories given for {surrogate.n_parts} parts")
    mean, std = np.asarray(surrogate.mean), np.asarray(surrogate.std)
    out = []
    for p, history in enumerate(histories):
        history = np.asarray(history, np.float64)
        if history.ndim != 2 or history.shape[1] > surrogate.n_dof:
            raise ConfigError(f"history of part {p} must be (n_steps, <= {surrogate.n_dof}), got {history.shape}")
        padded = np.pad(history, ((0, 0), (0, surrogate.n_dof - history.shape[1])))
        z = normalize(subsample(padded, surrogate.n_s, offset), mean[p][None], std[p][None])
        out.append(make_windows(z, surrogate.n_past, 1)[0])
    x = np.stack(out).astype(np.float32)
    if max_windows is not None and x.shape[1] > max_windows:
        x = x[:, np.unique(np.linspace(0, x.shape[1] - 1, int(max_windows)).round().astype(np.int64))]
    return x


def surrogate_signal_windows(surrogate: Surrogate, n_steps: int, *, offset: int = 0,
                             max_windows: int | None = None) -> np.ndarray:
    """The load signals of the windows :func:`surrogate_windows` makes from histories of
    ``n_steps`` steps (same ``offset`` and ``max_windows``), normalized as the surrogate
    normalizes them, for a surrogate with load input bound to its problem
    (:meth:`~jaxsync.surrogate.Surrogate.for_problem`).

    Returns:
        (n_parts, n_windows, n_p + n_f, n_load) float32 (the same for every part).
    """
    if not surrogate.n_load:
        raise ConfigError("these surrogates take no load signals (trained without load input)")
    if surrogate.load_signals is None:
        raise ConfigError("bind the surrogates to their problem first: surrogate.for_problem(problem)")
    n_s, n_p, n_f = surrogate.n_s, surrogate.n_past, surrogate.n_future
    n_windows = len(range(offset, n_steps, n_s)) - n_p  # those of make_windows(..., n_p, 1)
    if n_windows < 1:
        raise ConfigError(f"histories of {n_steps} steps make no window of n_p={n_p} snapshots every n_s={n_s} steps")
    table = np.asarray(surrogate.load_signals.at_steps(0, offset + n_s * (n_windows + n_p + n_f)), np.float64)
    rows = offset + n_s * (np.arange(n_windows)[:, None] + np.arange(n_p + n_f)[None, :])
    if max_windows is not None and n_windows > max_windows:
        rows = rows[np.unique(np.linspace(0, n_windows - 1, int(max_windows)).round().astype(np.int64))]
    scale = np.asarray(surrogate.signal_scale, np.float64)  # (n_parts, n_load)
    return (table[rows][None] / scale[:, None, None, :]).astype(np.float32)


def _outputs(surrogate: Surrogate, windows, compute_dtype, signals=None):
    """(n_parts, n_windows, n_f, n_dof) normalized predictions of every part's windows
    (``signals``: their load signals, surrogates with load input)."""
    arch = surrogate.arch
    mask = jnp.asarray(surrogate.dof_mask, arch.dtype)
    if surrogate.n_load and signals is None:
        raise ConfigError(f"these surrogates also read {surrogate.n_load} load signal(s): pass the windows' signals "
                          "(surrogate_signal_windows, after surrogate.for_problem(problem))")
    if signals is None:
        signals = jnp.zeros(windows.shape[:2] + (0,), arch.dtype)  # a placeholder per window, not read
    signals = jnp.asarray(signals, arch.dtype)

    def part(params, x, load, m, u):
        return jax.vmap(lambda w, uw: forward(params, arch, w, load, m, compute_dtype,
                                              uw if surrogate.n_load else None))(x, u)

    if arch.conditional:
        return jax.vmap(part)(surrogate.params, windows, jnp.asarray(surrogate.load_parameter), mask, signals)
    return jax.vmap(lambda params, x, m, u: part(params, x, None, m, u))(surrogate.params, windows, mask, signals)


def inference_deviation(surrogate: Surrogate, windows, dtype: str = "bfloat16",
                        signals=None) -> tuple[np.ndarray, np.ndarray]:
    """``(relative (n_parts,), max_abs (n_parts,))``: the deviation of ``dtype`` inference
    from the network's own dtype on ``windows`` (n_parts, n_windows, n_p, n_dof),
    normalized (as :func:`surrogate_windows` gives them), with their load signals
    ``signals`` (:func:`surrogate_signal_windows`) for surrogates with load input; module
    docstring."""
    check_compute_dtype(dtype)
    if dtype is None:
        raise ConfigError("inference_deviation compares a reduced dtype with full precision: give dtype='bfloat16'")
    windows = jnp.asarray(windows, surrogate.arch.dtype)
    if windows.ndim != 4 or windows.shape[0] != surrogate.n_parts or windows.shape[2:] != (surrogate.n_past,
                                                                                            surrogate.n_dof):
        raise ConfigError(f"windows must be (n_parts, n_windows, n_p, n_dof) = ({surrogate.n_parts}, n, "
                          f"{surrogate.n_past}, {surrogate.n_dof}), got {windows.shape}")
    full = np.asarray(_outputs(surrogate, windows, None, signals), np.float64)
    low = np.asarray(_outputs(surrogate, windows, dtype, signals), np.float64)
    mask = np.asarray(surrogate.dof_mask, bool)[:, None, None, :]
    diff = np.where(mask, low - full, 0.0)
    full = np.where(mask, full, 0.0)
    count = np.maximum(mask.sum(axis=(1, 2, 3)) * windows.shape[1] * surrogate.n_future, 1)
    rms_diff = np.sqrt(np.square(diff).sum(axis=(1, 2, 3)) / count)
    rms_full = np.sqrt(np.square(full).sum(axis=(1, 2, 3)) / count)
    relative = rms_diff / np.where(rms_full > 0, rms_full, 1.0)
    return relative, np.abs(diff).max(axis=(1, 2, 3))


def check_inference_precision(surrogate: Surrogate, windows, dtype: str = "bfloat16", *,
                              bound: float = DEFAULT_BOUND, signals=None,
                              on_excess: Literal["raise", "warn"] = "raise") -> InferencePrecisionReport:
    """Measure the deviation of ``dtype`` inference (:func:`inference_deviation`) and
    refuse or flag it above ``bound``.

    Args:
        surrogate: the replicas (their own ``inference_dtype`` is ignored: the network in
            ``arch.dtype`` is the reference).
        windows: (n_parts, n_windows, n_p, n_dof) normalized input windows
            (:func:`surrogate_windows`), ideally of the run the surrogate will predict.
        dtype: the reduced dtype, ``"bfloat16"``.
        signals: (n_parts, n_windows, n_p + n_f, n_load) the windows' normalized load
            signals (:func:`surrogate_signal_windows`); surrogates with load input only.
        bound: largest accepted relative deviation of any part (default
            :data:`DEFAULT_BOUND`, justified in the module docstring).
        on_excess: ``"raise"`` (:class:`~jaxsync.errors.InferencePrecisionError`) or
            ``"warn"`` (:class:`ReducedPrecisionWarning`, and the report is returned).

    Returns:
        :class:`InferencePrecisionReport`.
    """
    if on_excess not in ("raise", "warn"):
        raise ConfigError(f"on_excess must be 'raise' or 'warn', got {on_excess!r}")
    if not (isinstance(bound, (int, float)) and np.isfinite(bound) and bound > 0):
        raise ConfigError(f"bound must be a positive number, got {bound!r}")
    relative, max_abs = inference_deviation(surrogate, windows, dtype, signals)
    report = InferencePrecisionReport(dtype=dtype, bound=float(bound), deviation=relative, max_abs=max_abs,
                                      n_windows=int(np.shape(windows)[1]))
    if not report.passed:
        worst = int(np.argmax(relative))
        message = (f"{dtype} inference deviates from {surrogate.arch.dtype} by {100 * report.worst:.3g} % "
                   f"(RMS, normalized units) on part {worst}, above the bound {100 * bound:.3g} %: the network "
                   f"amplifies rounding; keep it in {surrogate.arch.dtype}")
        if on_excess == "raise":
            raise InferencePrecisionError(message)
        warnings.warn(message, ReducedPrecisionWarning, stacklevel=2)
    return report


def reduced_precision(surrogate: Surrogate, windows, dtype: str = "bfloat16", *, bound: float = DEFAULT_BOUND,
                      on_excess: Literal["raise", "warn"] = "raise",
                      signals=None) -> tuple[Surrogate, InferencePrecisionReport]:
    """``(surrogate computing in dtype, report)`` after :func:`check_inference_precision`
    (which raises, or warns, above ``bound``; ``signals``: the windows' load signals)."""
    report = check_inference_precision(surrogate, windows, dtype, bound=bound, on_excess=on_excess,
                                       signals=signals)
    return surrogate.with_inference_dtype(dtype), report
