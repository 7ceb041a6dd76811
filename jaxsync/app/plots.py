"""``jaxsync report``: compare a synchronization-avoiding run with the synchronized
reference, choose the monitored nodes, and write the figures and ``summary.json``.

:func:`write_report` compares an online (synchronization-avoiding) trajectory with the
synchronized reference (:func:`compare`), draws the figures of
:mod:`jaxsync.app.figures` (:func:`report_figures`) and writes them as PNG, plus
``summary.json``:

- ``displacement_nodes.png``: for each monitored node, the synchronized (reference,
  wide grey) and predicted (thin, coloured) displacement component, and below it the
  error d_hat - d;
- ``l2_error.png``: e(t) = ||d_hat(t) - d(t)||_2 over the whole field (paper eq. 24);
- ``shared_errors.png``: es(t) and es_hat(t) at the shared nodes (eqs. 25-26);
- ``et_histogram.png``: histograms of the time-averaged errors et_j and et_hat_j;
- ``es_tracking.png``: es_hat against es per predicted snapshot (how well the estimate,
  which needs no reference, stands in for the error; summarized in ``es_hat_tracking``
  of ``summary.json``, see :func:`jaxsync.metrics.estimate_quality`); with error control
  the run's own error estimate against the true largest nodal error is summarized in
  ``error_estimate_tracking``.

Every time plot marks the end of the initial synchronized phase (t(n_cri)) and shades the
re-synchronized intervals (synchronized snapshots after the first predicted one, as the
es_hat monitor of ``jaxsync predict --resync-tolerance`` makes them).

Monitored nodes. The user may name them (``nodes=``: node ids, coordinates (x, y, z)
meaning the nearest node, or a dict label -> id/coordinates; ``jaxsync report --node``).
By default they are chosen from the reference's motion: for each part, the node that is
neither shared nor constrained with the largest amplitude, plus the shared node with the
largest amplitude. The amplitude of a node is max over time of |d_c| in the plotted
component c (ties, and a component in which nothing moves, are decided by max over time
of the norm |d|); with ``component=None`` (a vessel, which moves in every direction) it
is max over time of |d|, and each node is shown and measured in its own dominant
component, the one of largest amplitude at that node. Constrained nodes (``fixed_nodes``,
the Dirichlet set) and nodes that never move in the reference are never chosen; a part
without any candidate is named in ``summary["node_notes"]``. On the cantilever (clamped
at x = 0) this picks a node at the free end x = 25 for the part that holds it.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping

import numpy as np

from ..errors import ConfigError, ProblemError
from ..metrics import estimate_quality, l2_error, node_error, predictions_by_node, shared_node_errors
from ..options import DEFAULT_COMPONENT, Component, check_option
from . import figures

__all__ = ["write_report", "compare", "Comparison", "report_figures", "report_summary", "report_nodes",
           "resolve_nodes", "parse_node", "moving_nodes", "constrained_nodes", "tip_node"]


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
    distance = np.linalg.norm(mesh.points - xyz, axis=1)
    node = int(np.argmin(distance))
    reach = _longest_edge(mesh)  # a point in or on the body is at most this far from a node
    if distance[node] > reach:
        lower, upper = mesh.points.min(axis=0), mesh.points.max(axis=0)
        raise ConfigError("node ({:g}, {:g}, {:g}) is off the mesh: its nearest node {} is {:.4g} cm away, more than "
                          "the longest element edge ({:.4g} cm); give coordinates on the body (its bounding box is "
                          "({:g}, {:g}, {:g}) to ({:g}, {:g}, {:g}) cm) or a node id".format(
                              *xyz, node, distance[node], reach, *lower, *upper))
    return node, "nearest to ({:g}, {:g}, {:g})".format(*xyz)


def _longest_edge(mesh) -> float:
    """The longest element edge [cm] of a mesh (or of a function space's mesh)."""
    tets = getattr(getattr(mesh, "mesh", mesh), "tets", None)
    points = getattr(mesh, "mesh", mesh).points
    if tets is None or not len(tets):
        return float("inf")
    p = points[tets]
    return float(max(np.linalg.norm(p[:, i] - p[:, j], axis=1).max() for i in range(4) for j in range(i + 1, 4)))


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


def _amplitude_order(displacement, component: int | None) -> np.ndarray:
    """(n_nodes,) rank of every node by amplitude (larger is larger): max_t |d_c|,
    ties broken by max_t |d| (component None: max_t |d| alone)."""
    d = np.asarray(displacement)
    amp = np.linalg.norm(d, axis=2).max(axis=0)
    amp_c = amp if component is None else np.abs(d[:, :, component]).max(axis=0)
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


def report_nodes(mesh, partition, fixed_nodes=(), *, reference=None, component: int | None = 2,
                 nodes=None) -> dict[str, int]:
    """Label -> node id of the nodes shown in ``displacement_nodes.png``.

    Args:
        mesh: the mesh.
        partition: the partition of the run.
        fixed_nodes: constrained (Dirichlet) nodes, never chosen by default.
        reference: (T, n_nodes, 3) synchronized displacement (or a Trajectory); needed
            for the default choice.
        component: displacement component that ranks the amplitudes (2 = z; None: the
            norm of the displacement).
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


def constrained_nodes(config_path, space, displacement) -> np.ndarray:
    """Constrained nodes of a run known by its trajectories only (``jaxsync report``).

    Every node that never moves in the (T, n, 3) reference ``displacement`` (this covers
    each fully clamped node, such as the cantilever's clamp, since Dirichlet values are
    constant in time), united, when ``config_path`` names the run's TOML configuration,
    with its Dirichlet set (which also catches nodes constrained in some components
    only). The configuration's conditions are applied to ``space`` (the trajectories'
    :attr:`~jaxsync.Trajectory.space`: their mesh and element; a mesh stands for its
    vertices), so a run made with
    another mesh file (``simulate --mesh``) or element (``--element``) is handled too. Without a configuration
    nothing is assumed about the problem: a default (the packaged cantilever) would
    exclude wrong nodes of any other problem on the same mesh.

    Raises:
        ConfigError: the configuration cannot be read, or one of its Dirichlet conditions
            selects no node of the trajectories' mesh.
    """
    still = np.flatnonzero(~moving_nodes(displacement))
    if config_path is None:
        return still
    from .config import load_config, problem_from_config

    if not hasattr(space, "element"):  # a mesh: its vertices
        from ..fem._space import function_space

        space = function_space(space, "P1")
    mesh = space.mesh
    problem, _ = problem_from_config(load_config(config_path), element=space.element)
    if (problem.mesh.n_nodes == mesh.n_nodes and np.array_equal(problem.mesh.tets, mesh.tets)
            and np.allclose(problem.mesh.points, mesh.points)):
        dirichlet = problem.dirichlet_dofs()[0] // 3
    else:
        selected = []
        for i, bc in enumerate(problem.dirichlet):
            try:
                ids = np.asarray(bc.nodes(space), dtype=np.int64)
            except ProblemError as exc:
                raise ConfigError(f"{config_path}: Dirichlet condition #{i} does not fit the "
                                  f"trajectories' mesh ({exc}); pass the configuration of the run") from exc
            if ids.size == 0:
                raise ConfigError(f"{config_path}: Dirichlet condition #{i} selects no node of the "
                                  "trajectories' mesh; pass the configuration of the run")
            selected.append(ids)
        dirichlet = np.concatenate(selected) if selected else np.zeros(0, np.int64)
    return np.union1d(dirichlet, still).astype(np.int64)


# ----------------------------------------------------------------------------- report


@dataclasses.dataclass(frozen=True)
class Comparison:
    """An online run against the synchronized reference, at the saved snapshots.

    Attributes:
        times: (T,) times of the snapshots [s].
        reference, predicted: (T, n_nodes, 3) synchronized and online displacement.
        space: the displacement's nodes (:attr:`jaxsync.Trajectory.space`: ``points``,
            ``n_nodes``; its ``mesh``).
        partition: the partition of the online run.
        component: displacement component shown and compared at the nodes (0, 1, 2), or
            None: each node's dominant component (:attr:`node_components`).
        nodes: label -> id of the monitored nodes; notes: why a part has none.
        fixed: (n_nodes,) bool, constrained nodes; shared: (n_nodes,) bool, shared nodes.
        t_switch, spans: end of the synchronized phase and re-synchronized intervals
            (:func:`jaxsync.app.figures.phases`).
        l2: (T,) e(t) of the whole field (paper eq. 24).
        steps: snapshots with predictions at the shared nodes; shared_errors: their
            :class:`jaxsync.metrics.SharedNodeErrors` and quality their
            :class:`jaxsync.metrics.EstimateQuality` (None without shared predictions).
        n_steps, n_synchronized: time steps of the online run, and how many were
            synchronized.
        snapshot_steps: (T,) the time step of every snapshot.
        train_until_step: the last step whose displacements fed training (None: not
            known); the summary's ``out_of_sample`` errors are measured after it.
        estimate_quality: how the online run's error estimate
            (:attr:`jaxsync.Trajectory.error_estimate`) tracks the true largest nodal
            error at its predicted snapshots (:class:`jaxsync.metrics.EstimateQuality`,
            true / estimate), or None when the run has none.
        strain: the reference's principal Green-Lagrange strains per snapshot
            (:func:`jaxsync.metrics.principal_strain_peaks`: tension (T,), its element
            (T,), compression (T,)), or None where not measured (a small-strain run,
            unless asked for).
    """

    times: np.ndarray
    reference: np.ndarray
    predicted: np.ndarray
    space: object
    partition: object
    component: int | None
    nodes: dict
    notes: list
    fixed: np.ndarray
    shared: np.ndarray
    t_switch: float | None
    spans: list
    l2: np.ndarray
    steps: np.ndarray
    shared_errors: object | None
    quality: object | None
    n_steps: int
    n_synchronized: int
    snapshot_steps: np.ndarray | None = None
    train_until_step: int | None = None
    estimate_quality: object | None = None
    strain: tuple | None = None

    def peak_strain(self, snapshots=slice(None)):
        """The reference's :class:`jaxsync.metrics.PeakStrain` over ``snapshots`` (an index
        of the snapshots; its ``snapshot`` counts from the first of them), or None where the
        strains were not measured."""
        from ..metrics import peak_of

        if self.strain is None:
            return None
        return peak_of(*(np.asarray(a)[snapshots] for a in self.strain))

    @property
    def node_components(self) -> dict[str, int]:
        """Label -> the component shown and measured at each monitored node: ``component``,
        or where it is None the node's dominant one (largest max_t |d_c| in the reference)."""
        if self.component is not None:
            return {label: self.component for label in self.nodes}
        return {label: int(np.argmax(np.abs(self.reference[:, node]).max(axis=0)))
                for label, node in self.nodes.items()}


