"""The end-to-end demonstration behind ``jaxsync demo``: two cases, one pipeline.

``case="cantilever"`` (the default): the built-in coarse cantilever split into 2 parts,
1e5 steps, with the library's training defaults (n_s = 150, n_p = n_f = 20, n_H = 50,
800 epochs of n_B = 10, as the paper's published code), error control at 1 % of the
synchronized run's largest shared-node displacement: about 4-5 minutes on a 2-core
laptop.

``case="vessel"``: the paper's coronary case (section 5.2) on the generated coronary
tree (:func:`jaxsync.coronary_mesh`) under the pulsatile lumen
pressure (:func:`jaxsync.coronary`), mass-scaled to 2.5 times its CFL step as in the
paper (2.02e-6 s -> 5e-6 s), split into the paper's 11 parts, one emulated device each,
with error control at 1 % of the synchronized run's largest shared-node displacement.
Sizes (:data:`VESSEL_SIZES`):
``"small"`` (about 5 000 tets, 3.9 s of physical time: about 15 minutes on a 2-core
laptop) and ``"paper"`` (about 250 000 dofs as the paper's mesh, 5 s = 1e6 steps at
5e-6 s, n_s = 1000: hours to days on a laptop; see ``benchmarks/paper_vessel.py``), or
a target tetrahedron count.

The pipeline: (vessel only) the run-time estimate on this machine, from short timed
pieces of the run (:mod:`jaxsync.app.run_estimate`); (0, vessel only) the mass-scaling
check of paper figure 19: one node's displacement at the CFL step and at the scaled
step, single-device runs over the same physical time; (1) a synchronized distributed
run; (2) training of one LSTM surrogate per part on it (its first half;
:func:`jaxsync.surrogate.train_surrogates`, as ``jaxsync train``); (3) the
synchronization-avoiding run from n_cri = n_s n_p on; (4) timing of the compiled
programs (:func:`jaxsync.perf.timing.speedup_breakdown`), the cost-model projection to
real interconnects (:func:`jaxsync.perf.costmodel.project`) and the report (figures,
``summary.json``). Every size is an argument; the defaults of a case are
:func:`demo_defaults`.
"""

from __future__ import annotations

import dataclasses
import math
import os
import shutil
import time

import numpy as np

from .demo_folder import DEMO_FILES, check_demo_output, install_folder, retarget_paths, staging_folder
from .mass_scaling import mass_scaling_check, mass_scaling_figure

__all__ = ["run_demo", "format_summary", "demo_defaults", "DemoDefaults", "DemoSettings", "SUMMARY_KEYS", "VESSEL_KEYS",
           "CASES", "VESSEL_SIZES", "vessel_problem", "DEMO_FILES", "check_demo_output", "check_demo_settings",
           "install_folder", "staging_folder", "retarget_paths"]

CASES = ("cantilever", "vessel")

VESSEL_SIZES = {"small": 5_000, "paper": 335_000}
"""Target tetrahedron counts of the vessel sizes. ``"paper"``: the paper's mesh has
373 435 tets and 250 659 dofs; the generated tree reaches about 250 000 dofs with fewer
tets (its wall is meshed more evenly)."""

SUMMARY_KEYS = ("n_steps", "n_synchronized", "n_predicted", "tip_max_abs_error",
                "tip_max_abs_displacement", "l2_error_final", "us_per_step_synchronized",
                "us_per_step_predicted", "speedup", "zeta", "t_s_us", "t_d_us", "n_devices",
                "device_kind", "train_until_step")
"""Keys of every case's ``summary.json`` (and ``out_of_sample``: the errors after
``train_until_step``, :func:`jaxsync.app.plots.out_of_sample`)."""

VESSEL_KEYS = ("es_max", "es_hat_max", "es_hat_tracking", "interior_max_relative_error", "mass_scaling",
               "projection", "n_elements", "n_dofs", "n_shared_nodes", "vessel", "estimate")
"""Keys the vessel case adds (es, es_hat and their correlation, the mass-scaling check,
the cost-model projection to 11 real processors, the mesh's size, the vessel section
of the report: :func:`jaxsync.app.vessel_report.vessel_section`, and the run-time
estimate printed before the first stage: :func:`jaxsync.app.run_estimate.measure_demo_estimate`)."""

