"""The ``jaxsync`` command line: ``demo``, ``simulate``, ``train``, ``predict``, ``report``.

Errors of the package's own types are printed as one line (``error: ...``) with exit
status 2; anything else is a bug and keeps its traceback.

Under ``mpiexec -n N`` (N > 1, detected from the launcher's environment) every rank joins
the others through ``jax.distributed`` before using JAX (:mod:`jaxsync.multiprocess`),
only rank 0 prints and writes files, and an error on any rank ends the whole job with a
non-zero status (the error is printed with its rank) instead of leaving the others waiting.
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
        "demo", help="run the whole pipeline on the built-in cantilever and print a summary",
        description="The paper's pipeline on the built-in coarse cantilever with two parts: "
                    "synchronized distributed run, training of one LSTM surrogate per part, "
                    "synchronization-avoiding run, report. Prints a summary table and writes "
                    "trajectories, the checkpoint, figures and summary.json into --out. The "
                    "default schedule takes a few minutes on a 2-core laptop.")
    p.add_argument("--out", default="jaxsync-demo", help="output folder (default: %(default)s)")
    p.add_argument("--steps", type=int, default=100000,
                   help="time steps of both runs (default: %(default)s, 35 s of physical time as "
                        "in the paper)")
    p.add_argument("--parts", type=int, default=2, help="number of parts (default: %(default)s)")
    p.add_argument("--n-s", type=int, default=80, help="sampling stride n_s (default: %(default)s)")
    p.add_argument("--n-past", type=int, default=20, help="input snapshots n_p (default: %(default)s)")
    p.add_argument("--n-future", type=int, default=20,
                   help="predicted snapshots n_f (default: %(default)s)")
    p.add_argument("--hidden", type=int, default=32, help="LSTM hidden size n_H (default: %(default)s)")
    p.add_argument("--layers", type=int, default=2,
                   help="bidirectional encoder layers (default: %(default)s)")
    p.add_argument("--epochs", type=int, default=300, help="training epochs (default: %(default)s)")
    p.add_argument("--eta0", type=float, default=2e-3,
                   help="initial learning rate (default: %(default)s)")
    p.add_argument("--gamma", type=float, default=0.995,
                   help="per-epoch learning-rate decay (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of METIS, initialization and shuffling (default: %(default)s)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    p.set_defaults(func=_run_demo)


def _run_demo(args) -> int:
    from .demo import format_summary, run_demo
    from .errors import ConfigError

    if _process_count() > 1:
        raise ConfigError("jaxsync demo runs in one process (it uses emulated devices); "
                          "start it without mpiexec")
    summary = run_demo(args.out, n_steps=args.steps, n_parts=args.parts, n_s=args.n_s,
                       n_past=args.n_past, n_future=args.n_future, hidden=args.hidden,
                       layers=args.layers, epochs=args.epochs, eta0=args.eta0, gamma=args.gamma,
                       seed=args.seed, progress=not args.no_progress)
    print("jaxsync demo: synchronization-avoiding cantilever")
    print(format_summary(summary))
    print(f"  summary written to {os.path.abspath(os.path.join(args.out, 'summary.json'))}")
    return 0


def _add_predict(subparsers) -> None:
    p = subparsers.add_parser(
        "predict", help="synchronization-avoiding run with trained surrogates",
        description="Run paper Algorithm 3: synchronized steps up to --n-cri, then the "
                    "surrogates of CHECKPOINT replace the synchronization. The partition is the "
                    "one of TRAJECTORY (the synchronized run the surrogates were trained on); "
                    "the problem comes from a TOML file (default: the packaged cantilever).")
    p.add_argument("trajectory", help="synchronized distributed trajectory (HDF5) that defines "
                                      "the partition")
    p.add_argument("checkpoint", help="surrogate checkpoint written by jaxsync train")
    p.add_argument("--config", default=None, help="TOML problem file (default: the cantilever)")
    p.add_argument("--mesh", default=None, help="mesh file to use instead of the config's")
    p.add_argument("--n-cri", type=int, default=None,
                   help="last synchronized step (default and minimum: n_p n_s + 1)")
    p.add_argument("--steps", type=int, default=None,
                   help="total steps (default: as many as the trajectory holds)")
    p.add_argument("--save-every", type=int, default=1,
                   help="snapshot stride; must divide n_cri and n_s n_f (default: %(default)s)")
    p.add_argument("--mode", choices=("preassembled", "recompute"), default="preassembled",
                   help="internal force formulation (default: %(default)s)")
    p.add_argument("--cond", type=float, default=None,
                   help="load parameter for conditional surrogates")
    p.add_argument("--resync-tolerance", type=float, default=None, metavar="CM",
                   help="re-synchronize for n_p n_s steps whenever es_hat, the parts' "
                        "disagreement at shared nodes (paper eq. 26), exceeds this many cm "
                        "(default: never)")
    p.add_argument("--output", "-o", default="online.h5", help="output trajectory (default: %(default)s)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=_run_predict)


def _run_predict(args) -> int:
    import numpy as np

    from .config import load_config, problem_from_config
    from .errors import PartitionError
    from .partition import partition_of
    from .surrogate.checkpoint import load_checkpoint
    from .syncavoid import simulate_sync_avoiding
    from .trajectory import Trajectory

    reference = Trajectory.load(args.trajectory)
    part = partition_of(reference)
    problem, _ = problem_from_config(load_config(args.config), mesh_file=args.mesh)
    if (problem.mesh.n_nodes != reference.mesh.n_nodes
            or not np.array_equal(problem.mesh.tets, reference.mesh.tets)):
        raise PartitionError(f"the problem's mesh differs from the mesh of {args.trajectory}; "
                             "pass the same --config/--mesh as the synchronized run")
    ckpt = load_checkpoint(args.checkpoint, [p.shared_nodes for p in part.parts])
    n_cri = args.n_cri or ckpt.n_s * ckpt.arch.n_past + 1
    n_steps = args.steps or int(round(float(reference.times[-1]) / reference.dt))
    online = simulate_sync_avoiding(problem, n_steps, partitions=part, surrogates=ckpt, n_cri=n_cri,
                                    dt=reference.dt, mode=args.mode, save_every=args.save_every,
                                    cond=args.cond, progress=not args.no_progress,
                                    resync_tolerance=args.resync_tolerance)
    online.save(args.output)
    resynced = online.parameters.get("resynchronized_at", [])
    print(f"{n_steps} steps ({n_cri} synchronized, {n_steps - n_cri} predicted"
          + (f"; re-synchronized {len(resynced)} times, at steps {list(resynced)}" if resynced else "")
          + f"); {online.parameters['us_per_step_predicted']:.1f} us per predicted step; wrote {args.output}")
    return 0


def _add_report(subparsers) -> None:
    p = subparsers.add_parser(
        "report", help="figures and summary.json comparing an online run with the synchronized one",
        description="Compare a synchronization-avoiding trajectory (jaxsync predict) with the "
                    "synchronized reference: displacement at chosen nodes, e_l2(t), es and "
                    "es_hat, et histograms (PNG) and summary.json.")
    p.add_argument("reference", help="synchronized trajectory (HDF5)")
    p.add_argument("online", help="synchronization-avoiding trajectory (HDF5)")
    p.add_argument("--out", "-o", default="report", help="output folder (default: %(default)s)")
    p.add_argument("--component", type=int, choices=(0, 1, 2), default=2,
                   help="displacement component of the node figure (default: %(default)s = z)")
    p.set_defaults(func=_run_report)


def _run_report(args) -> int:
    import dataclasses

    import numpy as np

    from .errors import CheckpointError
    from .partition import partition_of
    from .plots import write_report
    from .trajectory import Trajectory

    reference = Trajectory.load(args.reference)
    online = Trajectory.load(args.online)
    if online.synchronized is None:
        raise CheckpointError(f"{args.online} is not a synchronization-avoiding trajectory")
    stride, rest = divmod(online.save_every, reference.save_every)
    if rest or abs(online.dt - reference.dt) > 1e-12 * reference.dt:
        raise CheckpointError("the two trajectories do not share time steps (dt and save_every "
                              "must match, the reference saved at least as often)")
    n = online.n_saved
    if reference.n_saved < (n - 1) * stride + 1:
        raise CheckpointError(f"{args.reference} is shorter than {args.online}")
    reference = dataclasses.replace(reference, times=reference.times[:(n - 1) * stride + 1:stride],
                                    displacement=reference.displacement[:(n - 1) * stride + 1:stride],
                                    save_every=online.save_every)
    # nodes that never move (clamped) are left out of the node figure
    still = np.flatnonzero(np.all(np.asarray(reference.displacement) == 0.0, axis=(0, 2)))
    summary = write_report(reference, online, partition_of(online), args.out,
                           component=args.component, fixed_nodes=still,
                           extra={k: v for k, v in online.parameters.items() if k.startswith("us_")})
    print(f"wrote figures and summary.json to {os.path.abspath(args.out)}; free-end max |error| "
          f"{summary['tip_max_abs_error']:.3e} cm, e_l2 at the end {summary['l2_error_final']:.3e} cm")
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
                   help="distributed run over this many METIS parts (default: single device; "
                        "under mpiexec -n N: N parts, one per process)")
    p.add_argument("--sync", choices=("psum", "ppermute", "mpi"), default=None,
                   help="how parts sum shared-node forces every step: XLA psum of the whole "
                        "interface (emulated devices, gloo between processes, NCCL between "
                        "GPUs), XLA ppermute exchange of the nodes neighbouring devices share, "
                        "or an MPI Allreduce inside the compiled step, one device per process "
                        "(default: mpi across processes, psum in one process)")
    p.add_argument("--mode", choices=("preassembled", "recompute"), default="preassembled",
                   help="internal force: stored sparse K, or element quantities formed every "
                        "step (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="METIS seed (default: %(default)s)")
    p.add_argument("--timings", nargs="?", const="", default=None, metavar="JSON",
                   help="instead of running, measure the per-step breakdown t_e, t_m, t_s, t_t "
                        "(paper section 7; max-average over parts), print the table and write it "
                        "as JSON (default file: <output>.timings.json)")
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
    if args.timings is not None:
        from .timing import timing_breakdown

        report = timing_breakdown(problem, args.partitions or 1, mode=args.mode,
                                  dt=args.dt if args.dt is not None else run.dt, seed=args.seed)
        if _is_main_process():
            print(report.table())
            path = args.timings or os.path.splitext(output)[0] + ".timings.json"
            report.save_json(path)
            print(f"wrote {path}")
        return 0
    main_rank = _is_main_process()
    n_processes = _process_count()
    partitions = args.partitions
    if partitions is None and n_processes > 1:
        partitions = n_processes  # one part per process
    # passed only when asked for, so that simulate() keeps its own default
    sync = {} if args.sync is None else {"sync": args.sync}
    if main_rank:
        print(problem.summary())
        if n_processes > 1:
            print(f"{n_processes} processes, {partitions} parts")
    start = time.perf_counter()
    try:
        trajectory = simulate(problem, n_steps, dt=args.dt if args.dt is not None else run.dt,
                              save_every=save_every, progress=main_rank and not args.no_progress,
                              partitions=partitions, mode=args.mode, seed=args.seed,
                              checkpoint=checkpoint,
                              checkpoint_every=args.checkpoint_every or run.checkpoint_every,
                              **sync)
    except StabilityError as exc:
        partial = getattr(exc, "trajectory", None)
        if not main_rank:
            _barrier()  # let rank 0 write the partial trajectory before the job ends
            raise
        if partial is not None and partial.n_saved:
            root, ext = os.path.splitext(output)
            partial_path = f"{root}.partial{ext or '.h5'}"
            partial.save(partial_path)
            print(f"saved the {partial.n_saved} snapshots before divergence to {partial_path}",
                  file=sys.stderr)
        _barrier()
        raise
    elapsed = time.perf_counter() - start
    if not main_rank:  # rank 0 writes and prints
        return 0
    trajectory.save(output)
    print(f"{n_steps} steps in {elapsed:.2f} s ({1e6 * elapsed / max(n_steps, 1):.1f} us/step); "
          f"wrote {output}")
    if xdmf:
        trajectory.to_xdmf(xdmf)
        print(f"wrote {xdmf}")
    return 0


def _process_count() -> int:
    from .multiprocess import process_count

    return process_count()


def _is_main_process() -> bool:
    from .multiprocess import is_main_process

    return is_main_process()


def _barrier() -> None:
    """Wait for all processes (a no-op in a single-process run)."""
    if _process_count() > 1:
        from .multiprocess import world

        world().Barrier()


def build_parser() -> argparse.ArgumentParser:
    """The ``jaxsync`` argument parser with all subcommands."""
    from . import __version__

    parser = argparse.ArgumentParser(
        prog="jaxsync",
        description="Differentiable, distributed explicit FEM for linear elastodynamics on "
                    "tetrahedra, with LSTM surrogates that replace synchronization.")
    parser.add_argument("--version", action="version", version=f"jaxsync {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    from .surrogate.cli import add_train_parser

    _add_demo(subparsers)
    _add_simulate(subparsers)
    add_train_parser(subparsers)
    _add_predict(subparsers)
    _add_report(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``jaxsync`` console script."""
    from .errors import JaxsyncError

    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    from .multiprocess import abort_on_error, initialize, launched_by_mpi

    if launched_by_mpi():  # mpiexec -n N, N > 1: join the others before any JAX use
        with abort_on_error():
            initialize()
            _enable_x64()
            return int(args.func(args) or 0)
    _enable_x64()
    try:
        return int(args.func(args) or 0)
    except JaxsyncError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