def compare(reference, online, partition, *, component: Component | None = DEFAULT_COMPONENT,
            fixed_nodes=(), nodes=None, train_until_step: int | None = None,
            strain: bool | None = None) -> Comparison:
    """Compare ``online`` with ``reference`` (arguments as :func:`write_report`); writes nothing.

    ``strain``: measure the reference's principal strains (:attr:`Comparison.strain`);
    None: where the reference is a run of a hyperelastic law (its ``parameters["material"]``).

    Raises:
        ProblemError: trajectories of different shapes, or no node to show;
        ConfigError: a bad node in ``nodes``, or a component other than 0, 1, 2, or a
            ``train_until_step`` that leaves no snapshot after it.
    """
    from ..solve.coupling._syncavoid import step_counts

    ref = np.asarray(reference.displacement)
    pred = np.asarray(online.displacement)
    if ref.shape != pred.shape:
        raise ProblemError(f"reference {ref.shape} and online {pred.shape} trajectories differ in shape; "
                           "compare runs of the same mesh saved at the same steps")
    if component is not None:
        component = int(check_option("component", component, Component))
    space = online.space
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
        shown = resolve_nodes(space, nodes)
    times = np.asarray(online.times)
    t_switch, spans = figures.phases(times, online.synchronized)
    predictions, holds, steps = predictions_by_node(online, partition)
    errs = quality = None
    if partition.n_interface and len(steps):
        errs = shared_node_errors(ref[steps][:, partition.shared_nodes], predictions, holds)
        quality = estimate_quality(errs.es, errs.es_hat)
    tracked = None
    if getattr(online, "error_estimate", None) is not None:  # the error control's estimate
        estimate = np.asarray(online.error_estimate, dtype=float)
        at = np.isfinite(estimate)
        true = np.linalg.norm(pred[at] - ref[at], axis=2).max(axis=1)
        tracked = estimate_quality(true, estimate[at])
    shared = np.zeros(n_nodes, bool)
    shared[partition.shared_nodes] = True
    n_steps, n_synchronized = step_counts(online)
    snapshot_steps = np.rint(times / float(online.dt)).astype(np.int64)
    if train_until_step is not None:
        if isinstance(train_until_step, bool) or not isinstance(train_until_step, (int, np.integer)):
            raise ConfigError(f"train_until_step must be a step number, got {train_until_step!r}")
        if not np.any(snapshot_steps > train_until_step):
            raise ConfigError(f"no saved snapshot comes after train_until_step={train_until_step} (the last is "
                              f"step {snapshot_steps[-1]}): run past the training window to measure out of sample")
        train_until_step = int(train_until_step)
    return Comparison(times=times, reference=ref, predicted=pred, space=space, partition=partition,
                      component=component, nodes=shown, notes=notes, fixed=fixed, shared=shared,
                      t_switch=t_switch, spans=spans, l2=l2_error(ref, pred), steps=np.asarray(steps),
                      shared_errors=errs, quality=quality, n_steps=n_steps,
                      n_synchronized=n_synchronized, snapshot_steps=snapshot_steps,
                      train_until_step=train_until_step, estimate_quality=tracked,
                      strain=_strains(reference, ref) if _wants_strain(reference, strain) else None)


