"""Cheaper surrogates measured against the LSTM: online accuracy against t_d.

For the default and the skewed cantilever case of the experiment matrix (``experiments.py``)
(coarse beam, 2 parts, 1e5 steps, n_s 150, n_p = n_f = 20, trained on the first half):
the synchronized reference, then the synchronization-avoiding run from n_cri = n_s n_p
with each surrogate:

=============  ================================================================================
``lstm``       the default LSTM encoder-decoder: ``--checkpoint-<case>`` or, by default, the
               experiments' own ``benchmarks/results/experiments/<case>/training/<case>/
               surrogate.h5`` when present; otherwise trained here with the library's
               defaults (about 6 minutes per case on 2 cores)
``lstm_bf16``  the same networks with bfloat16 weights and activations, float32
               accumulation (``Surrogate.with_inference_dtype("bfloat16")``), after the
               check of ``jaxsync.surrogate.check_inference_precision`` (recorded; a deviation above the
               bound is flagged, and the run still made, so that the table shows what it costs)
``linear``     the linear autoregressive baseline, fitted here on the same windows (seconds)
=============  ================================================================================

Accuracy (``experiments.run_metrics``, the experiment matrix's definitions): the free end's
z error, largest over the saved steps in % of its largest |z| and final in % of its final
value, and e_l2 (the norm of the error field per saved step, cm; largest and final) and
its relative l2 over the run; the skewed case also reports y.

Cost: t_d per step, one refill prediction of every part at once in the SPMD program (as
the solver runs it) divided by the n_s n_f steps it serves, and each part's prediction
alone on one device; t_s, the synchronization the surrogate replaces, from the whole
synchronized SPMD programs (psum and ppermute) minus the program without synchronization;
and zeta, the synchronized program's step over the synchronization-avoiding one. These
are the quantities and the kernels of ``jaxsync.perf.timing.speedup_breakdown``
(``jaxsync.perf.kernels``), timed round-robin in one ``best_times`` call so that every
surrogate meets the same machine load; the stage breakdown is left out. The cost model
(``jaxsync.perf.costmodel``) adds the synchronization time t_s each interconnect preset
would take for this partition: the break-even t_d below which a surrogate pays off there.
On this machine's emulated CPU devices t_s is the cost of the device threads meeting, not
of a network.

``--quick``: 3 000 steps, n_s 10, n_p = n_f 5, an LSTM of n_H 8 and one layer trained
for 2 epochs, few timing repeats: a smoke run whose numbers mean nothing.

Usage:
    python benchmarks/bench_surrogates.py [--quick] [--case default skewed] [--steps N]
        [--checkpoint-default FILE] [--checkpoint-skewed FILE] [--seed S]
        [--out benchmarks/results/bench_surrogates.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import sys
import time
import warnings

os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                           + " --xla_force_host_platform_device_count=2").strip()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import experiments  # noqa: E402  (the settings, cases, metrics and training of the experiment matrix)

import jaxsync  # noqa: E402
from jaxsync.fem import SolverState, build_system, initial_state  # noqa: E402
from jaxsync.io import atomic_json  # noqa: E402
from jaxsync.parallel import Partition  # noqa: E402
from jaxsync.perf import kernels  # noqa: E402
from jaxsync.perf.costmodel import INTERCONNECTS, communication_pattern, sync_time  # noqa: E402
from jaxsync.perf.measure import best_times, per_step_times  # noqa: E402
from jaxsync.solve.executors import DistributedRunner, PredictedPhase  # noqa: E402
from jaxsync.surrogate import (  # noqa: E402  # noqa: E402
    DEFAULT_BOUND,
    Surrogate,
    TrainingChecks,
    check_inference_precision,
    surrogate_signal_windows,
    surrogate_windows,
)

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_OUT = os.path.join(HERE, "results", "bench_surrogates.json")
CASES = experiments.BODY_FORCES
VARIANTS = ("lstm", "lstm_bf16", "linear")


@dataclasses.dataclass(frozen=True)
class Settings:
    quick: bool
    n_steps: int
    n_s: int
    n_past: int
    n_future: int
    save_every: int
    train_fraction: float
    train_overrides: dict
    timing_repeats: int
    timing_cycles: int
    check_windows: int

    def to_dict(self) -> dict:
        return experiments.settings_record(self)


def full_settings() -> Settings:
    paper = experiments.paper_settings()
    return Settings(quick=False, n_steps=paper.n_steps, n_s=paper.n_s, n_past=paper.n_past, n_future=paper.n_future,
                    save_every=paper.save_every, train_fraction=paper.train_fraction, train_overrides={},
                    timing_repeats=10, timing_cycles=1, check_windows=400)


def quick_settings() -> Settings:
    """The experiment matrix's reduced settings (its smoke training), few timing repeats."""
    reduced = experiments.reduced_settings(2)
    return Settings(quick=True, n_steps=reduced.n_steps, n_s=reduced.n_s, n_past=reduced.n_past,
                    n_future=reduced.n_future, save_every=reduced.save_every, train_fraction=reduced.train_fraction,
                    train_overrides=reduced.train_overrides, timing_repeats=3, timing_cycles=2, check_windows=50)


