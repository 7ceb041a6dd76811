"""``jaxsync simulate``: run the explicit solver on a problem described by a TOML file
(:mod:`jaxsync.app.config`), on one device or distributed over parts; or, with
``--timings``, measure the per-step cost breakdown instead of running."""

from __future__ import annotations

import argparse
import os
import sys
import time

from ..options import Element, choices
from . import common


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate", help="run a problem described by a TOML file",
        description="Run the explicit solver on a problem described by a TOML file (default: "
                    "the packaged cantilever; see jaxsync.app.config for the layout). Command-line "
                    "options override the file's [run] and [mesh] entries; relative paths on the "
                    "command line are taken from the current directory, those in the file from "
                    "the file's folder. Existing output files are never overwritten without "
                    "--force.")
    common.accept_negative_numbers(p)
    p.add_argument("config", nargs="?", default=None,
                   help="TOML problem file (default: the packaged cantilever)")
    p.add_argument("--mesh", default=None,
                   help="mesh file, or SimVascular mesh folder (mesh-complete.mesh.vtu and "
                        "mesh-surfaces/*.vtp, one facet set per face), to use instead of [mesh]")
    p.add_argument("--element", choices=choices(Element), default=None,
                   help="finite element ([problem] element): P1 linear or P2 quadratic tetrahedra (P2 for "
                        "bending and nearly incompressible tissue, nu >= 0.45; default: P2 on a quadratic "
                        "tetra10 mesh, else P1)")
    p.add_argument("--steps", type=int, default=None, help="number of time steps ([run] n_steps)")
    p.add_argument("--save-every", type=int, default=None,
                   help="keep one snapshot every this many steps ([run] save_every)")
    p.add_argument("--shared-every", type=int, default=None,
                   help="distributed runs: keep each part's shared-node displacements every this "
                        "many steps, a divisor of --save-every (default: --save-every); surrogate "
                        "training (jaxsync train) needs 1, while the full field can stay thinned")
    common.add_compression_option(p)
    p.add_argument("--dt", type=float, default=None,
                   help="time step in s ([run] dt; default: the CFL step of the problem, after "
                        "mass scaling if any); must be positive and below the stability bound")
    scaling = p.add_mutually_exclusive_group()
    scaling.add_argument("--mass-scaling-dt", type=float, default=None, metavar="S",
                         help="artificial mass scaling (paper Algorithm 2): make every element "
                              "stable at this step in s, and run at it (at the CFL step where that is larger) "
                              "unless --dt is given "
                              "([run] mass_scaling_dt); the added mass is printed, with a warning "
                              "above 10 %%")
    scaling.add_argument("--mass-scaling-beta", type=float, default=None, metavar="B",
                         help="mass scaling to B times the CFL step ([run] mass_scaling_beta)")
    p.add_argument("--output", "-o", default=None,
                   help="HDF5 trajectory file ([run] output); with -o, an XDMF output the file "
                        "asks for ([run] xdmf) is named after it: <stem>.xdmf")
    p.add_argument("--xdmf", default=None, help="also write an XDMF time series for ParaView")
    p.add_argument("--vtu", default=None, metavar="PREFIX",
                   help="also write a VTU series for ParaView ([run] vtu): PREFIX.pvd and one "
                        "PREFIX/<name>_NNNNNN.vtu per snapshot (displacement and GlobalNodeID); "
                        "with -o, a VTU output the file asks for is named after it")
    p.add_argument("--force", action="store_true",
                   help="overwrite existing output files (trajectory, XDMF and its .xdmf.h5, "
                        "VTU series, timings JSON); without it the run is refused before it starts, except "
                        "when it resumes from an existing --checkpoint: it then continues the "
                        "run that wrote those outputs and replaces them")
    p.add_argument("--checkpoint", default=None,
                   help="resumable run: store the state here and continue from it if present "
                        "(a checkpoint of another problem, or altered after it was written, is "
                        "refused: delete it to start over)")
    p.add_argument("--checkpoint-every", type=int, default=None,
                   help="steps between checkpoints (default: every compiled chunk)")
    p.add_argument("--parts", type=int, default=None,
                   help="distributed run over this many METIS parts (default: single device; "
                        "under mpiexec -n N: N parts, one per process)")
    # the option's name before `--parts` became the one name of a part count everywhere
    p.add_argument("--partitions", dest="parts", type=int, help=argparse.SUPPRESS)
    common.add_sync_option(p, deep_halos=True)
    common.add_mode_option(p)
    p.add_argument("--seed", type=int, default=0, help="METIS seed (default: %(default)s)")
    p.add_argument("--timings", nargs="?", const="", default=None, metavar="JSON",
                   help="instead of running, measure the per-step breakdown t_e, t_m, t_s, t_t "
                        "(paper section 7; max-average over parts), print the table and write it "
                        "as JSON (default file: <output>.timings.json)")
    common.add_progress_option(p)
    p.add_argument("--print-config", action="store_true",
                   help="print the packaged default configuration and exit")
    p.set_defaults(func=run)