MASS_SCALING_BETA = 2.5
"""The vessel's step over its CFL step (paper: 5e-6 / 2.02e-6 = 2.48)."""


@dataclasses.dataclass(frozen=True)
class DemoDefaults:
    """The defaults of one demo case (every one can be changed: :class:`DemoSettings`).

    Attributes:
        n_steps, n_parts: time steps of both runs, parts (one emulated device each).
        n_s, n_past, n_future, n_hidden, n_layers: sampling and network.
        epochs, batch_size, eta0, gamma: the training schedule.
        n_candidates: networks trained per part, the lowest validation loss kept.
        train_fraction: the leading fraction n_ts of the synchronized run trained on; the
            steps after it (after ``train_until_step`` in ``summary.json``) are out of
            sample, and the summary's ``out_of_sample`` errors are measured over them
            (the cantilever and the vessel: the first half; the vessel's run is long
            enough for its first half to hold the pressure ramp of the first second and
            more than a pulse, its second half the following pulses).
        resync_tolerance: error control of the predicted run (None: none).
        shared_every_step: the synchronized run keeps the parts' shared histories at
            every step (the cantilever: small, and any n_s can be trained later); False:
            every ``save_every`` steps, all that training reads (the vessel: at the
            paper's size every step would take 69 GB).
        component: displacement component of the report (None: each node's dominant one).
    """

    n_steps: int
    n_parts: int
    n_s: int
    n_past: int
    n_future: int
    n_hidden: int
    n_layers: int
    epochs: int
    batch_size: int
    eta0: float
    gamma: float
    n_candidates: int
    train_fraction: float
    resync_tolerance: str | float | None
    shared_every_step: bool
    component: int | None


def demo_defaults(case: str = "cantilever", size: str | int = "small") -> DemoDefaults:
    """The defaults of ``case`` (and, for the vessel, ``size``): the cantilever's are
    the library's (:class:`~jaxsync.surrogate.Sampling`,
    :class:`~jaxsync.surrogate.ArchitectureChoice`,
    :class:`~jaxsync.surrogate.training.TrainConfig`, the paper's 1e5 steps), with error
    control at 1 %;
    the vessel's follow the paper's section 5.2 (11 parts, n_s = 1000; 1e6 steps, 5 s, at
    the paper's size, 5e5 steps, about 3.9 s, at the small one), with error control at
    1 %, trained on the first half of the synchronized run with n_B = 10.

    Raises:
        ConfigError: an unknown case or size.
    """
    from ..surrogate.models._architecture import ArchitectureChoice as Arch
    from ..surrogate.training._data import Sampling
    from ..surrogate.training._train import TrainConfig as Train

    _check_case(case)
    if case == "cantilever" and size != "small":
        from ..errors import ConfigError

        raise ConfigError(f"size={size!r} is for the vessel case (--case vessel); the cantilever has one size")
    base = dict(n_past=Sampling.n_past, n_future=Sampling.n_future, n_hidden=Arch.n_hidden, n_layers=Arch.n_layers,
                epochs=Train.n_epochs, batch_size=Train.batch_size, eta0=Train.eta0, gamma=Train.gamma)
    if case == "cantilever":
        return DemoDefaults(n_steps=100_000, n_parts=2, n_s=Sampling.n_s, train_fraction=0.5,
                            resync_tolerance="1%", shared_every_step=True, component=2,
                            n_candidates=Train.n_candidates, **base)
    paper = _vessel_target(size) >= VESSEL_SIZES["paper"]
    # n_H 32, 300 epochs of n_B = 10, one candidate per part: the 11 replicas train in about
    # 3.5 minutes on 2 cores (the library's n_H 50, 800 epochs and 2 candidates would take
    # the demo past 15 minutes); its error control re-synchronizes where a network falls short
    return DemoDefaults(n_steps=1_000_000 if paper else 500_000, n_parts=11, n_s=1000, train_fraction=0.5,
                        resync_tolerance="1%", shared_every_step=False, component=None, n_candidates=1,
                        **dict(base, n_hidden=32, epochs=300, batch_size=10))


def _check_case(case) -> None:
    from ..errors import ConfigError

    if case not in CASES:
        raise ConfigError(f"unknown demo case {case!r}; choose one of {', '.join(CASES)}")


