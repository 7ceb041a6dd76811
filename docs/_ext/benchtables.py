"""Benchmark tables rendered from the result files the scripts write, at build time.

```{bench-table} stepper
```

renders the table named ``stepper`` from ``benchmarks/results/stepper.json``: the numbers
in the documentation are always those of the result files in the checkout, and a rerun of
a benchmark script updates them with no edit of the pages. Each renderer below reads one
script's output (``RESULTS`` and the experiments' folders), and returns tables with the
files they came from and what the files record about the run (cores, JAX version, load
average, date). A missing file, or one whose layout a renderer does not know, is a build
warning (an error with ``-W``) that names the file.

Only the standard library and docutils are used: nothing is imported from jaxsync or from
the benchmark scripts, and nothing is computed beyond formatting and simple ratios.
"""

from __future__ import annotations

import glob
import json
import math
import os
from dataclasses import dataclass, field

from docutils import nodes
from sphinx.util import logging
from sphinx.util.docutils import SphinxDirective

logger = logging.getLogger(__name__)

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
RESULTS = os.path.join(ROOT, "benchmarks", "results")


# -- formatting -------------------------------------------------------------------------

def num(x, sig: int = 3) -> str:
    """A number for a table: ``sig`` significant digits, no exponent between 1e-3 and 1e6,
    thousands separated by a thin space."""
    if x is None:
        return "-"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int):
        return f"{x:,}".replace(",", "\u2009")
    if not isinstance(x, (int, float)) or math.isnan(x):
        return str(x)
    if x == 0:
        return "0"
    a = abs(x)
    if a >= 1e6 or a < 1e-3:
        return f"{x:.{sig - 1}e}"
    digits = max(sig - 1 - int(math.floor(math.log10(a))), 0)
    text = f"{x:,.{digits}f}".replace(",", "\u2009")
    return text


def pct(x, sig: int = 3) -> str:
    return "-" if x is None else num(100 * x, sig)


def met(flag) -> str:
    return "met" if flag else "missed"


def us(seconds, sig: int = 3) -> str:
    return "-" if seconds is None else num(1e6 * seconds, sig)


def mb(nbytes) -> str:
    return "-" if nbytes is None else num(nbytes / 1e6, 3)


@dataclass
class Table:
    columns: list[str]
    rows: list[list[str]]
    title: str = ""
    notes: list[str] = field(default_factory=list)


@dataclass
class Rendered:
    tables: list[Table]
    sources: list[str]                      # paths relative to the repository root
    recorded: str = ""                      # what the file records about the run


def load(path: str):
    full = path if os.path.isabs(path) else os.path.join(RESULTS, path)
    with open(full) as f:
        return json.load(f)


def rel(path: str) -> str:
    full = path if os.path.isabs(path) else os.path.join(RESULTS, path)
    return os.path.relpath(full, ROOT).replace(os.sep, "/")


def recorded(machine: dict | None = None, **extra) -> str:
    """One line from what a result file records about its run."""
    m = dict(machine or {})
    m.update({k: v for k, v in extra.items() if v is not None})
    parts = []
    cores = m.get("cores", m.get("cpus", m.get("cpu_count")))
    if cores:
        parts.append(f"{cores} CPU cores")
    if m.get("devices"):
        parts.append(str(m["devices"]))
    elif m.get("n_devices"):
        parts.append(f"{m['n_devices']} {m.get('device_kind', '')} devices".replace("  ", " "))
    if m.get("jax"):
        parts.append(f"jax {m['jax']}")
    load_avg = m.get("load_average")
    if isinstance(load_avg, (list, tuple)) and load_avg:
        load_avg = load_avg[0]
    if isinstance(load_avg, (int, float)):
        parts.append(f"load average {load_avg:.1f}")
    if m.get("date"):
        parts.append(str(m["date"]))
    return " ".join(", ".join(parts).split())


# -- renderers, one per result file (or folder) ------------------------------------------

def r_stepper() -> Rendered:
    d = load("stepper.json")
    rows_by_case: dict[tuple, dict] = {}
    for r in d["rows"]:
        rows_by_case.setdefault((r["dofs"], r.get("case", "")), {})[r["impl"]] = r
    bw = d.get("copy_bandwidth_GB_per_s")

    def timed(impls, name, bandwidth=False):
        r = impls.get(name)
        if not r:
            return "-"
        cell = f"{num(r['us_per_step'])} ({num(r.get('speedup_vs_scipy'))}x"
        if bandwidth and bw and r.get("GB_per_s"):
            cell += f", {num(100 * r['GB_per_s'] / bw, 2)} % of copy"
        return cell + ")"

    rows = []
    for (dofs, case), impls in sorted(rows_by_case.items()):
        widths = next((r.get("group_widths") for r in impls.values() if r.get("group_widths")), None)
        rows.append([case or "-", num(dofs), "/".join(str(w) for w in widths) if widths else "-",
                     num(impls.get("scipy-csr", {}).get("us_per_step")), timed(impls, "jax-1dev", True),
                     timed(impls, "jax-1dev-f32"), timed(impls, "jax-1dev-ell"), timed(impls, "jax-2dev"),
                     timed(impls, "jax-2dev-f32"), num(impls.get("jax-einsum", {}).get("us_per_step")),
                     num(impls.get("jax-bcoo", {}).get("us_per_step"))])
    notes = [f"Copy bandwidth (numpy, read + write) measured in the same run: {num(bw)} GB/s."] if bw else []
    return Rendered([Table(["case", "dofs", "group widths", "SciPy CSR", "jaxsync, 1 device (x SciPy)",
                            "1 device, float32 blocks", "1 device, one ELL", "2 devices (x SciPy)",
                            "2 devices, float32 blocks", "einsum blocks", "BCOO"], rows,
                           "Microseconds per explicit step", notes)],
                    ["stepper.json"], recorded(d.get("machine")))


def r_distributed() -> Rendered:
    d = load("distributed.json")
    tables = []
    for scenario, title in (("growing", "Growing mesh, 8 parts"), ("parts", "Fixed 2 525-node mesh, 1-8 parts")):
        rows = []
        for r in d["scenarios"].get(scenario, []):
            m = r["max_average"]
            rows.append([r["mode"], num(r["n_nodes"]), num(r["n_parts"]), num(r["n_shared_nodes"]),
                         us(m["t_e"]), us(m["t_m"]), us(m["t_s"]), us(m["t_t"]), num(m["r_s"], 2)])
        tables.append(Table(["mode", "nodes", "parts", "N_a", "t_e", "t_m", "t_s", "t_t", "r_s"], rows,
                            f"{title}: microseconds per step, max-average part"))
    base = d.get("baseline") or []
    rows = []
    for b in base:
        pick, buf = b.get("baseline_pickle", {}), b.get("baseline_buffers", {})
        rows.append([num(b["n_nodes"]), num(b["n_parts"]), us(pick.get("t_step")), us(buf.get("t_step")),
                     us(b.get("jaxsync_2_devices_s_per_step")), us(b.get("jaxsync_1_device_s_per_step")),
                     num(max(b.get("baseline_pickle_rel_diff", 0), b.get("baseline_buffers_rel_diff", 0)), 2)])
    if rows:
        tables.append(Table(["nodes", "parts", "paper pattern, pickled", "paper pattern, buffers",
                             "jaxsync, 2 devices", "jaxsync, 1 device", "largest relative difference"], rows,
                            "The paper code's per-step pattern (SciPy product per rank, forces gathered and "
                            "broadcast by MPI) against jaxsync: microseconds per step"))
    return Rendered(tables, ["distributed.json"],
                    recorded({"cores": d.get("cpu_count"), "jax": d.get("jax"),
                              "devices": f"{d.get('n_devices')} emulated CPU devices" if d.get("emulated_devices")
                              else None, "load_average": d.get("loadavg_end")}))


