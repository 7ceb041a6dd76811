"""``jaxsync report``: figures and ``summary.json`` comparing a synchronization-avoiding
run with the synchronized one (:func:`jaxsync.app.plots.write_report`), and, for a vessel
under a lumen pressure, its pressure-diameter loop, distensibility, compliance,
hysteresis and peak wall stress and strain by region
(:func:`jaxsync.app.vessel_report.vessel_section`; from the configuration ``jaxsync simulate``
records in the trajectory, or the run's TOML, ``--config``).
Given one trajectory only, the report is that section alone."""

from __future__ import annotations

import os

from ..options import DEFAULT_COMPONENT, Component, choices


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "report", help="figures and summary.json comparing an online run with the synchronized one, and a "
                       "vessel's pressure-diameter loop and wall stresses",
        description="Compare a synchronization-avoiding trajectory (jaxsync predict) with the "
                    "synchronized reference: displacement at monitored nodes, e_l2(t), es and "
                    "es_hat, et histograms (PNG) and summary.json. By default the monitored nodes "
                    "are, for each part, the node that is neither shared nor constrained with the "
                    "largest amplitude in the reference, and the shared node with the largest "
                    "amplitude; never a node that does not move in the reference or belongs to "
                    "the Dirichlet set of --config. With --config of a problem under a lumen pressure, "
                    "also the vessel section of the reference run: pressure-diameter and pressure-volume "
                    "loops (pressure_diameter.png), distensibility, compliance, the energy dissipated "
                    "per cycle, and the peak von Mises and principal stress and strain by region "
                    "(wall_stress.png; summary.json 'vessel'); a trajectory of jaxsync simulate records its "
                    "configuration, so --config is needed only for older ones. Given only one trajectory, "
                    "the report is that section alone; a problem without a pressure load is skipped "
                    "with a note.")
    p.add_argument("reference", help="synchronized trajectory (HDF5)")
    p.add_argument("online", nargs="?", default=None,
                   help="synchronization-avoiding trajectory (HDF5); leave it out for the vessel section "
                        "of REFERENCE alone")
    p.add_argument("--out", "-o", default="report", help="output folder (default: %(default)s)")
    p.add_argument("--component", type=int, choices=choices(Component), default=DEFAULT_COMPONENT,
                   help="displacement component shown and compared at the nodes (default: "
                        "%(default)s = z)")
    p.add_argument("--node", action="append", default=None, metavar="ID|X,Y,Z",
                   help="monitor this node instead of the automatic choice: a node id or "
                        "coordinates x,y,z (the nearest node); repeat for several")
    p.add_argument("--config", default=None,
                   help="TOML problem file of the run: its Dirichlet nodes are never chosen, and "
                        "its loads and material give the vessel section (default for the vessel section: the "
                        "configuration jaxsync simulate recorded in REFERENCE; for the nodes: none; then the "
                        "constrained nodes are those that never move in the reference, which covers "
                        "every fully clamped node)")
    p.add_argument("--lumen", default=None, metavar="FACET_SET",
                   help="the vessel section's lumen facet set (default: the surface of the first pressure "
                        "load of --config)")
    p.add_argument("--train-until-step", type=int, default=None, metavar="STEP",
                   help="the last step the surrogates were trained on (the demo's summary.json "
                        "train_until_step): summary.json then measures every error after it as well "
                        "(out_of_sample)")
    p.add_argument("--force", action="store_true",
                   help="replace the report (figures and summary.json) already in the output folder (without it "
                        "the run is refused before it starts)")
    p.set_defaults(func=run)


def same_steps(reference, online, reference_name: str, online_name: str):
    """``reference`` thinned to the saved steps of ``online``.

    Raises:
        CheckpointError: ``online`` is not synchronization-avoiding, the two do not share
            time steps, or the reference is shorter.
    """
    import dataclasses

    from ..errors import CheckpointError

    if online.synchronized is None:
        raise CheckpointError(f"{online_name} is not a synchronization-avoiding trajectory")
    stride, rest = divmod(online.save_every, reference.save_every)
    if rest or abs(online.dt - reference.dt) > 1e-12 * reference.dt:
        raise CheckpointError("the two trajectories do not share time steps (dt and save_every "
                              "must match, the reference saved at least as often)")
    n = online.n_saved
    if reference.n_saved < (n - 1) * stride + 1:
        raise CheckpointError(f"{reference_name} is shorter than {online_name}")
    kept = slice(None, (n - 1) * stride + 1, stride)
    return dataclasses.replace(reference, times=reference.times[kept],
                               displacement=reference.displacement[kept], save_every=online.save_every)


def run_config(args, reference) -> dict | None:
    """The run's configuration: ``--config``'s, else the one ``jaxsync simulate`` recorded in
    the trajectory (:data:`jaxsync.cli.simulate.CONFIG_PARAMETER`), else None (an
    older trajectory, or one written by the Python API)."""
    import json

    from ..app.config import load_config
    from .simulate import CONFIG_PARAMETER

    if args.config is not None:
        return load_config(args.config)
    recorded = reference.parameters.get(CONFIG_PARAMETER)
    return None if recorded is None else json.loads(recorded)


