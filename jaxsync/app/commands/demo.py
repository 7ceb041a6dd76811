"""``jaxsync demo``: the whole pipeline on the built-in cantilever (:mod:`jaxsync.app.demo`)."""

from __future__ import annotations

import os

from . import common


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "demo", help="run the whole pipeline on the built-in cantilever and print a summary",
        description="The paper's pipeline on the built-in coarse cantilever with two parts: "
                    "synchronized distributed run, training of one LSTM surrogate per part, "
                    "synchronization-avoiding run, report. Prints a summary table and writes "
                    "trajectories, the checkpoint, figures and summary.json into --out. The "
                    "default schedule takes a few minutes on a 2-core laptop.")
    p.add_argument("--out", "-o", default="jaxsync-demo", help="output folder (default: %(default)s)")
    p.add_argument("--steps", type=int, default=100000,
                   help="time steps of both runs (default: %(default)s, 35 s of physical time as "
                        "in the paper)")
    p.add_argument("--parts", type=int, default=2, help="number of parts (default: %(default)s)")
    common.add_surrogate_options(p)
    p.add_argument("--epochs", type=int, default=common.surrogate_defaults()["epochs"],
                   help="training epochs (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of METIS, initialization and shuffling (default: %(default)s)")
    p.add_argument("--save-every", type=int, default=None,
                   help="full-field snapshot stride of both runs; divides n_s n_p and n_s n_f "
                        "(default: n_s; the parts' shared nodes are kept at every step)")
    common.add_resync_tolerance_option(p, help="error control of the predicted run (see jaxsync predict --help)")
    common.add_progress_option(p, "the progress bars")
    p.set_defaults(func=run)


def run(args) -> int:
    from ...errors import ConfigError
    from ..demo import format_summary, run_demo

    if common.process_count() > 1:
        raise ConfigError("jaxsync demo runs in one process (it uses emulated devices); "
                          "start it without mpiexec")
    summary = run_demo(args.out, n_steps=args.steps, n_parts=args.parts, n_s=args.n_s,
                       n_past=args.n_past, n_future=args.n_future, n_hidden=args.n_hidden,
                       n_layers=args.n_layers, epochs=args.epochs, eta0=args.eta0, gamma=args.gamma,
                       seed=args.seed, save_every=args.save_every,
                       resync_tolerance=args.resync_tolerance, progress=not args.no_progress)
    print("jaxsync demo: synchronization-avoiding cantilever")
    print(format_summary(summary))
    print(f"  summary written to {os.path.abspath(os.path.join(args.out, 'summary.json'))}")
    return 0