def r_speedup() -> Rendered:
    d = load("speedup.json")
    rows = []
    any_halo = any(r.get("t_step_halo_us") for r in d["rows"])
    depths = sorted({int(k) for r in d["rows"] for k in (r.get("t_step_halo_us") or {})})
    for r in d["rows"]:
        sync = r["t_step_sync_us"]
        row = [r["scenario"], r["mode"], num(r["n_nodes"]), num(r["n_parts"]), num(r["n_hidden"]),
               f"{num(sync.get('psum'))} / {num(sync.get('ppermute'))}", num(r["t_step_avoiding_us"]),
               num(r["t_s_us"]),
               f"{num(r['t_d_us'])} ({num(1e3 * r['t_prediction_alone_ms'] / (d['n_s'] * d['n_f']))})",
               num(r["zeta"])]
        if any_halo:
            halo = {int(k): v for k, v in (r.get("t_step_halo_us") or {}).items()}
            zh = {int(k): v for k, v in (r.get("zeta_halo") or {}).items()}
            row += [f"{num(halo[k])} ({num(zh.get(k))})" if k in halo else "-" for k in depths]
        rows.append(row)
    cols = ["scenario", "mode", "nodes", "parts", "n_H", "synchronized, psum / ppermute", "avoiding", "t_s",
            "t_d (one part alone)", "zeta"] + [f"halo k={k} (zeta)" for k in depths]
    main = Table(cols, rows, "Microseconds per step on emulated devices; zeta = best synchronized / avoiding")
    # projections to interconnects: one row per configuration (neighbour exchange)
    proj_rows = []
    presets: list[str] = []
    configs = [r for r in d["rows"]]
    neighbour = [p for p in d.get("projections", []) if p.get("algorithm") == "neighbour"]
    for k, p in enumerate(neighbour):
        presets = presets or list(p["zeta"])
        n_h = configs[k]["n_hidden"] if k < len(configs) and configs[k]["scenario"] == p["scenario"] else "-"
        proj_rows.append([p["scenario"], p["mode"], num(p["n_nodes"]), num(p["n_parts"]), num(n_h)]
                         + [num(p["zeta"].get(i)) for i in presets])
    tables = [main]
    if proj_rows:
        tables.append(Table(["scenario", "mode", "nodes", "parts", "n_H"] + presets, proj_rows,
                            "zeta projected to real interconnects (one part per processor, neighbour exchange; "
                            "jaxsync.perf.costmodel.INTERCONNECTS)"))
    checks = d.get("model_check") or []
    if checks:
        errors = sorted(abs(c["relative_error"]) for c in checks if c.get("relative_error") is not None)
        median = errors[len(errors) // 2] if errors else None
        tables[0].notes.append(
            f"The cost model, fitted on bare psums of the same devices, predicts the measured t_s with a "
            f"median error of {pct(median, 2)} % over {len(errors)} configurations.")
    return Rendered(tables, ["speedup.json"], recorded(d.get("machine"), devices=d.get("devices", "").split(":")[0]))


def r_sync(path: str = "sync.json") -> Rendered:
    d = load(path)
    case = "vessel" if d.get("case") == "vessel" else "cantilever"
    coll: dict[int, dict] = {}
    methods: list[str] = []
    for r in d["rows"]:
        if r["kind"] == "collective" and r["method"] != "none":
            coll.setdefault(r["n_doubles"], {})[r["method"]] = r
            if r["method"] not in methods:
                methods.append(r["method"])
    rows = [[f"Allreduce of {num(n)} doubles"] + [
        f"{num(c[m]['us_per_step_best'])} / {num(c[m]['us_per_step_median'])}" if m in c else "-" for m in methods]
        for n, c in sorted(coll.items())]
    solver = {r["method"]: r for r in d["rows"] if r["kind"] == "solver"}
    if solver:
        rows.append([f"{case} step, synchronized"] + [
            f"{num(solver[m]['us_per_step_best'])} / {num(solver[m]['us_per_step_median'])}" if m in solver else "-"
            for m in methods])
    t1 = Table(["what"] + methods, rows, "Microseconds per step, best / median, slowest rank")
    names = {"nosync": "no synchronization (the floor)", "avoid-lstm-paper": "avoiding, the paper's LSTM",
             "avoid-lstm-default": "avoiding, the default LSTM", "avoid-linear": "avoiding, linear surrogate",
             "avoid-lstm-vessel-demo": "avoiding, the vessel demo's LSTM",
             "avoid-lstm-all": "avoiding, the same LSTM evaluating every application"}
    rows2 = []
    baseline = None
    for r in d["rows"]:
        if r["kind"] != "speedup":
            continue
        baseline = r.get("baseline", baseline)
        name = names.get(r["method"], r["method"])
        if r["method"].startswith("halo-"):
            name = f"deep halos, k = {r['method'].split('-', 1)[1]} (exact)"
        arch = r.get("architecture") or {}
        if arch:
            name += " (" + ", ".join(f"{k} {arch[k]}" for k in ("n_hidden", "rank", "highway_rank")
                                     if arch.get(k)) + \
                    (f", n_s {r['n_s']}" if r.get("n_s") else "") + \
                    (f", {r['refill_calls']} network calls per refill" if r.get("refill_calls") else "") + ")"
        rows2.append([name, f"{num(r['us_per_step_best'])} / {num(r['us_per_step_median'])}", num(r.get("zeta"), 3)])
    t2 = Table(["program", "us per step (best / median)", f"zeta against {baseline or 'the best synchronized step'}"],
               rows2, f"The {case}'s chunks on the same processes")
    rows3 = [[c["method"], num(c["latency_us"]), num(c["bandwidth_GBps"]), num(c["predicted_us"]),
              num(c["measured_us"]), f"{100 * c['relative_error']:+.0f} %"] for c in d.get("model_check", [])]
    t3 = Table(["transport", "latency [us]", "bandwidth [GB/s]", "predicted t_s [us]", "measured t_s [us]", "error"],
               rows3, "Cost model fitted to the bare collectives against the solver's measured t_s")
    rec = recorded({"cores": d.get("cpu_count"), "jax": d.get("jax"), "load_average": d.get("load_average")})
    rec = ", ".join(filter(None, [f"{d.get('processes')} processes on {len(d.get('hosts', []))} host(s)",
                                  " ".join(d.get("mpi_library", "").replace("Version:", "").split()), rec]))
    return Rendered([t1, t2, t3], [path], rec)


def r_sync_vessel() -> Rendered:
    return r_sync("sync_vessel.json")


def r_regime_map() -> Rendered:
    d = load("regime_map.json")
    names = {"avoid-lstm-paper": "paper LSTM", "avoid-lstm-default": "default LSTM", "avoid-linear": "linear"}
    rows = []
    surrogates = list(d["inputs"]["t_d_us"])
    for p in d["presets"]:
        halo = p.get("zeta_halo_at_measured_t_c") or {}
        best = max(halo.items(), key=lambda kv: kv[1]) if halo else None
        rows.append([p["interconnect"], num(p["latency_us"]), num(p["bandwidth_GBps"]),
                     f"{num(p['t_s_allreduce_us'])} / {num(p['t_s_neighbour_us'])}"]
                    + [num(p["zeta_surrogate_at_measured_t_c"].get(s)) for s in surrogates]
                    + [f"{num(best[1])} (k = {best[0]})" if best else "-"])
    t_d = ", ".join(f"{names.get(s, s)} {num(v)} us" for s, v in d["inputs"]["t_d_us"].items())
    table = Table(["interconnect", "latency [us]", "bandwidth [GB/s]", "t_s allreduce / neighbour [us]"]
                  + [f"zeta, {names.get(s, s)}" for s in surrogates] + ["zeta, best deep halo"], rows,
                  f"The {num(d['mesh_nodes'])}-node beam on {d['pattern']['n_parts']} parts, at the measured "
                  f"local step {num(d['inputs']['t_c_us'])} us",
                  [f"Surrogate costs per step (measured between real processes, sync.json): {t_d}. "
                   "t_s is also the break-even surrogate cost: a surrogate pays where its cost per step "
                   "is below it."])
    return Rendered([table], ["regime_map.json", "sync.json"])


def r_gpu_projection() -> Rendered:
    d = load("gpu_projection.json")
    depths = sorted({int(k) for r in d["scenarios"] for k in r["halos"]})

    def step(t, zeta):
        return f"{num(t)} ({num(zeta, 3)})"

    exact, learned = [], []
    for r in d["scenarios"]:
        halos = r["halos"]
        best = r["best_exact"]
        exact.append([r["label"], f"{num(r['gpus'])} ({num(r['parts'])})", num(r["t_c_us"]), num(r["t_s_us"]),
                      num(r["t_sync_us"])]
                     + [step(halos[str(k)]["t_step_us"], halos[str(k)]["zeta"]) if str(k) in halos else "-"
                        for k in depths]
                     + [f"{best['method']}: {step(best['t_step_us'], best['zeta'])}"])
        be = r["break_even_t_d_vs_best_exact_us"]
        surr = r["surrogates"]
        learned.append([r["label"], f"{num(r['gpus'])} ({num(r['parts'])})",
                        num(r["break_even_t_d_vs_synchronized_us"]),
                        num(be) if be > 0 else f"never ({num(be)})", num(r["zeta_ceiling_vs_best_exact"], 3)]
                       + [f"{num(surr[n]['t_d_cpu_rate_us'])}: {step(surr[n]['t_step_us'], surr[n]['zeta'])}"
                          for n in ("linear", "lstm")]
                       + [" / ".join("never" if surr[n]["rate_needed_vs_best_exact_GFlops"] is None
                                     else num(surr[n]["rate_needed_vs_best_exact_GFlops"], 2)
                                     for n in ("linear", "lstm"))])
    v, cost, site = d["vessel"], d["surrogate_cost"], d["stand_in"]
    t1 = Table(["scenario", "GPUs (parts)", "t_c", "t_s", "synchronized"] + [f"halo k = {k}" for k in depths]
               + ["best exact"], exact,
               f"Exact methods, projected for the paper-size vessel ({num(v['n_dofs'])} dofs): microseconds per "
               "step (zeta against the synchronized step)",
               [f"Inputs, {d['given']['sources']['h200']}; {d['given']['sources']['nccl']}; "
                f"{d['given']['sources']['xla']}. Per-step floor t_0 = {num(d['floor_us'])} us.",
                "Each exchange costs the cheaper of one collective sum of the interface vector (a ring allreduce) "
                "and one grouped neighbour exchange, latency + bytes / bandwidth (NVLink 4 in a node, InfiniBand "
                "NDR between nodes, HDR for the A100 figure).",
                f"Halo redundancy and interface sizes from the generated tree at {num(site['n_elements'])} "
                f"tetrahedra partitioned into each scenario's parts, scaled to the vessel by "
                f"c = {num(site['scale_c'])} (its recorded 11-part interface of {num(v['n_interface'])} nodes "
                "over the stand-in's)."])
    t2 = Table(["scenario", "GPUs (parts)", "break-even t_d vs synchronized", "break-even t_d vs best exact",
                "most gained over the best exact (t_d = 0)", "linear: t_d at the CPU rate, step (zeta)",
                "LSTM: t_d at the CPU rate, step (zeta)",
                "GFlop/s needed to beat the best exact, linear / LSTM"], learned,
               "The learned method: break-even surrogate cost per step [us], and the step with the surrogate "
               "run at the CPU's rate",
               [f"t_d is not measured on a GPU. At the CPU rate: {cost['cpu_rate_source']}, "
                f"{num(cost['cpu_rate_GFlops'])} GFlop/s, applied to each surrogate's flops per step "
                f"(widest part of 11: linear {num(cost['flops_per_step_per_part']['linear'] / 1e6)}, LSTM "
                f"{num(cost['flops_per_step_per_part']['lstm'] / 1e6)} MFlop per step, rank "
                f"{num(cost['linear_rank'])} linear map; on one GPU the 11 parts' refills together); the last column "
                "is the rate a GPU must sustain instead."])
    sources = ["gpu_projection.json"] + ([v["source"]] if v["source"].startswith("benchmarks/") else [])
    return Rendered([t1, t2], sources, recorded({"date": (d.get("generated") or {}).get("date")}))


def _tip_metrics(metrics: dict) -> dict:
    """The worst component's metrics (a skewed load is judged on y and z)."""
    if "tip_max_error_relative" in metrics:
        return metrics
    return max(metrics.values(), key=lambda m: m.get("tip_max_error_relative") or 0)


def r_surrogates() -> Rendered:
    d = load("bench_surrogates.json")
    names = {"lstm": "LSTM", "lstm_bf16": "LSTM, bfloat16", "linear": "linear"}
    rows = []
    for c in d["cases"]:
        for key, v in c["variants"].items():
            m = _tip_metrics(v["metrics"])
            rows.append([c["case"], names.get(key, key), pct(m["tip_max_error_relative"]),
                         pct(m["tip_final_error_relative"]), num(m["e_l2_max_cm"]), pct(m["l2_relative"]),
                         us(v.get("t_d")), num(v.get("zeta"))])
    t = Table(["case", "surrogate", "free end max %", "final %", "e_l2 max [cm]", "l2 relative %",
               "t_d [us/step]", "zeta (emulated)"], rows,
              "Errors over the online run; t_d: one refill of every part over the steps it serves")
    first = d["cases"][0]
    be = first.get("break_even") or {}
    if be:
        t.notes.append("Break-even surrogate cost for this partition (the synchronization each interconnect "
                       "preset would take per step): " + ", ".join(
                           f"{k} {us(v['t_s_model'], 2)} us" for k, v in be.items()) + ".")
    checks = [(c["case"], k, v) for c in d["cases"] for k, v in (c.get("bf16_check") or {}).items()]
    if checks:
        t.notes.append("bfloat16 inference check (largest RMS deviation from the float32 networks, bound "
                       f"{pct(d.get('bf16_bound'), 2)} %): " + ", ".join(
                           f"{case} {k.replace('_bf16', '')} {pct(v['worst'], 2)} %" for case, k, v in checks) + ".")
    return Rendered([t], ["bench_surrogates.json"], recorded(d.get("machine")))


EXPERIMENT_CASES = ("default", "sequence_length", "training_size", "refined_6_parts", "skewed", "step_off",
                    "initial_conditions", "loads", "full_system")


def _experiment_records(folder: str) -> list[tuple[str, dict]]:
    found = []
    for path in sorted(glob.glob(os.path.join(RESULTS, folder, "*", "*.json"))):
        if os.path.basename(path) == os.path.basename(os.path.dirname(path)) + ".json":
            found.append((path, load(path)))
    order = {c: i for i, c in enumerate(EXPERIMENT_CASES)}
    found.sort(key=lambda pr: order.get(pr[1].get("case"), len(order)))
    return found


def _experiment_rows(records, *, with_model: bool = False) -> list[list[str]]:
    rows = []
    for _, r in records:
        entries = [(v, v["name"], v["metrics"], v.get("online"), v["targets"]) for v in r["variants"]]
        entries += [(v, f"{v['name']}, predicted through the load jump", x["metrics"], x.get("online"), x["targets"])
                    for v in r["variants"] for x in [v.get("predicted_through_load_jumps")] if x]
        for v, variant, m, online, met in entries:
            tr = v.get("training") or {}
            passed = tr.get("case_parameters_passed", {})
            rollout = tr.get("rollout_relative")
            m = _tip_metrics(m)
            final = pct(m.get("tip_final_error_relative"))
            if m.get("tip_final_relative_to") == "amplitude":
                final += " (of amplitude)"
            row = [r["case"], variant]
            if with_model:
                row.append(r.get("model", "lstm"))
            row += [f"{num(r['mesh']['n_nodes'])} / {num(r['mesh']['n_elements'])}",
                    num(r["parameters"]["n_steps"]), num(r["n_parts"]),
                    num(passed.get("n_s", v["parameters"]["n_s"])),
                    f"{passed.get('n_past', v['parameters']['n_past'])}/{v['parameters']['n_future']}",
                    str(passed.get("train_fraction", v["parameters"].get("train_fraction"))),
                    num((online or {}).get("n_synchronized_steps")),
                    pct(m["tip_max_error_relative"]), final, pct(m["l2_relative"]),
                    pct(m.get("interior_max_error_relative")),
                    "-" if not rollout else pct(max(rollout)), "yes" if met.get("met") else "no"]
            rows.append(row)
    return rows


EXPERIMENT_COLUMNS = ["case", "variant", "nodes / tets", "steps", "parts", "n_s", "n_p/n_f", "n_ts",
                      "synchronized steps", "free end max %", "final %", "l2 relative %", "non-shared node max %",
                      "rollout check %", "targets met"]


def r_experiments() -> Rendered:
    records = _experiment_records("experiments")
    if not records:
        raise FileNotFoundError(os.path.join(RESULTS, "experiments", "<case>", "<case>.json"))
    t = Table(EXPERIMENT_COLUMNS, _experiment_rows(records), "The experiment matrix (LSTM surrogates)")
    machine = records[0][1].get("machine") or {}
    return Rendered([t], [rel(os.path.join("experiments", "<case>", "<case>.json"))], recorded(machine))


def r_experiments_linear() -> Rendered:
    records = _experiment_records("experiments_linear")
    if not records:
        raise FileNotFoundError(os.path.join(RESULTS, "experiments_linear", "<case>", "<case>.json"))
    t = Table(EXPERIMENT_COLUMNS, _experiment_rows(records), "The same cases with the linear surrogate")
    return Rendered([t], [rel(os.path.join("experiments_linear", "<case>", "<case>.json"))],
                    recorded(records[0][1].get("machine")))


def r_seeds() -> Rendered:
    paths = sorted(glob.glob(os.path.join(RESULTS, "experiments", "*", "*.json"))) + \
        sorted(glob.glob(os.path.join(RESULTS, "experiments", "seeds", "*", "*", "*.json")))
    rows = []
    for path in paths:
        if os.path.basename(path) != os.path.basename(os.path.dirname(path)) + ".json":
            continue
        r = load(path)
        if r.get("case") not in ("default", "skewed"):
            continue
        v = r["variants"][0]
        tr = v.get("training") or {}
        summary = tr.get("summary") or {}
        m = _tip_metrics(v["metrics"])
        rollout = tr.get("rollout_relative")
        rows.append([r["case"], num(r["parameters"].get("seed")),
                     (summary.get("sampling") or {}).get("split") or "-",
                     num((summary.get("candidates") or {}).get("n_candidates", 1) if summary else None),
                     pct(m["tip_max_error_relative"]), pct(m["tip_final_error_relative"]),
                     pct(m.get("interior_max_error_relative")), "-" if not rollout else pct(max(rollout)),
                     num(tr.get("train_seconds"), 3), "yes" if v["targets"].get("met") else "no"])
    rows.sort(key=lambda row: (row[0], row[2], row[1], row[3]))
    t = Table(["case", "seed", "validation split", "candidates", "free end max %", "final %",
               "non-shared node max %", "rollout check %", "training s", "targets met"], rows,
              "The default and skewed loads over seeds ('-': not recorded in the file)")
    return Rendered([t], [rel("experiments/default/default.json"), rel("experiments/skewed/skewed.json"),
                          rel("experiments/seeds/<run>/<case>/<case>.json")])


def r_refill() -> Rendered:
    """Smooth against raw refill: the same networks, both ways (the experiments that record both)."""
    rows = []
    sources = []
    for path, r in _experiment_records("experiments"):
        for v in r["variants"]:
            raw = v.get("raw_refill")
            if not raw:
                continue
            sources.append(rel(path))
            smooth_m, raw_m = _tip_metrics(v["metrics"]), _tip_metrics(raw["metrics"])
            hf = raw.get("high_frequency") or {}
            for name, m, fast in (("smooth (default)", smooth_m, hf.get("smooth")), ("raw (the paper's)", raw_m,
                                                                                     hf.get("raw"))):
                rows.append([r["case"], name, pct(m["tip_max_error_relative"]),
                             pct(m.get("interior_max_error_relative")), pct(m["l2_relative"]),
                             pct((fast or {}).get("relative"))])
    if not rows:
        raise FileNotFoundError(os.path.join(RESULTS, "experiments", "<case>", "<case>.json (raw_refill)"))
    t = Table(["case", "refill", "free end max %", "non-shared node max %", "l2 relative %",
               "fast part of the error, max %"], rows,
              "The same networks with the smooth and the raw refill (fast part: the error minus its moving "
              "average over 5 snapshots, in % of the model's largest displacement)")
    return Rendered([t], sources)


def r_load_jumps() -> Rendered:
    rows, sources = [], []
    for folder, model in (("experiments", "LSTM"), ("experiments_linear", "linear")):
        for path, r in _experiment_records(folder):
            if r.get("case") != "step_off":
                continue
            sources.append(rel(path))
            for v in r["variants"]:
                entries = [("synchronized through the jump (default)", v)]
                if v.get("predicted_through_load_jumps"):
                    entries.append(("predicted through the jump", v["predicted_through_load_jumps"]))
                for name, e in entries:
                    m = _tip_metrics(e["metrics"])
                    online = e.get("online") or {}
                    rows.append([model, name, num(online.get("n_synchronized_steps")),
                                 ", ".join(num(j) for j in online.get("load_jumps") or []) or "-",
                                 pct(m["tip_max_error_relative"]), pct(m["l2_relative"])])
    if not rows:
        raise FileNotFoundError(os.path.join(RESULTS, "experiments", "step_off", "step_off.json"))
    t = Table(["surrogate", "online run", "synchronized steps", "stayed synchronized through the jump at step",
               "free end max %", "l2 relative %"], rows, "The cantilever's load switched off at 3 s")
    return Rendered([t], sources)


def r_hyperelastic_vessel() -> Rendered:
    d = load("hyperelastic_vessel.json")
    rows = []
    for m in d["materials"]:
        for sur in m["surrogates"]:
            timing = sur.get("timing", {})
            for label in ("free", "controlled"):
                r = sur[label]
                q = r["estimate_over_error"]
                rows.append([m["material"], pct(m["peak_strain"]["green_lagrange"], 3), sur["surrogate"],
                             "none" if label == "free" else "1 %", pct(r["interior_max_relative_error"], 3),
                             ", ".join(pct(n["relative_max_error"], 2) for n in r["interior_nodes"]),
                             num(r["l2_error_max"]), num(r["max_nodal_error_cm"]),
                             f"{num(r['n_predicted_steps'])} of {num(m['n_steps'] - 20 * d['settings']['n_s'])}",
                             num(r["n_resynchronizations"]),
                             "-" if q.get("median") is None or math.isnan(q["median"]) else
                             f"{num(q['p10'], 2)} / {num(q['median'], 2)} / {num(q['p90'], 2)}",
                             num(timing.get("t_d_us")), num(timing.get("zeta"), 3),
                             num(sur.get("train_seconds"))])
    table = Table(["material", "peak strain [%]", "surrogate", "error control", "interior max rel. error [%]",
                   "per part [%]", "e_l2 max [cm]", "largest nodal error [cm]", "steps predicted",
                   "re-synchronizations", "estimate / error p10 / median / p90", "t_d per step [us]", "zeta",
                   "training [s]"], rows,
                  "The hyperelastic coronary vessel, out of sample (after the training window)")
    return Rendered([table], ["hyperelastic_vessel.json"],
                    recorded({"n_devices": d.get("n_devices"),
                              "device_kind": ("emulated " if d.get("emulated") else "") + str(d.get("device_kind")),
                              "date": d.get("date")}))


def r_untuned_vessel() -> Rendered:
    d = load("untuned_vessel/untuned_vessel.json")
    targets = d["targets"]
    rows = []
    for r in d["models"]:
        oos = r.get("error_over_tolerance_out_of_sample")
        rows.append([r["model"], f"{num(r['n_predicted'])} of {num(r['n_steps'] - r['n_cri'])}",
                     pct(r["predicted_fraction_after_n_cri"], 3), num(r["n_resynchronizations"]),
                     num(r["tolerance_cm"]), num(r["max_nodal_error_cm"]), num(r.get("error_over_tolerance"), 3),
                     "-" if oos is None else num(oos, 3),
                     "met" if r.get("meets_target") else "missed"])
    mesh = d["mesh"]
    table = Table(["surrogate", "steps predicted after n_cri", "%", "re-synchronizations", "tolerance [cm]",
                   "largest nodal error [cm]", "error / tolerance", "out of sample", "target"], rows,
                  f"{mesh['generator']}: {num(mesh['n_elements'])} tetrahedra, {d['n_parts']} parts, "
                  f"{num(d['n_steps'])} steps under the packaged coronary pressure, control at {d['tolerance']} "
                  f"(targets: at least {pct(targets['predicted_fraction_at_least'], 2)} % predicted, the largest "
                  f"nodal error within {num(targets['max_nodal_error_over_tolerance_at_most'], 2)}x the tolerance)")
    return Rendered([table], ["untuned_vessel/untuned_vessel.json"], recorded(d.get("machine")))


def r_guarantee() -> Rendered:
    d = load("guarantee.json")
    rows, tracking = [], []
    for case in d["rows"]:
        q = case["estimate_over_error"]
        tracking.append([case["case"], num(case["free_max_error_cm"]),
                         num(100 * case["free_max_error_cm"] / case["shared_amplitude_cm"], 3),
                         num(q["p10"], 2), num(q["median"], 2), num(q["p90"], 2)])
        for r in case["runs"]:
            rows.append([case["case"], num(100 * r["tolerance_fraction"], 2) + " %", num(r["tolerance_cm"]),
                         r["indicator"], num(r["max_error_over_tolerance"], 2),
                         f"{num(r['n_predicted_steps'])} of {num(r['n_steps_after_n_cri'])}",
                         num(r["n_resynchronizations"])])
    tables = [Table(["case", "largest error without control [cm]", "% of the shared amplitude",
                     "estimate / error p10", "median", "p90"], tracking,
                    "How the error estimate tracks the true largest nodal error (predicted snapshots, error "
                    "above 5 % of its largest)"),
              Table(["case", "tolerance (of the shared amplitude)", "[cm]", "indicator", "largest error / tolerance",
                     "steps predicted", "re-synchronizations"], rows, "The error held to the tolerance")]
    costs = [[c["case"], num(c["n_dofs"]), num(c["save_every"]), num(c["us_per_step_plain"]),
              num(c["us_per_step_probed"]), num(c["us_per_step_host_estimate"])] for c in d.get("probe_cost", [])]
    if costs:
        tables.append(Table(["mesh", "dofs", "probe every (steps)", "predicted step [us]", "with the probe [us]",
                             "host estimate per step [us]"], costs, "The probe's cost"))
    return Rendered(tables, ["guarantee.json"],
                    recorded({"n_devices": d.get("n_devices"),
                              "device_kind": ("emulated " if d.get("emulated") else "") + str(d.get("device_kind")),
                              "date": d.get("date")}))


def r_error_control() -> Rendered:
    d = load("error_control.json")
    none = next((r for r in d["rows"] if r["tolerance"] == "none"), None)
    rows = []
    for r in d["rows"]:
        tr = r.get("es_hat_tracking") or {}
        base = none["max_abs_error_cm"] if none else None
        vs = "-" if not base else num(r["max_abs_error_cm"] / base, 2)
        rows.append([r["tolerance"] + ("" if r["tolerance"] == "none" or r["tolerance"].endswith("%") else " cm"),
                     r.get("indicator") or "-",
                     num(r["max_abs_error_cm"]), vs, num(r["n_synchronized_steps"]), num(r["n_predicted_steps"]),
                     num(r["n_discarded_steps"]), num(r["n_resynchronizations"]),
                     num(tr.get("ratio_median"), 2), num(tr.get("ratio_p95"), 2)])
    t = Table(["tolerance", "indicator", "largest error [cm]", "vs none", "synchronized", "predicted", "recomputed",
               "re-synchronizations", "es/es_hat median", "es/es_hat p95"], rows,
              f"{d.get('case', '')}: {num(d.get('n_steps'))} steps, n_cri {num(d.get('n_cri'))}")
    return Rendered([t], ["error_control.json"],
                    recorded({"cores": d.get("cpu_count"), "n_devices": d.get("n_devices"),
                              "device_kind": ("emulated " if d.get("emulated") else "") + str(d.get("device_kind")),
                              "date": d.get("date")}))


def _grad_row(r) -> list[str]:
    return [num(r["n_steps"]), ", ".join(r["wrt"]), "recomputed" if r["checkpoints"] else "plain",
            num(r["forward_s"]), num(r["grad_s"]), num(r["ratio"], 2), mb(r["temp_bytes"]),
            mb(r["all_states_bytes"]), pct(r["vs_all_states"], 2)]


GRAD_COLUMNS = ["steps", "in", "reverse mode", "forward [s]", "gradient [s]", "ratio", "temporaries [MB]",
                "all states [MB]", "temporaries / all states %"]


def r_gradients() -> Rendered:
    d = load("gradients.json")
    tables = [Table(GRAD_COLUMNS, [_grad_row(r) for r in d["rows"]],
                    f"{d.get('problem', '')} ({num(d.get('n_dofs'))} dofs); loss: the tip's vertical "
                    "displacement at the end")]
    large = d.get("large")
    if large:
        rows = [_grad_row(r) for r in large.get("rows", []) + large.get("breakdown", [])]
        notes = []
        if large.get("plain_1e4_estimate_bytes"):
            notes.append(f"Plain reverse mode through 1e4 steps of this mesh would hold about "
                         f"{num(large['plain_1e4_estimate_bytes'] / 1e9)} GB of temporaries (estimated from "
                         "its per-step residuals; not run).")
        tables.append(Table(GRAD_COLUMNS, rows, f"{large.get('mesh', 'large mesh')}: {num(large['n_dofs'])} dofs",
                            notes))
    fd_rows = []
    for f in d.get("fd_checks", []):
        e, a = f["E"], f["alpha"]
        fd_rows.append([num(f["partitions"]), num(f["n_steps"]), f"{num(e['rel_diff'][e['best_h']], 2)} "
                        f"(h = {e['best_h']})", num(e["rel_diff_richardson"], 2),
                        f"{num(a['rel_diff'][a['best_h']], 2)} (h = {a['best_h']})",
                        num(a["rel_diff_richardson"], 2), "yes" if e.get("met") and a.get("met") else "no"])
    if fd_rows:
        tables.append(Table(["parts", "steps", "d/dE, central difference", "d/dE, Richardson",
                             "d/dalpha, central difference", "d/dalpha, Richardson",
                             f"within {num(d['fd_checks'][0].get('target'))}"], fd_rows,
                            "Relative difference between jax.grad and finite differences (h relative to E and "
                            "alpha)"))
    return Rendered(tables, ["gradients.json"], recorded(d.get("machine")))


def r_finetune() -> Rendered:
    d = load("finetune.json")
    rows = []
    for r in d["rows"]:
        b, a, ft = r["before"], r["after"], r["fine_tune"]
        rows.append([r["case"],
                     f"{pct(b['tip_max_error_relative'])} -> {pct(a['tip_max_error_relative'])}",
                     f"{pct(b['tip_final_error_relative'])} -> {pct(a['tip_final_error_relative'])}",
                     f"{pct(b['interior_max_error_relative'])} -> {pct(a['interior_max_error_relative'])}",
                     f"{pct(b['l2_relative'])} -> {pct(a['l2_relative'])}",
                     f"{num(ft['improvement'], 2)} (iteration {ft['best_iteration']})",
                     num(ft["seconds"], 3), num(r.get("train_seconds"), 3)])
    cfg = d.get("config", {})
    t = Table(["case", "free end max %", "final %", "interior max %", "l2 relative %",
               "validation loss kept / start", "fine-tuning [s]", "training [s]"], rows,
              f"Before -> after {cfg.get('n_iterations', '')} Adam steps at {cfg.get('learning_rate', '')}, "
              f"windows of {cfg.get('window_cycles', '')} refill cycles")
    return Rendered([t], ["finetune.json"], recorded(d.get("machine")))


def r_training() -> Rendered:
    rows, sources = [], []
    for name in ("bench_training.json", "bench_training_nH50_nB10.json"):
        if not os.path.exists(os.path.join(RESULTS, name)):
            continue
        d = load(name)
        sources.append(name)
        rows.append([num(d["n_hidden"]), num(d["batch_size"]), num(d["n_train_windows"]), num(d["seconds_per_epoch"]),
                     num(d["gradient_steps_per_second"]), num(d["projected_full_schedule_hours"], 2),
                     num(1e3 * d["refill_call_seconds"])])
    if not rows:
        raise FileNotFoundError(os.path.join(RESULTS, "bench_training.json"))
    t = Table(["n_H", "n_B", "training windows", "s per epoch", "gradient steps/s",
               "paper schedule (13 812 epochs) [h]", "one refill call [ms]"], rows,
              "Two replicas trained together (paper configuration: n_p = n_f = 20, n_s = 80)")
    return Rendered([t], sources, recorded({"cores": d.get("cpu_count"), "jax": d.get("jax")}))


def r_paper_cantilever() -> Rendered:
    d = load("paper_cantilever/paper_cantilever.json")
    s = d.get("summary", {})
    rows = [["mesh, steps", f"{d['mesh']}, {num(d['n_steps'])}"],
            ["synchronized to step (n_cri), predicted steps", f"{num(d['n_cri'])}, {num(s.get('n_predicted'))}"],
            ["network", f"n_H {d['n_hidden']}, n_B {d['batch_size']}, eta0 {d['eta0']}, "
                        f"{num(d['epochs_run'])} of the paper's {num(d['epochs_paper_rule'])} epochs "
                        f"({num(d['seconds_per_epoch'])} s per epoch)"],
            ["free end: largest error, % of its largest amplitude (target 2 %)",
             f"{pct(d['tip_max_error_relative_to_amplitude'])} ({met(d['target_tip_max_2_percent'])})"],
            ["free end: final error, % of its final value (target 1 %)",
             f"{pct(d['tip_final_relative_error'])} ({met(d['target_tip_final_1_percent'])})"],
            ["e_l2 largest / final [cm]", f"{num(d['e_l2_max'])} / {num(d['e_l2_final'])}"],
            ["es / es_hat at the end [cm]", f"{num(s.get('es_final'))} / {num(s.get('es_hat_final'))}"],
            ["us per step, synchronized / predicted (2 emulated devices)",
             f"{num(s.get('us_per_step_synchronized'))} / {num(s.get('us_per_step_predicted'))}"]]
    return Rendered([Table(["", "measured"], rows)], ["paper_cantilever/paper_cantilever.json"],
                    recorded(d.get("machine")))


def r_paper_vessel_small() -> Rendered:
    d = load("paper_vessel/paper_vessel_small_run.json")
    t, s = d["targets"], d["summary"]
    ms = s.get("mass_scaling", {})
    per_part = [e for e in s.get("node_errors", []) if e.get("label", "").startswith("part ")]
    rows = [["mesh", f"{num(s.get('n_elements'))} tets, {num(s.get('n_dofs'))} dofs, {num(s.get('n_parts'))} parts, "
                     f"{num(s.get('n_shared_nodes'))} shared nodes"],
            ["steps: synchronized / predicted", f"{num(s.get('n_synchronized'))} / {num(s.get('n_predicted'))}"],
            ["mass scaling: step, added mass, difference at the node that moves most",
             f"{num(ms.get('dt_cfl'))} -> {num(ms.get('dt_scaled'))} s, +{num(t.get('added_mass_percent'))} %, "
             f"{pct(t.get('mass_scaling_relative_difference'))} % of its amplitude"],
            ["non-shared node of every part: largest error, % of its amplitude (target 5 %)",
             ", ".join(pct(e["relative_max_error"], 2) for e in per_part)
             + f" ({'met' if t.get('interior_within_5_percent') else 'missed'})"],
            ["e_l2 largest / final [cm]", f"{num(s.get('l2_error_max'))} / {num(s.get('l2_error_final'))}"]]
    oos = s.get("out_of_sample")
    if oos:
        rows += [["trained on steps 0 to", f"{num(s.get('train_until_step'))} (of {num(s.get('n_steps'))})"],
                 ["after it: non-shared node of every part, % of its amplitude there (target 5 %)",
                  ", ".join(pct(e["relative_max_error"], 2) for e in oos["node_errors"]
                            if e.get("label", "").startswith("part "))
                  + f" ({'met' if t.get('out_of_sample_within_5_percent') else 'missed'})"],
                 ["after it: monitored node, % of its amplitude; e_l2 largest [cm]",
                  f"{pct(oos.get('monitored_relative_max_error'), 2)} %; {num(oos.get('l2_error_max'))}"]]
    rows += [["error control", f"tolerance {t.get('resync_tolerance')} "
                              f"({num(s.get('resync_tolerance_cm'))} cm), "
                              f"{num(t.get('n_resynchronizations'))} re-synchronizations"],
            ["es / es_hat largest [cm]", f"{num(t.get('es_max_cm'))} / {num(t.get('es_hat_max_cm'))}"],
            ["es/es_hat: log-correlation, median, 95th percentile",
             f"{num(t.get('es_es_hat_log_correlation'), 2)}, "
             f"{num((s.get('es_hat_tracking') or {}).get('ratio_median'), 2)}, "
             f"{num((s.get('es_hat_tracking') or {}).get('ratio_p95'), 2)}"],
            ["us per step synchronized / predicted (emulated devices)",
             f"{num(s.get('us_per_step_synchronized'))} / {num(s.get('us_per_step_predicted'))}"],
            ["zeta of the compiled programs (emulated); t_s / t_d [us]",
             f"{num(t.get('zeta_emulated'), 3)}; {num(s.get('t_s_us'))} / {num(s.get('t_d_us'))}"],
            ["zeta projected to real processors",
             ", ".join(f"{k} {num(v, 2)}" for k, v in (t.get("zeta_projected") or {}).items())],
            ["training", f"{num(s.get('training_seconds'))} s"]]
    return Rendered([Table(["", "measured"], rows, "Small size, end to end")],
                    ["paper_vessel/paper_vessel_small_run.json"],
                    recorded({"n_devices": s.get("n_devices"), "device_kind": s.get("device_kind")}))


def r_paper_vessel_paper() -> Rendered:
    d = load("paper_vessel/paper_vessel_paper_measure.json")
    mesh, msc, part = d["mesh"], d["mass_scaling"], d["partition"]
    prog, proj = d["programs"], d["projection_of_the_whole_run"]
    rows = [["mesh (paper's)", f"{num(mesh['n_elements'])} tets, {num(mesh['n_dofs'])} dofs "
                               f"({num(mesh['paper']['n_elements'])}, {num(mesh['paper']['n_dofs'])})"],
            ["shared nodes per part, mean (paper's)",
             f"{num(part['shared_nodes_per_part_mean'])} ({num(part['paper']['shared_nodes_per_part'])})"],
            ["CFL step -> mass-scaled step, added mass (paper's)",
             f"{num(msc['dt_cfl'])} -> {num(msc['dt_scaled'])} s, +{num(msc['added_mass_percent'])} % "
             f"({num(msc['paper']['dt_cfl'])} -> {num(msc['paper']['dt_scaled'])} s, "
             f"+{num(msc['paper']['added_mass_percent'])} %)"],
            ["us per step: psum / ppermute / no synchronization / avoiding",
             f"{num(prog['us_per_step']['psum'])} / {num(prog['us_per_step']['ppermute'])} / "
             f"{num(prog['us_per_step_nosync'])} / {num(prog['us_per_step_avoiding_at_run_n_s'])}"],
            ["zeta (emulated devices)", num(prog["zeta_emulated_at_run_n_s"], 3)],
            ["training [s per epoch]", num(d["training"]["seconds_per_epoch"])],
            ["whole run at the demo's settings, projected [h]", num(proj["hours"], 3)],
            ["zeta projected to real processors", ", ".join(
                f"{row['interconnect']['name']} {num(row['zeta'], 2)}" for row in prog["projection"]["rows"])]]
    return Rendered([Table(["", "measured"], rows, "Paper size: measured per-step costs and the projected run")],
                    ["paper_vessel/paper_vessel_paper_measure.json"], recorded(d.get("machine")))


def r_locking() -> Rendered:
    d = load("locking.json")
    elements = ("P1", "P1-ANP", "P2")
    by_case: dict[tuple, dict] = {}
    for r in d["rows"]:
        by_case.setdefault((r["case"], r["size"] or 0.0, r["nu"]), {})[r["element"]] = r
    rows = []
    for (case, size, nu), cells in sorted(by_case.items(), key=lambda kv: (kv[0][0] != "lame", -kv[0][1], kv[0][2])):
        if not all(e in cells for e in elements):
            continue
        dofs = f"{num(cells['P1']['dofs'])} / {num(cells['P2']['dofs'])}"
        rows.append([case, num(size) if size else "-", num(nu, 4), dofs,
                     *(pct(cells[e]["error"], 3) for e in elements),
                     " / ".join(num(1e6 * cells[e]["stable_dt"], 3) for e in elements)])
    t = Table(["case", "mesh size [cm]", "nu", "dofs P1 / P2", "P1 error %", "P1-ANP error %", "P2 error %",
               "stable step P1 / P1-ANP / P2 [us]"], rows,
              "Error against the analytic solution (Lame: rms nodal error over the largest exact displacement; "
              "cantilever: tip against Euler-Bernoulli, signed)")
    return Rendered([t], ["locking.json"], recorded(d.get("machine")))


def r_float32() -> Rendered:
    d = load("float32.json")
    rows = [[r["case"], num(r["dofs"]), num(r["steps"]), num(r["error"], 2),
             ", ".join(num(q, 2) for q in r["at_quarters"])] for r in d["rows"]]
    t = Table(["case", "dofs", "steps", "largest error / largest displacement", "at 1/4, 1/2, 3/4 and the end"],
              rows, "Float32 stiffness blocks against float64, the same run")
    return Rendered([t], ["float32.json"], recorded(d.get("machine")))


def r_hyperelastic() -> Rendered:
    d = load("hyperelastic.json")
    names = {"NeoHookean": "neo-Hookean", "NearlyIncompressibleNeoHookean": "nearly incompressible",
             "HolzapfelGasserOgden": "Holzapfel-Gasser-Ogden", "LinearElastic": "linear, pre-assembled"}
    rows = []
    for r in d["rows"]:
        law = names.get(r["law"], r["law"])
        if r["law"] == "LinearElastic":
            rows.append([r["case"], r["element"], law, num(r["elements"]), num(r["matvec_us"]), "-", "-", "-", "-",
                         "-", "-", num(r["step_us"]), "1"])
            continue
        rows.append([r["case"], r["element"], law, num(r["elements"]), num(r["matvec_us"]),
                     num(r["elements_per_s_per_core"] / 1e6), num(r["xla_flops_per_element"]),
                     num(r["analytic_flops_per_element"]), num(r["bytes_per_element"]),
                     num(r["intensity_flop_per_byte"]), r["bound"], num(r["times_roofline"]),
                     num(r["step_us"]), num(r["step_vs_linear"])])
    t = Table(["case", "element", "law", "elements", "f_int [us]", "M elements/s/core", "flop/element (XLA)",
               "flop/element (formula)", "bytes/element", "flop/byte", "bound", "x roofline", "step [us]",
               "x linear step"], rows,
              "Total-Lagrangian internal force on one core against the roofline, and the explicit step against "
              "the pre-assembled linear one")
    t.notes.append(f"One core: float64 matrix product {num(d['peak_flops_per_core'] / 1e9)} GFlop/s, copy "
                   f"bandwidth {num(d['bandwidth_Bps'] / 1e9)} GB/s (balance "
                   f"{num(d['machine_balance_flop_per_byte'])} flop/byte). Target: within "
                   f"{num(d['target_times_roofline'])}x of the roofline: {met(d['target_met'])}.")
    return Rendered([t], ["hyperelastic.json"], recorded(d.get("machine")))


def r_predicted_step() -> Rendered:
    d = load("predicted_step.json")
    rows = [[r["surrogate"], num(r["rank"]), num(r["refill_calls"]), num(r["t_sync_us"]), num(r["t_nosync_us"]),
             num(r["t_avoid_us"]), num(r["t_d_us"]), f"{num(100 * r['t_d_over_t_sync'], 2)} %", num(r["rest_us"], 2),
             num(r["zeta"])]
            for r in d["rows"]]
    t = Table(["surrogate", "rank", "network calls per refill", "t_sync", "t_nosync", "t_avoid", "t_d",
               "t_d / t_sync", "rest", "zeta"], rows, d["header"])
    return Rendered([t], ["predicted_step.json"], recorded(d.get("machine")))


def r_product() -> Rendered:
    d = load("product/product.json")
    rows = []
    for r in d["rows"]:
        f, c = r["fused"], r["compact"]
        rows.append([r["case"], num(r["parts"]), num(r["slots"]), num(r["n_steps"]),
                     f"{num(f['compile_s'], 2)} / {num(c['compile_s'], 2)}",
                     f"{num(f['wall_s'], 3)} / {num(c['wall_s'], 3)}",
                     f"{num(f['us_per_step'])} / {num(c['us_per_step'])}",
                     "-" if r["break_even_slot_steps"] is None else num(r["break_even_slot_steps"], 2)])
    t = Table(["case", "parts", "slots", "steps", "compile [s] fused / compact", "simulate [s] fused / compact",
               "step [us] fused / compact", "break-even slot-steps"], rows,
              "The stiffness product fused (unrolled) and compact (one gather, one reduction)")
    t.notes.append(f"product='auto' takes the compact form below {num(d['compact_slot_steps'], 2)} slot-steps "
                   "(stored slots times steps); '-': the compact form was not slower per step.")
    return Rendered([t], ["product/product.json"], recorded(d.get("machine")))


def r_ensemble() -> Rendered:
    d = load("ensemble/ensemble.json")
    names = {"E": "E", "E,nu,rho": "E, nu, rho"}
    beams = [r for r in d["rows"] if r.get("problem", "cantilever") == "cantilever"]
    vessels = [r for r in d["rows"] if r.get("problem") == "vessel"]
    rows = [[names.get(r["case"], r["case"]), num(r["members"]), num(r["setup_ms_per_member"]["cold"]),
             num(r["setup_ms_per_member"]["warm"], 2), num(r["problems_ms_per_member"]),
             num(r["own_systems_ms_per_member"]), num(r["us_per_batched_step"]), num(r["run_steps_per_s"]),
             num(r["max_rel_diff_members_vs_problems"], 2)] for r in beams]
    t = Table(["members differ in", "members", "setup [ms/member], first call", "setup, compiled",
               "given as problems", "one system per problem", "batched step [us]", "run-steps/s",
               "members vs problems"], rows,
              "Ensembles of coarse cantilevers whose members differ in material, set up in one vectorised pass")
    tables = [t]
    if vessels:
        v = vessels[0]
        rows = [[names.get(r["case"], r["case"]), num(r["members"]), num(r["steps"]),
                 num(r["setup_ms_per_member"]["cold"]), num(r["setup_ms_per_member"]["warm"], 2),
                 num(r["us_per_batched_step"]), num(r["us_per_batched_step"] / r["members"]),
                 num(r["us_per_step_member_alone"]), num(r["run_steps_per_s"]),
                 num(r["max_rel_diff_member_vs_simulate"], 2)] for r in vessels]
        t = Table(["members differ in", "members", "steps", "setup [ms/member], first call", "setup, compiled",
                   "batched step [us]", "per member [us]", "one member alone [us]", "run-steps/s",
                   "a member vs its own simulate"], rows,
                  f"Ensembles of the demo's coronary tree ({num(v['elements'])} tets, {num(v['dofs'])} dofs, "
                  f"mass-scaled, dt {num(v['dt'])} s)")
        t.notes.append("One member alone: jaxsync.simulate of that member's own problem, the step of a single run "
                       "on the same device; the last column: its largest difference from the member's trajectory "
                       "over its largest displacement.")
        tables.append(t)
    return Rendered(tables, ["ensemble/ensemble.json"], recorded(d.get("machine")))


def r_ensemble_inverse() -> Rendered:
    d = load("ensemble_inverse.json")
    s, p = d["settings"], d["problem"]
    rows = [[str(r), num(m["E_true"]), num(m["E_fit"]), num(m["relative_error"], 2),
             num(m["cramer_rao_relative_std"], 2), f"{m['z']:+.2f}"] for r, m in enumerate(d["members"])]
    t = Table(["member", "E true [dyn/cm^2]", "E fitted", "relative error", "Cramer-Rao std", "z"], rows,
              f"{s['members']} coronary trees ({num(p['tets'])} tets, {num(p['dofs'])} dofs) fitted at once: "
              f"{s['steps']} steps, {s['observed']} wall nodes observed every {s['save']} steps, noise "
              f"{100 * s['noise']:g} % of the RMS signal")
    t.notes.append(f"Gauss-Newton from E_0 = {num(p['E0'])} for every member: {len(d['gauss_newton_steps'])} "
                   "iterations, largest steps in log E " + ", ".join(num(x, 2) for x in d["gauss_newton_steps"])
                   + f"; max |z| {num(d['max_abs_z'], 3)}. One batched run {num(d['seconds']['forward'], 3)} s, "
                   f"its gradient {num(d['seconds']['gradient'], 3)} s; gradient against central differences: "
                   + ", ".join(num(c["relative_difference"], 2) for c in d["gradient_check"]) + ".")
    return Rendered([t], ["ensemble_inverse.json"], recorded(d.get("machine")))


RENDERERS = {
    "product": r_product,
    "ensemble-inverse": r_ensemble_inverse,
    "ensemble": r_ensemble,
    "float32": r_float32,
    "predicted-step": r_predicted_step,
    "hyperelastic": r_hyperelastic,
    "locking": r_locking,
    "stepper": r_stepper,
    "distributed": r_distributed,
    "speedup": r_speedup,
    "sync": r_sync,
    "sync-vessel": r_sync_vessel,
    "regime-map": r_regime_map,
    "gpu-projection": r_gpu_projection,
    "surrogates": r_surrogates,
    "experiments": r_experiments,
    "experiments-linear": r_experiments_linear,
    "seeds": r_seeds,
    "error-control": r_error_control,
    "guarantee": r_guarantee,
    "untuned-vessel": r_untuned_vessel,
    "hyperelastic-vessel": r_hyperelastic_vessel,
    "refill": r_refill,
    "load-jumps": r_load_jumps,
    "gradients": r_gradients,
    "finetune": r_finetune,
    "training": r_training,
    "paper-cantilever": r_paper_cantilever,
    "paper-vessel-small": r_paper_vessel_small,
    "paper-vessel-paper": r_paper_vessel_paper,
}


# -- the directive ------------------------------------------------------------------------

def table_node(table: Table) -> nodes.table:
    node = nodes.table(classes=["bench-table"])
    if table.title:
        node += nodes.title(text=table.title)
    group = nodes.tgroup(cols=len(table.columns))
    node += group
    for k, col in enumerate(table.columns):       # widths for the text builders; HTML sizes itself
        width = max([len(col)] + [len(str(row[k])) for row in table.rows if k < len(row)])
        group += nodes.colspec(colwidth=max(min(width, 40), 3))
    head = nodes.thead()
    group += head
    row = nodes.row()
    for col in table.columns:
        row += nodes.entry("", nodes.paragraph(text=col))
    head += row
    body = nodes.tbody()
    group += body
    for cells in table.rows:
        row = nodes.row()
        for cell in cells:
            row += nodes.entry("", nodes.paragraph(text=str(cell)))
        body += row
    return node


class BenchTable(SphinxDirective):
    """``bench-table NAME``: the tables of one result file (see :data:`RENDERERS`)."""

    required_arguments = 1
    has_content = False

    def run(self):
        name = self.arguments[0]
        renderer = RENDERERS.get(name)
        if renderer is None:
            logger.warning(f"unknown benchmark table {name!r}; known: {', '.join(RENDERERS)}",
                           location=self.get_location())
            return []
        try:
            out = renderer()
        except FileNotFoundError as exc:
            logger.warning(f"benchmark table {name!r}: result file missing: {exc.filename or exc}",
                           location=self.get_location())
            return []
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            logger.warning(f"benchmark table {name!r}: the result file's layout is not the one this table reads "
                           f"({type(exc).__name__}: {exc}); update docs/_ext/benchtables.py",
                           location=self.get_location())
            return []
        for source in out.sources:
            full = os.path.join(ROOT, source) if "/" in source else os.path.join(RESULTS, source)
            if "<" not in full:
                self.env.note_dependency(full)
        result = []
        for table in out.tables:
            result.append(table_node(table))
            for note in table.notes:
                result.append(nodes.paragraph(text=note))
        para = nodes.paragraph(classes=["bench-source"])
        para += nodes.Text("Source: ")
        for k, source in enumerate(out.sources):
            path = source if source.startswith("benchmarks/") else rel(source)
            if k:
                para += nodes.Text(", ")
            para += nodes.literal(text=path)
        if out.recorded:
            para += nodes.Text(f" (recorded: {out.recorded})")
        para += nodes.Text(".")
        result.append(para)
        return result


def setup(app):
    app.add_directive("bench-table", BenchTable)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
