"""Error metrics of synchronization-avoiding runs (paper section 6, eqs. 24-26).

All functions take plain NumPy arrays; T is the number of compared snapshots, n the
number of nodes, N_a the number of shared nodes, n_c the number of parts.

- :func:`l2_error` e(t) = ||d(t) - d_hat(t)||_2 over all dofs (eq. 24).
- :func:`shared_node_errors` at the shared nodes, where every node is predicted by each
  of the (at least two) parts that hold it:
  es(t): mean over shared nodes and over the parts predicting them of the component-mean
  absolute error (1/3) sum_c |d_hat_{p,i,c}(t) - d_{i,c}(t)| (eq. 25);
  es_hat(t): the same with the truth replaced by the other part's prediction, averaged
  over the pairs of parts that share the node -- it needs no reference, so it can monitor
  a run (eq. 26); et_j: the time average of each node's error.
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np

from .errors import ProblemError

__all__ = ["l2_error", "SharedNodeErrors", "shared_node_errors", "predictions_by_node"]


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
        values = np.asarray(trajectory.parts[p]["predicted_shared_displacement"])
        out[p][:, cols] = values.reshape(len(steps), -1, 3)
        holds[p, cols] = True
    return out, holds, steps
