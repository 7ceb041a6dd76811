"""Regime map: where does avoiding the per-step synchronization pay, as a function of the
interconnect's latency and of the local work per step? A pure cost-model plot (seconds).

    python benchmarks/regime_map.py [--sync-json PATH] [--out-dir benchmarks/results]

Model, per explicit step and per part (:mod:`jaxsync.perf.costmodel`, alpha-beta messages):

* synchronized:  t_t   = t_c + t_s,  t_s = ``sync_time(pattern, Interconnect(L, B), a)``
  for a = "allreduce" (psum-like: the cheaper of recursive doubling, ceil(log2 p)
  messages of the interface vector, and the ring, 2 (p - 1) messages of 1/p of it) or
  a = "neighbour" (ppermute-like: one message per neighbouring part, one after another);
* surrogate:     t_t'  = t_c + t_d,  t_d the measured surrogate cost per step (one batched
  refill prediction per n_s n_f steps, amortized); zeta = t_t / t_t'. zeta = 1 where
  t_d = t_s(L), independent of t_c: the surrogate break-even lines are vertical;
* deep halos of depth k (:mod:`jaxsync.parallel.exchange`): t_t'' = r_k t_c + t_s,halo / k,
  r_k = ``halo_partition(partition, k).redundancy()`` (elements held by all parts over the
  mesh's elements: the redundant work), t_s,halo = ``sync_time`` of the halo interface's
  pattern (its nodes carry 6 values: 2 displacement levels x 3 components; the pattern is
  built from the parts' halo interface nodes the way ``communication_pattern`` builds it
  from a partition's interface). zeta = t_t / t_t''; break-even where
  t_c (r_k - 1) = t_s(L) - t_s,halo(L) / k.

Axes: x = per-message latency L (0.1 us .. 3 ms), y = local step cost per part t_c
(0.3 us .. 30 ms), bandwidth fixed at :data:`BANDWIDTH_BPS` (12.5 GB/s, 100 Gb Ethernet
line rate). Partition: the 2525-node box beam of the benchmarks
(``cantilever(box_beam(25, 1, 1, (100, 4, 4)))``) on 8 METIS parts, so that allreduce
(3 rounds) and the neighbour exchange (1 or 2 neighbours per part) differ. Left panel:
the best surrogate's zeta against the faster synchronized baseline; right panel: the best
depth's (k in 1, 2, 4, 8) deep-halo zeta against the same. Lines zeta = 1 (labelled): each
surrogate against the allreduce (solid) and the neighbour (dashed) baseline; deep halos
k = 2, 4, 8 against the neighbour baseline, their halo exchanged by neighbour messages.

Assumptions: those of :mod:`jaxsync.perf.costmodel` (no overlap, serialized messages per
part, no contention or topology, free reduction arithmetic, balanced parts); t_c and t_d
do not depend on the interconnect; the surrogate's cost is the same on every part and its
accuracy is not part of the map (zeta is the speed at equal step count); r_k t_c assumes
the local work scales with the elements held; t_d measured on the coarse cantilever's
surrogates (interface of 4 nodes) is used unchanged for the 8-part mesh.

Inputs: ``--sync-json`` (default ``benchmarks/results/sync.json``, :mod:`bench_sync`):
its ``speedup`` rows give t_d = us_per_step_best(avoid-*) - us_per_step_best(nosync)
(clipped at >= 0.05 us) and the measured t_c = us_per_step_best(nosync); its ``solver``
rows give the measured solver t_s = us_per_step_best(method) - t_c of ``mpi4jax`` and
``psum-gloo`` on 2 real processes, drawn as points at L = t_s (the coarse cantilever's
interface of 96 bytes makes the bandwidth term negligible, so its t_s is an effective
latency). Without those rows t_d falls back to the constants of :data:`FALLBACK_T_D_US`
and t_c to :data:`FALLBACK_T_C_US`, and the output says so. The paper vessel
(``benchmarks/results/paper_vessel/paper_vessel_paper_measure.json``, if present) is
marked at t_c = its projection's t_compute and L = its measured t_s on emulated devices
(11 parts, a different pattern: a note, not a point of this map's partition).
Interconnect presets (:data:`jaxsync.perf.costmodel.INTERCONNECTS`) are marked at their
latency along the top; their own bandwidths are used in the printed table only.

Writes ``regime_map.png`` and ``regime_map.json`` into ``--out-dir`` and prints a table:
per preset, t_s of both algorithms for the 8-part pattern (= the largest t_d that still
pays against each) and each surrogate's zeta at the measured t_c.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import LogNorm  # noqa: E402

import jaxsync  # noqa: E402
from jaxsync.io import atomic_path  # noqa: E402
from jaxsync.parallel.exchange import halo_partition  # noqa: E402
from jaxsync.perf.costmodel import (  # noqa: E402
    INTERCONNECTS,
    CommunicationPattern,
    Interconnect,
    communication_pattern,
    sync_time,
)

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_SYNC_JSON = os.path.join(HERE, "results", "sync.json")
DEFAULT_OUT_DIR = os.path.join(HERE, "results")
VESSEL_JSON = os.path.join(HERE, "results", "paper_vessel", "paper_vessel_paper_measure.json")

BANDWIDTH_BPS = 12.5e9
N_PARTS = 8
HALO_DEPTHS = (1, 2, 4, 8)
HALO_LINES = (2, 4, 8)
L_RANGE_US = (0.1, 3000.0)
TC_RANGE_US = (0.3, 30000.0)
T_D_FLOOR_US = 0.05
SURROGATES = (("avoid-lstm-paper", "LSTM paper n_H=100"),
              ("avoid-lstm-default", "LSTM default n_H=50"),
              ("avoid-linear", "linear"))
FALLBACK_T_D_US = {"avoid-lstm-paper": 25.0, "avoid-lstm-default": 10.0, "avoid-linear": 1.0}
FALLBACK_T_C_US = 4.0
MEASURED_SOLVERS = ("mpi4jax", "psum-gloo")
ALGOS = ("allreduce", "neighbour")


# --------------------------------------------------------------------------- model

def t_sync(pattern: CommunicationPattern, latency_s, bandwidth_Bps: float, algorithm: str) -> np.ndarray:
    """sync_time [s] for each latency of ``latency_s`` (array) at a fixed bandwidth."""
    lat = np.atleast_1d(np.asarray(latency_s, dtype=float))
    return np.array([sync_time(pattern, Interconnect("map", float(x), bandwidth_Bps), algorithm)
                     for x in lat])


def zeta_surrogate(t_c, t_s, t_d):
    """(t_c + t_s) / (t_c + t_d): speed-up of the surrogate over the synchronized step."""
    return (np.asarray(t_c) + np.asarray(t_s)) / (np.asarray(t_c) + np.asarray(t_d))


def zeta_halo(t_c, t_s, redundancy: float, t_s_halo, depth: int):
    """(t_c + t_s) / (r_k t_c + t_s,halo / k): speed-up of deep halos of depth k."""
    return (np.asarray(t_c) + np.asarray(t_s)) / (redundancy * np.asarray(t_c) + np.asarray(t_s_halo) / depth)


def break_even_latency(pattern: CommunicationPattern, t_d_s: float, bandwidth_Bps: float,
                       algorithm: str) -> float:
    """The latency [s] at which t_s(L) = t_d (the surrogate pays at larger latencies).

    0.0 when t_d is below t_s even at zero latency (pays everywhere); inf when the pattern
    needs no synchronization. t_s(L) is increasing and piecewise affine: bisection."""
    def f(lat):
        return sync_time(pattern, Interconnect("map", lat, bandwidth_Bps), algorithm) - t_d_s
    lo, hi = 1e-15, 10.0
    if f(lo) >= 0:
        return 0.0
    if f(hi) < 0:
        return math.inf
    for _ in range(200):
        mid = math.sqrt(lo * hi) if hi / lo > 4 else 0.5 * (lo + hi)
        lo, hi = (mid, hi) if f(mid) < 0 else (lo, mid)
        if hi - lo <= 1e-15 * hi:
            break
    return 0.5 * (lo + hi)


def halo_pattern(halo) -> CommunicationPattern:
    """The :class:`CommunicationPattern` of a deep-halo exchange: the halo interface, 6
    values per node (two displacement levels)."""
    return communication_pattern(halo, dofs_per_node=6)


def build_patterns(n_parts: int = N_PARTS, depths=HALO_DEPTHS):
    """The benchmark beam on ``n_parts`` METIS parts: its pattern, and per depth (r_k, halo pattern)."""
    problem = jaxsync.cantilever(jaxsync.box_beam(25.0, 1.0, 1.0, (100, 4, 4)))
    partition = jaxsync.partition(problem.mesh, n_parts)
    halos = {}
    for k in depths:
        h = halo_partition(partition, k)
        halos[k] = (float(h.redundancy()), halo_pattern(h))
    return problem.mesh, communication_pattern(partition), halos


# --------------------------------------------------------------------------- inputs

def read_inputs(path: str) -> dict:
    """t_d per surrogate, the measured t_c and solver t_s [us] from a bench_sync JSON."""
    notes, rows = [], []
    try:
        with open(path) as f:
            rows = json.load(f).get("rows", [])
    except FileNotFoundError:
        notes.append(f"{path} not found")
    except (OSError, ValueError, AttributeError) as exc:
        notes.append(f"{path} unreadable ({exc})")
    best = {}
    for r in rows:
        if isinstance(r, dict) and r.get("kind") in ("speedup", "solver") and "us_per_step_best" in r:
            best[(r["kind"], r.get("method"))] = float(r["us_per_step_best"])
    t_c = best.get(("speedup", "nosync"))
    t_d, t_d_source = {}, {}
    for key, _ in SURROGATES:
        if t_c is not None and ("speedup", key) in best:
            t_d[key] = max(best[("speedup", key)] - t_c, T_D_FLOOR_US)
            t_d_source[key] = "measured (avoid - nosync, sync.json speedup rows)"
        else:
            t_d[key] = FALLBACK_T_D_US[key]
            t_d_source[key] = "fallback constant (no speedup rows)"
    if any(s.startswith("fallback") for s in t_d_source.values()):
        notes.append("no 'speedup' rows for every surrogate in the sync JSON: t_d falls back to the "
                     "constants " + ", ".join(f"{k}={FALLBACK_T_D_US[k]:g} us" for k in t_d
                                              if t_d_source[k].startswith("fallback")))
    t_c_source = "measured (nosync us_per_step_best)"
    if t_c is None:
        t_c, t_c_source = FALLBACK_T_C_US, "fallback constant (no nosync row)"
        notes.append(f"no 'nosync' row: measured t_c falls back to {FALLBACK_T_C_US:g} us and no measured "
                     "point is drawn")
    solver_t_s = {}
    if t_c_source.startswith("measured"):
        for m in MEASURED_SOLVERS:
            if ("solver", m) in best:
                solver_t_s[m] = max(best[("solver", m)] - t_c, T_D_FLOOR_US)
    return {"t_d_us": t_d, "t_d_source": t_d_source, "t_c_us": t_c, "t_c_source": t_c_source,
            "solver_t_s_us": solver_t_s, "notes": notes}


def read_vessel(path: str = VESSEL_JSON):
    """(t_c [us], t_s [us], n_parts) of the paper vessel's measurement, or None."""
    try:
        with open(path) as f:
            d = json.load(f)
        prog = d["programs"]
        return {"t_c_us": 1e6 * float(prog["projection"]["t_compute"]), "t_s_us": float(prog["t_s_us"]),
                "n_parts": int(prog["projection"]["pattern"]["n_parts"]), "source": path}
    except (OSError, ValueError, KeyError, TypeError):
        return None