def _wants_strain(reference, strain: bool | None) -> bool:
    from ..fem.materials._hyperelastic import HYPERELASTIC

    if strain is not None:
        return bool(strain)
    material = getattr(reference, "parameters", {}).get("material")
    return material in {law.__name__ for law in HYPERELASTIC}


def _strains(reference, displacement) -> tuple:
    from ..metrics import principal_strain_peaks

    return principal_strain_peaks(reference.space, displacement)


def report_figures(c: Comparison) -> dict:
    """File name -> :class:`matplotlib.figure.Figure` of every figure of the report (the
    shared-node figures only when the online run has predictions at shared nodes)."""
    out = {"displacement_nodes.png": figures.nodes_figure(c.times, c.reference, c.predicted, c.nodes,
                                                          c.node_components, c.t_switch, c.spans, c.space),
           "l2_error.png": figures.l2_error_figure(c.times, c.l2, c.t_switch, c.spans)}
    if c.shared_errors is not None:
        out["shared_errors.png"] = figures.shared_errors_figure(c.times, c.steps, c.shared_errors,
                                                                c.t_switch, c.spans)
        out["et_histogram.png"] = figures.histogram_figure(c.shared_errors)
        out["es_tracking.png"] = figures.tracking_figure(c.shared_errors, c.quality)
    return out


