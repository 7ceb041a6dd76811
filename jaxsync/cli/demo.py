"""``jaxsync demo``: the whole pipeline on the built-in cantilever or the generated coronary
tree (:mod:`jaxsync.app.demo`)."""

from __future__ import annotations

import argparse
import os

from . import common


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "demo", help="run the whole pipeline on the built-in cantilever (or --case vessel) and print a summary",
        description="The paper's pipeline: synchronized distributed run, training of one LSTM surrogate per "
                    "part, synchronization-avoiding run under error control at 1 %, report. --case cantilever "
                    "(default): the built-in coarse cantilever with two parts, a few minutes on a 2-core laptop. "
                    "--case vessel: the paper's coronary case on a generated coronary tree with 11 parts, mass "
                    "scaling (with the check of paper figure 19) and error control at 1 %; --size small (default, "
                    "about 5 000 tets, about 15 minutes on a 2-core laptop) or paper (about 250 000 "
                    "dofs and 1e6 steps: hours to days); before its first stage the vessel prints how long the run "
                    "will take on this machine, from short timed pieces of it. Prints a summary table and writes "
                    "trajectories, the surrogate file, figures and summary.json into --out; a folder that holds an "
                    "earlier demo is replaced only with --force, and only once the new run is complete.")
    p.add_argument("--case", choices=("cantilever", "vessel"), default="cantilever",
                   help="the problem (default: %(default)s)")
    p.add_argument("--size", default="small",
                   help="vessel only: small, paper, or a target tetrahedron count (default: %(default)s)")
    p.add_argument("--out", "-o", default="jaxsync-demo", help="output folder (default: %(default)s)")
    p.add_argument("--force", action="store_true",
                   help="replace the files of an earlier demo in --out (without it the run is refused "
                        "before it starts); the new files take their place only when the run is complete")
    p.add_argument("--steps", type=int, default=None,
                   help="time steps of both runs (default: the case's; cantilever 100000, 35 s as in the "
                        "paper; vessel small 500000, about 3.9 s; vessel paper 1000000, 5 s as in the paper)")
    p.add_argument("--parts", type=int, default=None,
                   help="number of parts (default: the case's; cantilever 2, vessel 11 as in the paper)")
    common.add_surrogate_options(p, case_defaults=True)
    p.add_argument("--train-fraction", type=float, default=None,
                   help="the leading fraction of the synchronized run the surrogates train on; the summary "
                        "measures the errors after it (out_of_sample) as well (default: 0.5)")
    p.add_argument("--epochs", type=int, default=None,
                   help="training epochs (default: the case's; cantilever 800, vessel 300)")
    p.add_argument("--candidates", dest="n_candidates", type=int, default=None,
                   help="networks trained per part, the lowest validation loss kept (default: the case's; "
                        "cantilever 2, vessel 1)")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of METIS, initialization and shuffling (default: %(default)s)")
    p.add_argument("--save-every", type=int, default=None,
                   help="full-field snapshot stride of both runs; divides n_s n_p and n_s n_f "
                        "(default: n_s; the cantilever keeps the parts' shared nodes at every step)")
    p.add_argument("--load-input", dest="load_input", action=argparse.BooleanOptionalAction, default=None,
                   help="feed the surrogates the known load signals, as jaxsync train does (default: on, the "
                        "synchronized run records them); --no-load-input trains the load-blind surrogates")
    p.add_argument("--highway", action=argparse.BooleanOptionalAction, default=None,
                   help="give the LSTM surrogates a linear highway, as jaxsync train --highway does (default: "
                        "jaxsync train's)")
    p.add_argument("--resync-tolerance", default="default", metavar="CM|PCT%|none",
                   help="error control of the predicted run (see jaxsync predict --help); none turns it "
                        "off (default: 1%% of the synchronized run's largest shared-node displacement)")
    common.add_progress_option(p, "the progress bars")
    p.set_defaults(func=run)


def demo_parts(args) -> int:
    """The parts the demo runs, read without starting JAX (for the emulated devices)."""
    if args.parts is not None:
        return int(args.parts)
    return 11 if args.case == "vessel" else 2


def run(args) -> int:
    from ..app.demo import DemoSettings, format_summary, run_demo
    from ..errors import ConfigError

    if common.process_count() > 1:
        raise ConfigError("jaxsync demo runs in one process (it uses emulated devices); "
                          "start it without mpiexec")
    tolerance = None if str(args.resync_tolerance).lower() == "none" else args.resync_tolerance
    settings = DemoSettings(n_steps=args.steps, n_parts=args.parts, n_s=args.n_s, n_past=args.n_past,
                            n_future=args.n_future, n_hidden=args.n_hidden, n_layers=args.n_layers,
                            train_fraction=args.train_fraction, epochs=args.epochs, eta0=args.eta0,
                            gamma=args.gamma, n_candidates=args.n_candidates,
                            save_every=args.save_every, resync_tolerance=tolerance, load_input=args.load_input,
                            highway=args.highway)
    summary = run_demo(args.out, settings, case=args.case, size=args.size, seed=args.seed,
                       progress=not args.no_progress, force=args.force)
    what = "cantilever" if args.case == "cantilever" else f"coronary tree ({summary['n_elements']} tets)"
    print(f"jaxsync demo: synchronization-avoiding {what}")
    print(format_summary(summary))
    print(f"  summary written to {os.path.abspath(os.path.join(args.out, 'summary.json'))}")
    return 0