def _vessel_target(size) -> int:
    """The target tetrahedron count of a vessel size: a name of :data:`VESSEL_SIZES` or a
    count of 1 000 to 2 000 000."""
    from ..errors import ConfigError

    if isinstance(size, str) and size in VESSEL_SIZES:
        return VESSEL_SIZES[size]
    try:
        count = int(size)
    except (TypeError, ValueError):
        count = None
    if count is None or isinstance(size, float) and size != count or not 1_000 <= count <= 2_000_000:
        raise ConfigError(f"vessel size {size!r}: give {' or '.join(map(repr, VESSEL_SIZES))}, or a target "
                          "tetrahedron count from 1000 to 2000000")
    return count


def vessel_problem(size: str | int = "small", *, beta: float = MASS_SCALING_BETA):
    """The demo's vessel: (problem at the CFL step, mass-scaled problem, added mass [%]).

    The generated coronary tree of about ``size`` tetrahedra (:data:`VESSEL_SIZES`)
    under :func:`jaxsync.coronary`, and its mass scaling to ``beta`` times the CFL step
    (:func:`jaxsync.mass_scaling`; the paper's 2.5 added 21 % on its mesh)."""
    from .. import coronary, mass_scaling
    from ..cases import coronary_mesh

    problem = coronary(coronary_mesh(target_elements=_vessel_target(size)))
    scaled, added = mass_scaling(problem, beta=beta, warn_above_percent=None)
    return problem, scaled, float(added)


@dataclasses.dataclass(frozen=True)
class DemoSettings:
    """What a demo run changes of its case's defaults (:func:`demo_defaults`): every field
    left None keeps the case's value.

    Attributes:
        n_steps, n_parts, n_s, n_past, n_future, n_hidden, n_layers, epochs, batch_size,
            eta0, gamma, train_fraction, n_candidates: as in :class:`DemoDefaults`.
        resync_tolerance: error control of the predicted run: ``"default"`` (the case's),
            None (none), a number [cm] or a percentage string (of the largest shared-node
            displacement of the synchronized run, the surrogates' training data; passed on
            in cm).
        save_every: full-field snapshot stride of both runs; divides n_s n_p and n_s n_f
            (default: the largest divisor of n_s that divides n_steps).
        mass_scaling_seconds: the vessel's mass-scaling check runs over this physical
            time [s] (default: the first half of the run up to 50 000 tets, 0.05 s above,
            where single-device runs at the CFL step take hours).
        load_input: the surrogates' load input
            (:class:`~jaxsync.surrogate.ArchitectureChoice`): None (default, on: the
            synchronized run records its load signals), True or False.
        highway: the LSTM's linear highway (:class:`~jaxsync.surrogate.ArchitectureChoice`):
            None (default: the choice's default), True or False.
    """

    n_steps: int | None = None
    n_parts: int | None = None
    n_s: int | None = None
    n_past: int | None = None
    n_future: int | None = None
    n_hidden: int | None = None
    n_layers: int | None = None
    epochs: int | None = None
    batch_size: int | None = None
    eta0: float | None = None
    gamma: float | None = None
    train_fraction: float | None = None
    n_candidates: int | None = None
    resync_tolerance: str | float | None = "default"
    save_every: int | None = None
    mass_scaling_seconds: float | None = None
    load_input: bool | None = None
    highway: bool | None = None

    def applied_to(self, defaults: DemoDefaults) -> DemoDefaults:
        """``defaults`` with the fields these settings give."""
        given = {f.name: getattr(self, f.name) for f in dataclasses.fields(DemoDefaults)
                 if hasattr(self, f.name) and getattr(self, f.name) is not None}
        given.pop("resync_tolerance", None)
        d = dataclasses.replace(defaults, **given)
        if self.resync_tolerance != "default":
            d = dataclasses.replace(d, resync_tolerance=self.resync_tolerance)
        return d