def _node_table(c: Comparison, snapshots=slice(None)) -> list[dict]:
    """One row per monitored node, its errors over ``snapshots`` (an index of the
    snapshots; amplitudes are those of the same snapshots)."""
    rows = []
    components = c.node_components
    reference, predicted = c.reference[snapshots], c.predicted[snapshots]
    for label, node in c.nodes.items():
        k = components[label]
        e = node_error(reference, predicted, node, k)
        rows.append({
            "label": label, "node": int(node), "coordinates": [float(v) for v in c.space.points[node]],
            "shared": bool(c.shared[node]), "constrained": bool(c.fixed[node]),
            "component": figures.AXES[k], "max_abs_displacement": e.amplitude,
            "max_abs_error": e.max_error, "relative_max_error": e.relative,
            "final_abs_error": e.final_error, "rms_error": e.rms_error,
            "max_error_norm": node_error(reference, predicted, node).max_error,
        })
    return rows


def _interior_max(table: list[dict]) -> float | None:
    interior = [row["relative_max_error"] for row in table
                if not row["shared"] and row["relative_max_error"] is not None]
    return max(interior) if interior else None


def out_of_sample(c: Comparison) -> dict | None:
    """The errors over the snapshots after ``c.train_until_step`` (None when it is not
    known): ``from_step`` and ``from_time`` (the first such snapshot), ``n_snapshots``,
    ``node_errors`` (as the whole run's, amplitudes over the same snapshots),
    ``interior_max_relative_error``, ``monitored_relative_max_error`` (the node with the
    largest amplitude there), ``l2_error_max`` and, with shared predictions among them,
    ``es_max`` and ``es_hat_max``."""
    if c.train_until_step is None:
        return None
    after = np.flatnonzero(c.snapshot_steps > c.train_until_step)
    table = _node_table(c, after)
    top = max(table, key=lambda row: row["max_abs_displacement"])
    out = {"from_step": int(c.snapshot_steps[after[0]]), "from_time": float(c.times[after[0]]),
           "n_snapshots": int(after.size), "node_errors": table,
           "interior_max_relative_error": _interior_max(table),
           "monitored_node": top["node"], "monitored_relative_max_error": top["relative_max_error"],
           "l2_error_max": float(c.l2[after].max())}
    if c.shared_errors is not None:
        shared_after = c.snapshot_steps[c.steps] > c.train_until_step
        if shared_after.any():
            out.update(es_max=float(c.shared_errors.es[shared_after].max()),
                       es_hat_max=float(c.shared_errors.es_hat[shared_after].max()))
    if c.strain is not None:
        peak = c.peak_strain(after).to_dict()
        peak["snapshot"] = int(after[peak["snapshot"]])
        out["peak_strain"] = peak
    return out