FORMAT_OPTIONS = (("xdmf", "--xdmf"), ("vtu", "--vtu"))
"""The output formats ``jaxsync simulate`` writes besides the trajectory: (the name of the
writer in :mod:`jaxsync.io.writers`, its command-line option); the ``[run]`` key of each is
the writer's name."""


def outputs(args, config: dict) -> tuple[str, str | None, bool]:
    """(trajectory path, checkpoint path or None, resuming) of a ``jaxsync simulate`` run,
    from the command line over the (path-resolved) config."""
    from ..app.config import RunConfig

    run_table = config.get("run", {})
    output = args.output or run_table.get("output", RunConfig.output)
    checkpoint = args.checkpoint or run_table.get("checkpoint")
    return output, checkpoint, bool(checkpoint) and os.path.exists(checkpoint)


def format_outputs(args, config: dict) -> list[tuple[str, object, str, tuple]]:
    """(option, writer, path, :class:`jaxsync.io.OutputFile` s) of each output format a
    ``jaxsync simulate`` run writes (:data:`FORMAT_OPTIONS`), from the command line over
    the (path-resolved) config. An output that the file asks for is named after ``-o``
    when that is given (``-o out/b.h5``: ``out/b.xdmf``, ``out/b.pvd``), so that two runs of
    one file with different ``-o`` keep their own."""
    from ..io.writers import writer_for

    run_table = config.get("run", {})
    found = []
    for name, option in FORMAT_OPTIONS:
        writer = writer_for(name)
        path = getattr(args, name)
        if not path and run_table.get(name):
            path = os.path.splitext(args.output)[0] + writer.suffixes[0] if args.output else run_table[name]
        if path:
            files = tuple(writer.outputs(path))  # a location the writer refuses is refused here
            found.append((option, writer, files[-1].path, files))
    return found


def report_warnings(caught) -> None:
    """Show warnings recorded while building the problem
    (:func:`jaxsync.cli.common.report_warnings`: the package's own as one
    ``warning: ...`` line on stderr, any other as Python shows it)."""
    common.report_warnings(caught)


def check_locations(output, checkpoint, timings_path=None, formats=()) -> None:
    """Refuse, before anything runs, output locations that cannot be written
    (``formats``: :func:`format_outputs`)."""
    if timings_path is not None:
        common.check_outputs((timings_path, "timings JSON", "--timings"))
        return
    common.check_outputs((output, "trajectory", "-o"),
                         *((f.path, f.what, option, f.folder) for option, _, _, files in formats for f in files),
                         (checkpoint, "checkpoint", "--checkpoint"))


def partial_output(output: str, *, force: bool = False) -> str:
    """Where a diverged run keeps its snapshots: ``<output stem>.partial.h5``; without
    ``force`` an existing one (an earlier run's) is kept and the next free name
    ``<stem>.partial-2.h5``, ``-3``... is used."""
    root, ext = os.path.splitext(output)
    ext = ext or ".h5"
    path, k = f"{root}.partial{ext}", 1
    while not force and os.path.lexists(path):
        k += 1
        path = f"{root}.partial-{k}{ext}"
    return path