def run_demo(out: str, settings: DemoSettings | None = None, *, case: str = "cantilever",
             size: str | int = "small", seed: int = 0, progress: bool = True, log=print,
             force: bool = False) -> dict:
    """Run the pipeline of ``case`` and write everything into ``out``; return the summary.

    ``out`` is refused before anything runs when it holds the files of a demo
    (:data:`DEMO_FILES`) unless ``force``, or cannot be written. The run writes into a
    fresh folder beside ``out`` (``<out>.partial-<pid>@<host>.<random>``) that takes the place
    of ``out`` only when complete (:func:`install_folder`): an interrupted or failed run
    leaves ``out`` as it was (its staging folder removed), never old and new files
    mixed. Every path printed or stored in the files names ``out``.

    Args:
        out: output folder.
        settings: :class:`DemoSettings`, what to change of the case's defaults
            (:func:`demo_defaults`); None: the defaults.
        case: ``"cantilever"`` or ``"vessel"``.
        size: the vessel's size, ``"small"``, ``"paper"`` or a target tetrahedron count.
        seed: seed of METIS, initialization and shuffling.
        progress: progress bars; log: where the stage lines go.
        force: replace a folder that holds a demo.

    Files: ``synchronized.h5`` (reference every ``save_every`` steps, per-part shared
    histories every step for the cantilever, every n_s steps for the vessel),
    ``surrogate/`` (checkpoint, loss curves, training summary), ``online.h5`` (the
    synchronization-avoiding run), ``report/`` (figures; for the vessel also
    ``mass_scaling.png``) and ``summary.json`` (:data:`SUMMARY_KEYS`, and for the vessel
    :data:`VESSEL_KEYS`).

    Raises:
        ConfigError: an unknown case or size; ``out`` holds a demo and ``force`` is False.
        OutputError: ``out`` cannot be written (before anything runs), or a write failed.
    """
    settings = DemoSettings() if settings is None else settings
    d = settings.applied_to(demo_defaults(case, size))
    if not 0.0 < d.train_fraction <= 1.0:
        from ..errors import ConfigError

        raise ConfigError(f"train fraction must be in (0, 1], got {d.train_fraction!r} (--train-fraction)")
    save_every, mass_scaling_seconds = settings.save_every, settings.mass_scaling_seconds
    final = os.path.abspath(os.fspath(out))
    check_demo_output(final, force=force)  # before anything runs
    check_demo_settings(d, save_every, seed=seed)  # every option, before the long synchronized run
    staging = staging_folder(final)
    try:
        summary = _pipeline(staging, final, d, case=case, size=size, seed=seed, save_every=save_every,
                            mass_scaling_seconds=mass_scaling_seconds, progress=progress, log=log,
                            load_input=settings.load_input, highway=settings.highway)
        retarget_paths(staging, final)
        install_folder(staging, final)
    except BaseException as exc:
        shutil.rmtree(staging, ignore_errors=True)
        if isinstance(exc, OSError):
            from ..io.atomic import OutputError, os_reason

            kept = (f"{final} is left as it was" if os.path.exists(final) else f"{final} was not created")
            reason = str(exc) if isinstance(exc, OutputError) else f"could not write {final}: {os_reason(exc)}"
            raise OutputError(f"{reason.replace(staging, final)}; the demo's new files were discarded and "
                              f"{kept}") from exc
        raise
    return summary


