"""Figures of synchronization-avoiding runs, for papers (matplotlib, no pyplot state).

:func:`write_report` compares an online (synchronization-avoiding) trajectory with the
synchronized reference and writes PNG figures plus ``summary.json``:

- ``displacement_nodes.png``: predicted against synchronized displacement at chosen nodes
  (the free-end node, a shared node, and a non-shared node of each part), with the
  training/prediction boundary t(n_cri) marked;
- ``l2_error.png``: e(t) (paper eq. 24);
- ``shared_errors.png``: es(t) and es_hat(t) (eqs. 25-26);
- ``et_histogram.png``: histograms of the time-averaged errors et_j and et_hat_j.
"""

from __future__ import annotations

import json
import os

import numpy as np

from .metrics import l2_error, predictions_by_node, shared_node_errors

__all__ = ["write_report", "report_nodes", "tip_node"]


def _figure(width=6.4, height=4.0):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=150)
    return fig


def _save(fig, path):
    from .trajectory import atomic_path

    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")


def tip_node(mesh) -> int:
    """The node at the largest x with the largest y + z (the cantilever's free-end corner)."""
    p = mesh.points
    at_end = np.isclose(p[:, 0], p[:, 0].max())
    return int(np.argmax(np.where(at_end, p[:, 1] + p[:, 2], -np.inf)))


def report_nodes(mesh, partition, fixed_nodes=()) -> dict[str, int]:
    """Nodes shown in the displacement figure: the free end, the shared node farthest
    from the clamp, and for each part the free (not shared, not clamped) node farthest
    from the interface."""
    nodes = {"free end": tip_node(mesh)}
    excluded = set(np.asarray(fixed_nodes).tolist())
    if partition.n_interface:
        candidates = [n for n in partition.shared_nodes if n not in excluded] or list(partition.shared_nodes)
        nodes["shared"] = int(max(candidates, key=lambda n: mesh.points[n, 0]))
    excluded |= set(partition.shared_nodes.tolist())
    interface_points = mesh.points[partition.shared_nodes] if partition.n_interface else mesh.points[:1]
    for part in partition.parts:
        own = np.array([n for n in part.nodes if n not in excluded])
        if own.size:
            dist = np.min(np.linalg.norm(mesh.points[own][:, None] - interface_points[None], axis=2), axis=1)
            nodes[f"part {part.index} interior"] = int(own[np.argmax(dist)])
    return nodes


def write_report(reference, online, partition, out_dir, *, component: int = 2,
                 fixed_nodes=(), extra: dict | None = None) -> dict:
    """Write the figures and ``summary.json`` into ``out_dir``; return the summary.

    Args:
        reference: synchronized :class:`jaxsync.Trajectory` with the same saved steps.
        online: synchronization-avoiding :class:`jaxsync.Trajectory`.
        partition: the partition of the online run.
        component: displacement component shown in the node figure (2 = z).
        fixed_nodes: Dirichlet nodes, left out of the node figure (their motion is zero).
        extra: more entries for ``summary.json`` (timings...).
    """
    os.makedirs(out_dir, exist_ok=True)
    ref = np.asarray(reference.displacement)
    pred = np.asarray(online.displacement)
    if ref.shape != pred.shape:
        raise ValueError(f"reference {ref.shape} and online {pred.shape} trajectories differ in shape")
    times = np.asarray(online.times)
    synchronized = np.asarray(online.synchronized, bool)
    t_switch = times[synchronized][-1] if synchronized.any() else times[0]
    nodes = report_nodes(online.mesh, partition, fixed_nodes)

    fig = _figure(7.0, 2.2 * len(nodes))
    for k, (label, node) in enumerate(nodes.items()):
        ax = fig.add_subplot(len(nodes), 1, k + 1)
        ax.plot(times, ref[:, node, component], color="0.2", lw=1.2, label="synchronized")
        ax.plot(times, pred[:, node, component], color="tab:red", lw=1.0, ls="--", label="predicted")
        ax.axvline(t_switch, color="tab:blue", lw=0.8, ls=":", label="end of synchronized phase")
        ax.set_ylabel(f"d_{'xyz'[component]} [cm]")
        ax.set_title(f"{label} (node {node})", fontsize=9)
        if k == 0:
            ax.legend(fontsize=7, loc="best")
    ax.set_xlabel("t [s]")
    _save(fig, os.path.join(out_dir, "displacement_nodes.png"))

    e = l2_error(ref, pred)
    fig = _figure()
    ax = fig.add_subplot(1, 1, 1)
    ax.plot(times, e, color="tab:red")
    ax.axvline(t_switch, color="tab:blue", lw=0.8, ls=":")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("e(t) = ||d - d_hat||_2 [cm]")
    _save(fig, os.path.join(out_dir, "l2_error.png"))

    predictions, holds, steps = predictions_by_node(online, partition)
    summary_shared = {}
    if partition.n_interface and len(steps):
        truth = ref[steps][:, partition.shared_nodes]
        errs = shared_node_errors(truth, predictions, holds)
        fig = _figure()
        ax = fig.add_subplot(1, 1, 1)
        ax.semilogy(times[steps], np.maximum(errs.es, 1e-300), label="es (against synchronized)")
        ax.semilogy(times[steps], np.maximum(errs.es_hat, 1e-300), ls="--", label="es_hat (between parts)")
        ax.set_xlabel("t [s]")
        ax.set_ylabel("mean shared-node error [cm]")
        ax.legend(fontsize=8)
        _save(fig, os.path.join(out_dir, "shared_errors.png"))
        fig = _figure()
        ax = fig.add_subplot(1, 1, 1)
        ax.hist([errs.et, errs.et_hat], bins=20, label=["et_j", "et_hat_j"])
        ax.set_xlabel("time-averaged error per shared node [cm]")
        ax.set_ylabel("nodes")
        ax.legend(fontsize=8)
        _save(fig, os.path.join(out_dir, "et_histogram.png"))
        summary_shared = {"es_final": float(errs.es[-1]), "es_hat_final": float(errs.es_hat[-1]),
                          "et_mean": float(errs.et.mean()), "et_hat_mean": float(errs.et_hat.mean())}

    tip = nodes["free end"]
    tip_err = np.abs(pred[:, tip, component] - ref[:, tip, component])
    summary = {
        "n_steps": int(round(times[-1] / online.dt)),
        "n_synchronized": int(online.parameters.get("n_cri", 0)),
        "n_predicted": int(round(times[-1] / online.dt)) - int(online.parameters.get("n_cri", 0)),
        "n_parts": partition.n_parts,
        "tip_node": tip,
        "tip_max_abs_error": float(tip_err.max()),
        "tip_max_abs_displacement": float(np.abs(ref[:, tip, component]).max()),
        "tip_final_relative_error": float(tip_err[-1] / max(abs(ref[-1, tip, component]), 1e-300)),
        "l2_error_final": float(e[-1]),
        "l2_error_max": float(e.max()),
        "nodes": nodes,
        **summary_shared, **(extra or {}),
    }
    from .trajectory import atomic_path

    with atomic_path(os.path.join(out_dir, "summary.json")) as tmp:
        with open(tmp, "w") as f:
            json.dump(summary, f, indent=2)
    return summary
