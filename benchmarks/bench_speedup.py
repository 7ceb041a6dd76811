"""Speed-up of avoiding synchronization (paper section 7, Figures 25-34), roofline and a
projection to clusters.

Every configuration is measured with :func:`jaxsync.perf.timing.speedup_breakdown`: the whole
SPMD programs -- synchronized with a psum of the interface and with the ppermute
neighbour exchange, without synchronization, and synchronization-avoiding (n_s n_f
unsynchronized steps and one batched refill prediction per part, no collective) -- are
timed round-robin in the same run, so zeta = t_t / t_t' compares the synchronization-
avoiding solver with the synchronized baseline at its best. The per-part stages t_e, t_m,
t_s, t_d, t_o and the max-average rows (paper Table 2) come with it. The surrogates are
untrained replicas of the chosen architecture, each refill evaluating every one of the n_s
applications (`refill_samples=None`, the paper's refill; a network's cost does not depend on its
weights; accuracy is what `jaxsync demo` and `paper_cantilever.py` measure).

Deep halos (:mod:`jaxsync.parallel.exchange`), the exact communication-avoiding scheme, are
timed in the same round-robin for depths k = 1, 2, 4, 8 (``t_step_halo_us``, ``zeta_halo``).

Scenarios (the paper's):
- ``coarse``: the paper's coarse cantilever on 2 devices, both modes, for the paper's
  network (n_H = 100, 2 layers) and the demo's (n_H = 32, 2 layers);
- ``growing``: 8 parts cut along x (shared nodes on planes x = const) on a growing mesh;
- ``fixed``: a fixed 2525-node mesh over 2, 4 and 8 METIS parts;
each with and without pre-assembly. n_s = 80, n_p = n_f = 20 (paper).

The devices are EMULATED: XLA host devices (``--xla_force_host_platform_device_count=8``)
that share this machine's cores, so a collective is a rendezvous of threads on
oversubscribed cores, not a network message; the output says so.

Roofline: bytes and flops per step of each stage (:mod:`jaxsync.perf.roofline`) against the
measured stage times and this machine's copy bandwidth.

t_d is what the synchronization-avoiding program pays: one prediction of all parts at
once (8 networks on 2 cores cost about 4x one network alone); the projection to
clusters uses a part's own step and its network alone (one part per processor).

Cost model (:mod:`jaxsync.perf.costmodel`): latency + bytes / bandwidth per message, times
the messages of the synchronization pattern. It is calibrated on this machine by timing
a bare psum of growing size between 2, 4 and 8 emulated devices (one fit of latency and
bandwidth per device count: the "latency" of emulated devices is their threads meeting,
which grows with their number), checked against every measured t_s (psum: the
"collective" pattern; ppermute: "collective-permute", one call per device offset), then
fed the measured compute times and t_d to predict zeta on named interconnects (MPI
allreduce and neighbour exchange algorithms).

Usage: python benchmarks/bench_speedup.py [--quick] [--out benchmarks/results/speedup.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                           + " --xla_force_host_platform_device_count=8").strip()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.sharding import Mesh  # noqa: E402

import jaxsync  # noqa: E402
from jaxsync.parallel import (  # noqa: E402
    AXIS,
    partition_from_elements,  # noqa: E402
    spmd_program,
)
from jaxsync.perf import costmodel, measure, roofline  # noqa: E402
from jaxsync.perf.timing import speedup_breakdown  # noqa: E402
from jaxsync.surrogate import Surrogate  # noqa: E402

N_S, N_P, N_F = 80, 20, 20
HALO_DEPTHS = (1, 2, 4, 8)  # deep halos timed beside the surrogate: exact, one exchange every k steps
DEVICES_NOTE = (f"{len(jax.devices())} EMULATED CPU devices (XLA host devices sharing "
                f"{os.cpu_count()} cores): collectives are thread rendezvous, not messages")


def x_slabs(mesh, n_parts):
    """Element partition into n_parts slabs along x (shared nodes on x = const planes)."""
    x = mesh.points[mesh.tets].mean(axis=1)[:, 0]
    edges = np.linspace(x.min(), x.max() + 1e-9, n_parts + 1)
    return partition_from_elements(mesh, np.clip(np.searchsorted(edges, x, side="right") - 1,
                                                 0, n_parts - 1))


def psum_times(n_devices, sizes, n_iter=200, repeats=7):
    """Per-call seconds of a psum of ``size`` doubles between ``n_devices`` emulated devices
    (inside a scan, as in the solver; the same scan without the psum subtracted)."""
    mesh = Mesh(np.array(jax.devices()[:n_devices]), (AXIS,))

    def program(with_psum):
        def step(c, _):  # one part per device: the psum over the devices sums all parts
            return 0.5 * (jax.lax.psum(c, AXIS) if with_psum else c), None

        per_part = lambda x: jax.lax.scan(step, x, None, length=n_iter)[0]  # noqa: E731
        return spmd_program(per_part, mesh, n_in=1, n_out=1)

    out = []
    for size in sizes:
        x = jnp.ones((n_devices, size))
        best = measure.best_times({"psum": (program(True), (x,)), "scan": (program(False), (x,))}, repeats)
        out.append(max(best["psum"] - best["scan"], 1e-9) / n_iter)
    return np.array(out)


def scenario_configs(quick):
    coarse = jaxsync.cantilever()
    growing = [(40, 2, 2), (80, 4, 4)] if quick else [(40, 2, 2), (80, 4, 4), (120, 6, 6)]
    fixed = jaxsync.cantilever(jaxsync.box_beam(25.0, 1.0, 1.0, (100, 4, 4)))
    configs = []
    for mode in ("preassembled", "recompute"):
        for n_hidden in (100, 32):
            configs.append(dict(scenario="coarse", problem=coarse, n_parts=2, mode=mode,
                                n_hidden=n_hidden, devices=jax.devices()[:2], cut="metis"))
        for div in growing:
            p = jaxsync.cantilever(jaxsync.box_beam(25.0, 1.0, 1.0, div))
            configs.append(dict(scenario="growing", problem=p, n_parts=8, mode=mode, n_hidden=100,
                                devices=None, cut="x"))
        for n_parts in ((2, 8) if quick else (2, 4, 8)):
            configs.append(dict(scenario="fixed", problem=fixed, n_parts=n_parts, mode=mode,
                                n_hidden=100, devices=None, cut="metis"))
    return configs


def run_config(cfg, bandwidth, peak_flops, repeats, stage_repeats):
    problem, n_parts = cfg["problem"], cfg["n_parts"]
    part = x_slabs(problem.mesh, n_parts) if cfg["cut"] == "x" else jaxsync.partition(problem.mesh, n_parts)
    # every one of the n_s applications per refill, as the paper's refill (the default smooth
    # refill evaluates DEFAULT_REFILL_SAMPLES of them: bench_predicted_step.py times both)
    predictor = Surrogate.initialized(part, N_S, n_hidden=cfg["n_hidden"], n_layers=2,
                                      n_past=N_P, n_future=N_F).with_refill_samples(None)
    start = time.perf_counter()
    report = speedup_breakdown(problem, part, predictor, mode=cfg["mode"], repeats=repeats, stage_repeats=stage_repeats,
                               syncs=(jaxsync.Psum(cfg["devices"]), jaxsync.Ppermute(cfg["devices"])),
                               halo_depths=HALO_DEPTHS)
    top = report.synchronized.max_average
    costs = roofline.step_costs_for(problem, part, mode=cfg["mode"])[top.part]
    costs = dict(costs, t_d=roofline.surrogate_step_cost(predictor.arch, N_S, calls=predictor.refill_calls))
    times = {"t_e": top.t_e, "t_m": top.t_m, "t_s": report.t_s, "t_o": top.t_o,
             "t_d": report.avoiding.rows[top.part].t_d}
    points = roofline.achieved_stages(costs, times, bandwidth, peak_flops)
    pattern = costmodel.communication_pattern(part)
    return {"scenario": cfg["scenario"], "mode": cfg["mode"], "n_parts": n_parts,
            "n_nodes": problem.mesh.n_nodes, "n_elements": problem.mesh.n_elements,
            "n_shared_nodes": part.n_interface, "n_hidden": cfg["n_hidden"],
            "n_devices": report.synchronized.n_devices, "zeta": report.zeta,
            "sync": report.sync, "t_step_sync_us": {k: 1e6 * v for k, v in report.t_step_sync.items()},
            "t_step_nosync_us": 1e6 * report.t_step_nosync,
            "t_step_avoiding_us": 1e6 * report.t_step_avoiding, "t_s_us": 1e6 * report.t_s,
            "t_step_halo_us": {k: 1e6 * v for k, v in report.t_step_halo.items()},
            "zeta_halo": report.zeta_halo,
            "t_d_us": 1e6 * report.t_d, "t_prediction_ms": 1e3 * report.t_prediction_spmd,
            "t_prediction_alone_ms": 1e3 * max(report.t_prediction),
            "surrogate_pays": report.surrogate_pays,
            "t_compute_us": 1e6 * top.t_local,
            "roofline": {k: v.to_dict() for k, v in points.items()},
            "pattern": pattern.to_dict(), "report": report.to_dict(),
            "table": report.table(), "seconds": time.perf_counter() - start}


def model_check(rows, links):
    """Predicted t_s (emulated link fitted for the run's device count) against every
    measured whole-program t_s."""
    checks = []
    for r in rows:
        pattern = costmodel.CommunicationPattern(**r["pattern"])  # lists from to_dict are accepted
        link = links[r["n_devices"]]
        for method, algorithm in (("psum", "collective"), ("ppermute", "collective-permute")):
            measured = max(r["t_step_sync_us"][method] - r["t_step_nosync_us"], 1e-3) * 1e-6
            predicted = costmodel.sync_time(pattern, link, algorithm)
            checks.append({"scenario": r["scenario"], "mode": r["mode"], "n_parts": r["n_parts"],
                           "n_nodes": r["n_nodes"], "sync": method, "measured_us": 1e6 * measured,
                           "predicted_us": 1e6 * predicted,
                           "relative_error": float(costmodel.relative_error(predicted, measured))})
    return checks


def projections(rows):
    out = []
    for r in rows:
        pattern = costmodel.CommunicationPattern(**r["pattern"])  # lists from to_dict are accepted
        for algorithm in ("allreduce", "neighbour"):
            # one part per processor on a cluster: its own step and its own network alone
            t_d_alone = r["t_prediction_alone_ms"] * 1e-3 / (N_S * N_F)
            proj = costmodel.project(r["t_compute_us"] * 1e-6, t_d_alone, pattern,
                                     algorithm=algorithm)
            out.append({"scenario": r["scenario"], "mode": r["mode"], "n_parts": r["n_parts"],
                        "n_nodes": r["n_nodes"], "algorithm": algorithm,
                        "zeta": {p.interconnect.name: p.zeta for p in proj.rows},
                        "t_s_us": {p.interconnect.name: 1e6 * p.t_s for p in proj.rows}})
    return out


def plot(rows, path_prefix):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4), constrained_layout=True)
    for mode, marker in (("preassembled", "o"), ("recompute", "s")):
        g = [r for r in rows if r["scenario"] == "growing" and r["mode"] == mode]
        axes[0].plot([r["n_nodes"] for r in g], [r["zeta"] for r in g], marker=marker, label=mode)
        f = [r for r in rows if r["scenario"] == "fixed" and r["mode"] == mode]
        axes[1].plot([r["n_parts"] for r in f], [r["zeta"] for r in f], marker=marker, label=mode)
    axes[0].set(xscale="log", xlabel="mesh nodes (8 parts, cut along x)", ylabel=r"speed-up $\zeta$")
    axes[1].set(xlabel="parts $n_c$ (2525-node mesh)", ylabel=r"speed-up $\zeta$")
    for ax in axes:
        ax.axhline(1.0, color="0.6", lw=0.8)
        ax.legend()
    fig.suptitle("synchronization-avoiding speed-up, " + DEVICES_NOTE, fontsize=8)
    fig.savefig(path_prefix + "_zeta.png", dpi=150)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(10, 4), constrained_layout=True)
    labels, stages = [], ("t_e", "t_m", "t_s", "t_d", "t_o")
    bottoms = None
    values = {s: [] for s in stages}
    for r in rows:
        for label, key in (("sync", "synchronized"), ("avoid", "avoiding")):
            top = r["report"][key]["max_average"]
            labels.append(f"{r['scenario'][:5]} {r['mode'][:3]} n{r['n_nodes']} p{r['n_parts']} {label}")
            for s in stages:
                values[s].append(top[s] * 1e6)
    x = np.arange(len(labels))
    bottoms = np.zeros(len(labels))
    for s in stages:
        ax.bar(x, values[s], bottom=bottoms, label=s)
        bottoms += np.array(values[s])
    ax.set_xticks(x, labels, rotation=90, fontsize=5)
    ax.set(ylabel="us per step (max-average part)", yscale="log")
    ax.legend(fontsize=7)
    ax.set_title("stage breakdown, " + DEVICES_NOTE, fontsize=8)
    fig.savefig(path_prefix + "_stages.png", dpi=150)
    plt.close(fig)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer meshes and repeats")
    parser.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "speedup.json"))
    args = parser.parse_args(argv)
    repeats, stage_repeats = (2, 5) if args.quick else (4, 20)

    bandwidth = measure.copy_bandwidth()
    peak_flops = measure.matmul_flop_rate()
    sizes = np.array([12, 1200, 12000, 120000])  # doubles
    calib, links = {}, {}
    for n in (2, 4, 8):
        calib[n] = psum_times(n, sizes)
        try:
            links[n] = costmodel.fit_interconnect(
                sizes * 8, calib[n], name=f"emulated-{n}-devices",
                source=f"fitted on this machine: psum between {n} emulated devices")
        except jaxsync.JaxsyncError as exc:  # too noisy to fit: say so, keep the latency
            print(f"cost model calibration ({n} devices): {exc}")
            links[n] = costmodel.Interconnect(f"emulated-{n}-devices", float(calib[n][0]), 1e10,
                                              f"smallest psum between {n} emulated devices")

    rows = []
    for cfg in scenario_configs(args.quick):
        r = run_config(cfg, bandwidth, peak_flops, repeats, stage_repeats)
        rows.append(r)
        print(f"{r['scenario']:<8} {r['mode']:<12} nodes {r['n_nodes']:>6} parts {r['n_parts']} "
              f"n_H {r['n_hidden']:>3}: sync {r['t_step_sync_us']['psum']:9.1f} (psum) "
              f"{r['t_step_sync_us']['ppermute']:9.1f} (ppermute)  avoid {r['t_step_avoiding_us']:9.1f} "
              f"us/step  t_s {r['t_s_us']:8.1f}  t_d {r['t_d_us']:7.2f} (alone "
              f"{1e3 * r['t_prediction_alone_ms'] / (N_S * N_F):5.2f})  zeta {r['zeta']:5.2f}; deep halos "
              + " ".join(f"k={k} {t:.1f} (zeta {r['zeta_halo'][k]:.2f})" for k, t in r["t_step_halo_us"].items())
              + f" ({r['seconds']:.0f} s)", flush=True)

    checks = model_check(rows, links)
    proj = projections(rows)
    print()
    print(DEVICES_NOTE)
    print(f"copy bandwidth {bandwidth / 1e9:.1f} GB/s; float32 matmul peak {peak_flops / 1e9:.0f} "
          "GFlop/s; emulated links fitted: " + "; ".join(
              f"{n} devices latency {1e6 * link.latency_s:.1f} us, bandwidth "
              f"{link.bandwidth_Bps / 1e9:.2f} GB/s" for n, link in links.items()))
    for method in ("psum", "ppermute"):
        e = np.abs([c["relative_error"] for c in checks if c["sync"] == method])
        print(f"cost model vs measured t_s ({method}): median |relative error| {np.median(e):.0%}, "
              f"max {e.max():.0%} over {len(e)} measurements")
    print("\nroofline (max-average part): stage GB/s, GFlop/s, measured / roofline time")
    for r in rows:
        print(f"  {r['scenario']:<8} {r['mode'][:3]} nodes {r['n_nodes']:>6} parts {r['n_parts']} "
              f"n_H {r['n_hidden']:>3}: "
              + ", ".join(f"{k} {v['GB_per_s']:.1f} GB/s {v['GFlop_per_s']:.1f} GF/s x{v['distance']:.1f}"
                          for k, v in r["roofline"].items()))
    print("\nprojected zeta (neighbour exchange; allreduce in the JSON):")
    names = list(costmodel.INTERCONNECTS)
    print(f"  {'scenario':<8} {'mode':<12} {'nodes':>6} {'parts':>5} " + " ".join(f"{n:>15}" for n in names))
    for p in proj:
        if p["algorithm"] == "neighbour":
            print(f"  {p['scenario']:<8} {p['mode']:<12} {p['n_nodes']:>6} {p['n_parts']:>5} "
                  + " ".join(f"{p['zeta'][n]:>15.3f}" for n in names))

    result = {"benchmark": "speedup", "devices": DEVICES_NOTE, "n_s": N_S, "n_p": N_P, "n_f": N_F,
              "copy_bandwidth_Bps": bandwidth, "matmul_peak_flops": peak_flops, "calibration": {
                  "sizes_doubles": sizes.tolist(), "psum_s": {str(k): v.tolist() for k, v in calib.items()},
                  "links": {str(n): link.to_dict() for n, link in links.items()}},
              "rows": rows, "model_check": checks, "projections": proj,
              "machine": {"platform": platform.platform(), "cores": os.cpu_count(),
                          "python": sys.version.split()[0], "jax": jax.__version__,
                          "load_average": os.getloadavg()[0]}}
    from jaxsync.io import atomic_path

    with atomic_path(args.out) as tmp:
        with open(tmp, "w") as f:
            json.dump(result, f, indent=2, default=float)
    plot(rows, os.path.splitext(args.out)[0])
    print(f"wrote {args.out} and {os.path.splitext(args.out)[0]}_{{zeta,stages}}.png")


if __name__ == "__main__":
    main()
