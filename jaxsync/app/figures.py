"""The figures of ``jaxsync report`` (matplotlib, no pyplot state): each function returns a
:class:`matplotlib.figure.Figure` made from arrays; :func:`jaxsync.app.plots.write_report`
chooses what to show and writes them (:func:`save_figure`).

- :func:`nodes_figure`: for each monitored node, the synchronized (reference, wide grey)
  and predicted (thin, coloured) displacement component, and below it the error d_hat - d;
- :func:`l2_error_figure`: e(t) = ||d_hat(t) - d(t)||_2 over the whole field (paper eq. 24);
- :func:`shared_errors_figure`: es(t) and es_hat(t) at the shared nodes (eqs. 25-26);
- :func:`histogram_figure`: histograms of the time-averaged errors et_j and et_hat_j;
- :func:`tracking_figure`: es_hat against es per predicted snapshot;
- :func:`pressure_diameter_figure`: a vessel's pressure-diameter and pressure-volume loops
  (:mod:`jaxsync.vessel_metrics`);
- :func:`wall_stress_figure`: a vessel's largest von Mises stress per region over time.

Every time plot marks the end of the initial synchronized phase (t(n_cri)) and shades the
re-synchronized intervals (:func:`phases`, :func:`mark_phases`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["new_figure", "save_figure", "phases", "mark_phases", "histogram_bins", "nodes_figure",
           "l2_error_figure", "shared_errors_figure", "tracking_figure", "histogram_figure",
           "pressure_diameter_figure", "wall_stress_figure",
           "REFERENCE_STYLE", "PREDICTED_STYLE", "ERROR_STYLE", "SWITCH_STYLE", "RESYNC_STYLE"]

AXES = "xyz"
REFERENCE_STYLE = dict(color="0.6", lw=3.2, solid_capstyle="butt", zorder=2)
PREDICTED_STYLE = dict(color="tab:red", lw=1.0, zorder=3)
ERROR_STYLE = dict(color="tab:purple", lw=0.9)
SWITCH_STYLE = dict(color="k", lw=1.2, ls=(0, (4, 2)), zorder=4)
RESYNC_STYLE = dict(color="tab:blue", alpha=0.15, lw=0, zorder=1)


def new_figure(width=7.0, height=4.2):
    """A figure of ``width`` x ``height`` inches at 150 dpi, constrained layout."""
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), dpi=150, layout="constrained")


def save_figure(fig, path) -> None:
    """Write ``fig`` as PNG to ``path``, atomically (:func:`jaxsync.io.atomic_path`)."""
    from ..io.atomic import atomic_path

    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")


def phases(times, synchronized):
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


def mark_phases(ax, t_switch, spans, label=True):
    """End of the synchronized phase (dashed line) and re-synchronized intervals (shaded)."""
    if t_switch is not None:
        ax.axvline(t_switch, label="end of synchronized phase, t(n_cri)" if label else None, **SWITCH_STYLE)
    for i, (a, b) in enumerate(spans):
        ax.axvspan(a, b, label="re-synchronized" if label and i == 0 else None, **RESYNC_STYLE)


def nodes_figure(times, ref, pred, nodes, component, t_switch, spans, mesh):
    """Displacement component ``component`` (0, 1, 2, or a dict label -> component per
    node) of the reference ``ref`` and prediction ``pred`` (T, n_nodes, 3) at each node
    of ``nodes`` (label -> id), with the error below."""
    components = component if isinstance(component, dict) else {label: component for label in nodes}
    same = len(set(components.values())) == 1
    k = len(nodes)
    fig = new_figure(8.0, 1.1 + 3.0 * k)
    grid = fig.add_gridspec(2 * k, 1, height_ratios=[2.6, 1.0] * k)
    first = None
    handles = None
    for i, (label, node) in enumerate(nodes.items()):
        component = components[label]
        c = AXES[component]
        ax = fig.add_subplot(grid[2 * i], sharex=first)
        first = first or ax
        err_ax = fig.add_subplot(grid[2 * i + 1], sharex=first)
        ax.plot(times, ref[:, node, component], label="synchronized (reference)", **REFERENCE_STYLE)
        ax.plot(times, pred[:, node, component], label="synchronization-avoiding (predicted)",
                **PREDICTED_STYLE)
        err_ax.plot(times, pred[:, node, component] - ref[:, node, component],
                    label=r"error $\hat d - d$", **ERROR_STYLE)
        err_ax.axhline(0.0, color="0.3", lw=0.5)
        for a in (ax, err_ax):
            mark_phases(a, t_switch, spans, label=(a is ax))
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
    shown = f"$d_{c}$" if same else "the dominant displacement component"
    fig.suptitle(f"{shown} at the monitored nodes: synchronized vs predicted")
    fig.legend(*handles, loc="outside lower center", ncol=3, fontsize=8)
    return fig


def l2_error_figure(times, e, t_switch, spans):
    """e(t), the l2 error of the whole field (paper eq. 24), over time."""
    fig = new_figure()
    ax = fig.add_subplot(1, 1, 1)
    ax.plot(times, e, color="tab:red", lw=1.0, label=r"$e(t) = \|\hat d(t) - d(t)\|_2$ (eq. 24)", zorder=3)
    mark_phases(ax, t_switch, spans)
    ax.set_xlabel("time t [s]")
    ax.set_ylabel("e(t) [cm]")
    ax.set_title("Error of the whole displacement field against the synchronized run")
    ax.grid(True, alpha=0.3)
    fig.legend(*ax.get_legend_handles_labels(), loc="outside lower center", ncol=3, fontsize=8)
    return fig


def shared_errors_figure(times, steps, errs, t_switch, spans):
    """es(t) and es_hat(t) (:class:`jaxsync.metrics.SharedNodeErrors` ``errs`` at the
    snapshots ``steps``; the lines break at synchronized snapshots), log scale."""
    es = np.full(len(times), np.nan)
    es_hat = np.full(len(times), np.nan)
    tiny = np.finfo(float).tiny
    es[steps] = np.maximum(errs.es, tiny)  # NaN elsewhere: the lines break at synchronized snapshots
    es_hat[steps] = np.maximum(errs.es_hat, tiny)
    fig = new_figure()
    ax = fig.add_subplot(1, 1, 1)
    ax.semilogy(times, es, color="tab:red", lw=1.0, label=r"$e_s(t)$: predictions vs synchronized (eq. 25)",
                zorder=3)
    ax.semilogy(times, es_hat, color="tab:green", lw=1.0, ls="--",
                label=r"$\hat e_s(t)$: between the parts' predictions (eq. 26)", zorder=3)
    mark_phases(ax, t_switch, spans)
    ax.set_xlabel("time t [s]")
    ax.set_ylabel("mean error per shared node [cm]")
    ax.set_title("Errors at the shared nodes while predicted")
    ax.grid(True, which="both", alpha=0.3)
    fig.legend(*ax.get_legend_handles_labels(), loc="outside lower center", ncol=2, fontsize=8)
    return fig


def tracking_figure(errs, quality):
    """es_hat against es, one point per predicted snapshot (log-log), with the lines
    es_hat = es and a factor 2 either way: how far the estimate can stand in for the error."""
    tiny = np.finfo(float).tiny
    es, es_hat = np.maximum(errs.es, tiny), np.maximum(errs.es_hat, tiny)
    fig = new_figure(5.6, 5.0)
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
    return fig


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


def histogram_figure(errs):
    """Histograms of the time-averaged errors et_j and et_hat_j of the shared nodes."""
    from matplotlib.ticker import MaxNLocator

    n = len(errs.et)
    edges = histogram_bins(np.concatenate([errs.et, errs.et_hat]))
    fig = new_figure()
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
    return fig


KPA = 1.0e4  # dyn/cm^2 per kPa


def pressure_diameter_figure(loop, metrics):
    """The pressure-diameter loop (left: p [mmHg] against the mean lumen diameter D [mm])
    and the pressure-volume loop (right: p against the lumen volume V [mm^3 = uL]) of a
    :class:`jaxsync.vessel_metrics.PressureDiameterLoop`: the whole record thin and grey,
    the measured cycle (:class:`jaxsync.vessel_metrics.VesselMetrics`) bold, with an arrow
    in the direction of travel (clockwise: energy dissipated)."""
    from ..vessel_metrics import MMHG

    fig = new_figure(9.0, 4.2)
    cycle = np.arange(len(loop.times)) if loop.cycle is None else loop.cycle
    p = np.asarray(loop.pressure) / MMHG
    what = "last full cycle" if metrics.full_cycle else "whole record"
    for k, (x, label) in enumerate(((10.0 * np.asarray(loop.diameter), "mean lumen diameter D = 4V/A [mm]"),
                                    (1.0e3 * np.asarray(loop.volume), r"lumen volume V [mm$^3$]"))):
        ax = fig.add_subplot(1, 2, k + 1)
        ax.plot(x, p, color="0.7", lw=0.8, label="whole record")
        ax.plot(x[cycle], p[cycle], color="tab:red", lw=1.6, label=f"{what}, t = {metrics.t_start:.3g}-"
                f"{metrics.t_end:.3g} s")
        if len(cycle) > 2:
            i = int(cycle[len(cycle) // 3])
            j = int(cycle[len(cycle) // 3 + 1])
            ax.annotate("", xy=(x[j], p[j]), xytext=(x[i], p[i]),
                        arrowprops=dict(arrowstyle="-|>", color="tab:red", lw=1.2))
        ax.set_xlabel(label)
        ax.set_ylabel("lumen pressure p [mmHg]")
        ax.grid(True, alpha=0.3)
        if k == 0:
            ax.legend(fontsize=7, loc="upper left")
    if metrics.distensibility is None:
        detail = "constant pressure"
    else:
        hysteresis = "" if metrics.hysteresis is None else f", hysteresis {metrics.hysteresis:.3g} erg/cycle"
        detail = (f"distensibility {100 * metrics.distensibility * MMHG:.3g} %/mmHg, compliance "
                  f"{1e3 * metrics.volume_compliance * MMHG:.3g} " + r"mm$^3$/mmHg" + hysteresis)
    fig.suptitle(f"Pressure-diameter and pressure-volume loops of the lumen '{loop.surface}'\n{detail}",
                 fontsize=10)
    return fig


def wall_stress_figure(times, peaks):
    """The largest von Mises stress [kPa] of each region over time
    (:class:`jaxsync.vessel_metrics.RegionPeaks` by name), its peak marked."""
    fig = new_figure()
    ax = fig.add_subplot(1, 1, 1)
    styles = ("-", "--", ":", "-.")  # regions with the same peak element draw the same line: tell them apart
    for k, (name, region) in enumerate(peaks.items()):
        line, = ax.plot(times, np.asarray(region.history) / KPA, lw=1.6 if name == "wall" else 1.0,
                        ls=styles[k % len(styles)],
                        label=f"{name} ({region.n_elements} elements): peak {region.von_mises.value / KPA:.3g} kPa")
        ax.plot(region.von_mises.time, region.von_mises.value / KPA, "o", ms=4, color=line.get_color())
    ax.set_xlabel("time t [s]")
    ax.set_ylabel("largest von Mises stress [kPa]")
    ax.set_title("Peak wall stress by region (elements with a face on each facet set; wall: all)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7)
    return fig
