"""GPU projection: where the learned surrogates beat deep halos (exact) on GPUs, and where
they do not. A cost-model calculation from measured figures: nothing is timed here.

    python benchmarks/gpu_projection.py [--out-dir benchmarks/results]
        [--stand-in-elements 80000] [--max-parts 64] [--floor-us 10] [--refill-calls 16]

Case: the paper-size coronary vessel of the demo (generated tree, 380 825 tetrahedra,
273 576 dofs, float64), partitioned as in the scenarios below.

Measured inputs (:data:`GIVEN`, on one NVIDIA H200, float64, the paper-size vessel, and
published figures):

* T_1 = 115 us, the synchronized step with the whole mesh on one device;
* 163 us per step as 11 parts sharing that device with the psum of the interface forces,
  156 us without any exchange: t_c = 156 us, and the exchange on one device
  t_s = 163 - 156 = 7 us;
* the per-step floor of a small mesh on the same device, t_0 = 10 us (``--floor-us``:
  the stepper rows of ``bench_gpu.py`` measured 10-12 us);
* the device's copy bandwidth, 3.5 TB/s (the ``copy`` row of ``bench_gpu.py``);
* published NCCL latencies of one collective: 3-6 us between GPUs of an NVLink node,
  about 30 us between nodes;
* an unstructured halo exchange through XLA's collectives, measured at 0.5-1.5 ms on
  16-64 A100 GPUs (taken as the latency of one exchange).

Recorded by the repository's benchmarks (``benchmarks/results/``; constants of
:data:`VESSEL_FALLBACK` where the file is missing, and the output says so):

* ``paper_vessel/paper_vessel_paper_measure.json``: the vessel's 11-part interface
  (N_a = 2 823 shared nodes, the widest part 2 310 shared dofs), its demo surrogate
  settings (LSTM n_H 32, 2 layers, n_p = n_f = 20, n_s = 1 000; 722 training windows)
  and **one refill of the widest part's LSTM alone at n_s = 1 000, 0.960 s on a 2-core
  CPU** (float32): t_d = 48.0 us per step over the n_s n_f = 20 000 steps it serves;
* ``bench_surrogates.json`` (context only, not used in the projection): the LSTM and the
  linear surrogate timed side by side on the coarse cantilever (12 shared dofs), CPU.

The surrogates' cost t_d on a GPU is not measured. The projection therefore gives, per
scenario, the break-even t_d (the largest surrogate cost per step at which the learned
method still wins) and the flop rate a GPU would have to sustain to reach it, and shows
the surrogate's step at its CPU rate (a reference, not a GPU figure): t_d = the
surrogate's flops per step / R_cpu, with R_cpu = the LSTM's refill flops over its
measured 0.960 s (about 58 GFlop/s, a call of all n_s = 1 000 windows; a call of 16
windows uses the cores less well, so the CPU-rate column is a lower bound there).

A refill evaluates ``--refill-calls`` windows (default 16, the smooth refill that
:class:`jaxsync.surrogate.Surrogate` runs: :data:`jaxsync.surrogate.DEFAULT_REFILL_SAMPLES`
applications estimate the block means its curve goes through; ``--refill-calls 1000``:
the paper's raw refill, every application), and serves n_s n_f steps. Flops per window:

* LSTM: :func:`jaxsync.perf.roofline.surrogate_flop_breakdown` (n_dof D, n_H 32, 2
  bidirectional encoder layers, decoder, dense layer, normalization, mask);
* linear: 2 n_p D r + 2 r n_f D (the two factors of W) + n_f D (bias) + 2 D (n_p + n_f)
  (normalization) + n_f D (mask) per window, rank r = the training windows (722: the
  largest rank a fit can give).

At the vessel's interface the linear map (r = 722 directions over 46 200 inputs) costs
2.4 times the LSTM's flops; on the cantilever's 12 dofs it costs 38 times less per step
(measured with every window, ``bench_surrogates.json``). The per-step cost is that of the GPU's widest part
(D(p) shared dofs); on one GPU the 11 parts' refills, padded to the widest, add up. A
refill is one batched call whose dependent chain (the LSTM's 2 x 2 x n_p encoder and n_f
decoder cell steps) is spread over n_s n_f = 20 000 steps: a few us of launch latency per
dependent step adds under 0.05 us per step, so the flop rate is what decides.

Model, per step, on the GPU that carries the most work (alpha-beta,
:mod:`jaxsync.perf.costmodel`):

* local work of one part of p on its own GPU: t_c(p) = t_0 + (T_1 - t_0) / p (the
  floor, then the mesh's share); 11 parts sharing one GPU: t_c = 156 us (measured);
* an exchange costs the cheaper of (a) one collective sum of the interface vector, as
  jaxsync's psum runs it: latency + 2 (p - 1) / p x the vector's bytes / B (what a ring
  allreduce moves per GPU), and (b) a grouped neighbour exchange (all of a part's
  messages in one call, as an NCCL group or one collective permute would send them):
  latency + the busiest part's bytes / B (nodes counted once per neighbour that shares
  them). B is the link's bandwidth: NVLink 4 (450 GB/s) in a node, InfiniBand NDR
  (50 GB/s) between nodes, HDR (25 GB/s) for the A100 figure. Both are
  :func:`~jaxsync.perf.costmodel.sync_time` with ``algorithm="collective"`` (latency +
  bytes / bandwidth) of a pattern holding the bytes moved. On one device only (a), its
  latency fitted so that t_s = 7 us (the measurement), its bandwidth the copy bandwidth;
* synchronized: t_sync = t_c + t_s, the exchange of the interface forces (N_a nodes x 3
  float64);
* learned: t' = t_c + t_d (:func:`~jaxsync.perf.costmodel.project`); zeta = t_sync / t';
  the break-even against the synchronized step is t_d = t_s, against the best exact
  method t_d = t_best - t_c;
* deep halos of depth k (:mod:`jaxsync.parallel.exchange`): t'' = t_0 + r_k (t_c - t_0) +
  t_s,halo / k, r_k the redundancy (elements held by all parts over the mesh's), one
  exchange of the halo interface (6 float64 per node: two displacement levels) every k
  steps; zeta = t_sync / t'';
* best exact: the fastest of the synchronized step, deep halos k = 1, 2, 4, 8 and the
  whole mesh on one GPU (T_1 = 115 us: the paper-size vessel fits on one device); the
  most the learned method can gain over it is t_best / t_c (a free surrogate);
* the rate a GPU must sustain for the surrogate to beat the best exact method: its flops
  per step over t_best - t_c (none where t_best <= t_c).

Halo redundancy and interface sizes of the vessel. Building the paper-size mesh takes
about a minute, so the partitions are computed on a stand-in: the same generator
(:func:`jaxsync.coronary_mesh`) at ``--stand-in-elements`` tetrahedra (80 000 target:
73 392 tets), partitioned by METIS into each scenario's p parts
(:func:`jaxsync.partition`), grown by :func:`jaxsync.parallel.exchange.halo_partition`. Its
interfaces are scaled to the vessel by c = 2 823 / N_a(stand-in, 11 parts) (the
vessel's recorded 11-part interface over the stand-in's; surfaces of the same
partition): N_a(p) = c N_a'(p) (the recorded 2 823 at 11 parts), the busiest part's
exchanged nodes likewise, the widest
part's shared dofs D(p) = 2 310 D'(p) / D'(11), the halo's exchanged nodes
c N_halo'(k, p), and its redundant elements
(r_k - 1) n_vessel = c (r_k' - 1) n' (the elements k layers deep around an interface
node do not depend on the mesh size, while the layers are thin next to the parts).

Assumptions: those of :mod:`jaxsync.perf.costmodel` (no overlap of the exchange with the
step, which needs the summed force; no contention, no topology) and balanced parts (the
redundancy is an average over parts); t_c and T_1 from the H200 apply to every scenario
(the XLA figure comes from A100s); the surrogate step runs without the error control's
probe and re-synchronizations; one part per GPU beyond one device; accuracy is not part
of the model (zeta is the speed at equal step count).

Writes ``gpu_projection.json`` into ``--out-dir`` and prints the table.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import jaxsync  # noqa: E402
from jaxsync.errors import PartitionError  # noqa: E402
from jaxsync.io import atomic_path  # noqa: E402
from jaxsync.parallel.exchange import halo_partition  # noqa: E402
from jaxsync.perf.costmodel import (  # noqa: E402
    INTERCONNECTS,
    Interconnect,
    communication_pattern,
    project,
    sync_time,
)
from jaxsync.perf.roofline import surrogate_flop_breakdown  # noqa: E402
from jaxsync.surrogate import DEFAULT_REFILL_SAMPLES  # noqa: E402
from jaxsync.surrogate.models import LSTMArchitecture  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_OUT_DIR = os.path.join(HERE, "results")
VESSEL_JSON = os.path.join(HERE, "results", "paper_vessel", "paper_vessel_paper_measure.json")
SURROGATES_JSON = os.path.join(HERE, "results", "bench_surrogates.json")

HALO_DEPTHS = (1, 2, 4, 8)
REFERENCE_PARTS = 11  # the vessel's recorded partition
ALGORITHM = "collective"

#: Figures measured on one NVIDIA H200 (float64, the paper-size vessel) and published ones.
GIVEN = {
    "single_device_step_us": 115.0,
    "parts_on_one_device": 11,
    "parts_on_one_device_step_us": 163.0,
    "parts_on_one_device_nosync_step_us": 156.0,
    "device_copy_Bps": 3.5e12,
    "nvlink_latency_us": (3.0, 6.0),
    "internode_latency_us": 30.0,
    "xla_halo_exchange_us": (500.0, 1500.0),
    "sources": {
        "h200": "measured on one NVIDIA H200, float64, the paper-size vessel (273 576 dofs): 115 us per "
                "synchronized step on one device; 163 us as 11 parts sharing it, 156 us of it without any "
                "exchange; copy bandwidth 3.5 TB/s and a per-step floor of 10-12 us on small meshes "
                "(benchmarks/bench_gpu.py)",
        "nccl": "published NCCL latencies of one collective: 3-6 us inside an NVLink node, about 30 us "
                "between nodes",
        "xla": "an unstructured halo exchange through XLA's collectives, measured at 0.5-1.5 ms on 16-64 "
               "A100 GPUs",
    },
}

#: The vessel's recorded figures, used when paper_vessel_paper_measure.json is missing.
VESSEL_FALLBACK = {"n_elements": 380825, "n_dofs": 273576, "n_interface": 2823, "shared_dofs_max": 2310,
                   "n_s": 1000, "n_past": 20, "n_future": 20, "n_hidden": 32, "n_layers": 2,
                   "n_train_windows": 722, "refill_seconds_widest_alone": 0.9596028509986354}


@dataclasses.dataclass(frozen=True)
class Scenario:
    """One projected configuration: ``parts`` parts on ``gpus`` GPUs, one collective
    costing ``latency_us`` plus the bytes over ``link``'s bandwidth (a preset of
    :data:`~jaxsync.perf.costmodel.INTERCONNECTS`, or ``"device"``: one GPU)."""

    key: str
    label: str
    gpus: int
    parts: int
    latency_us: float
    link: str


SCENARIOS = (
    Scenario("one-gpu", "11 parts on one GPU", 1, 11, 7.0, "device"),
    Scenario("nvlink-3us", "NVLink node, 3 us", 8, 8, 3.0, "nvlink-4"),
    Scenario("nvlink-6us", "NVLink node, 6 us", 8, 8, 6.0, "nvlink-4"),
    Scenario("nodes-16", "between nodes, 30 us", 16, 16, 30.0, "infiniband-ndr"),
    Scenario("nodes-32", "between nodes, 30 us", 32, 32, 30.0, "infiniband-ndr"),
    Scenario("nodes-64", "between nodes, 30 us", 64, 64, 30.0, "infiniband-ndr"),
    Scenario("xla-16", "XLA collectives, 0.5 ms", 16, 16, 500.0, "infiniband-hdr"),
    Scenario("xla-64", "XLA collectives, 1.5 ms", 64, 64, 1500.0, "infiniband-hdr"),
)


# --------------------------------------------------------------------------- inputs

def read_vessel(path: str = VESSEL_JSON) -> tuple[dict, list]:
    """The vessel's recorded interface, surrogate settings and CPU refill time (or the
    fallback constants, with a note)."""
    try:
        with open(path) as f:
            d = json.load(f)
        de, prog = d["defaults"], d["programs"]
        n_s = int(de["n_s"])
        return {"n_elements": int(d["mesh"]["n_elements"]), "n_dofs": int(d["mesh"]["n_dofs"]),
                "n_interface": int(d["partition"]["n_interface"]),
                "shared_dofs_max": int(d["partition"]["shared_dofs_per_part_max"]),
                "n_s": n_s, "n_past": int(de["n_past"]), "n_future": int(de["n_future"]),
                "n_hidden": int(de["n_hidden"]), "n_layers": int(de["n_layers"]),
                "n_train_windows": int(d["training"]["n_train_windows"]),
                "refill_seconds_widest_alone": float(prog["refill_seconds_widest_part_alone"][str(n_s)]),
                "source": os.path.relpath(path, os.path.dirname(HERE))}, []
    except (OSError, ValueError, KeyError, TypeError) as exc:
        return dict(VESSEL_FALLBACK, source="fallback constants"), [
            f"{path} unreadable ({type(exc).__name__}: {exc}): the vessel's recorded figures fall back to "
            "the constants of VESSEL_FALLBACK"]


def read_cantilever_context(path: str = SURROGATES_JSON):
    """t_d of the LSTM and the linear surrogate measured side by side on the coarse
    cantilever (CPU), for context; None when the file is missing."""
    try:
        with open(path) as f:
            d = json.load(f)
        case = d["cases"][0]
        out = {"case": case["case"], "source": os.path.relpath(path, os.path.dirname(HERE)),
               "cores": (d.get("machine") or {}).get("cores")}
        for key in ("lstm", "linear"):
            v = case["variants"][key]
            out[key] = {"t_d_us": 1e6 * float(v["t_d"]), "architecture": v["architecture"], "n_s": v["n_s"]}
        return out
    except (OSError, ValueError, KeyError, TypeError, IndexError):
        return None


# --------------------------------------------------------------------------- surrogate cost

def lstm_flops_per_step(n_dof: int, vessel: dict, calls: int) -> float:
    """Flops of the LSTM's refill of ``calls`` windows per solver step (one part, its
    n_dof shared dofs; the refill serves n_s n_f steps)."""
    arch = LSTMArchitecture(n_dof=int(n_dof), n_hidden=vessel["n_hidden"], n_layers=vessel["n_layers"],
                            n_past=vessel["n_past"], n_future=vessel["n_future"])
    return sum(surrogate_flop_breakdown(arch, int(calls)).values()) / (vessel["n_s"] * vessel["n_future"])


def linear_flops_per_step(n_dof: int, vessel: dict, calls: int) -> float:
    """Flops of the linear surrogate's refill of ``calls`` windows per solver step (module
    docstring)."""
    d, r = int(n_dof), vessel["n_train_windows"]
    n_p, n_f = vessel["n_past"], vessel["n_future"]
    per_window = 2 * n_p * d * r + 2 * r * n_f * d + n_f * d + 2 * d * (n_p + n_f) + n_f * d
    return per_window * int(calls) / (vessel["n_s"] * n_f)  # one refill serves n_s n_f steps


FLOPS = {"linear": linear_flops_per_step, "lstm": lstm_flops_per_step}


def cpu_rate(vessel: dict) -> float:
    """R_cpu [flop/s]: the LSTM refill's flops over its measured CPU time (a refill of
    all n_s windows, as it was measured)."""
    steps = vessel["n_s"] * vessel["n_future"]
    return (lstm_flops_per_step(vessel["shared_dofs_max"], vessel, vessel["n_s"]) * steps
            / vessel["refill_seconds_widest_alone"])


# --------------------------------------------------------------------------- stand-in

def busiest(pattern) -> int:
    """Node values the busiest part exchanges with all its neighbours (a node shared with
    two neighbours counts twice)."""
    return int(max(sum(n for _, n in row) for row in pattern.neighbours))


def stand_in(n_target: int, parts_list, depths=HALO_DEPTHS) -> dict:
    """Partitions and halos of the generated tree at ``n_target`` tetrahedra."""
    start = time.perf_counter()
    mesh = jaxsync.coronary_mesh(target_elements=int(n_target))
    out = {"target_elements": int(n_target), "n_elements": int(mesh.n_elements), "n_nodes": int(mesh.n_nodes),
           "mesh_seconds": time.perf_counter() - start, "partitions": {}}
    for p in sorted(set(parts_list)):
        part = jaxsync.partition(mesh, p)
        pattern = communication_pattern(part)
        halos, notes = {}, []
        for k in depths:
            try:
                h = halo_partition(part, k)
            except PartitionError as exc:
                notes.append(f"depth {k}: {exc}")
                continue
            halo_pattern = communication_pattern(h, dofs_per_node=6)
            halos[k] = {"redundancy": float(h.redundancy()), "n_halo": int(h.n_interface),
                        "busiest": busiest(halo_pattern), "pattern": halo_pattern}
        out["partitions"][p] = {"pattern": pattern, "n_interface": int(pattern.n_interface),
                                "busiest": busiest(pattern),
                                "shared_max": int(max(q.n_shared for q in part.parts)), "halos": halos,
                                "notes": notes}
    out["seconds"] = time.perf_counter() - start
    return out


# --------------------------------------------------------------------------- model

def collective_link(s: Scenario, n_interface: int) -> Interconnect:
    """The scenario's link for one collective sum of the interface vector (module docstring);
    ``n_interface``: the vessel's interface nodes, to which one device's latency is fitted."""
    if s.link == "device":
        bandwidth = GIVEN["device_copy_Bps"]
        latency = 1e-6 * s.latency_us - 24 * n_interface / bandwidth  # t_s = 7 us at the vessel's interface
        return Interconnect("one-device", latency, bandwidth,
                            "one H200: latency fitted to the measured 7 us exchange of the 11-part interface, "
                            "bandwidth its copy bandwidth")
    preset = INTERCONNECTS[s.link]
    ring = 2 * (s.parts - 1) / s.parts
    return Interconnect(f"{s.key}-collective", 1e-6 * s.latency_us, preset.bandwidth_Bps / ring,
                        f"latency {s.latency_us:g} us per collective; {preset.name} bandwidth "
                        f"{preset.bandwidth_Bps / 1e9:g} GB/s over the 2 (p - 1) / p = {ring:.3f} of the vector's "
                        "bytes a ring allreduce moves per GPU")


def grouped_link(s: Scenario) -> Interconnect:
    """The scenario's link for a grouped neighbour exchange: one latency, the busiest
    part's own bytes at the link's bandwidth."""
    preset = INTERCONNECTS[s.link]
    return Interconnect(f"{s.key}-grouped", 1e-6 * s.latency_us, preset.bandwidth_Bps,
                        f"latency {s.latency_us:g} us per grouped exchange; {preset.name} bandwidth "
                        f"{preset.bandwidth_Bps / 1e9:g} GB/s")


def exchange(s: Scenario, pattern, n_vector: int, c: float, n_fit: int) -> dict:
    """The cheaper of the two exchanges of ``pattern`` (a stand-in's, its counts scaled by
    ``c``): one collective sum of the ``n_vector``-node interface vector, or (between
    GPUs) a grouped neighbour exchange of the busiest part's values. The time is
    :func:`~jaxsync.perf.costmodel.sync_time` of a pattern and a link in the
    ``"collective"`` model (the grouped exchange as a collective of that part's nodes)."""
    options = [("collective sum", dataclasses.replace(pattern, n_interface=int(n_vector)),
                collective_link(s, n_fit))]
    if s.gpus > 1:
        options.append(("grouped neighbour exchange",
                        dataclasses.replace(pattern, n_interface=int(round(c * busiest(pattern)))),
                        grouped_link(s)))
    timed = [(1e6 * sync_time(pat, link, ALGORITHM), name, pat, link) for name, pat, link in options]
    t, name, pat, link = min(timed, key=lambda x: x[0])
    return {"t_us": t, "method": name, "pattern": pat, "link": link,
            "options_us": {n: tt for tt, n, _, _ in timed}}


def project_scenario(s: Scenario, site: dict, vessel: dict, c: float, d_ref: int, t_0: float,
                     r_cpu: float, calls: int) -> dict:
    """One row: exact methods, surrogates and break-even costs [us]."""
    t_1 = GIVEN["single_device_step_us"]
    if s.gpus == 1:
        t_c = GIVEN["parts_on_one_device_nosync_step_us"]
    else:
        t_c = t_0 + (t_1 - t_0) / s.parts
    part = site["partitions"][s.parts]
    n_a = vessel["n_interface"] if s.parts == REFERENCE_PARTS else int(round(c * part["n_interface"]))
    sync = exchange(s, part["pattern"], n_a, c, vessel["n_interface"])
    t_s = sync["t_us"]
    t_sync = t_c + t_s
    # deep halos
    halos = {}
    for k, h in part["halos"].items():
        redundancy = 1.0 + c * (h["redundancy"] - 1.0) * site["n_elements"] / vessel["n_elements"]
        n_halo = int(round(c * h["n_halo"]))
        halo_exchange = exchange(s, h["pattern"], n_halo, c, vessel["n_interface"])
        t_sh = halo_exchange["t_us"]
        t_step = t_0 + redundancy * (t_c - t_0) + t_sh / k
        halos[k] = {"redundancy": redundancy, "n_halo": n_halo, "t_s_halo_us": t_sh,
                    "exchange": halo_exchange["method"], "exchange_options_us": halo_exchange["options_us"],
                    "t_step_us": t_step, "zeta": t_sync / t_step}
    candidates = [("synchronized", t_sync)] + [(f"halo k={k}", h["t_step_us"]) for k, h in halos.items()]
    candidates.append(("whole mesh on one GPU", t_1))
    best_name, best = min(candidates, key=lambda kv: kv[1])
    # surrogates: flops per step on the GPU that carries the most (all parts when they share it)
    width = d_ref if s.gpus == 1 else int(round(d_ref * part["shared_max"] / site["partitions"][REFERENCE_PARTS]
                                                ["shared_max"]))
    parts_per_gpu = s.parts // s.gpus
    break_even_best = best - t_c
    surrogates = {}
    for name, flops_of in FLOPS.items():
        flops = parts_per_gpu * flops_of(width, vessel, calls)
        t_d = 1e6 * flops / r_cpu
        proj = project(1e-6 * t_c, 1e-6 * t_d, sync["pattern"], [sync["link"]], algorithm=ALGORITHM).rows[0]
        surrogates[name] = {
            "flops_per_step": flops, "t_d_cpu_rate_us": t_d, "t_step_us": 1e6 * proj.t_t_prime, "zeta": proj.zeta,
            "beats_best_exact": t_c + t_d < best,
            "rate_needed_vs_synchronized_GFlops": flops / (1e3 * t_s),
            "rate_needed_vs_best_exact_GFlops": flops / (1e3 * break_even_best) if break_even_best > 0 else None}
    assert abs(1e6 * proj.t_t - t_sync) < 1e-6 * t_sync  # project() and the row agree
    return {"key": s.key, "label": s.label, "gpus": s.gpus, "parts": s.parts, "latency_us": s.latency_us,
            "interconnect": sync["link"].to_dict(), "exchange": sync["method"],
            "exchange_options_us": sync["options_us"], "t_c_us": t_c, "n_interface": n_a,
            "shared_dofs_widest": width, "t_s_us": t_s, "t_sync_us": t_sync,
            "break_even_t_d_vs_synchronized_us": t_s, "halos": {str(k): v for k, v in halos.items()},
            "best_exact": {"method": best_name, "t_step_us": best, "zeta": t_sync / best},
            "break_even_t_d_vs_best_exact_us": break_even_best, "zeta_ceiling_vs_best_exact": best / t_c,
            "surrogates": surrogates}


# --------------------------------------------------------------------------- output

def format_table(record: dict) -> str:
    rows = record["scenarios"]
    lines = [f"GPU projection of the paper-size vessel ({record['vessel']['n_dofs']} dofs), us per step; "
             f"zeta = synchronized / method; t_d of the surrogates at the CPU rate "
             f"({record['surrogate_cost']['cpu_rate_GFlops']:.0f} GFlop/s), not a GPU measurement",
             f"{'scenario':<26}{'GPUs':>5}{'parts':>6}{'t_c':>7}{'t_s':>8}{'sync':>8} "
             + "".join(f"{'halo k=' + str(k):>16}" for k in HALO_DEPTHS)
             + f"  {'best exact':<28}{'be sync':>8}{'be best':>8}"
             + "".join(f"{n + ' t_d':>11}{n + ' step (zeta)':>22}" for n in ("linear", "lstm"))]
    for r in rows:
        halo = "".join(f"{h['t_step_us']:>8.1f} ({h['zeta']:>4.2f})" if h else f"{'-':>16}"
                       for h in (r["halos"].get(str(k)) for k in HALO_DEPTHS))
        best = r["best_exact"]
        best_text = f"{best['method']} {best['t_step_us']:.1f}"
        surr = "".join(f"{v['t_d_cpu_rate_us']:>11.1f}{v['t_step_us']:>13.1f} ({v['zeta']:>6.3f})"
                       for v in r["surrogates"].values())
        lines.append(f"{r['label']:<26}{r['gpus']:>5}{r['parts']:>6}{r['t_c_us']:>7.1f}{r['t_s_us']:>8.1f}"
                     f"{r['t_sync_us']:>8.1f} {halo}  {best_text:<28}"
                     f"{r['break_even_t_d_vs_synchronized_us']:>8.1f}{r['break_even_t_d_vs_best_exact_us']:>8.1f}"
                     + surr)
    lines.append("be sync / be best: break-even surrogate cost t_d [us per step] against the synchronized step "
                 "and against the best exact method (negative: the learned method cannot win)")
    lines.append("most the learned method can gain over the best exact method (t_d = 0, best exact / t_c): "
                 + "; ".join(f"{r['key']} {r['zeta_ceiling_vs_best_exact']:.2f}" for r in rows))
    lines.append("GFlop/s a GPU must sustain to reach 'be best' (linear / LSTM): " + "; ".join(
        f"{r['key']} " + " / ".join("never" if v["rate_needed_vs_best_exact_GFlops"] is None
                                    else f"{v['rate_needed_vs_best_exact_GFlops']:.0f}"
                                    for v in r["surrogates"].values()) for r in rows))
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out-dir", default=DEFAULT_OUT_DIR)
    ap.add_argument("--stand-in-elements", type=int, default=80_000,
                    help="target tetrahedra of the generated tree the partitions and halos are computed on")
    ap.add_argument("--max-parts", type=int, default=64, help="leave out the scenarios with more parts")
    ap.add_argument("--floor-us", type=float, default=10.0, help="t_0, the per-step floor of a small mesh [us]")
    ap.add_argument("--vessel-json", default=VESSEL_JSON, help="paper_vessel.py --size paper output")
    ap.add_argument("--refill-calls", type=int, default=DEFAULT_REFILL_SAMPLES,
                    help="network calls (windows) per refill: the smooth refill's samples (default %(default)s), "
                         "or n_s for the paper's raw refill")
    args = ap.parse_args(argv)
    start = time.perf_counter()
    vessel, notes = read_vessel(args.vessel_json)
    scenarios = [s for s in SCENARIOS if s.parts <= args.max_parts]
    site = stand_in(args.stand_in_elements, [REFERENCE_PARTS] + [s.parts for s in scenarios])
    c = vessel["n_interface"] / site["partitions"][REFERENCE_PARTS]["n_interface"]
    r_cpu = cpu_rate(vessel)
    calls = min(args.refill_calls, vessel["n_s"])
    rows = [project_scenario(s, site, vessel, c, vessel["shared_dofs_max"], args.floor_us, r_cpu, calls)
            for s in scenarios]
    for p, v in site["partitions"].items():
        notes += [f"stand-in, {p} parts: {n}" for n in v["notes"]]
    d_ref = vessel["shared_dofs_max"]
    record = {
        "benchmark": "GPU projection (cost model)",
        "command": " ".join(["python benchmarks/gpu_projection.py"] + list(sys.argv[1:] if argv is None else argv)),
        "given": GIVEN, "floor_us": args.floor_us, "algorithm": ALGORITHM,
        "vessel": vessel,
        "surrogate_cost": {
            "cpu_rate_GFlops": r_cpu / 1e9,
            "cpu_rate_source": (f"the LSTM's refill of the widest part (n_dof {d_ref}, n_H {vessel['n_hidden']}, "
                                f"n_s {vessel['n_s']}) alone, {vessel['refill_seconds_widest_alone']:.3f} s on a "
                                f"2-core CPU ({vessel['source']})"),
            "refill_calls": calls,
            "flops_per_step_per_part": {n: f(d_ref, vessel, calls) for n, f in FLOPS.items()},
            "t_d_cpu_us_per_part": {n: 1e6 * f(d_ref, vessel, calls) / r_cpu for n, f in FLOPS.items()},
            "linear_rank": vessel["n_train_windows"],
            "cantilever_context": read_cantilever_context()},
        "stand_in": {"generator": f"jaxsync.coronary_mesh(target_elements={args.stand_in_elements})",
                     "n_elements": site["n_elements"], "n_nodes": site["n_nodes"], "scale_c": c,
                     "mesh_seconds": site["mesh_seconds"],
                     "partitions": {str(p): {"n_interface": v["n_interface"], "shared_max": v["shared_max"],
                                             "busiest": v["busiest"],
                                             "halos": {str(k): {"redundancy": h["redundancy"], "n_halo": h["n_halo"],
                                                                "busiest": h["busiest"]}
                                                       for k, h in v["halos"].items()}}
                                    for p, v in site["partitions"].items()}},
        "scenarios": rows, "notes": notes,
        "generated": {"date": datetime.date.today().isoformat(), "jaxsync": getattr(jaxsync, "__version__", None),
                      "seconds": time.perf_counter() - start},
    }
    os.makedirs(args.out_dir, exist_ok=True)
    path = os.path.join(args.out_dir, "gpu_projection.json")
    with atomic_path(path) as tmp:
        with open(tmp, "w") as f:
            json.dump(record, f, indent=1, allow_nan=False)
    print(format_table(record))
    for n in notes:
        print("note:", n)
    print(f"stand-in: {site['n_elements']} tets, c = {c:.3f}; {time.perf_counter() - start:.1f} s; wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
