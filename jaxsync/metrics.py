"""Error metrics of synchronization-avoiding runs (paper section 6, eqs. 24-26).

All functions take plain NumPy arrays; T is the number of compared snapshots, n the
number of nodes, N_a the number of shared nodes, n_c the number of parts.

- :func:`l2_error` e(t) = ||d(t) - d_hat(t)||_2 over all dofs (eq. 24).
- :func:`node_error` at one node (one displacement component, or the vector): the largest
  error over the run, also as a fraction of the node's largest amplitude, the final and
  the rms error (the free end of the paper's figures, the monitored nodes of a report).
- :func:`shared_node_errors` at the shared nodes, where every node is predicted by each
  of the (at least two) parts that hold it:
  es(t): mean over shared nodes and over the parts predicting them of the component-mean
  absolute error (1/3) sum_c |d_hat_{p,i,c}(t) - d_{i,c}(t)| (eq. 25);
  es_hat(t): the same with the truth replaced by the other part's prediction, averaged
  over the pairs of parts that share the node -- it needs no reference, so it can monitor
  a run (eq. 26); et_j: the time average of each node's error.
- :func:`estimate_quality`: how well es_hat tracks es over a run (section 6's promise
  that the estimate can stand in for the error).
- :func:`peak_strain`: the largest principal Green-Lagrange strain (and its logarithmic
  stretch) over the elements and saved snapshots of a displacement history: how far a
  run is from small strain.
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np

from .errors import ProblemError

__all__ = ["l2_error", "NodeError", "node_error", "SharedNodeErrors", "shared_node_errors", "predictions_by_node",
           "EstimateQuality", "estimate_quality", "PeakStrain", "peak_strain",
           "principal_strain_peaks", "peak_of"]


def l2_error(reference: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    """e(t) (T,) = ||d(t) - d_hat(t)||_2 over all dofs [cm].

    Args:
        reference, predicted: (T, n, 3) (or (T, n_dof)) displacements.
    """
    reference, predicted = np.asarray(reference), np.asarray(predicted)
    if reference.shape != predicted.shape:
        raise ProblemError(f"l2_error needs equal shapes, got {reference.shape} and {predicted.shape}")
    diff = (predicted - reference).reshape(len(reference), -1)
    return np.linalg.norm(diff, axis=1)


@dataclasses.dataclass(frozen=True)
class NodeError:
    """The error of one node's displacement over the compared snapshots: of one component
    c (|.| the absolute value) or of the displacement vector (|.| the Euclidean norm).

    Attributes:
        node: the node id.
        component: 0, 1, 2 (x, y, z), or None for the vector.
        amplitude: max_t |d(t)|, the node's largest amplitude in the reference [cm].
        max_error: max_t |d_hat(t) - d(t)| [cm].
        final_error: |d_hat - d| at the last snapshot [cm].
        rms_error: sqrt(mean_t |d_hat(t) - d(t)|^2) [cm].
    """

    node: int
    component: int | None
    amplitude: float
    max_error: float
    final_error: float
    rms_error: float

    @property
    def relative(self) -> float | None:
        """max_error / amplitude: the largest error as a fraction of the node's largest
        amplitude (None where the node never moves in the reference)."""
        return self.max_error / self.amplitude if self.amplitude > 0 else None


def node_error(reference: np.ndarray, predicted: np.ndarray, node: int, component: int | None = None) -> NodeError:
    """The error at ``node`` of ``predicted`` against ``reference``.

    Args:
        reference, predicted: (T, n, 3) displacements at the same snapshots.
        node: the node id.
        component: 0, 1 or 2 (x, y, z); None: the displacement vector (its norm).
    """
    reference, predicted = np.asarray(reference), np.asarray(predicted)
    if reference.shape != predicted.shape or reference.ndim != 3 or reference.shape[2] != 3:
        raise ProblemError(f"node_error needs two (T, n, 3) arrays of equal shapes, got {reference.shape} and "
                           f"{predicted.shape}")
    if not 0 <= int(node) < reference.shape[1]:
        raise ProblemError(f"node {node} is not one of the {reference.shape[1]} nodes")
    if component is not None and component not in (0, 1, 2):
        raise ProblemError(f"component must be 0, 1, 2 (x, y, z) or None (the vector), got {component!r}")
    node = int(node)
    if component is None:
        error = np.linalg.norm(predicted[:, node] - reference[:, node], axis=1)
        size = np.linalg.norm(reference[:, node], axis=1)
    else:
        error = np.abs(predicted[:, node, component] - reference[:, node, component])
        size = np.abs(reference[:, node, component])
    return NodeError(node=node, component=component, amplitude=float(size.max()), max_error=float(error.max()),
                     final_error=float(error[-1]), rms_error=float(np.sqrt(np.mean(error ** 2))))


@dataclasses.dataclass(frozen=True)
class SharedNodeErrors:
    """Errors at the shared nodes (paper eqs. 25-26).

    Attributes:
        es: (T,) mean error against the truth [cm].
        es_hat: (T,) mean disagreement between the parts' predictions [cm].
        et: (N_a,) time-averaged error per shared node against the truth [cm].
        et_hat: (N_a,) time-averaged disagreement per shared node [cm].
    """

    es: np.ndarray
    es_hat: np.ndarray
    et: np.ndarray
    et_hat: np.ndarray


def shared_node_errors(truth: np.ndarray, predictions: np.ndarray, holds: np.ndarray) -> SharedNodeErrors:
    """es, es_hat, et of the parts' predictions at the shared nodes.

    Args:
        truth: (T, N_a, 3) synchronized displacement at the shared nodes.
        predictions: (n_c, T, N_a, 3) each part's prediction (any value where the part
            does not hold the node).
        holds: (n_c, N_a) bool, True where part p holds (and predicts) node i; every node
            must be held by at least two parts.
    """
    truth, predictions, holds = np.asarray(truth), np.asarray(predictions), np.asarray(holds, bool)
    n_c, T, N_a, _ = predictions.shape
    if truth.shape != (T, N_a, 3) or holds.shape != (n_c, N_a):
        raise ProblemError(f"shapes do not fit: truth {truth.shape}, predictions {predictions.shape}, "
                           f"holds {holds.shape}")
    counts = holds.sum(axis=0)
    if np.any(counts < 2):
        raise ProblemError("every shared node must be predicted by at least two parts")
    # per part and node: component-mean absolute error, (n_c, T, N_a)
    err = np.abs(predictions - truth[None]).mean(axis=-1)
    err_node = np.where(holds[:, None, :], err, 0.0).sum(axis=0) / counts  # (T, N_a)
    pair_sum = np.zeros((T, N_a))
    pair_count = np.zeros(N_a)
    for p, q in itertools.combinations(range(n_c), 2):
        both = holds[p] & holds[q]
        if both.any():
            pair_sum[:, both] += np.abs(predictions[p][:, both] - predictions[q][:, both]).mean(axis=-1)
            pair_count[both] += 1
    hat_node = pair_sum / pair_count
    return SharedNodeErrors(es=err_node.mean(axis=1), es_hat=hat_node.mean(axis=1),
                            et=err_node.mean(axis=0), et_hat=hat_node.mean(axis=0))


def predictions_by_node(trajectory, partition) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rearrange a synchronization-avoiding trajectory's per-part predictions.

    Returns:
        (predictions (n_c, T_pred, N_a, 3), holds (n_c, N_a), predicted-snapshot indices
        (T_pred,)) with the nodes in ``partition.shared_nodes`` order.
    """
    steps = np.flatnonzero(~np.asarray(trajectory.synchronized, bool))
    shared = partition.shared_nodes
    index = {int(node): k for k, node in enumerate(shared)}
    out = np.zeros((partition.n_parts, len(steps), len(shared), 3))
    holds = np.zeros((partition.n_parts, len(shared)), bool)
    for p, part in enumerate(partition.parts):
        cols = np.array([index[int(n)] for n in part.shared_nodes], dtype=int)
        values = np.asarray(trajectory.parts[p].predicted_shared_displacement)
        out[p][:, cols] = values.reshape(len(steps), len(cols), 3)
        holds[p, cols] = True
    return out, holds, steps