def checkpoint_step(checkpoint: str | None) -> int:
    """The step a run resumes from: that of the solver checkpoint ``checkpoint`` (0 when
    there is none, or it is not one: the solver then refuses it with the reason)."""
    if not checkpoint or not os.path.exists(checkpoint):
        return 0
    from ..io.checkpoint import committed_step

    return committed_step(checkpoint) or 0


def devices_text(st, parts) -> str:
    """``2 cpu devices in 2 processes, emulated, 2 parts per device`` from a run's
    statistics (``n_devices``: every process's devices together)."""
    n_devices = int(st.n_devices or 1)
    n_processes = int(getattr(st, "n_processes", None) or 1)
    text = f"{n_devices} {st.device_kind} device{'s' if n_devices > 1 else ''}"
    if n_processes > 1:
        text += f" in {n_processes} processes"
    if st.emulated:
        text += ", emulated"
    if parts and parts > n_devices:
        text += f", {parts // n_devices} parts per device"
    return text


def run(args) -> int:
    import warnings

    from ..app.config import default_config_path, load_config, problem_from_config

    if args.print_config:
        with open(default_config_path()) as f:
            sys.stdout.write(f.read())
        return 0
    main_rank = common.is_main_process()
    config = load_config(args.config)
    output, checkpoint, resuming = outputs(args, config)
    if args.checkpoint_every is not None and not checkpoint:
        from ..errors import ConfigError

        raise ConfigError(f"--checkpoint-every {args.checkpoint_every} needs a checkpoint file: add --checkpoint "
                          "PATH (or [run] checkpoint in the configuration)")
    formats = format_outputs(args, config) if args.timings is None else []
    inputs = [args.config, args.mesh, config.get("mesh", {}).get("file")]  # never written over
    if args.timings is not None:
        timings_path = args.timings or os.path.splitext(output)[0] + ".timings.json"
        if main_rank:
            check_locations(output, checkpoint, timings_path)
            common.refuse_to_overwrite([timings_path], force=args.force, inputs=inputs, options="--timings")
    elif main_rank:  # the writer; checked before the mesh is read and anything runs
        check_locations(output, checkpoint, formats=formats)
        common.refuse_to_overwrite([output] + [f.path for *_, files in formats for f in files],
                                   force=args.force or resuming, checkpoint=checkpoint, inputs=inputs,
                                   options="/".join(["-o"] + [option for _, option in FORMAT_OPTIONS]))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        problem, run_config = problem_from_config(config, mesh_file=args.mesh,
                                                  mass_scaling_dt=args.mass_scaling_dt,
                                                  mass_scaling_beta=args.mass_scaling_beta,
                                                  element=args.element)
    if main_rank:
        report_warnings(caught)
    from .unload import start_problem

    problem, start = start_problem(problem, config)  # a [zero_pressure] table: the unloaded or prestressed start
    if start and main_rank:
        print(start)
    dt = args.dt if args.dt is not None else run_config.dt  # None: the (mass-scaled) CFL step
    sync = common.sync_of(args)  # only when asked for: the library keeps its one default
    if args.timings is not None:
        from ..perf.timing import timing_breakdown

        if args.float32_blocks:
            from ..errors import ConfigError

            raise ConfigError("--timings measures the float64 stages; leave out --float32-blocks")

        report = timing_breakdown(problem, _partitions(problem, args.parts or 1, args.seed), mode=args.mode,
                                  dt=dt, **sync)
        if main_rank:
            print(report.table())
            with common.writing(timings_path):
                report.save_json(timings_path)
            print(f"wrote {timings_path}")
        return 0
    return _simulate(args, problem, run_config, dt=dt, sync=sync, output=output, formats=formats,
                     checkpoint=checkpoint, main_rank=main_rank, config=config)


def _partitions(problem, n_parts: int, seed: int):
    """``n_parts`` (METIS with seed 0, rank 0's parts on every rank), or the partition of
    another ``--seed``."""
    from ..parallel._partitioning import partition

    return n_parts if not seed else partition(problem.mesh, n_parts, seed=seed)


