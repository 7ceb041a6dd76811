"""Solver-in-the-loop fine-tuning does it lower the long-horizon error?

For the demo case (coarse cantilever, 2 parts, n_s 150, n_p = n_f 20, 1e5 steps, trained on
the first half) and the skewed load (body force (0, -0.5, -0.5)), the paper-experiment
pipeline: the synchronized reference, ``train_surrogates`` with the library's defaults, the
synchronization-avoiding run over all 1e5 steps; then
:func:`jaxsync.solve.fine_tune_in_the_loop` on windows inside the training half
(n_s n_p synchronized steps, then ``--window-cycles`` refill cycles, against the
synchronized run), and the same online run with the fine-tuned networks. The errors are
those of the experiment matrix (``experiments.run_metrics``: free-end max and final error,
interior noise, relative L2 over the run), measured over the whole run: the second half was never seen by either
training.

Usage:
    python benchmarks/bench_finetune.py [--case default skewed] [--iterations 60]
        [--window-cycles 2] [--learning-rate 1e-4] [--seed 0] [--quick]
        [--out benchmarks/results/finetune.json]

``--quick``: 3 000 steps, n_s 10, n_p = n_f 5, a tiny network trained 2 epochs, 4
fine-tuning iterations (the test's smoke run; its numbers mean nothing).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import experiments  # noqa: E402  (the settings, cases and metrics of the experiment matrix)

import jaxsync  # noqa: E402
from jaxsync.io import atomic_json  # noqa: E402
from jaxsync.solve import FineTuneConfig, fine_tune_in_the_loop  # noqa: E402
from jaxsync.surrogate import Surrogate  # noqa: E402

DEFAULT_OUT = os.path.join(HERE, "results", "finetune.json")
FORCES = experiments.BODY_FORCES


def sizes_of(quick: bool):
    """The experiment matrix's settings (``experiments.py``: the paper's, or the tests'
    reduced ones): steps, n_s, n_p, n_f, save_every, the training span and overrides."""
    return experiments.reduced_settings(2) if quick else experiments.paper_settings()


def metrics_of(problem, parts, reference, online, tip):
    excluded = experiments.excluded_nodes(problem, parts)
    m = experiments.run_metrics(reference.displacement, online.displacement, tip, excluded)
    return {k: m[k] for k in ("tip_max_error_relative", "tip_final_error_relative", "l2_relative",
                              "l2_relative_final", "interior_max_error_relative")}


def run_case(name: str, sizes, config: FineTuneConfig, seed: int, progress: bool) -> dict:
    problem = jaxsync.cantilever(body_force=FORCES[name])
    parts = jaxsync.partition(problem.mesh, 2, seed=seed)
    tip = experiments.check_tip(problem.mesh, parts)
    n_cri = sizes.n_s * sizes.n_past
    print(f"[{name}] synchronized reference: {sizes.n_steps} steps", flush=True)
    reference = jaxsync.simulate(problem, sizes.n_steps, partitions=parts, save=jaxsync.SaveAt(sizes.save_every, 1),
                                 executor=jaxsync.HostExecutor(progress=progress))
    print(f"[{name}] training (library defaults)", flush=True)
    (trained, training), train_seconds = experiments.timed(
        experiments.train, reference, dict(n_s=sizes.n_s, n_past=sizes.n_past, n_future=sizes.n_future,
                                           train_fraction=sizes.train_fraction, seed=seed),
        overrides=sizes.train_overrides, progress=progress)
    if training["rollout_warning"]:
        print(f"[{name}] {training['rollout_warning']}", flush=True)
    surrogate = Surrogate.from_saved(trained.saved)

    def online(s):
        return experiments.timed(jaxsync.simulate_sync_avoiding, problem, sizes.n_steps, partitions=parts,
                                 surrogates=s, n_cri=n_cri, save=sizes.save_every,
                                 executor=jaxsync.HostExecutor(progress=progress))

    print(f"[{name}] online run, trained networks", flush=True)
    before, before_seconds = online(surrogate)
    print(f"[{name}] fine-tuning in the loop ({config.n_iterations} windows of {config.window_cycles} cycles)",
          flush=True)
    span = int(sizes.train_fraction * sizes.n_steps)  # the steps the networks were trained on
    tuned = fine_tune_in_the_loop(problem, surrogate, parts, n_steps=span, config=config, progress=progress)
    print(f"[{name}] online run, fine-tuned networks", flush=True)
    after, after_seconds = online(tuned.surrogate)
    sized = {k: getattr(sizes, k) for k in ("n_steps", "n_s", "n_past", "n_future", "save_every",
                                             "train_fraction")}
    return {"case": name, "body_force": list(FORCES[name]),
            "sizes": sized | {"train_overrides": sorted(sizes.train_overrides)},
            "train_seconds": train_seconds, "fine_tune": tuned.summary(),
            "fine_tune_loss_history": tuned.loss_history.tolist(),
            "before": metrics_of(problem, parts, reference, before, tip) | {"online_seconds": before_seconds},
            "after": metrics_of(problem, parts, reference, after, tip) | {"online_seconds": after_seconds}}


def table(rows) -> str:
    head = ("| case | free end max % | final % | interior % | L2 % | window loss kept/start | fine-tune s "
            "| training s |\n|---|---|---|---|---|---|---|---|")
    lines = [head]
    for r in rows:
        b, a = r["before"], r["after"]

        def pair(key):
            return f"{100 * b[key]:.3g} -> {100 * a[key]:.3g}"

        lines.append(f"| {r['case']} | {pair('tip_max_error_relative')} | {pair('tip_final_error_relative')} | "
                     f"{pair('interior_max_error_relative')} | {pair('l2_relative')} | "
                     f"{r['fine_tune']['improvement']:.3f} (iteration {r['fine_tune']['best_iteration']}) | "
                     f"{r['fine_tune']['seconds']:.0f} | {r['train_seconds']:.0f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", nargs="+", choices=sorted(FORCES), default=["default", "skewed"])
    parser.add_argument("--iterations", type=int, default=None, help="fine-tuning windows (default 60; quick 4)")
    parser.add_argument("--window-cycles", type=int, default=2)
    parser.add_argument("--learning-rate", type=float, default=FineTuneConfig.learning_rate)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--quiet", action="store_true")
    parser.add_argument("--out", default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    sizes = sizes_of(args.quick)
    iterations = args.iterations or (4 if args.quick else FineTuneConfig.n_iterations)
    config = FineTuneConfig(n_iterations=iterations, window_cycles=args.window_cycles,
                            learning_rate=args.learning_rate, seed=args.seed,
                            validate_every=min(FineTuneConfig.validate_every, iterations),
                            **({"n_starts": 6, "n_validation": 2} if args.quick else {}))
    rows = [run_case(name, sizes, config, args.seed, not args.quiet) for name in args.case]
    text = table(rows)
    print(text)
    atomic_json(args.out, {"rows": rows, "config": dataclasses.asdict(config), "quick": args.quick,
                           "machine": experiments.machine(), "table": text})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