# --------------------------------------------------------------------------- map

def compute_map(pattern, halos, t_d_us: dict, n_l: int = 160, n_c: int = 140) -> dict:
    lat_us = np.geomspace(*L_RANGE_US, n_l)
    tc_us = np.geomspace(*TC_RANGE_US, n_c)
    lat = 1e-6 * lat_us
    ts = {a: 1e6 * t_sync(pattern, lat, BANDWIDTH_BPS, a) for a in ALGOS}
    ts_best = np.minimum(ts["allreduce"], ts["neighbour"])
    TC = tc_us[:, None]
    zeta_s = np.max([zeta_surrogate(TC, ts_best[None, :], td) for td in t_d_us.values()], axis=0)
    halo_ts = {k: {a: 1e6 * t_sync(hp, lat, BANDWIDTH_BPS, a) for a in ALGOS} for k, (_, hp) in halos.items()}
    zeta_k_best = {k: zeta_halo(TC, ts_best[None, :], halos[k][0],
                                np.minimum(*halo_ts[k].values())[None, :], k) for k in halos}
    zeta_k_nb = {k: zeta_halo(TC, ts["neighbour"][None, :], halos[k][0], halo_ts[k]["neighbour"][None, :], k)
                 for k in halos}
    stack = np.array([zeta_k_best[k] for k in halos])
    return {"lat_us": lat_us, "tc_us": tc_us, "ts": ts, "zeta_s": zeta_s,
            "zeta_h": stack.max(axis=0), "k_best": np.array(list(halos))[stack.argmax(axis=0)],
            "zeta_k_nb": zeta_k_nb}