def report_summary(c: Comparison, extra: dict | None = None) -> dict:
    """The entries of ``summary.json`` (see :func:`write_report`), plus ``extra``."""
    table = _node_table(c)
    top = max(table, key=lambda row: row["max_abs_displacement"])
    errs = c.shared_errors
    summary_shared = {} if errs is None else {
        "es_final": float(errs.es[-1]), "es_hat_final": float(errs.es_hat[-1]),
        "es_max": float(errs.es.max()), "es_hat_max": float(errs.es_hat.max()),
        "et_mean": float(errs.et.mean()), "et_hat_mean": float(errs.et_hat.mean()),
        "es_hat_tracking": c.quality.to_dict()}
    if c.estimate_quality is not None:
        summary_shared["error_estimate_tracking"] = c.estimate_quality.to_dict()
    return {
        "n_steps": c.n_steps,
        "n_synchronized": c.n_synchronized,
        "n_predicted": c.n_steps - c.n_synchronized,
        "n_parts": c.partition.n_parts,
        "component": "dominant" if c.component is None else figures.AXES[c.component],
        "monitored_node": top["node"],
        "monitored_label": top["label"],
        "tip_max_abs_error": top["max_abs_error"],
        "tip_max_abs_displacement": top["max_abs_displacement"],
        "interior_max_relative_error": _interior_max(table),
        "l2_error_final": float(c.l2[-1]),
        "l2_error_max": float(c.l2.max()),
        "nodes": {label: int(node) for label, node in c.nodes.items()},
        "node_errors": table,
        "node_notes": c.notes,
        "resynchronized_intervals": [[a, b] for a, b in c.spans],
        "train_until_step": c.train_until_step,
        "out_of_sample": out_of_sample(c),
        **({} if c.strain is None else {"peak_strain": c.peak_strain().to_dict()}),
        **summary_shared, **(extra or {}),
    }


def write_report(reference, online, partition, out_dir, *, component: Component | None = DEFAULT_COMPONENT,
                 fixed_nodes=(), nodes=None, extra: dict | None = None, train_until_step: int | None = None) -> dict:
    """Write the figures and ``summary.json`` into ``out_dir``; return the summary.

    Args:
        reference: synchronized :class:`jaxsync.Trajectory` with the same saved steps.
        online: synchronization-avoiding :class:`jaxsync.Trajectory`.
        partition: the partition of the online run.
        component: displacement component shown and compared at the nodes (2 = z), or
            None: each node's dominant component.
        fixed_nodes: constrained (Dirichlet) nodes, e.g.
            ``np.unique(problem.dirichlet_dofs()[0] // 3)``; never chosen by default
            (neither are nodes that never move in the reference).
        nodes: nodes to show instead of the default choice: node ids, coordinates
            (x, y, z) (nearest node) or a dict label -> either (see :func:`resolve_nodes`).
        extra: more entries for ``summary.json`` (timings...).
        train_until_step: the last step whose displacements fed the surrogates' training
            (:func:`jaxsync.surrogate.training.last_trained_step`); the summary then holds
            the errors over the snapshots after it (``out_of_sample``, see
            :func:`out_of_sample`).

    Summary entries about nodes (errors in the plotted component, in cm):
        ``nodes`` (label -> id), ``node_errors`` (one row per monitored node: node,
        coordinates, shared, constrained, component, max_abs_displacement (its reference
        amplitude), max_abs_error, relative_max_error, final_abs_error, rms_error,
        max_error_norm (of the displacement vector)), ``node_notes`` (parts without a
        node to show), ``interior_max_relative_error`` (the largest relative_max_error of
        the monitored nodes that are not shared: with the default choice, the worst
        part's), and ``monitored_node`` / ``monitored_label``: the monitored node
        with the largest reference amplitude. ``tip_max_abs_error`` and
        ``tip_max_abs_displacement`` are kept for compatibility and refer to that node
        (on the cantilever, a node at the free end), not to a fixed geometric tip.

    Raises:
        ProblemError: trajectories of different shapes, or no node to show;
        ConfigError: a bad node in ``nodes``.
    """
    from ..io.atomic import atomic_json

    comparison = compare(reference, online, partition, component=component, fixed_nodes=fixed_nodes,
                         nodes=nodes, train_until_step=train_until_step)
    os.makedirs(out_dir, exist_ok=True)
    for name, fig in report_figures(comparison).items():
        figures.save_figure(fig, os.path.join(out_dir, name))
    summary = report_summary(comparison, extra)
    atomic_json(os.path.join(out_dir, "summary.json"), summary)
    return summary
