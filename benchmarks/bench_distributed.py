"""Cost of the distributed explicit solver per step, broken down as in the paper's
section 7 (Figures 25-34), on EMULATED devices, with the paper's published code pattern
as a baseline.

Scenarios (cantilever, ``jaxsync.cantilever(jaxsync.box_beam(25, 1, 1, (nx, ny, nz)))``):

* growing mesh: n_c = 8 parts, finer and finer meshes; cost against N_a shared nodes;
* part count: one fixed mesh split into 1 to 8 parts; cost against n_c;
* both with pre-assembly (stored K) and element recompute (paper Remark 2).

Each configuration is one :func:`jaxsync.perf.timing.timing_breakdown` (method and limits in
that module's docstring): t_e, t_m, t_s, t_o, t_t and ratios of the "max-average" part.
Column ``|sum-1|`` (JSON ``stage_sum_error``) is the largest over the parts of
|(t_e + t_m + t_o) / t_local - 1|: how far the separately timed stages miss the measured
local step (stage additivity; within 10 % on an unloaded machine, both modes).

Baseline, side by side: ``benchmarks/paper_baseline.py`` under ``mpiexec -n 2`` (two
processes on this machine, loopback), doing per step what the paper's published code
does (SciPy CSR product per rank, partial forces gathered on rank 0, summed, broadcast
back, central-difference update), on the same mesh, the same METIS partition into 2
parts and the same number of steps as jaxsync's distributed solver on 2 emulated
devices; the final displacements of both are compared, and the per-step ratio reported.

The devices are emulated: ``XLA_FLAGS=--xla_force_host_platform_device_count=8`` is set
before jax is imported, so the 8 "devices" are threads sharing this machine's CPU cores.
The load average is recorded; other people's jobs may share the machine.

    python benchmarks/bench_distributed.py [--quick] [--out benchmarks/results] [--plot-only]

Writes ``distributed.json`` and PNG plots into ``--out`` and prints a table.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time

N_DEVICES = 8
if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                               + f" --xla_force_host_platform_device_count={N_DEVICES}").strip()
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
import scipy.sparse as sp  # noqa: E402

import jaxsync  # noqa: E402
from jaxsync.fem import advance  # noqa: E402
from jaxsync.io import atomic_path  # noqa: E402
from jaxsync.perf.measure import best_time  # noqa: E402
from jaxsync.perf.reports import STAGES  # noqa: E402
from jaxsync.perf.timing import timing_breakdown  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
EMULATION_NOTE = (f"EMULATED devices: {N_DEVICES} XLA host devices "
                  "(XLA_FLAGS=--xla_force_host_platform_device_count) that share "
                  f"{os.cpu_count()} CPU cores of one machine; not separate processors")

FULL = {"growing": [(25, 1, 1), (50, 2, 2), (75, 3, 3), (100, 4, 4), (150, 6, 6)],
        "fixed": (100, 4, 4), "part_counts": [1, 2, 3, 4, 5, 6, 7, 8], "repeats": 60,
        "baseline": [((25, 1, 1), 4000), ((100, 4, 4), 500)]}
QUICK = {"growing": [(25, 1, 1), (50, 2, 2)], "fixed": (50, 2, 2), "part_counts": [1, 2, 4, 8],
         "repeats": 30, "baseline": [((25, 1, 1), 1000), ((50, 2, 2), 400)]}
MODES = ("preassembled", "recompute")


def cantilever(divisions):
    return jaxsync.cantilever(jaxsync.box_beam(25.0, 1.0, 1.0, tuple(divisions)))


def run_scenario(name, configs, repeats, log):
    """[(divisions, n_parts)] -> list of report dicts (both modes)."""
    out = []
    for divisions, n_parts in configs:
        problem = cantilever(divisions)
        partition = jaxsync.partition(problem.mesh, n_parts)
        for mode in MODES:
            start = time.perf_counter()
            # default n_steps: about 1 ms calls (the per-call cost is measured and removed)
            report = timing_breakdown(problem, partition, mode=mode, repeats=repeats)
            entry = report.to_dict()
            entry.update(scenario=name, divisions=list(divisions), wall_s=time.perf_counter() - start,
                         stage_sum_error=stage_sum_error(report))
            out.append(entry)
            log(summary_line(entry))
    return out


def stage_sum_error(report) -> float:
    """max over the parts of |(t_e + t_m + t_o) / t_local - 1| (0 when nothing was measured)."""
    return max((abs((r.t_e + r.t_m + r.t_o) / r.t_local - 1.0) for r in report.rows if r.t_local > 0),
               default=0.0)


def summary_line(e) -> str:
    m = e["max_average"]
    return (f"{e['scenario']:<8} {e['mode']:<12} {'x'.join(map(str, e['divisions'])):>9} "
            f"{e['n_nodes']:>6} {e['n_parts']:>3} {e['n_shared_nodes']:>5} "
            + " ".join(f"{1e6 * m[k]:>8.2f}" for k in (*STAGES, "t_t"))
            + "  " + " ".join(f"{m[k]:>5.2f}" for k in ("r_e", "r_m", "r_s", "r_o"))
            + f" {1e6 * e['t_step']:>9.2f} {1e6 * e['t_step_nosync']:>9.2f} {e['stage_sum_error']:>7.3f}")


HEADER = (f"{'scenario':<8} {'mode':<12} {'mesh':>9} {'nodes':>6} {'n_c':>3} {'N_a':>5} "
          + " ".join(f"{k:>8}" for k in (*STAGES, "t_t"))
          + "  " + " ".join(f"{k:>5}" for k in ("r_e", "r_m", "r_s", "r_o"))
          + f" {'step':>9} {'nosync':>9} {'|sum-1|':>7}")


# ---------------------------------------------------------------------------------------
# Baseline


def baseline_input(problem, partition, path) -> dict:
    """Write the per-part arrays ``paper_baseline.py`` reads; returns the global initial
    state and system used (for running jaxsync from the same start)."""
    from jaxsync.fem import Ramp, build_system, element_blocks, initial_state

    if len(problem.loads) != 1 or not isinstance(problem.loads[0].time, Ramp):
        raise ValueError("the baseline handles one ramped load (the cantilever)")
    dt = float(problem.dt)
    system = build_system(problem, dt, "preassembled")
    state = initial_state(problem, system)
    m = problem.material
    k_lambda, k_mu = element_blocks(problem.mesh)
    mass = np.repeat(np.asarray(problem.lumped_mass()), 3)
    load = np.asarray(problem.load_vectors()[0][0]).reshape(-1)
    fixed = partition.dirichlet_local(problem.dirichlet_dofs()[0])
    arrays = {"n_parts": partition.n_parts, "n_nodes": problem.mesh.n_nodes, "dt": dt,
              "alpha": float(problem.damping), "t_ramp": float(problem.loads[0].time.t_end),
              "d0": np.asarray(state.displacement).reshape(-1),
              "dm1": np.asarray(state.previous).reshape(-1)}
    for r, part in enumerate(partition.parts):
        local = (3 * part.local_tets[:, :, None] + np.arange(3)).reshape(-1, 12)
        values = float(m.lam) * k_lambda[part.elements] + float(m.mu) * k_mu[part.elements]
        K = sp.coo_matrix((values.ravel(), (np.repeat(local, 12, axis=1).ravel(), np.tile(local, (1, 12)).ravel())),
                          shape=(3 * part.n_local,) * 2).tocsr()
        dofs = (3 * part.nodes[:, None] + np.arange(3)).ravel()
        arrays.update({f"K{r}_data": K.data, f"K{r}_indices": K.indices, f"K{r}_indptr": K.indptr,
                       f"nodes{r}": part.nodes, f"mass{r}": mass[dofs], f"load{r}": load[dofs],
                       f"fixed{r}": fixed[r]})
    np.savez(path, **arrays)
    return {"system": system, "state": state}


def run_baseline(divisions, n_steps, log, repeats=3, jax_repeats=5) -> dict:
    from jaxsync.solve.executors import DistributedRunner

    problem = cantilever(divisions)
    partition = jaxsync.partition(problem.mesh, 2)
    entry = {"divisions": list(divisions), "n_nodes": problem.mesh.n_nodes,
             "n_elements": problem.mesh.n_elements, "n_steps": n_steps, "n_parts": 2,
             "n_shared_nodes": partition.n_interface}
    with tempfile.TemporaryDirectory() as tmp:
        data = os.path.join(tmp, "parts.npz")
        start = baseline_input(problem, partition, data)
        for comm in ("pickle", "buffers"):
            out = os.path.join(tmp, f"{comm}.json")
            runs = []
            for _ in range(repeats):  # separate processes: the best run's own timings are kept
                subprocess.run(["mpiexec", "-n", "2", sys.executable, os.path.join(HERE, "paper_baseline.py"),
                                data, out, "--steps", str(n_steps), "--comm", comm],
                               check=True, env={k: v for k, v in os.environ.items() if k != "XLA_FLAGS"})
                with open(out) as f:
                    runs.append(json.load(f))
            best = min(runs, key=lambda result: result["t_step"])
            entry[f"baseline_{comm}"] = {k: v for k, v in best.items() if k != "final_displacement"}
            entry[f"baseline_{comm}_final"] = np.asarray(best["final_displacement"]).reshape(-1, 3)

    # jaxsync's compiled chunks of n_steps steps from the same start: on 2 emulated devices
    # (the distributed runner's program) and on one device (the single-device solver's)
    system, state = start["system"], start["state"]
    runner = DistributedRunner(problem, system, partition, save_every=n_steps,
                               sync=jaxsync.Psum(devices=jax.devices()[:2]))
    local_start = runner.from_global(state)
    distributed, one_device = runner.program(1), jax.jit(advance, static_argnums=(2, 3))
    entry["jaxsync_2_devices_s_per_step"] = best_time(distributed, jax_repeats, runner.parts, local_start) / n_steps
    entry["jaxsync_1_device_s_per_step"] = best_time(one_device, jax_repeats, system, state, 1, n_steps) / n_steps
    result = {"distributed": runner.to_global(distributed(runner.parts, local_start)[0]).displacement,
              "single": np.asarray(one_device(system, state, 1, n_steps)[0].displacement)}
    scale = float(np.abs(result["single"]).max())
    for comm in ("pickle", "buffers"):
        final = entry.pop(f"baseline_{comm}_final")
        entry[f"baseline_{comm}_rel_diff"] = float(np.abs(final - result["distributed"]).max() / scale)
        entry[f"ratio_{comm}"] = entry[f"baseline_{comm}"]["t_step"] / entry["jaxsync_2_devices_s_per_step"]
    entry["jaxsync_rel_diff_1_vs_2"] = float(np.abs(result["single"] - result["distributed"]).max() / scale)
    entry["loadavg"] = list(os.getloadavg())
    log(f"baseline {'x'.join(map(str, divisions)):>9} {entry['n_nodes']:>6} nodes, {n_steps} steps: "
        f"paper pattern (pickle) {1e6 * entry['baseline_pickle']['t_step']:.1f} us/step "
        f"[t_m {1e6 * entry['baseline_pickle']['max_average']['t_m']:.1f}, "
        f"t_s {1e6 * entry['baseline_pickle']['max_average']['t_s']:.1f}], "
        f"buffers {1e6 * entry['baseline_buffers']['t_step']:.1f} us/step; "
        f"jaxsync 2 emulated devices {1e6 * entry['jaxsync_2_devices_s_per_step']:.1f} us/step, "
        f"1 device {1e6 * entry['jaxsync_1_device_s_per_step']:.1f} us/step; "
        f"baseline/jaxsync {entry['ratio_pickle']:.1f}x (pickle), {entry['ratio_buffers']:.1f}x (buffers); "
        f"final-state rel. diff {entry['baseline_pickle_rel_diff']:.1e}")
    return entry


# ---------------------------------------------------------------------------------------
# Plots


def plot(results, out_dir) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    styles = {"t_t": ("k", "o", "t_t total"), "t_e": ("tab:green", "s", "t_e element"),
              "t_m": ("tab:blue", "^", "t_m mat-vec"), "t_s": ("tab:red", "v", "t_s sync"),
              "t_o": ("tab:gray", "d", "t_o other")}
    for scenario, xkey, xlabel, fname in (
            ("growing", "n_shared_nodes", "N_a (shared nodes), n_c = 8", "distributed_growing_mesh.png"),
            ("parts", "n_parts", "n_c (parts), fixed mesh", "distributed_part_count.png")):
        entries = [e for e in results["scenarios"][scenario]]
        fig, axes = plt.subplots(2, 2, figsize=(11, 8), sharex="col")
        for col, mode in enumerate(MODES):
            rows = sorted((e for e in entries if e["mode"] == mode), key=lambda e: e[xkey])
            x = np.array([e[xkey] for e in rows], dtype=float)
            ax = axes[0, col]
            for key, (color, marker, label) in styles.items():
                y = np.array([1e6 * e["max_average"][key] for e in rows])
                if np.any(y > 0):
                    ax.plot(x, np.where(y > 0, y, np.nan), color=color, marker=marker, label=label)
            ax.plot(x, [1e6 * e["t_step"] for e in rows], "k--", lw=1, label="whole SPMD step")
            ax.set_yscale("log")
            ax.set_ylabel("max-average cost per step [us]")
            ax.set_title(f"{mode}")
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=8)
            ax = axes[1, col]
            for key in ("t_e", "t_m", "t_s", "t_o"):
                color, marker, label = styles[key]
                ax.plot(x, [e["max_average"]["r" + key[1:]] for e in rows], color=color, marker=marker,
                        label="r" + key[1:])
            ax.set_ylim(0, 1.05)
            ax.set_ylabel("ratio to t_t")
            ax.set_xlabel(xlabel)
            ax.grid(True, alpha=0.3)
            ax.legend(fontsize=8)
            if scenario == "growing":
                for a in axes[:, col]:
                    a.set_xscale("log")
                    a.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
            axes[1, col].set_xticks(x, [f"{v:g}" for v in x])
        fig.suptitle(f"jaxsync distributed step, cantilever; {EMULATION_NOTE}", fontsize=8)
        fig.tight_layout()
        path = os.path.join(out_dir, fname)
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=110, format="png")
        plt.close(fig)
        written.append(path)

    base = results["baseline"]
    fig, ax = plt.subplots(figsize=(8, 4.5))
    labels = [f"{e['n_nodes']} nodes\n{e['n_steps']} steps" for e in base]
    series = [("paper pattern, mpi4py pickle", [e["baseline_pickle"]["t_step"] for e in base], "tab:red"),
              ("paper pattern, mpi4py buffers", [e["baseline_buffers"]["t_step"] for e in base], "tab:orange"),
              ("jaxsync, 2 emulated devices", [e["jaxsync_2_devices_s_per_step"] for e in base], "tab:blue"),
              ("jaxsync, 1 device", [e["jaxsync_1_device_s_per_step"] for e in base], "tab:cyan")]
    width = 0.2
    for i, (label, values, color) in enumerate(series):
        ax.bar(np.arange(len(base)) + (i - 1.5) * width, 1e6 * np.asarray(values), width, label=label, color=color)
    ax.set_xticks(np.arange(len(base)), labels)
    ax.set_yscale("log")
    ax.set_ylabel("wall time per synchronized step [us]")
    ax.set_title("2 parts: published-code pattern (2 MPI processes) vs jaxsync", fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(True, axis="y", which="both", alpha=0.3)
    fig.tight_layout()
    path = os.path.join(out_dir, "distributed_baseline.png")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    written.append(path)
    return written


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="short run: fewer meshes, part counts, repeats")
    parser.add_argument("--out", default=os.path.join(HERE, "results"), help="output folder (default: %(default)s)")
    parser.add_argument("--no-baseline", action="store_true", help="skip the mpiexec baseline")
    parser.add_argument("--plot-only", action="store_true",
                        help="only redraw the PNGs from the existing distributed.json in --out")
    args = parser.parse_args(argv)
    if args.plot_only:
        with open(os.path.join(args.out, "distributed.json")) as f:
            results = json.load(f)
        pngs = plot(results, args.out)
        print("wrote", *pngs)
        return results
    config = QUICK if args.quick else FULL
    os.makedirs(args.out, exist_ok=True)
    if len(jax.devices()) < N_DEVICES:
        raise SystemExit(f"need {N_DEVICES} devices, have {len(jax.devices())}: XLA_FLAGS was set "
                         "before this script could set it")

    def log(line):
        print(line, flush=True)

    started = time.perf_counter()
    load_start = list(os.getloadavg())
    print(EMULATION_NOTE)
    print(f"load average at start: {load_start}; all times in us per step")
    print(HEADER)
    growing = run_scenario("growing", [(d, 8) for d in config["growing"]], config["repeats"], log)
    parts = run_scenario("parts", [(config["fixed"], n) for n in config["part_counts"]], config["repeats"], log)
    baseline = [] if args.no_baseline else [run_baseline(d, n, log) for d, n in config["baseline"]]
    results = {
        "kind": "jaxsync-bench-distributed", "quick": args.quick, "emulated_devices": True,
        "note": EMULATION_NOTE, "n_devices": len(jax.devices()), "cpu_count": os.cpu_count(),
        "platform": platform.platform(), "python": platform.python_version(), "jax": jax.__version__,
        "loadavg_start": load_start, "loadavg_end": list(os.getloadavg()),
        "config": {k: v for k, v in config.items()},
        "scenarios": {"growing": growing, "parts": parts}, "baseline": baseline,
        "wall_s": time.perf_counter() - started,
    }
    path = os.path.join(args.out, "distributed.json")
    with atomic_path(path) as tmp:
        with open(tmp, "w") as f:
            json.dump(results, f, indent=1)
    pngs = plot(results, args.out) if baseline else []
    print(f"load average at end: {results['loadavg_end']}; wall {results['wall_s']:.0f} s")
    print("wrote", path, *pngs)
    return results


if __name__ == "__main__":
    main()