def preset_table(pattern, halos, inputs) -> list[dict]:
    t_c = inputs["t_c_us"]
    rows = []
    for ic in INTERCONNECTS.values():
        ts = {a: 1e6 * sync_time(pattern, ic, a) for a in ALGOS}
        best = min(ts.values())
        surr = {k: float(zeta_surrogate(t_c, best, td)) for k, td in inputs["t_d_us"].items()}
        halo = {k: float(zeta_halo(t_c, best, r, 1e6 * min(sync_time(hp, ic, a) for a in ALGOS), k))
                for k, (r, hp) in halos.items()}
        rows.append({"interconnect": ic.name, "latency_us": 1e6 * ic.latency_s,
                     "bandwidth_GBps": ic.bandwidth_Bps / 1e9,
                     "t_s_allreduce_us": ts["allreduce"], "t_s_neighbour_us": ts["neighbour"],
                     "break_even_t_d_allreduce_us": ts["allreduce"],
                     "break_even_t_d_neighbour_us": ts["neighbour"],
                     "zeta_surrogate_at_measured_t_c": surr,
                     "pays_at_measured_t_c": {k: z > 1 for k, z in surr.items()},
                     "zeta_halo_at_measured_t_c": {str(k): z for k, z in halo.items()}})
    return rows


def format_table(rows, inputs, pattern) -> str:
    short = {"avoid-lstm-paper": "paper", "avoid-lstm-default": "default", "avoid-linear": "linear"}
    lines = [f"Per-step synchronization on the presets, 8-part beam (N_a={pattern.n_interface} nodes, "
             f"S={pattern.interface_bytes} B); break-even t_d = t_s (a surrogate pays against a "
             "baseline while t_d < its t_s)",
             "t_d [us]: " + ", ".join(f"{short[k]}={v:.2f} ({inputs['t_d_source'][k].split(' ')[0]})"
                                       for k, v in inputs["t_d_us"].items())
             + f"; zeta at t_c={inputs['t_c_us']:.2f} us ({inputs['t_c_source'].split(' ')[0]}) "
               "against the faster baseline",
             f"{'interconnect':<15} {'L us':>6} {'GB/s':>6} {'t_s ar':>8} {'t_s nb':>8} "
             + " ".join(f"{'z ' + short[k]:>11}" for k in inputs["t_d_us"]) + f" {'z halo best':>13}"]
    for r in rows:
        zs = " ".join(f"{z:>7.2f} {'yes' if r['pays_at_measured_t_c'][k] else 'no ':>3}"
                      for k, z in r["zeta_surrogate_at_measured_t_c"].items())
        kz = max(r["zeta_halo_at_measured_t_c"].items(), key=lambda kv: kv[1])
        lines.append(f"{r['interconnect']:<15} {r['latency_us']:>6.1f} {r['bandwidth_GBps']:>6.1f} "
                     f"{r['t_s_allreduce_us']:>8.2f} {r['t_s_neighbour_us']:>8.2f} {zs} "
                     f"{kz[1]:>7.2f} (k={kz[0]})")
    return "\n".join(lines)


