"""Figures of synchronization-avoiding runs, for papers (matplotlib, no pyplot state).

:func:`write_report` compares an online (synchronization-avoiding) trajectory with the
synchronized reference and writes PNG figures plus ``summary.json``:

- ``displacement_nodes.png``: for each monitored node, the synchronized (reference,
  wide grey) and predicted (thin, coloured) displacement component, and below it the
  error d_hat - d;
- ``l2_error.png``: e(t) = ||d_hat(t) - d(t)||_2 over the whole field (paper eq. 24);
- ``shared_errors.png``: es(t) and es_hat(t) at the shared nodes (eqs. 25-26);
- ``et_histogram.png``: histograms of the time-averaged errors et_j and et_hat_j;
- ``es_tracking.png``: es_hat against es per predicted snapshot (how well the estimate,
  which needs no reference, stands in for the error; summarized in ``es_hat_tracking``
  of ``summary.json``, see :func:`jaxsync.metrics.estimate_quality`).

Every time plot marks the end of the initial synchronized phase (t(n_cri)) and shades the
re-synchronized intervals (synchronized snapshots after the first predicted one, as the
es_hat monitor of ``jaxsync predict --resync-tolerance`` makes them).

Monitored nodes. The user may name them (``nodes=``: node ids, coordinates (x, y, z)
meaning the nearest node, or a dict label -> id/coordinates; ``jaxsync report --node``).
By default they are chosen from the reference's motion: for each part, the node that is
neither shared nor constrained with the largest amplitude, plus the shared node with the
largest amplitude. The amplitude of a node is max over time of |d_c| in the plotted
component c (ties, and a component in which nothing moves, are decided by max over time
of the norm |d|). Constrained nodes (``fixed_nodes``, the Dirichlet set) and nodes that
never move in the reference are never chosen; a part without any candidate is named in
``summary["node_notes"]``. On the cantilever (clamped at x = 0) this picks a node at the
free end x = 25 for the part that holds it.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping

import numpy as np

from ..errors import ConfigError, ProblemError
from ..metrics import estimate_quality, l2_error, predictions_by_node, shared_node_errors

__all__ = ["write_report", "report_nodes", "resolve_nodes", "parse_node", "moving_nodes", "constrained_nodes",
           "histogram_bins", "tip_node"]

_AXES = "xyz"
REFERENCE_STYLE = dict(color="0.6", lw=3.2, solid_capstyle="butt", zorder=2)
PREDICTED_STYLE = dict(color="tab:red", lw=1.0, zorder=3)
ERROR_STYLE = dict(color="tab:purple", lw=0.9)
SWITCH_STYLE = dict(color="k", lw=1.2, ls=(0, (4, 2)), zorder=4)
RESYNC_STYLE = dict(color="tab:blue", alpha=0.15, lw=0, zorder=1)


def _figure(width=7.0, height=4.2):
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), dpi=150, layout="constrained")


def _save(fig, path):
    from ..trajectory import atomic_path

    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")


def tip_node(mesh) -> int:
    """The node at the largest x with the largest y + z: the corner of the cantilever's
    free end. Purely geometric, so on other shapes (a vessel clamped at both ends) it can
    be a constrained node; :func:`write_report` no longer uses it."""
    p = mesh.points
    at_end = np.isclose(p[:, 0], p[:, 0].max())
    return int(np.argmax(np.where(at_end, p[:, 1] + p[:, 2], -np.inf)))


# ----------------------------------------------------------------------------- nodes


def parse_node(text: str):
    """A node given on the command line: ``"12"`` (a node id) or ``"25,1,1"`` (x, y, z
    coordinates: the nearest node). Raises :class:`ConfigError` otherwise."""
    parts = [p.strip() for p in str(text).split(",")]
    try:
        if len(parts) == 1:
            return int(parts[0])
        if len(parts) == 3:
            return tuple(float(p) for p in parts)
    except ValueError:
        pass
    raise ConfigError(f"cannot read node {text!r}: give a node id (--node 12) or coordinates x,y,z "
                      "(--node 25,1,1, the nearest node)")


def _resolve_one(mesh, spec) -> tuple[int, str]:
    """(node id, default label) of one node spec: an id, coordinates or a CLI string."""
    if isinstance(spec, str):
        spec = parse_node(spec)
    n_nodes = mesh.n_nodes
    if isinstance(spec, (bool, np.bool_)):
        raise ConfigError(f"node {spec!r} is neither a node id nor coordinates (x, y, z)")
    if isinstance(spec, (int, np.integer)):
        node = int(spec)
        if not 0 <= node < n_nodes:
            raise ConfigError(f"node {node} does not exist: the mesh has nodes 0 .. {n_nodes - 1}; "
                              "give an id in that range or coordinates (x, y, z) for the nearest node")
        return node, f"node {node}"
    try:
        xyz = np.asarray(spec, dtype=float)
    except (TypeError, ValueError):
        xyz = None
    if xyz is None or xyz.shape != (3,) or not np.all(np.isfinite(xyz)):
        raise ConfigError(f"node {spec!r} is neither a node id nor finite coordinates (x, y, z)")
    node = int(np.argmin(np.linalg.norm(mesh.points - xyz, axis=1)))
    return node, "nearest to ({:g}, {:g}, {:g})".format(*xyz)


def resolve_nodes(mesh, nodes) -> dict[str, int]:
    """Label -> node id of user-named nodes.

    Args:
        nodes: a sequence of node ids, coordinates (x, y, z) (the nearest node is taken)
            or strings ``"12"`` / ``"25,1,1"``; or a dict label -> one of those.

    Raises:
        ConfigError: an id outside the mesh, or something that is neither.
    """
    items = list(nodes.items()) if isinstance(nodes, Mapping) else [(None, n) for n in nodes]
    if not items:
        raise ConfigError("no node given: pass at least one node id or coordinates, or nodes=None "
                          "for the automatic choice")
    out: dict[str, int] = {}
    for label, spec in items:
        node, auto = _resolve_one(mesh, spec)
        label = str(label) if label is not None else auto
        if label in out and out[label] != node:
            label = f"{label} #{len(out)}"
        out[label] = node
    return out


def moving_nodes(displacement) -> np.ndarray:
    """(n_nodes,) bool: nodes whose displacement changes at some time of (T, n, 3)."""
    d = np.asarray(displacement)
    return np.any(d != d[:1], axis=(0, 2))


def _amplitude_order(displacement, component: int) -> np.ndarray:
    """(n_nodes,) rank of every node by amplitude (larger is larger): max_t |d_c|,
    ties broken by max_t |d|."""
    d = np.asarray(displacement)
    amp_c = np.abs(d[:, :, component]).max(axis=0)
    amp = np.linalg.norm(d, axis=2).max(axis=0)
    rank = np.empty(d.shape[1], dtype=np.int64)
    rank[np.lexsort((amp, amp_c))] = np.arange(d.shape[1])
    return rank


def _default_nodes(displacement, partition, fixed_nodes, component) -> tuple[dict[str, int], list[str]]:
    n_nodes = np.shape(displacement)[1]
    candidate = moving_nodes(displacement)
    fixed = np.asarray(fixed_nodes, dtype=np.int64).ravel()
    candidate[fixed[(fixed >= 0) & (fixed < n_nodes)]] = False
    rank = _amplitude_order(displacement, component)
    shared = np.zeros(n_nodes, bool)
    shared[partition.shared_nodes] = True

    def largest(mask):
        ids = np.flatnonzero(mask)
        return int(ids[np.argmax(rank[ids])]) if ids.size else None

    nodes: dict[str, int] = {}
    notes: list[str] = []
    for part in partition.parts:
        mask = np.zeros(n_nodes, bool)
        mask[part.nodes] = True
        node = largest(mask & candidate & ~shared)
        if node is None:
            notes.append(f"part {part.index}: every node is shared, constrained or never moves in the "
                         "reference; no interior node shown")
        else:
            nodes[f"part {part.index}, largest amplitude"] = node
    if partition.n_interface:
        node = largest(shared & candidate)
        if node is None:
            notes.append("every shared node is constrained or never moves in the reference; "
                         "no shared node shown")
        else:
            nodes["shared, largest amplitude"] = node
    else:
        notes.append("the partition has no shared nodes (one part)")
    if not nodes:
        raise ProblemError("no node to monitor: every node is constrained (Dirichlet) or never moves "
                           "in the reference; name nodes with nodes=[...] (jaxsync report --node ID "
                           "or --node X,Y,Z)")
    return nodes, notes


def report_nodes(mesh, partition, fixed_nodes=(), *, reference=None, component: int = 2,
                 nodes=None) -> dict[str, int]:
    """Label -> node id of the nodes shown in ``displacement_nodes.png``.

    Args:
        mesh: the mesh.
        partition: the partition of the run.
        fixed_nodes: constrained (Dirichlet) nodes, never chosen by default.
        reference: (T, n_nodes, 3) synchronized displacement (or a Trajectory); needed
            for the default choice.
        component: displacement component that ranks the amplitudes (2 = z).
        nodes: user-named nodes (see :func:`resolve_nodes`); None for the default choice
            (see the module docstring).

    Raises:
        ConfigError: a bad user-given node; ProblemError: no node to show.
    """
    if nodes is not None:
        return resolve_nodes(mesh, nodes)
    if reference is None:
        raise ProblemError("the default node choice ranks nodes by their motion: pass reference=")
    displacement = getattr(reference, "displacement", reference)
    return _default_nodes(displacement, partition, fixed_nodes, component)[0]


def constrained_nodes(config_path, mesh, displacement) -> np.ndarray:
    """Constrained nodes of a run known by its trajectories only (``jaxsync report``).

    Every node that never moves in the (T, n, 3) reference ``displacement`` (this covers
    each fully clamped node, such as the cantilever's clamp, since Dirichlet values are
    constant in time), united, when ``config_path`` names the run's TOML configuration,
    with its Dirichlet set (which also catches nodes constrained in some components
    only). The configuration's conditions are applied to ``mesh``, so a run made with
    another mesh file (``simulate --mesh``) is handled too. Without a configuration
    nothing is assumed about the problem: a default (the packaged cantilever) would
    exclude wrong nodes of any other problem on the same mesh.

    Raises:
        ConfigError: the configuration cannot be read, or one of its Dirichlet conditions
            selects no node of ``mesh``.
    """
    still = np.flatnonzero(~moving_nodes(displacement))
    if config_path is None:
        return still
    from .config import load_config, problem_from_config

    problem, _ = problem_from_config(load_config(config_path))
    if (problem.mesh.n_nodes == mesh.n_nodes and np.array_equal(problem.mesh.tets, mesh.tets)
            and np.allclose(problem.mesh.points, mesh.points)):
        dirichlet = problem.dirichlet_dofs()[0] // 3
    else:
        selected = []
        for i, bc in enumerate(problem.dirichlet):
            try:
                ids = np.asarray(bc.nodes(mesh), dtype=np.int64)
            except ProblemError as exc:
                raise ConfigError(f"{config_path}: Dirichlet condition #{i} does not fit the "
                                  f"trajectories' mesh ({exc}); pass the configuration of the run") from exc
            if ids.size == 0:
                raise ConfigError(f"{config_path}: Dirichlet condition #{i} selects no node of the "
                                  "trajectories' mesh; pass the configuration of the run")
            selected.append(ids)
        dirichlet = np.concatenate(selected) if selected else np.zeros(0, np.int64)
    return np.union1d(dirichlet, still).astype(np.int64)


# ----------------------------------------------------------------------------- phases


def _phases(times, synchronized):
    """(t of the last synchronized snapshot before the first predicted one or None,
    [(t_start, t_end)] of the re-synchronized intervals)."""
    times = np.asarray(times, float)
    sync = np.ones(len(times), bool) if synchronized is None else np.asarray(synchronized, bool)
    predicted = np.flatnonzero(~sync)
    if not predicted.size:
        return None, []
    first = int(predicted[0])
    t_switch = float(times[max(first - 1, 0)])
    spans = []
    k = first
    while k < len(sync):
        if sync[k]:
            a = k
            while k + 1 < len(sync) and sync[k + 1]:
                k += 1
            b = k
            # each synchronized snapshot stands for the steps around it: midpoints
            start = 0.5 * (times[a - 1] + times[a])
            end = 0.5 * (times[b] + times[b + 1]) if b + 1 < len(sync) else float(times[b])
            spans.append((float(start), float(end)))
        k += 1
    return t_switch, spans


def _mark_phases(ax, t_switch, spans, label=True):
    """End of the synchronized phase (dashed line) and re-synchronized intervals (shaded)."""
    if t_switch is not None:
        ax.axvline(t_switch, label="end of synchronized phase, t(n_cri)" if label else None, **SWITCH_STYLE)
    for i, (a, b) in enumerate(spans):
        ax.axvspan(a, b, label="re-synchronized" if label and i == 0 else None, **RESYNC_STYLE)


# ----------------------------------------------------------------------------- figures


def _plot_nodes(path, times, ref, pred, nodes, component, t_switch, spans, mesh):
    c = _AXES[component]
    k = len(nodes)
    fig = _figure(8.0, 1.1 + 3.0 * k)
    grid = fig.add_gridspec(2 * k, 1, height_ratios=[2.6, 1.0] * k)
    first = None
    handles = None
    for i, (label, node) in enumerate(nodes.items()):
        ax = fig.add_subplot(grid[2 * i], sharex=first)
        first = first or ax
        err_ax = fig.add_subplot(grid[2 * i + 1], sharex=first)
        ax.plot(times, ref[:, node, component], label="synchronized (reference)", **REFERENCE_STYLE)
        ax.plot(times, pred[:, node, component], label="synchronization-avoiding (predicted)",
                **PREDICTED_STYLE)
        err_ax.plot(times, pred[:, node, component] - ref[:, node, component],
                    label=rf"error $\hat d_{c} - d_{c}$", **ERROR_STYLE)
        err_ax.axhline(0.0, color="0.3", lw=0.5)
        for a in (ax, err_ax):
            _mark_phases(a, t_switch, spans, label=(a is ax))
            a.grid(True, alpha=0.3)
        x, y, z = mesh.points[node]
        ax.set_title(f"{label}: node {node} at ({x:.3g}, {y:.3g}, {z:.3g}) cm", fontsize=9)
        ax.set_ylabel(f"$d_{c}$ [cm]")
        err_ax.set_ylabel("error [cm]")
        ax.tick_params(labelbottom=False)
        if handles is None:
            handles = ax.get_legend_handles_labels()
            eh = err_ax.get_legend_handles_labels()
            handles = (handles[0] + eh[0], handles[1] + eh[1])
    err_ax.set_xlabel("time t [s]")
    fig.suptitle(f"Displacement $d_{c}$ at the monitored nodes: synchronized vs predicted")
    fig.legend(*handles, loc="outside lower center", ncol=3, fontsize=8)
    _save(fig, path)


def _plot_l2(path, times, e, t_switch, spans):
    fig = _figure()
    ax = fig.add_subplot(1, 1, 1)
    ax.plot(times, e, color="tab:red", lw=1.0, label=r"$e(t) = \|\hat d(t) - d(t)\|_2$ (eq. 24)", zorder=3)
    _mark_phases(ax, t_switch, spans)
    ax.set_xlabel("time t [s]")
    ax.set_ylabel("e(t) [cm]")
    ax.set_title("Error of the whole displacement field against the synchronized run")
    ax.grid(True, alpha=0.3)
    fig.legend(*ax.get_legend_handles_labels(), loc="outside lower center", ncol=3, fontsize=8)
    _save(fig, path)


def _plot_shared(path, times, steps, errs, t_switch, spans):
    es = np.full(len(times), np.nan)
    es_hat = np.full(len(times), np.nan)
    tiny = np.finfo(float).tiny
    es[steps] = np.maximum(errs.es, tiny)  # NaN elsewhere: the lines break at synchronized snapshots
    es_hat[steps] = np.maximum(errs.es_hat, tiny)
    fig = _figure()
    ax = fig.add_subplot(1, 1, 1)
    ax.semilogy(times, es, color="tab:red", lw=1.0, label=r"$e_s(t)$: predictions vs synchronized (eq. 25)",
                zorder=3)
    ax.semilogy(times, es_hat, color="tab:green", lw=1.0, ls="--",
                label=r"$\hat e_s(t)$: between the parts' predictions (eq. 26)", zorder=3)
    _mark_phases(ax, t_switch, spans)
    ax.set_xlabel("time t [s]")
    ax.set_ylabel("mean error per shared node [cm]")
    ax.set_title("Errors at the shared nodes while predicted")
    ax.grid(True, which="both", alpha=0.3)
    fig.legend(*ax.get_legend_handles_labels(), loc="outside lower center", ncol=2, fontsize=8)
    _save(fig, path)


def _plot_tracking(path, errs, quality):
    """es_hat against es, one point per predicted snapshot (log-log), with the lines
    es_hat = es and a factor 2 either way: how far the estimate can stand in for the error."""
    tiny = np.finfo(float).tiny
    es, es_hat = np.maximum(errs.es, tiny), np.maximum(errs.es_hat, tiny)
    fig = _figure(5.6, 5.0)
    ax = fig.add_subplot(1, 1, 1)
    ax.loglog(es, es_hat, ".", ms=2.5, alpha=0.5, color="tab:blue", label="predicted snapshots")
    low, high = min(es.min(), es_hat.min()), max(es.max(), es_hat.max())
    line = np.array([low, high])
    ax.loglog(line, line, color="0.2", lw=1.0, label=r"$\hat e_s = e_s$")
    ax.loglog(line, line / 2, color="0.5", lw=0.8, ls="--", label="a factor 2 off")
    ax.loglog(line, line * 2, color="0.5", lw=0.8, ls="--")
    ax.set_xlabel(r"$e_s$: error at the shared nodes against the synchronized run [cm]")
    ax.set_ylabel(r"$\hat e_s$: disagreement between the parts [cm]")
    ax.set_title(f"Does the estimate track the error? es/es_hat median {quality.ratio_median:.2g}, "
                 f"95 % {quality.ratio_p95:.2g}", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    _save(fig, path)


def histogram_bins(values, max_bins: int = 20) -> np.ndarray:
    """Bin edges for a few to a few thousand values: about 2 sqrt(n) bins (3 to
    ``max_bins``), logarithmic when positive values span more than two decades."""
    v = np.asarray(values, float).ravel()
    v = v[np.isfinite(v)]
    n_bins = int(np.clip(np.ceil(2 * np.sqrt(max(v.size, 1))), 3, max_bins))
    if not v.size:
        return np.linspace(0.0, 1.0, n_bins + 1)
    if v.min() == v.max():  # one value: a narrow range around it, not numpy's +-0.5
        half = 0.1 * abs(v[0]) or 1e-12
        return np.linspace(v[0] - half, v[0] + half, n_bins + 1)
    if v.min() > 0 and v.max() / v.min() > 100:
        return np.geomspace(v.min(), v.max(), n_bins + 1)
    return np.histogram_bin_edges(v, bins=n_bins)


def _plot_histogram(path, errs):
    from matplotlib.ticker import MaxNLocator

    n = len(errs.et)
    edges = histogram_bins(np.concatenate([errs.et, errs.et_hat]))
    fig = _figure()
    ax = fig.add_subplot(1, 1, 1)
    ax.hist([errs.et, errs.et_hat], bins=edges, color=["tab:red", "tab:green"],
            label=[rf"$e_{{t,j}}$: vs synchronized (eq. 25), mean {errs.et.mean():.2e} cm",
                   rf"$\hat e_{{t,j}}$: between parts (eq. 26), mean {errs.et_hat.mean():.2e} cm"])
    if edges[0] > 0 and edges[-1] / edges[0] > 100:
        ax.set_xscale("log")
    ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("time-averaged error of a shared node over the predicted snapshots [cm]")
    ax.set_ylabel("number of shared nodes")
    ax.set_title(f"Time-averaged errors at the {n} shared node{'s' if n != 1 else ''}")
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(fontsize=8)
    _save(fig, path)


# ----------------------------------------------------------------------------- report


def _node_table(times, ref, pred, nodes, component, mesh, shared, fixed):
    rows = []
    for label, node in nodes.items():
        err_c = np.abs(pred[:, node, component] - ref[:, node, component])
        amp = float(np.abs(ref[:, node, component]).max())
        rows.append({
            "label": label, "node": int(node), "coordinates": [float(v) for v in mesh.points[node]],
            "shared": bool(shared[node]), "constrained": bool(fixed[node]),
            "max_abs_displacement": amp,
            "max_abs_error": float(err_c.max()),
            "relative_max_error": float(err_c.max() / amp) if amp > 0 else None,
            "final_abs_error": float(err_c[-1]),
            "rms_error": float(np.sqrt(np.mean(err_c ** 2))),
            "max_error_norm": float(np.linalg.norm(pred[:, node] - ref[:, node], axis=1).max()),
        })
    return rows


def write_report(reference, online, partition, out_dir, *, component: int = 2,
                 fixed_nodes=(), nodes=None, extra: dict | None = None) -> dict:
    """Write the figures and ``summary.json`` into ``out_dir``; return the summary.

    Args:
        reference: synchronized :class:`jaxsync.Trajectory` with the same saved steps.
        online: synchronization-avoiding :class:`jaxsync.Trajectory`.
        partition: the partition of the online run.
        component: displacement component shown and compared at the nodes (2 = z).
        fixed_nodes: constrained (Dirichlet) nodes, e.g.
            ``np.unique(problem.dirichlet_dofs()[0] // 3)``; never chosen by default
            (neither are nodes that never move in the reference).
        nodes: nodes to show instead of the default choice: node ids, coordinates
            (x, y, z) (nearest node) or a dict label -> either (see :func:`resolve_nodes`).
        extra: more entries for ``summary.json`` (timings...).

    Summary entries about nodes (errors in the plotted component, in cm):
        ``nodes`` (label -> id), ``node_errors`` (one row per monitored node: node,
        coordinates, shared, constrained, max_abs_displacement (its reference
        amplitude), max_abs_error, relative_max_error, final_abs_error, rms_error,
        max_error_norm (of the displacement vector)), ``node_notes`` (parts without a
        node to show), and ``monitored_node`` / ``monitored_label``: the monitored node
        with the largest reference amplitude. ``tip_max_abs_error`` and
        ``tip_max_abs_displacement`` are kept for compatibility and refer to that node
        (on the cantilever, a node at the free end), not to a fixed geometric tip.

    Raises:
        ProblemError: trajectories of different shapes, or no node to show;
        ConfigError: a bad node in ``nodes``.
    """
    ref = np.asarray(reference.displacement)
    pred = np.asarray(online.displacement)
    if ref.shape != pred.shape:
        raise ProblemError(f"reference {ref.shape} and online {pred.shape} trajectories differ in shape; "
                           "compare runs of the same mesh saved at the same steps")
    if component not in (0, 1, 2):
        raise ConfigError(f"component must be 0, 1 or 2 (x, y, z), got {component!r}")
    mesh = online.mesh
    n_nodes = ref.shape[1]
    fixed = np.zeros(n_nodes, bool)
    fixed_ids = np.asarray(fixed_nodes, dtype=np.int64).ravel()
    if fixed_ids.size and (fixed_ids.min() < 0 or fixed_ids.max() >= n_nodes):
        raise ProblemError(f"fixed_nodes holds ids outside the mesh's 0 .. {n_nodes - 1}")
    fixed[fixed_ids] = True
    notes: list[str] = []
    if nodes is None:
        shown, notes = _default_nodes(ref, partition, fixed_ids, component)
    else:
        shown = resolve_nodes(mesh, nodes)
    os.makedirs(out_dir, exist_ok=True)
    times = np.asarray(online.times)
    t_switch, spans = _phases(times, online.synchronized)

    _plot_nodes(os.path.join(out_dir, "displacement_nodes.png"), times, ref, pred, shown, component,
                t_switch, spans, mesh)
    e = l2_error(ref, pred)
    _plot_l2(os.path.join(out_dir, "l2_error.png"), times, e, t_switch, spans)

    predictions, holds, steps = predictions_by_node(online, partition)
    summary_shared = {}
    if partition.n_interface and len(steps):
        truth = ref[steps][:, partition.shared_nodes]
        errs = shared_node_errors(truth, predictions, holds)
        _plot_shared(os.path.join(out_dir, "shared_errors.png"), times, steps, errs, t_switch, spans)
        _plot_histogram(os.path.join(out_dir, "et_histogram.png"), errs)
        quality = estimate_quality(errs.es, errs.es_hat)
        _plot_tracking(os.path.join(out_dir, "es_tracking.png"), errs, quality)
        summary_shared = {"es_final": float(errs.es[-1]), "es_hat_final": float(errs.es_hat[-1]),
                          "es_max": float(errs.es.max()), "es_hat_max": float(errs.es_hat.max()),
                          "et_mean": float(errs.et.mean()), "et_hat_mean": float(errs.et_hat.mean()),
                          "es_hat_tracking": quality.to_dict()}

    shared = np.zeros(n_nodes, bool)
    shared[partition.shared_nodes] = True
    table = _node_table(times, ref, pred, shown, component, mesh, shared, fixed)
    top = max(table, key=lambda row: row["max_abs_displacement"])
    from ..solve.syncavoid import step_counts

    n_steps, n_synchronized = step_counts(online)
    summary = {
        "n_steps": n_steps,
        "n_synchronized": n_synchronized,
        "n_predicted": n_steps - n_synchronized,
        "n_parts": partition.n_parts,
        "component": _AXES[component],
        "monitored_node": top["node"],
        "monitored_label": top["label"],
        "tip_max_abs_error": top["max_abs_error"],
        "tip_max_abs_displacement": top["max_abs_displacement"],
        "l2_error_final": float(e[-1]),
        "l2_error_max": float(e.max()),
        "nodes": {label: int(node) for label, node in shown.items()},
        "node_errors": table,
        "node_notes": notes,
        "resynchronized_intervals": [[a, b] for a, b in spans],
        **summary_shared, **(extra or {}),
    }
    from ..trajectory import atomic_path

    with atomic_path(os.path.join(out_dir, "summary.json")) as tmp:
        with open(tmp, "w") as f:
            json.dump(summary, f, indent=2)
    return summary