def log(text: str, quiet: bool) -> None:
    if not quiet:
        print(text, file=sys.stderr, flush=True)


def fit(reference, settings: Settings, seed: int, model: str, quiet: bool):
    """``experiments.train`` with the case's parameters (the library's defaults for the
    rest; the LSTM with the settings' overrides, the linear surrogate with their E_mse
    measure only); the offline check's RolloutWarning is recorded, not raised."""
    parameters = dict(n_s=settings.n_s, n_past=settings.n_past, n_future=settings.n_future,
                      train_fraction=settings.train_fraction, seed=seed, model=model)
    if model == "lstm":
        overrides = settings.train_overrides
    else:
        overrides = {"emse_applications": settings.train_overrides.get("emse_applications",
                                                                       TrainingChecks.emse_applications)}
    (trained, record), seconds = experiments.timed(experiments.train, reference, parameters, overrides=overrides,
                                                   progress=not quiet)
    return trained.saved, {"source": "trained here", "model": model, "train_seconds": seconds,
                                "rollout_warning": record["rollout_warning"]}


def lstm_checkpoint(case: str, reference, settings: Settings, seed: int, path: str | None, quiet: bool):
    """(checkpoint or its file, record): the given file, else the experiments' one when
    present (full mode), else a training with the library's defaults."""
    if path is None and not settings.quick:
        candidate = os.path.join(HERE, "results", "experiments", case, "training", case, "surrogate.h5")
        path = candidate if os.path.exists(candidate) else None
    if path is not None:
        return path, {"source": os.path.relpath(os.path.abspath(path), os.path.dirname(HERE)), "model": "lstm"}
    if not settings.quick:
        warnings.warn(f"no LSTM checkpoint for case {case!r}: training one with the library's defaults "
                      "(about 6 minutes on 2 cores); pass --checkpoint-" + case + " to reuse one", stacklevel=2)
    log(f"[{case}] training the LSTM", quiet)
    return fit(reference, settings, seed, "lstm", quiet)


def surrogate_timing(problem, parts: Partition, surrogates: dict, settings: Settings) -> dict:
    """t_d, t_s and zeta of every surrogate, timed round-robin in one run (module docstring;
    the programs of :func:`jaxsync.perf.timing.speedup_breakdown`)."""
    first = next(iter(surrogates.values()))
    cycle_steps, history = first.n_s * first.n_future, first.n_s * first.n_past
    n_steps = settings.timing_cycles * cycle_steps
    system = build_system(problem, problem.dt, "preassembled")
    start = initial_state(problem, system)
    d0, dm1 = np.asarray(start.displacement), np.asarray(start.previous)
    runners = {m: DistributedRunner(problem, system, parts, save_every=n_steps, sync=m) for m in ("psum", "ppermute")}
    runner = runners["psum"]
    state = runner.from_global(SolverState(d0, dm1, 0))
    buffer = runner.put(np.zeros((parts.n_parts, history, first.n_dof)))
    calls = {f"sync:{m}": (kernels.distributed_step(r, n_steps, True), (r.parts, state)) for m, r in runners.items()}
    calls["nosync"] = (kernels.distributed_step(runner, n_steps, False), (runner.parts, state))
    calls["call"] = (kernels.distributed_no_step(runner), (runner.parts, state))
    predict = kernels.prediction_program(runner.device_mesh)
    for name, surrogate in surrogates.items():
        if surrogate.n_s * surrogate.n_future != cycle_steps or surrogate.n_s * surrogate.n_past != history:
            raise ValueError(f"surrogate {name} has another refill geometry than {next(iter(surrogates))}")
        online = PredictedPhase(runner, surrogate, save_every=cycle_steps)
        calls[f"avoid:{name}"] = (online.prepare(state, buffer, settings.timing_cycles, cycle_steps),
                                  (runner.parts, online.predictor, state, buffer, online.step_counter(0)))
        calls[f"predict:{name}"] = (predict, (online.predictor, buffer))
    whole = per_step_times(best_times(calls, settings.timing_repeats), n_steps)
    t_sync = {m: whole[f"sync:{m}"] for m in runners}
    best = min(t_sync, key=t_sync.get)
    t_s = {m: max(t - whole["nosync"], 0.0) for m, t in t_sync.items()}

    one = {"predict": kernels.part_prediction(), "call": kernels.no_prediction()}
    out = {"t_step_sync": t_sync, "t_step_nosync": whole["nosync"], "t_s": t_s, "sync": best,
           "cycle_steps": cycle_steps, "n_steps_timed": n_steps, "repeats": settings.timing_repeats,
           "loadavg": list(os.getloadavg()), "surrogates": {}}
    for name, surrogate in surrogates.items():
        alone = []
        for p in range(parts.n_parts):
            own = jax.device_put(surrogate.part(p), runner.devices[0])
            buf = jax.device_put(np.zeros((history, surrogate.n_dof)), runner.devices[0])
            t = best_times({"predict": (one["predict"], (own, buf)), "call": (one["call"], (buf,))},
                           max(settings.timing_repeats, 5))
            alone.append(max(t["predict"] - t["call"], 0.0))
        t_prediction_spmd = whole[f"predict:{name}"] * n_steps
        out["surrogates"][name] = {
            "t_d": t_prediction_spmd / cycle_steps, "t_prediction_spmd": t_prediction_spmd,
            "t_prediction_part_alone": alone, "t_step_avoiding": whole[f"avoid:{name}"],
            "zeta": t_sync[best] / whole[f"avoid:{name}"] if whole[f"avoid:{name}"] > 0 else None}
    return out


