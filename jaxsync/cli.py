"""The ``jaxsync`` command line: ``demo``, ``simulate`` and ``train``.

Errors of the package's own types are printed as one line (``error: ...``) with exit
status 2; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time


def _enable_x64() -> None:
    import jax

    jax.config.update("jax_enable_x64", True)


def _add_demo(subparsers) -> None:
    p = subparsers.add_parser(
        "demo", help="run the built-in cantilever end to end and print a summary",
        description="Run the paper's cantilever on the built-in coarse mesh (synchronized "
                    "single-device run), print a summary table and write the trajectory, "
                    "an XDMF time series and summary.json into --out.")
    p.add_argument("--out", default="jaxsync-demo", help="output folder (default: %(default)s)")
    p.add_argument("--steps", type=int, default=40000,
                   help="number of time steps (default: %(default)s, about 14 s of physical time)")
    p.add_argument("--save-every", type=int, default=100,
                   help="keep one snapshot every this many steps (default: %(default)s)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=_run_demo)


def _run_demo(args) -> int:
    import numpy as np

    from .problem import cantilever
    from .solver import simulate, steady_state

    problem = cantilever()
    os.makedirs(args.out, exist_ok=True)
    start = time.perf_counter()
    trajectory = simulate(problem, args.steps, save_every=args.save_every,
                          progress=not args.no_progress)
    elapsed = time.perf_counter() - start
    static = steady_state(problem)
    tip = int(np.argmax(np.where(np.isclose(problem.mesh.points[:, 0], problem.mesh.points[:, 0].max()),
                                 problem.mesh.points[:, 1] + problem.mesh.points[:, 2], -np.inf)))
    tip_z = np.asarray(trajectory.displacement[:, tip, 2])
    summary = {
        "problem": "cantilever (paper Table 1), built-in coarse mesh",
        "n_nodes": problem.mesh.n_nodes, "n_elements": problem.mesh.n_elements,
        "dt": problem.dt, "n_steps": args.steps, "n_synchronized": args.steps, "n_predicted": 0,
        "t_end": float(trajectory.times[-1]), "tip_node": tip,
        "tip_z_final": float(tip_z[-1]), "tip_z_min": float(tip_z.min()),
        "tip_z_static": float(static[tip, 2]),
        "us_per_step_synchronized": 1e6 * elapsed / max(args.steps, 1),
        "wall_seconds": elapsed,
    }
    trajectory.save(os.path.join(args.out, "trajectory.h5"))
    trajectory.to_xdmf(os.path.join(args.out, "trajectory.xdmf"))
    with open(os.path.join(args.out, "summary.json"), "w") as f:
        json.dump(summary, f, indent=2)
    rows = [("mesh", f"{summary['n_nodes']} nodes, {summary['n_elements']} tetrahedra"),
            ("time step (CFL)", f"{summary['dt']:.4e} s"),
            ("steps", f"{args.steps} (t = {summary['t_end']:.3f} s)"),
            ("tip z, final", f"{summary['tip_z_final']:.6e} cm"),
            ("tip z, most negative", f"{summary['tip_z_min']:.6e} cm"),
            ("tip z, static solution", f"{summary['tip_z_static']:.6e} cm"),
            ("time per step", f"{summary['us_per_step_synchronized']:.1f} us (incl. compile)"),
            ("output", os.path.abspath(args.out))]
    width = max(len(k) for k, _ in rows)
    print("jaxsync demo: synchronized cantilever")
    for k, v in rows:
        print(f"  {k:<{width}}  {v}")
    return 0


def _add_simulate(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate", help="run a problem described by a TOML file",
        description="Run the explicit solver on a problem described by a TOML file (default: "
                    "the packaged cantilever; see jaxsync.config for the layout). Command-line "
                    "options override the file's [run] and [mesh] entries.")
    p.add_argument("config", nargs="?", default=None,
                   help="TOML problem file (default: the packaged cantilever)")
    p.add_argument("--mesh", default=None, help="mesh file to use instead of [mesh]")
    p.add_argument("--steps", type=int, default=None, help="number of time steps ([run] n_steps)")
    p.add_argument("--save-every", type=int, default=None,
                   help="keep one snapshot every this many steps ([run] save_every)")
    p.add_argument("--dt", type=float, default=None, help="time step in s (default: CFL step)")
    p.add_argument("--output", "-o", default=None, help="HDF5 trajectory file ([run] output)")
    p.add_argument("--xdmf", default=None, help="also write an XDMF time series for ParaView")
    p.add_argument("--checkpoint", default=None,
                   help="resumable run: store the state here and continue from it if present")
    p.add_argument("--checkpoint-every", type=int, default=None,
                   help="steps between checkpoints (default: every compiled chunk)")
    p.add_argument("--partitions", type=int, default=None,
                   help="distributed run over this many METIS parts (default: single device)")
    p.add_argument("--mode", choices=("preassembled", "recompute"), default="preassembled",
                   help="internal force: stored sparse K, or element quantities formed every "
                        "step (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="METIS seed (default: %(default)s)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.add_argument("--print-config", action="store_true",
                   help="print the packaged default configuration and exit")
    p.set_defaults(func=_run_simulate)


def _run_simulate(args) -> int:
    from .config import default_config_path, load_config, problem_from_config
    from .errors import StabilityError
    from .solver import simulate

    if args.print_config:
        with open(default_config_path()) as f:
            sys.stdout.write(f.read())
        return 0
    problem, run = problem_from_config(load_config(args.config), mesh_file=args.mesh)
    n_steps = args.steps if args.steps is not None else run.n_steps
    save_every = args.save_every if args.save_every is not None else run.save_every
    output = args.output or run.output
    xdmf = args.xdmf or run.xdmf
    checkpoint = args.checkpoint or run.checkpoint
    print(problem.summary())
    start = time.perf_counter()
    try:
        trajectory = simulate(problem, n_steps, dt=args.dt if args.dt is not None else run.dt,
                              save_every=save_every, progress=not args.no_progress,
                              partitions=args.partitions, mode=args.mode, seed=args.seed,
                              checkpoint=checkpoint,
                              checkpoint_every=args.checkpoint_every or run.checkpoint_every)
    except StabilityError as exc:
        partial = getattr(exc, "trajectory", None)
        if partial is not None and partial.n_saved:
            root, ext = os.path.splitext(output)
            partial_path = f"{root}.partial{ext or '.h5'}"
            partial.save(partial_path)
            print(f"saved the {partial.n_saved} snapshots before divergence to {partial_path}",
                  file=sys.stderr)
        raise
    elapsed = time.perf_counter() - start
    trajectory.save(output)
    print(f"{n_steps} steps in {elapsed:.2f} s ({1e6 * elapsed / max(n_steps, 1):.1f} us/step); "
          f"wrote {output}")
    if xdmf:
        trajectory.to_xdmf(xdmf)
        print(f"wrote {xdmf}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The ``jaxsync`` argument parser with all subcommands."""
    from . import __version__

    parser = argparse.ArgumentParser(
        prog="jaxsync",
        description="Differentiable, distributed explicit FEM for linear elastodynamics on "
                    "tetrahedra, with LSTM surrogates that replace synchronization.")
    parser.add_argument("--version", action="version", version=f"jaxsync {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    _add_demo(subparsers)
    _add_simulate(subparsers)
    try:
        from .surrogate.cli import add_train_parser
    except ImportError:  # surrogate package not installed in this build
        pass
    else:
        add_train_parser(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``jaxsync`` console script."""
    from .errors import JaxsyncError

    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    _enable_x64()
    try:
        return int(args.func(args) or 0)
    except JaxsyncError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