# --------------------------------------------------------------------------- figure

def draw(path, grid, pattern, halos, inputs, break_even, vessel):
    lat_us, tc_us = grid["lat_us"], grid["tc_us"]
    norm = LogNorm(vmin=1 / 8, vmax=8)
    fig, axes = plt.subplots(1, 2, figsize=(13.5, 6.4), sharey=True, constrained_layout=True)
    colours = {"avoid-lstm-paper": "#1b7837", "avoid-lstm-default": "#762a83", "avoid-linear": "#e08214"}
    labels = dict(SURROGATES)
    for ax, z, title in ((axes[0], grid["zeta_s"], "best surrogate"),
                         (axes[1], grid["zeta_h"], "best deep-halo depth k in {1, 2, 4, 8}")):
        mesh = ax.pcolormesh(lat_us, tc_us, np.clip(z, 1 / 8, 8), norm=norm, cmap="RdBu", shading="auto",
                             rasterized=True)
        ax.contour(lat_us, tc_us, z, levels=[1.0], colors="k", linewidths=0.8, linestyles=":")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlim(*L_RANGE_US)
        ax.set_ylim(*TC_RANGE_US)
        ax.set_xlabel("per-message latency L [us]")
        ax.set_title(f"{title}: zeta against the faster of allreduce / neighbour", fontsize=10, pad=52)
        # presets along the top, grouped by latency
        by_lat = {}
        for ic in INTERCONNECTS.values():
            by_lat.setdefault(1e6 * ic.latency_s, []).append(ic.name)
        for i, (x, names) in enumerate(sorted(by_lat.items())):
            ax.axvline(x, color="0.35", lw=0.6, alpha=0.6)
            ax.annotate(",\n".join(names) if i % 2 else ", ".join(names), (x, 1.0),
                        xycoords=("data", "axes fraction"), xytext=(0, 3 if i % 2 else 26),
                        textcoords="offset points", ha="center", va="bottom", fontsize=7, color="0.2",
                        arrowprops=None if i % 2 else dict(arrowstyle="-", color="0.5", lw=0.5))
        # measured points and the vessel
        for i, (m, ts) in enumerate(inputs["solver_t_s_us"].items()):
            ax.plot(ts, inputs["t_c_us"], marker="o^"[i % 2], ms=7, mfc="w", mec="k", mew=1.4, ls="")
            right = ts > 100
            ax.annotate(f"coarse cantilever,\n2 processes, {m}\n(t_s={ts:.0f} us)", (ts, inputs["t_c_us"]),
                        xytext=(-6, 6) if right else (6, -4), textcoords="offset points", fontsize=7,
                        va="bottom" if right else "top",
                        ha="right" if right else "left",
                        bbox=dict(boxstyle="round,pad=0.2", fc="w", ec="none", alpha=0.8))
        if inputs["t_c_source"].startswith("measured"):
            ax.axhline(inputs["t_c_us"], color="k", lw=0.6, ls="-.", alpha=0.6)
        if vessel is not None:
            ax.plot(vessel["t_s_us"], vessel["t_c_us"], marker="s", ms=7, mfc="w", mec="k", mew=1.4, ls="")
            ax.annotate(f"vessel, {vessel['n_parts']} emulated\nparts (t_s as L)", (vessel["t_s_us"],
                        vessel["t_c_us"]), xytext=(-8, -6), textcoords="offset points", fontsize=7,
                        ha="right", va="top", bbox=dict(boxstyle="round,pad=0.2", fc="w", ec="none", alpha=0.8))
    ax = axes[0]
    for key, be in break_even.items():
        for algo, ls, yfrac in (("allreduce", "-", 0.05), ("neighbour", "--", 0.30)):
            x = 1e6 * be[algo]
            if not L_RANGE_US[0] <= x <= L_RANGE_US[1]:
                continue
            ax.axvline(x, color=colours[key], lw=1.8, ls=ls)
            ax.annotate(f"{labels[key]} vs {algo}", (x, yfrac), xycoords=("data", "axes fraction"),
                        xytext=(-3, 0), textcoords="offset points", rotation=90, ha="right", va="bottom",
                        fontsize=7.5, color=colours[key],
                        bbox=dict(boxstyle="round,pad=0.15", fc="w", ec="none", alpha=0.75))
    ax.set_ylabel("local step cost per part t_c [us]")
    ax = axes[1]
    styles = {2: "-", 4: "--", 8: "-."}
    for k in HALO_LINES:
        cs = ax.contour(lat_us, tc_us, grid["zeta_k_nb"][k], levels=[1.0], colors="k",
                        linewidths=1.6, linestyles=styles[k])
        # label each line at its own latency: t_c* = (t_s - t_s,halo / k) / (r_k - 1)
        i = int(np.searchsorted(lat_us, {2: 1000.0, 4: 40.0, 8: 200.0}[k]))
        r = halos[k][0]
        ts_nb = grid["ts"]["neighbour"][i]
        tsh = 1e6 * sync_time(halos[k][1], Interconnect("map", 1e-6 * lat_us[i], BANDWIDTH_BPS), "neighbour")
        y = (ts_nb - tsh / k) / (r - 1) if r > 1 else None
        if y is not None and TC_RANGE_US[0] < y < TC_RANGE_US[1]:
            ax.clabel(cs, fmt={1.0: f"k={k} (r={r:.2f})"}, fontsize=8, inline=True, manual=[(lat_us[i], y)])
        else:
            ax.clabel(cs, fmt={1.0: f"k={k} (r={r:.2f})"}, fontsize=8, inline=True)
    ax.text(0.02, 0.98, "k = 2, 4, 8 against the neighbour baseline:\nbelow / right of a line the halo pays",
            transform=ax.transAxes, va="top", fontsize=8,
            bbox=dict(boxstyle="round,pad=0.3", fc="w", ec="0.6", alpha=0.85))
    axes[0].text(0.02, 0.98, "zeta = 1: solid vs allreduce, dashed vs neighbour;\nright of a line the "
                 "surrogate pays", transform=axes[0].transAxes, va="top", fontsize=8,
                 bbox=dict(boxstyle="round,pad=0.3", fc="w", ec="0.6", alpha=0.85))
    cb = fig.colorbar(mesh, ax=axes, shrink=0.85, pad=0.01)
    cb.set_label("zeta = t_synchronized / t_method (>1: method faster)")
    cb.set_ticks([1 / 8, 1 / 4, 1 / 2, 1, 2, 4, 8])
    cb.set_ticklabels(["1/8", "1/4", "1/2", "1", "2", "4", "8"])
    cb.ax.minorticks_off()
    fig.suptitle(f"Regime map (cost model): 2525-node beam on {pattern.n_parts} METIS parts, "
                 f"N_a={pattern.n_interface} interface nodes, bandwidth {BANDWIDTH_BPS / 1e9:g} GB/s; "
                 f"t_d: " + ", ".join(f"{labels[k]} {v:.1f} us" for k, v in inputs["t_d_us"].items()),
                 fontsize=10)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=150, format="png")
    plt.close(fig)