def break_even(parts: Partition, timing: dict) -> dict:
    """Per interconnect preset: the model's t_s of this partition (allreduce), the t_d
    below which a surrogate pays off, and which surrogates are below it."""
    pattern = communication_pattern(parts)
    out = {}
    for name, link in INTERCONNECTS.items():
        t_s = sync_time(pattern, link, "allreduce")
        out[name] = {"t_s_model": t_s,
                     "pays_off": {v: bool(r["t_d"] < t_s) for v, r in timing["surrogates"].items()}}
    return out


def run_case(case: str, settings: Settings, seed: int, checkpoint: str | None, quiet: bool) -> dict:
    mesh = jaxsync.box_beam()
    problem = jaxsync.cantilever(mesh, body_force=CASES[case])
    parts = jaxsync.partition(mesh, 2, seed=seed)
    tip = experiments.check_tip(mesh, parts)
    excluded = experiments.excluded_nodes(problem, parts)
    log(f"[{case}] synchronized reference: {settings.n_steps} steps", quiet)
    reference, seconds = experiments.timed(jaxsync.simulate, problem, settings.n_steps, partitions=parts,
                                           save=jaxsync.SaveAt(settings.save_every, 1),
                                           executor=jaxsync.HostExecutor(progress=not quiet))
    record = {"case": case, "body_force": list(CASES[case]), "n_steps": settings.n_steps, "n_parts": parts.n_parts,
              "tip_node": tip, "reference": experiments.run_stats(reference, seconds), "variants": {}}

    lstm_source, lstm_record = lstm_checkpoint(case, reference, settings, seed, checkpoint, quiet)
    lstm = Surrogate.from_saved(lstm_source).for_problem(problem)  # load-aware replicas read its loads
    log(f"[{case}] fitting the linear surrogate", quiet)
    linear_ckpt, linear_record = fit(reference, dataclasses.replace(settings, n_s=lstm.n_s, n_past=lstm.n_past,
                                                                    n_future=lstm.n_future), seed, "linear", quiet)
    linear = Surrogate.from_saved(linear_ckpt).for_problem(problem)

    # the check of reduced-precision inference on the reference's own windows
    histories = [p.shared_displacement for p in reference.parts]
    checks = {}
    for name, surrogate in (("lstm_bf16", lstm), ("linear_bf16", linear)):
        windows = surrogate_windows(surrogate, histories, max_windows=settings.check_windows)
        signals = (surrogate_signal_windows(surrogate, len(histories[0]), max_windows=settings.check_windows)
                   if surrogate.n_load else None)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            report = check_inference_precision(surrogate, windows, signals=signals, on_excess="warn")
        checks[name] = {**report.to_dict(), "flagged": [str(w.message) for w in caught]}
    record["bf16_check"] = checks

    surrogates = {"lstm": lstm, "lstm_bf16": lstm.with_inference_dtype("bfloat16"), "linear": linear}
    sources = {"lstm": lstm_record, "lstm_bf16": {**lstm_record, "inference_dtype": "bfloat16"},
               "linear": linear_record}
    n_cri = lstm.n_s * lstm.n_past
    components = (1, 2) if case == "skewed" else (2,)
    for name, surrogate in surrogates.items():
        log(f"[{case}/{name}] online run from n_cri {n_cri}", quiet)
        online, seconds = experiments.timed(jaxsync.simulate_sync_avoiding, problem, settings.n_steps,
                                            partitions=parts, surrogates=surrogate, n_cri=n_cri,
                                            save=settings.save_every, executor=jaxsync.HostExecutor(progress=not quiet))
        metrics = {"xyz"[c]: experiments.run_metrics(reference.displacement, online.displacement, tip, excluded,
                                                     component=c) for c in components}
        record["variants"][name] = {"surrogate": sources[name], "architecture": surrogate.arch.to_dict(),
                                    "kind": surrogate.arch.kind, "inference_dtype": surrogate.inference_dtype,
                                    "n_s": surrogate.n_s, "n_cri": n_cri,
                                    "online": experiments.run_stats(online, seconds), "metrics": metrics}
    log(f"[{case}] timing t_d, t_s and zeta", quiet)
    timing = surrogate_timing(problem, parts, surrogates, settings)
    record["timing"] = timing
    record["break_even"] = break_even(parts, timing)
    for name in surrogates:
        record["variants"][name]["t_d"] = timing["surrogates"][name]["t_d"]
        record["variants"][name]["zeta"] = timing["surrogates"][name]["zeta"]
    return record