def check_demo_settings(d: DemoDefaults, save_every: int | None = None, *, seed: int = 0) -> None:
    """Check every option of a demo run before anything runs (the synchronized run takes
    minutes, on the vessel a quarter of an hour): the parts (2 or more: one part has no
    shared nodes, nothing to predict), the steps, the training options (by building the
    :class:`~jaxsync.surrogate.Sampling`, :class:`~jaxsync.surrogate.ArchitectureChoice`
    and :class:`~jaxsync.surrogate.training.TrainConfig` the run will use), the snapshot
    strides, that the trained leading part of the run holds one window of n_p + n_f
    snapshots, and the error control's tolerance.

    Raises:
        ConfigError, ProblemError: the first option that cannot be used, named with its fix.
    """
    from ..errors import ConfigError
    from ..solve._strategies import SaveAt
    from ..solve.coupling._syncavoid import ResyncTolerance
    from ..surrogate.models._architecture import ArchitectureChoice
    from ..surrogate.training._data import Sampling, trained_rows
    from ..surrogate.training._train import TrainConfig

    def integer(value) -> bool:
        return isinstance(value, (int, np.integer)) and not isinstance(value, bool)

    if not integer(d.n_parts) or d.n_parts < 2:
        raise ConfigError(f"the demo needs 2 parts or more, got {d.n_parts!r} (--parts): a 1-part run has no shared "
                          "nodes, so there is nothing for the surrogates to predict; use --parts 2 or more")
    if not integer(d.n_steps) or d.n_steps < 1:
        raise ConfigError(f"n_steps must be an integer >= 1, got {d.n_steps!r} (--steps)")
    Sampling(n_s=d.n_s, n_past=d.n_past, n_future=d.n_future, train_fraction=d.train_fraction, seed=seed)
    ArchitectureChoice(n_hidden=d.n_hidden, n_layers=d.n_layers)
    TrainConfig(batch_size=d.batch_size, eta0=d.eta0, gamma=d.gamma, n_epochs=d.epochs, n_candidates=d.n_candidates)
    every = math.gcd(d.n_s, d.n_steps) if save_every is None else save_every
    save = SaveAt(every, 1 if d.shared_every_step else every)
    save.check_steps(d.n_steps)
    n_cri, cycle = d.n_s * d.n_past, d.n_s * d.n_future
    if d.n_s % save.shared_every or n_cri % save.every or cycle % save.every:
        raise ConfigError(f"--save-every {save.every} must divide n_s = {d.n_s}, n_s n_p = {n_cri} and n_s n_f = "
                          f"{cycle} (the synchronized run keeps the training data, and the predicted run its "
                          "snapshots, at that stride); choose a divisor of n_s")
    length, stride = d.n_past + d.n_future, d.n_s // save.shared_every
    rows = trained_rows(d.n_steps // save.shared_every + 1, d.train_fraction)
    if -(-rows // stride) < length:
        raise ConfigError(f"{d.n_steps} steps give {-(-rows // stride)} training snapshots (every n_s = {d.n_s} steps "
                          f"over the first {100 * d.train_fraction:g} % of the run), fewer than one window of "
                          f"n_p + n_f = {length}; use more --steps, a larger --train-fraction or a smaller --n-s")
    if d.resync_tolerance is not None:
        ResyncTolerance.parse(d.resync_tolerance)


def _pipeline(out: str, final: str, d: DemoDefaults, *, case, size, seed, save_every, mass_scaling_seconds,
              progress, log, load_input=None, highway=None) -> dict:
    """The stages of :func:`run_demo`, writing into the folder ``out``; every path that
    is printed or stored names ``final``, where the folder is moved at the end."""
    from .. import HostExecutor, SaveAt, cantilever, partition, simulate
    from ..io.atomic import atomic_json
    from ..parallel.devices import device_summary
    from ..solve.coupling._syncavoid import describe_run, simulate_sync_avoiding
    from ..surrogate import ArchitectureChoice, Sampling, TrainingChecks, TrainingState
    from ..surrogate.training._data import last_trained_step
    from ..surrogate.training._fit import train_surrogates
    from ..surrogate.training._train import TrainConfig
    from .plots import write_report

    started = time.perf_counter()
    extra: dict = {"case": case}
    if case == "vessel":
        problem_cfl, problem, added = vessel_problem(size)
        mesh = problem.mesh
        log(f"vessel: generated coronary tree, {mesh.n_elements} tets, {mesh.n_nodes} nodes, "
            f"{3 * mesh.n_nodes} dofs; CFL dt {problem_cfl.dt:.3e} s, mass-scaled to {problem.dt:.3e} s "
            f"(+{added:.2f} % mass)")
        extra.update(size=size, n_elements=int(mesh.n_elements), n_dofs=int(3 * mesh.n_nodes))
    else:
        problem = cantilever()
    parts = partition(problem.mesh, d.n_parts, seed=seed)
    log(parts.summary())
    save_every = math.gcd(d.n_s, d.n_steps) if save_every is None else int(save_every)
    shared_every = 1 if d.shared_every_step else save_every
    devices = device_summary()
    n_stages = 5 if case == "vessel" else 4
    stage = iter(range(1, n_stages + 1))
    if case == "vessel":
        window = ((0.5 * d.n_steps * problem.dt if _vessel_target(size) <= 50_000 else 0.05)
                  if mass_scaling_seconds is None else float(mass_scaling_seconds))
        from .run_estimate import measure_demo_estimate  # timed pieces of the run, before its long stages

        log("estimating the run time: timing the synchronized step, the single-device step and a training epoch")
        extra["estimate"] = measure_demo_estimate(problem, parts, d, shared_every=shared_every, seed=seed,
                                                  mass_scaling=(window, problem_cfl.dt), load_input=load_input,
                                                  highway=highway, log=log)
        log(extra["estimate"]["text"])
        log(f"[{next(stage)}/{n_stages}] mass-scaling check over {window:.3g} s: single-device runs at the CFL "
            f"step and at the scaled step")
        extra["mass_scaling"] = mass_scaling_check(problem_cfl, problem, added, window, progress=progress)
        log(f"  node {extra['mass_scaling']['node']}: largest |difference| "
            f"{extra['mass_scaling']['max_abs_difference']:.3e} cm = "
            f"{100 * extra['mass_scaling']['relative_difference']:.2f} % of its amplitude "
            f"{extra['mass_scaling']['max_abs_displacement']:.3e} cm")

    log(f"[{next(stage)}/{n_stages}] synchronized run: {d.n_steps} steps, dt = {problem.dt:.4e} s, on "
        f"{devices['n_devices']} {devices['device_kind']} device(s){' (emulated)' if devices['emulated'] else ''}")
    reference = simulate(problem, d.n_steps, partitions=parts, save=SaveAt(save_every, shared_every),
                         executor=HostExecutor(progress=progress))
    reference_path = os.path.join(out, "synchronized.h5")
    reference.save(reference_path)

    log(f"[{next(stage)}/{n_stages}] training {d.n_parts} LSTM replicas (n_s={d.n_s}, n_p={d.n_past}, "
        f"n_f={d.n_future}, n_H={d.n_hidden}, {d.epochs} epochs, n_B={d.batch_size}, "
        f"{d.n_candidates} candidate{'s' if d.n_candidates > 1 else ''} per part, on the first "
        f"{100 * d.train_fraction:g} % of the run)")
    surrogate_folder = os.path.join(out, "surrogate")
    trained = train_surrogates(
        reference_path, architecture=ArchitectureChoice(
            n_hidden=d.n_hidden, n_layers=d.n_layers, load_input=load_input,
            **({} if highway is None else {"highway": highway})),
        sampling=Sampling(n_s=d.n_s, n_past=d.n_past, n_future=d.n_future, train_fraction=d.train_fraction,
                          seed=seed),
        optimizer=TrainConfig(batch_size=d.batch_size, eta0=d.eta0, gamma=d.gamma, n_epochs=d.epochs,
                              n_candidates=d.n_candidates),
        checks=TrainingChecks(emse_applications=0), state=TrainingState(surrogate_folder),
        progress=progress).write(surrogate_folder)
    log(f"  {trained.result.n_epochs_run} epochs in {trained.train_seconds:.1f} s; validation MSE per part "
        + ", ".join(f"{v:.3e}" for v in trained.final_val_loss)
        + f"; wrote {os.path.join(final, os.path.relpath(trained.files['surrogate'], out))}")

    n_cri = d.n_s * d.n_past
    tolerance = _tolerance(d.resync_tolerance, trained.shared_amplitude or _shared_amplitude(reference))
    tolerance_cm = None if tolerance is None else tolerance.cm(0.0)
    log(f"[{next(stage)}/{n_stages}] synchronization-avoiding run: synchronized to step {n_cri}, then predicted"
        + (f", error control at {tolerance_cm:.3e} cm ({tolerance}: es_hat and the estimated error)"
           if tolerance else ""))
    online = simulate_sync_avoiding(problem, d.n_steps, partitions=parts, surrogates=trained.saved,
                                    n_cri=n_cri, save=save_every, resync_tolerance=tolerance,
                                    executor=HostExecutor(progress=progress))
    online.save(os.path.join(out, "online.h5"))
    log("  " + describe_run(online))

    log(f"[{next(stage)}/{n_stages}] timing (compiled programs, round-robin) and report")
    from ..fem.forces._internal_force import run_force_model
    from ..perf.timing import speedup_breakdown

    # the vessel's timed calls are long (one refill cycle, n_s n_f = 20 000 steps, about 10 s)
    # and its refills take about a second: one timed call each, psum alone (it won every
    # vessel run; the emulated devices share the CPU, so a neighbour exchange saves nothing)
    if case == "cantilever":
        settings = dict(repeats=3, stage_repeats=10)
    else:
        settings = dict(repeats=1, stage_repeats=3, prediction_repeats=2, syncs=("psum",))
    # the programs in the form the runs compiled (a short run's compact product)
    timing = speedup_breakdown(problem, parts, trained.surrogate,
                               mode=run_force_model("preassembled", problem, d.n_steps), **settings)
    us_sync = float(reference.stats.us_per_step)
    us_pred = online.stats.us_per_step_predicted  # None when every step was re-synchronized
    extra.update({
        "us_per_step_synchronized": us_sync, "us_per_step_predicted": us_pred,
        "speedup": None if not us_pred else us_sync / float(us_pred), "zeta": timing.zeta, "zeta_sync": timing.sync,
        "t_s_us": 1e6 * timing.t_s, "t_d_us": 1e6 * timing.t_d, "dt": problem.dt,
        "training_seconds": trained.train_seconds, "final_val_loss": trained.final_val_loss.tolist(),
        "n_devices": devices["n_devices"], "device_kind": devices["device_kind"],
        "devices_emulated": devices["emulated"],
        "compile_seconds": reference.stats.compile_seconds + online.stats.compile_seconds,
        "save_every": save_every, "n_s": d.n_s, "n_shared_nodes": int(parts.n_interface),
        "resync_tolerance": None if d.resync_tolerance is None else str(d.resync_tolerance),
        "resync_tolerance_cm": tolerance_cm, "shared_amplitude_cm": _shared_amplitude(reference),
        "projection": cost_projection(timing, parts).to_dict(),
        **{k: v for k, v in online.stats.to_dict().items()
           if k in ("n_synchronized_steps", "n_predicted_steps", "n_discarded_steps", "n_resynchronizations")}})
    if case == "vessel":
        figure = mass_scaling_figure(extra["mass_scaling"])
        from .figures import save_figure

        os.makedirs(os.path.join(out, "report"), exist_ok=True)
        save_figure(figure, os.path.join(out, "report", "mass_scaling.png"))
    fixed_nodes = np.unique(problem.dirichlet_dofs()[0] // 3)
    extra["wall_seconds"] = time.perf_counter() - started
    train_until = last_trained_step(d.n_steps, shared_every, d.train_fraction)
    summary = write_report(reference, online, parts, os.path.join(out, "report"), component=d.component,
                           fixed_nodes=fixed_nodes, extra=extra,
                           train_until_step=train_until if train_until < d.n_steps else None)
    if case == "vessel":  # the pressure-diameter loop and the wall's peaks of the synchronized run
        from .vessel_report import write_vessel_section

        summary["vessel"] = write_vessel_section(problem, reference, os.path.join(out, "report"))
    summary["report"] = os.path.join(final, "report")
    atomic_json(os.path.join(out, "summary.json"), summary)
    return summary


def _shared_amplitude(reference) -> float:
    """The largest |displacement| at the shared nodes in the synchronized run [cm]."""
    return max(float(np.abs(part.shared_displacement).max(initial=0.0)) for part in reference.parts)


def _tolerance(tolerance, amplitude: float):
    """The demo's error control, a :class:`~jaxsync.solve.ResyncTolerance`
    (None: none): a percentage is of ``amplitude`` [cm], the largest shared-node
    displacement in the steps the surrogates were trained on (as ``jaxsync predict``
    takes it: under the vessel's pressure ramp the amplitude the online run has seen by
    n_cri is a small fraction of the final one, and a tolerance of it would reject
    well-trained cycles)."""
    from ..solve.coupling._syncavoid import ResyncTolerance

    if tolerance is None:
        return None
    tolerance = ResyncTolerance.parse(tolerance)
    if tolerance.relative is None or tolerance.amplitude is not None:
        return tolerance
    return dataclasses.replace(tolerance, amplitude=amplitude)


def cost_projection(timing, parts):
    """The measured step projected to one part per real processor on the preset
    interconnects (:func:`jaxsync.perf.costmodel.project`): the local work of the
    slowest part and one part's refill prediction alone, amortized over n_s n_f steps."""
    from ..perf import costmodel

    top = timing.synchronized.max_average
    t_d_alone = max(timing.t_prediction) / timing.steps_per_prediction
    return costmodel.project(top.t_local, t_d_alone, costmodel.communication_pattern(parts))


def format_summary(summary: dict) -> str:
    """The demo's summary table."""
    node_label = summary.get("monitored_label", "")
    component = summary.get("component", "z")
    rows = [
        ("steps", f"{summary['n_steps']}"),
        ("synchronized / predicted", f"{summary['n_synchronized']} / {summary['n_predicted']}"
         + (f" ({summary.get('n_resynchronizations')} re-synchronizations, tolerance "
            f"{summary['resync_tolerance']})" if summary.get("resync_tolerance") else "")),
        (f"node {summary.get('monitored_node', '')} {component}: max |error|",
         f"{summary['tip_max_abs_error']:.3e} cm "
         f"({100 * summary['tip_max_abs_error'] / summary['tip_max_abs_displacement']:.2f} % of its largest "
         f"amplitude; {node_label or 'the monitored node that moves most'})"),
        (f"node {summary.get('monitored_node', '')} {component}: largest |d|",
         f"{summary['tip_max_abs_displacement']:.3e} cm"),
    ]
    if summary.get("interior_max_relative_error") is not None:
        rows.append(("worst part, interior node", f"{100 * summary['interior_max_relative_error']:.2f} % of its "
                                                  "largest amplitude (max over the parts' monitored nodes)"))
    oos = summary.get("out_of_sample")
    if oos:
        interior = oos["interior_max_relative_error"]
        rows.append((f"out of sample (after step {summary['train_until_step']})",
                     f"node {oos['monitored_node']} {100 * (oos['monitored_relative_max_error'] or 0.0):.2f} %"
                     + ("" if interior is None else f", worst part's interior node {100 * interior:.2f} %")
                     + f" of their largest amplitude there; e_l2 largest {oos['l2_error_max']:.3e} cm"))
    rows.append(("e_l2 at the end", f"{summary['l2_error_final']:.3e} cm (largest {summary['l2_error_max']:.3e} cm)"
                 if "l2_error_max" in summary else f"{summary['l2_error_final']:.3e} cm"))
    if "es_max" in summary:
        q = summary.get("es_hat_tracking") or {}
        rows.append(("es / es_hat, largest", f"{summary['es_max']:.3e} / {summary['es_hat_max']:.3e} cm; "
                                             f"log correlation {q.get('log_correlation', float('nan')):.2f}"))
    tracked = summary.get("error_estimate_tracking")
    if tracked and tracked.get("n_snapshots"):
        rows.append(("error / its estimate", f"median {tracked['ratio_median']:.2f}, within a factor 2 at "
                                             f"{100 * tracked['within_factor_2']:.0f} % of the predicted snapshots"))
    if "mass_scaling" in summary:
        m = summary["mass_scaling"]
        rows.append(("mass scaling", f"dt {m['dt_cfl']:.3e} -> {m['dt_scaled']:.3e} s, +{m['added_mass_percent']:.2f} "
                                     f"% mass; node {m['node']} differs by at most "
                                     f"{100 * (m['relative_difference'] or 0.0):.2f} % over {m['seconds']:.3g} s"))
    rows += [
        ("devices", f"{summary['n_devices']} x {summary['device_kind']}"
                    + (" (emulated in one process, sharing the CPU cores)" if summary.get("devices_emulated") else "")),
        ("time per step, synchronized", f"{summary['us_per_step_synchronized']:.1f} us"),
        ("time per step, predicted", "no step predicted" if summary["us_per_step_predicted"] is None
                                     else f"{summary['us_per_step_predicted']:.1f} us"),
        ("speed-up, end to end", "none (no step predicted)" if summary["speedup"] is None else
                                 f"{summary['speedup']:.2f}x (compiled chunks; compilation "
                                 f"{summary.get('compile_seconds', 0.0):.1f} s not included)"),
        ("zeta, compiled steps", f"{summary['zeta']:.2f}x against the {summary.get('zeta_sync', '')} "
                                 f"baseline (jaxsync.perf.timing.speedup_breakdown): synchronization "
                                 f"{summary['t_s_us']:.1f} us/step, surrogate {summary['t_d_us']:.1f} us/step"),
    ]
    if "projection" in summary:
        proj = summary["projection"]
        zetas = ", ".join(f"{r['interconnect']['name']} {r['zeta']:.2f}x" for r in proj["rows"])
        rows.append((f"zeta projected, {summary.get('n_parts', '')} processors", zetas))
    rows.append(("figures", summary.get("report", "")))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"  {k:<{width}}  {v}" for k, v in rows)