CONFIG_PARAMETER = "config"
"""The trajectory parameter (``Trajectory.parameters``, HDF5 attribute ``param_config``) that
holds the run's configuration, as JSON with its paths resolved: ``jaxsync report`` rebuilds
the run's loads and material from it."""


def _simulate(args, problem, run_config, *, dt, sync, output, formats, checkpoint, main_rank, config) -> int:
    import dataclasses
    import json

    from ..errors import StabilityError
    from ..solve._solver import simulate
    from ..solve._strategies import HostExecutor, SaveAt, SolverCheckpoint

    n_steps = args.steps if args.steps is not None else run_config.n_steps
    save_every = args.save_every if args.save_every is not None else run_config.save_every
    n_processes = common.process_count()
    parts = args.parts
    if parts is None and n_processes > 1:
        parts = n_processes  # one part per process
    if main_rank:
        print(problem.summary(dt))
        if run_config.added_mass_percent is not None:
            target = run_config.mass_scaling_dt
            if target is not None and float(problem.dt) > target:  # every element already stable at the target
                print(f"mass scaling to dt {target:.4e} s: added mass {run_config.added_mass_percent:.2f} % of the "
                      f"total (every element is stable at a larger step); the run takes the CFL step "
                      f"{float(problem.dt):.4e} s")
            else:
                print(f"mass scaling to dt {float(problem.dt):.4e} s: added mass "
                      f"{run_config.added_mass_percent:.2f} % of the total")
        if n_processes > 1:
            print(f"{n_processes} processes, {parts} parts")
        if parts is not None:  # how the parts exchange: the transport of this run
            from ..solve._strategies import transport

            print(f"exchange: {transport(sync.get('sync'), parts)}")
    first_step = checkpoint_step(checkpoint)  # where a resumed run starts
    start = time.perf_counter()
    try:
        every = args.checkpoint_every if args.checkpoint_every is not None else run_config.checkpoint_every
        trajectory = simulate(
            problem, n_steps, dt=dt, save=SaveAt(save_every, args.shared_every),
            partitions=None if parts is None else _partitions(problem, parts, args.seed), mode=common.mode_of(args),
            checkpoint=None if checkpoint is None else SolverCheckpoint(checkpoint, every),
            executor=HostExecutor(progress=main_rank and not args.no_progress), **sync)
    except StabilityError as exc:
        partial = getattr(exc, "trajectory", None)
        if not main_rank:
            common.barrier()  # let rank 0 write the partial trajectory before the job ends
            raise
        if partial is not None and partial.n_saved:
            partial_path = partial_output(output, force=args.force)
            with common.writing(partial_path):
                partial.save(partial_path)
            print(f"saved the {partial.n_saved} snapshot{'s' if partial.n_saved > 1 else ''} before divergence "
                  f"to {partial_path}", file=sys.stderr)
        common.barrier()
        raise
    elapsed = time.perf_counter() - start
    if not main_rank:  # rank 0 writes and prints
        return 0
    extra = {CONFIG_PARAMETER: json.dumps(config)}
    if run_config.added_mass_percent is not None:
        extra["added_mass_percent"] = float(run_config.added_mass_percent)
    trajectory = dataclasses.replace(trajectory, parameters={**trajectory.parameters, **extra})
    with common.writing(output):
        trajectory.save(output, compression=common.compression_of(args))
    st = trajectory.stats
    speed = (f"{st.us_per_step:.1f} us/step, compilation {st.compile_seconds:.2f} s not included"
             if st.us_per_step is not None else "no steps run")
    ran = max(int(n_steps) - first_step, 0)
    steps = (f"resumed from step {first_step} of {n_steps} (checkpoint {checkpoint}): {ran} steps"
             if first_step else f"{ran} steps")
    print(f"{steps} in {elapsed:.2f} s ({speed}; {devices_text(st, parts)}); wrote {output}")
    from ..io.writers import write_output

    for _, writer, path, files in formats:
        with common.writing(*(f.path for f in files)):
            write_output(trajectory, path, writer)
        others = [f.path for f in files[:-1]]
        print(f"wrote {path}" + (f" (with {', '.join(others)})" if others else ""))
    return 0