def vessel_entry(args, reference) -> dict:
    """The ``vessel`` entry of the report (:func:`jaxsync.app.vessel_report.vessel_section`
    of ``reference`` under the problem of its configuration, :func:`run_config`, on the
    trajectory's mesh (the unloaded one of a run from its zero-pressure geometry; a
    prestressed start's prestrain computed again); its figures written to ``--out``), or the
    note of why there is none."""
    from ..app.config import problem_from_config
    from ..app.vessel_report import vessel_note, write_vessel_section
    from .unload import settings, start_problem

    config = run_config(args, reference)
    if config is None:
        return vessel_note(reference)
    problem, _ = problem_from_config(config, mesh_file=reference.mesh, element=reference.space.element)
    if "zero_pressure" in config and settings(None, config)["start"] == "prestressed":
        problem, _ = start_problem(problem, config)
    return write_vessel_section(problem, reference, args.out, surface=args.lumen)


def print_vessel(entry: dict) -> None:
    """The vessel section in a few lines (or its note)."""
    if entry["skipped"]:
        print(f"note: {entry['note']}")
        return
    from ..vessel_metrics import VesselMetrics

    print(f"vessel (lumen '{entry['surface']}'): " + VesselMetrics(**{
        k: v for k, v in entry["metrics"].items() if k != "distensibility_per_mmHg"}).summary())
    for name, peaks in entry["peaks"].items():
        mises, strain = peaks["von_mises"], peaks["max_principal_strain"]
        print(f"  {name}: peak von Mises {mises['value'] / 1e4:.4g} kPa (element {mises['element']}, t = "
              f"{mises['time']:.4g} s), largest principal strain {100 * strain['value']:.3g} % (element "
              f"{strain['element']}, t = {strain['time']:.4g} s)")


def run(args) -> int:
    from ..app.plots import constrained_nodes, write_report
    from ..errors import ConfigError
    from ..io.atomic import atomic_json
    from ..io.trajectory import Trajectory
    from ..parallel._partitioning import partition_of
    from .common import check_outputs, refuse_to_overwrite

    check_outputs((args.out, "report folder", "-o", True))
    if args.online is None and (args.node or args.train_until_step is not None):
        raise ConfigError("--node and --train-until-step choose what the comparison of two runs shows: give the "
                          "synchronization-avoiding trajectory too, or leave them out for the vessel section alone")
    # summary.json marks a report: an earlier one is replaced only with --force
    refuse_to_overwrite([os.path.join(args.out, "summary.json")], force=args.force,
                        inputs=[args.reference, args.online, args.config])
    reference = Trajectory.load(args.reference)
    if args.online is None and run_config(args, reference) is None:
        raise ConfigError("jaxsync report with one trajectory writes its vessel section, which needs the run's "
                          "configuration: this trajectory does not record it (written before jaxsync simulate "
                          "kept it, or by the Python API), so give the run's TOML file with --config, or give "
                          "the synchronization-avoiding trajectory to compare")
    if args.online is None:
        entry = vessel_entry(args, reference)
        atomic_json(os.path.join(args.out, "summary.json"),
                    {"trajectory": os.path.abspath(args.reference), "vessel": entry})
        print_vessel(entry)
        print(f"wrote {'summary.json' if entry['skipped'] else 'figures and summary.json'} to "
              f"{os.path.abspath(args.out)}")
        return 0
    online = Trajectory.load(args.online)
    thinned = same_steps(reference, online, args.reference, args.online)
    entry = vessel_entry(args, reference)  # over every snapshot of the reference
    reference = thinned
    fixed = constrained_nodes(args.config, online.space, reference.displacement)
    summary = write_report(reference, online, partition_of(online), args.out,
                           component=args.component, fixed_nodes=fixed, nodes=args.node,
                           extra={"online_statistics": online.stats.to_dict(), "vessel": entry},
                           train_until_step=args.train_until_step)
    for line in summary["node_notes"]:
        print(f"note: {line}")
    print_vessel(entry)
    if online.stats.to_dict():
        from ..solve.coupling._syncavoid import describe_run

        print(describe_run(online))
    if "peak_strain" in summary:  # a hyperelastic run's
        from ..metrics import PeakStrain

        print("reference " + PeakStrain(**summary["peak_strain"]).summary())
    if "es_hat_tracking" in summary:
        from ..metrics import EstimateQuality

        print(EstimateQuality(**summary["es_hat_tracking"]).summary())
    c = "xyz"[args.component]
    print(f"wrote figures and summary.json to {os.path.abspath(args.out)}; largest-amplitude monitored "
          f"node {summary['monitored_node']} ({summary['monitored_label']}): max |error| in d_{c} "
          f"{summary['tip_max_abs_error']:.3e} cm of {summary['tip_max_abs_displacement']:.3e} cm; "
          f"e_l2 at the end {summary['l2_error_final']:.3e} cm")
    return 0