def pct(value) -> str:
    return "-" if value is None else f"{100 * value:.2f}"


def table(records: list) -> str:
    lines = [f"{'case':<8} {'surrogate':<10} {'tip max %':>9} {'tip fin %':>9} {'e_l2 max':>9} {'e_l2 fin':>9} "
             f"{'l2 rel %':>8} {'t_d us':>7} {'zeta':>6}"]
    for r in records:
        for name, v in r["variants"].items():
            m = v["metrics"]["z"]
            lines.append(f"{r['case']:<8} {name:<10} {pct(m['tip_max_error_relative']):>9} "
                         f"{pct(m['tip_final_error_relative']):>9} {m['e_l2_max_cm']:>9.2e} "
                         f"{m['e_l2_final_cm']:>9.2e} {pct(m['l2_relative']):>8} {1e6 * v['t_d']:>7.2f} "
                         + ("     -" if v["zeta"] is None else f"{v['zeta']:>6.3f}"))
        t = r["timing"]
        lines.append(f"{'':<8} t_s psum {1e6 * t['t_s']['psum']:.2f} us, ppermute {1e6 * t['t_s']['ppermute']:.2f} "
                     f"us per step (emulated devices); bf16 deviation: LSTM "
                     f"{pct(r['bf16_check']['lstm_bf16']['worst'])} %, linear "
                     f"{pct(r['bf16_check']['linear_bf16']['worst'])} % (bound {100 * DEFAULT_BOUND:g} %)")
    if records:
        lines.append("break-even t_d (the model's t_s of this partition, allreduce), us per step: "
                     + ", ".join(f"{k} {1e6 * v['t_s_model']:.2f}" for k, v in records[0]["break_even"].items()))
    return "\n".join(lines)


def parse_args(argv):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="smoke run: 3000 steps, tiny LSTM, few repeats")
    parser.add_argument("--case", nargs="+", choices=sorted(CASES), default=list(CASES))
    parser.add_argument("--steps", type=int, default=None, help="total steps of every run (default: the mode's)")
    for case in CASES:
        parser.add_argument(f"--checkpoint-{case}", default=None, metavar="FILE",
                            help=f"LSTM checkpoint of the {case} case (default: the experiments' one if present)")
    parser.add_argument("--seed", type=int, default=0, help="METIS and training seed")
    parser.add_argument("--out", default=DEFAULT_OUT)
    parser.add_argument("--quiet", action="store_true")
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    settings = quick_settings() if args.quick else full_settings()
    if args.steps is not None:
        settings = dataclasses.replace(settings, n_steps=args.steps)
    if settings.n_steps < settings.n_s * settings.n_past + settings.n_s * settings.n_future:
        raise SystemExit(f"--steps {settings.n_steps} leaves no predicted cycle after n_cri")
    if settings.n_steps % settings.save_every:
        settings = dataclasses.replace(settings, save_every=math.gcd(settings.n_steps, settings.save_every))
    start = time.perf_counter()
    records = []
    for case in args.case:
        records.append(run_case(case, settings, args.seed, getattr(args, f"checkpoint_{case}"), args.quiet))
    result = {"benchmark": "bench_surrogates", "settings": settings.to_dict(), "seed": args.seed,
              "bf16_bound": DEFAULT_BOUND, "cases": records, "machine": experiments.machine(),
              "wall_seconds": time.perf_counter() - start}
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    atomic_json(args.out, result)
    print(table(records))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