@dataclasses.dataclass(frozen=True)
class EstimateQuality:
    """How well es_hat (needs no reference) tracks es (needs it) over the compared
    snapshots. es_hat measures the parts' DISAGREEMENT: when the parts' networks err
    alike (same bias at a node), es_hat stays small while es grows, so the ratio es /
    es_hat, not only the correlation, tells whether es_hat can stand in for es.

    Attributes:
        n_snapshots: compared snapshots (those with es > 0).
        ratio_median, ratio_p95, ratio_max: quantiles of es / es_hat (1: exact; above 1:
            es_hat underestimates the error).
        log_correlation: Pearson correlation of log10 es and log10 es_hat (1: they rise
            and fall together).
        within_factor_2: share of snapshots with es / 2 <= es_hat <= 2 es.
        underestimated: share of snapshots with es_hat < es / 2 (the direction that
            hides errors from a monitor).
    """

    n_snapshots: int
    ratio_median: float
    ratio_p95: float
    ratio_max: float
    log_correlation: float
    within_factor_2: float
    underestimated: float

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @property
    def es_hat_zero(self) -> bool:
        """True when es_hat is 0 at every compared snapshot (the parts' predictions agree
        exactly): the ratios and the correlation are not measurable (nan; null in
        ``summary.json``)."""
        return bool(self.n_snapshots) and all(_missing(v) for v in (
            self.ratio_median, self.ratio_p95, self.ratio_max, self.log_correlation)) and self.underestimated == 1

    def summary(self) -> str:
        """One line for a report."""
        if not self.n_snapshots:
            return "es_hat tracks es: no snapshot with es > 0 to compare"
        if self.es_hat_zero:
            return (f"es_hat is 0 at every one of the {self.n_snapshots} compared snapshots (the parts' predictions "
                    "agree exactly): its tracking of es cannot be measured")

        def num(value, spec):
            return "n/a" if _missing(value) else format(value, spec)

        return (f"es_hat tracks es: es/es_hat median {num(self.ratio_median, '.3g')}, 95th percentile "
                f"{num(self.ratio_p95, '.3g')}, max {num(self.ratio_max, '.3g')}; log-correlation "
                f"{num(self.log_correlation, '.3f')}; within a factor 2 at {100 * self.within_factor_2:.1f} % "
                f"of {self.n_snapshots} snapshots, underestimated (es_hat < es/2) at "
                f"{100 * self.underestimated:.1f} %")