# --------------------------------------------------------------------------- main

def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sync-json", default=DEFAULT_SYNC_JSON, help="bench_sync.py output (t_d, t_c)")
    ap.add_argument("--out-dir", default=DEFAULT_OUT_DIR)
    args = ap.parse_args(argv)
    inputs = read_inputs(args.sync_json)
    vessel = read_vessel()
    mesh, pattern, halos = build_patterns()
    grid = compute_map(pattern, halos, inputs["t_d_us"])
    break_even = {k: {a: break_even_latency(pattern, 1e-6 * td, BANDWIDTH_BPS, a) for a in ALGOS}
                  for k, td in inputs["t_d_us"].items()}
    rows = preset_table(pattern, halos, inputs)
    notes = list(inputs["notes"])
    if vessel is None:
        notes.append("paper vessel not marked: no measured per-step times in "
                     "benchmarks/results/paper_vessel/paper_vessel_paper_measure.json")
    else:
        notes.append(f"paper vessel marked at t_c={vessel['t_c_us']:.0f} us (its projection's t_compute) and "
                     f"L={vessel['t_s_us']:.0f} us (its measured t_s, psum on {vessel['n_parts']} emulated "
                     "devices sharing 2 cores; a different partition from the map's)")
    notes.append("measured points: coarse cantilever (interface 4 nodes) on 2 real processes, at L = its "
                 "measured solver t_s; the map's colours are for the 8-part beam")
    os.makedirs(args.out_dir, exist_ok=True)
    png = os.path.join(args.out_dir, "regime_map.png")
    draw(png, grid, pattern, halos, inputs, break_even, vessel)
    record = {
        "benchmark": "regime map (cost model)", "sync_json": args.sync_json,
        "bandwidth_Bps": BANDWIDTH_BPS, "mesh_nodes": int(mesh.n_nodes),
        "pattern": pattern.to_dict(),
        "halos": {str(k): {"depth": k, "redundancy": r, "n_interface": hp.n_interface,
                           "dofs_per_node": hp.dofs_per_node} for k, (r, hp) in halos.items()},
        "inputs": inputs, "vessel": vessel,
        "break_even_latency_us": {k: {a: (1e6 * v if math.isfinite(v) else None)
                                      for a, v in be.items()} for k, be in break_even.items()},
        "presets": rows, "notes": notes,
        "map": {"latency_us": grid["lat_us"][::8].tolist(), "t_c_us": grid["tc_us"][::7].tolist(),
                "zeta_surrogate_best": grid["zeta_s"][::7, ::8].tolist(),
                "zeta_halo_best": grid["zeta_h"][::7, ::8].tolist()},
        "png": png,
    }
    path = os.path.join(args.out_dir, "regime_map.json")
    with atomic_path(path) as tmp:
        with open(tmp, "w") as f:
            json.dump(record, f, indent=1, allow_nan=False)
    print(format_table(rows, inputs, pattern))
    print("break-even latency [us] (surrogate pays at larger L): " + "; ".join(
        f"{k}: " + ", ".join(f"{a} {1e6 * v:.2f}" for a, v in be.items()) for k, be in break_even.items()))
    print("halos: " + ", ".join(f"k={k} r={r:.3f} N_halo={hp.n_interface}" for k, (r, hp) in halos.items()))
    for n in notes:
        print("note:", n)
    print(f"wrote {png} and {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