def _missing(value) -> bool:
    """None (null read back from summary.json) or nan: a value that was not measured."""
    return value is None or value != value


def _percentile(values: np.ndarray, q: float) -> float:
    """``np.percentile(values, q)`` (linear interpolation) where ``values`` may hold +inf
    (es_hat = 0): inf at and above the first inf, never the nan of inf - inf."""
    s = np.sort(values)
    pos = q / 100.0 * (len(s) - 1)
    lo = int(np.floor(pos))
    hi, frac = min(lo + 1, len(s) - 1), pos - lo
    if frac == 0.0 or s[lo] == s[hi]:
        return float(s[lo])
    if np.isinf(s[hi]):
        return float("inf")
    return float(np.percentile(s, q))


def estimate_quality(es: np.ndarray, es_hat: np.ndarray) -> EstimateQuality:
    """Compare es_hat with es (both (T,) [cm], paper eqs. 25-26) over the snapshots where
    es > 0; es_hat = 0 there counts as an infinite ratio. Where es_hat is 0 at every one
    of them (the parts' predictions agree exactly, e.g. identical fits of parts that hold
    the same shared nodes), nothing of its tracking can be measured: the ratios and the
    correlation are nan (null in ``summary.json``; :attr:`EstimateQuality.es_hat_zero`)."""
    es, es_hat = np.asarray(es, float), np.asarray(es_hat, float)
    if es.shape != es_hat.shape or es.ndim != 1:
        raise ProblemError(f"es and es_hat must be equal (T,) arrays, got {es.shape} and {es_hat.shape}")
    keep = es > 0
    es, es_hat = es[keep], es_hat[keep]
    nan = float("nan")
    if not len(es):
        return EstimateQuality(0, nan, nan, nan, nan, nan, nan)
    both = es_hat > 0
    if not both.any():
        return EstimateQuality(n_snapshots=int(len(es)), ratio_median=nan, ratio_p95=nan, ratio_max=nan,
                               log_correlation=nan, within_factor_2=0.0, underestimated=1.0)
    with np.errstate(divide="ignore"):
        ratio = np.where(both, es / np.where(both, es_hat, 1.0), np.inf)
    if both.sum() > 2 and np.ptp(np.log10(es[both])) > 0 and np.ptp(np.log10(es_hat[both])) > 0:
        correlation = float(np.corrcoef(np.log10(es[both]), np.log10(es_hat[both]))[0, 1])
    else:
        correlation = float("nan")
    return EstimateQuality(
        n_snapshots=int(len(es)), ratio_median=float(np.median(ratio)),
        ratio_p95=_percentile(ratio, 95), ratio_max=float(ratio.max()),
        log_correlation=correlation,
        within_factor_2=float(np.mean((ratio >= 0.5) & (ratio <= 2.0))),
        underestimated=float(np.mean(ratio > 2.0)))


@dataclasses.dataclass(frozen=True)
class PeakStrain:
    """The largest strains of a displacement history (:func:`peak_strain`).

    Attributes:
        green_lagrange: the largest principal Green-Lagrange strain E = (F^T F - I) / 2 over
            every quadrature point of every element and every snapshot [-] (tension
            positive).
        logarithmic: the same principal direction's logarithmic strain ln(lambda), with the
            stretch lambda = sqrt(1 + 2 E) [-].
        compression: the smallest principal Green-Lagrange strain [-] (negative in
            compression; >= -1/2).
        snapshot: the snapshot (index into the history) and element of the largest
            tension.
        element: see ``snapshot``.
    """

    green_lagrange: float
    logarithmic: float
    compression: float
    snapshot: int
    element: int

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def summary(self) -> str:
        return (f"peak strain: largest principal Green-Lagrange strain {100 * self.green_lagrange:.2f} % "
                f"(logarithmic {100 * self.logarithmic:.2f} %) at snapshot {self.snapshot}, element "
                f"{self.element}; largest compression {100 * self.compression:.2f} %")


def principal_strain_peaks(space, displacement, *, chunk_bytes: int = 2 ** 27):
    """Per snapshot, the largest and the smallest principal Green-Lagrange strain over the
    elements' quadrature points, and the element of the largest (see :func:`peak_strain`).

    Returns:
        (tension (T,), element (T,) int, compression (T,)) [-].
    """
    from .fem._space import function_space
    from .fem.forces._total_lagrangian import reference_geometry

    if not hasattr(space, "cells"):
        space = function_space(space, "P1")
    d = np.asarray(displacement, dtype=float)
    if d.ndim == 2:
        d = d[None]
    if d.ndim != 3 or d.shape[1:] != (space.n_nodes, 3):
        raise ProblemError(f"peak_strain: displacement of shape {np.shape(displacement)} does not fit the "
                           f"space's {space.n_nodes} nodes: give (T, {space.n_nodes}, 3) or ({space.n_nodes}, 3)")
    gradients, _ = reference_geometry(space)  # (m, q, k, 3)
    cells = np.asarray(space.cells)
    m, q = gradients.shape[:2]
    block = max(1, int(chunk_bytes // max(1, m * q * 9 * 8 * 4)))
    tension, element, compression = (np.empty(len(d)), np.empty(len(d), np.int64), np.empty(len(d)))
    for start in range(0, len(d), block):
        u = d[start:start + block][:, cells]  # (t, m, k, 3)
        H = np.einsum("tmka,mqkj->tmqaj", u, gradients)  # grad_X u
        E = 0.5 * (H + np.swapaxes(H, -1, -2) + np.einsum("...ka,...kb->...ab", H, H))
        principal = np.linalg.eigvalsh(E)  # ascending
        top = principal[..., -1].max(axis=2)  # (t, m) over quadrature points
        rows = slice(start, start + len(u))
        element[rows] = np.argmax(top, axis=1)
        tension[rows] = top.max(axis=1)
        compression[rows] = principal[..., 0].min(axis=(1, 2))
    return tension, element, compression


def peak_strain(space, displacement, *, chunk_bytes: int = 2 ** 27) -> PeakStrain:
    """The largest principal strains of ``displacement`` over elements and snapshots.

    At every quadrature point of the element rule of the total-Lagrangian force
    (:func:`jaxsync.fem.forces._total_lagrangian.reference_geometry`: one point on P1, four on
    P2), F = I + grad_X u and the Green-Lagrange strain E = (F^T F - I) / 2, whose
    eigenvalues are the principal strains. Kinematics only: the same for every law
    (for a small-strain law it measures how far its runs are from small strain).

    Args:
        space: a :class:`jaxsync.fem.FunctionSpace` (``Trajectory.space``) or a
            :class:`jaxsync.Mesh` (its P1 space).
        displacement: (T, n_nodes, 3) or (n_nodes, 3) displacements [cm] of its nodes.
        chunk_bytes: working memory per block of snapshots (the strains are formed a block
            at a time).

    Raises:
        ProblemError: a displacement of another shape than the space's nodes.
    """
    return peak_of(*principal_strain_peaks(space, displacement, chunk_bytes=chunk_bytes))


def peak_of(tension, element, compression) -> PeakStrain:
    """The :class:`PeakStrain` of per-snapshot peaks (:func:`principal_strain_peaks`), over
    the snapshots given."""
    at = int(np.argmax(tension))
    value = float(tension[at])
    return PeakStrain(green_lagrange=value, logarithmic=float(0.5 * np.log1p(2.0 * value)),
                      compression=float(compression.min()), snapshot=at, element=int(element[at]))
