"""The paper's cantilever experiment matrix (Tong & Schiavazzi 2022, section 5.1), one case at a time.

Every case trains per-part LSTM surrogates on synchronized runs of the cantilever (the
library's training defaults: only the case's own parameters n_s, n_p, n_f, n_ts, q and the
seed are passed; trainings on the 10-run ensembles take the default schedule counted in
gradient steps, 800 / 10 epochs with the decay gamma ** 10 per epoch) and compares the
synchronization-avoiding run, predicted from n_cri = n_s n_p on, with the synchronized
reference:

=====================  ====================================================================
``default``            the demo's pipeline: coarse cantilever, 2 parts, n_s 150, n_p = n_f 20,
                       1e5 steps, trained on the first half (the baseline)
``sequence_length``    (n_p, n_f) in (5, 5), (20, 20), (50, 50), (20, 5)       (figure 9)
``training_size``      n_ts in 0.2, 0.35, 0.5, 0.75                             (figure 10)
``refined_6_parts``    box_beam(divisions=(48, 4, 4)), 6 parts, n_s 350, 5e5 steps (11-12)
``skewed``             body force (0, -0.5, -0.5); y and z at the free end      (figure 13)
``step_off``           the load switched off at t = 3 s                          (figure 14)
``initial_conditions`` 10 runs from (1 + u) u_static, u ~ U(-0.25, 0.25) (one ensemble),
                       an unseen u; unconditional and conditional (q = 12) decoders (15)
``loads``              10 runs with f_z ~ U(0.3, 0.7), conditional decoder, unseen f_z (16-17)
``full_system``        one network over every dof of the serial problem, 98 400 steps
                       predicted without the solver (figures 18-20)
=====================  ====================================================================

Each case writes ``<out>/<case>/``: ``<case>.json`` (parameters, errors, timings, the
settings and time of every training, machine), ``<case>.png`` (the paper's figure),
``series.npz`` (times, free-end displacement and the saved fields of the reference and of
every online run: what the errors are computed from) and, except in reduced mode,
``training/<variant>/`` (the surrogate checkpoint, loss curves, ``train_summary.json``). ``--table`` (re)writes
``<out>/table.md`` from the JSON files found. Targets are recorded (met or not), never
asserted.

``--model linear``: every case with the linear autoregressive surrogate
(``train_surrogates(architecture=ArchitectureChoice(model="linear"))``, least squares on
the same windows; the full-system case fits it over every dof with ``fit_linear``) instead
of the LSTM; it is unconditional, so the ensemble cases train one unconditional variant
(``linear``). Write those elsewhere
(``--out benchmarks/results/experiments_linear``).

``--reduced`` (the tests): 3 000 steps (4 000 refined on a (12, 2, 2) beam), n_s 10 (20
refined), n_p = n_f = 5, (n_p, n_f) in (5, 5), (5, 2), n_ts in 0.25, 0.5, ensembles of 3
runs, the refined case on as many parts as devices (up to 6), n_H 8, one encoder layer, 2
epochs, no E_mse and no training files: a smoke run of the whole matrix in a few minutes,
whose errors mean nothing.

Within one process, ``default``, ``sequence_length`` and ``training_size`` share one
synchronized reference, and their variants with the default settings ((20, 20), n_ts 0.5)
one training and online run: the JSON says which case computed them (``reused_from``).

The settings, the metrics and the training wrapper, which other benchmark scripts use
too, are in ``experiments.py``; this script runs the cases, draws their figures and
writes the table.

Usage:
    python benchmarks/paper_experiments.py --case NAME [NAME ...] [--reduced] [--mesh FILE]
        [--steps N] [--seed S] [--out benchmarks/results/experiments] [--quiet]
    python benchmarks/paper_experiments.py --all [--reduced] ...
    python benchmarks/paper_experiments.py --table [--out DIR]
"""

from __future__ import annotations

import argparse
import dataclasses
import glob
import json
import math
import os
import sys
import time
import traceback

N_DEVICES = 6  # the refined case's parts (experiments.PAPER_REFINED_PARTS), one emulated device each

if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    # before jax is imported; in-process callers (the tests) have set their own count
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                               + f" --xla_force_host_platform_device_count={N_DEVICES}").strip()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import experiments  # noqa: E402
from experiments import (  # noqa: E402
    BODY_FORCES,
    Settings,
    check_tip,
    excluded_nodes,
    high_frequency_error,
    paper_settings,
    reduced_settings,
    run_metrics,
    run_stats,
    targets,
    timed,
)

import jaxsync  # noqa: E402
from jaxsync.app.plots import tip_node  # noqa: E402
from jaxsync.io import atomic_json, atomic_path  # noqa: E402
from jaxsync.metrics import l2_error, node_error  # noqa: E402
from jaxsync.options import SurrogateModel, choices  # noqa: E402
from jaxsync.surrogate import (  # noqa: E402
    LSTMArchitecture,
    Surrogate,
    TrainConfig,
    TrainingChecks,
    build_dataset,
    fit_linear,
    stack_replicas,
    train_replicas,
)
from jaxsync.surrogate.training import rollout_errors  # noqa: E402

CASES = ("default", "sequence_length", "training_size", "refined_6_parts", "skewed", "step_off",
         "initial_conditions", "loads", "full_system")
DEFAULT_OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "experiments")
PAPER_FIGURES = {"default": "7-8", "sequence_length": "9", "training_size": "10", "refined_6_parts": "11-12",
                 "skewed": "13", "step_off": "14", "initial_conditions": "15", "loads": "16-17",
                 "full_system": "18-20"}
# the offline check's tolerance of train_surrogates (the full-system case applies the same)
ROLLOUT_TOLERANCE = TrainingChecks.rollout_tolerance


@dataclasses.dataclass
class Context:
    settings: Settings
    out: str
    mesh_file: str | None
    seed: int
    progress: bool
    steps: int | None  # --steps: every case's total steps
    model: str = "lstm"  # --model: the surrogate every case trains
    # synchronized references already computed in this process (default, sequence_length
    # and training_size share one), by what defines them
    references: dict = dataclasses.field(default_factory=dict)
    # their variants with the same settings (sequence_length (20, 20) and training_size 0.5
    # are the default case): the training and online run are reused too
    online_runs: dict = dataclasses.field(default_factory=dict)

    def n_steps(self, default: int) -> int:
        return default if self.steps is None else self.steps

    def coarse_mesh(self):
        return jaxsync.read_mesh(self.mesh_file) if self.mesh_file else jaxsync.box_beam()

    def mesh_name(self) -> str:
        return os.path.abspath(self.mesh_file) if self.mesh_file else "box_beam()"

    def executor(self) -> jaxsync.HostExecutor:
        return jaxsync.HostExecutor(progress=self.progress)


def log(ctx: Context, text: str) -> None:
    if ctx.progress:
        print(text, file=sys.stderr, flush=True)


# ----------------------------------------------------------------------------- runs


def train(ctx: Context, trajectories, folder: str, *, n_s: int, n_past: int, n_future: int,
          train_fraction: float, n_cond_repeat: int = 0):
    """:func:`experiments.train` with the case's parameters only (the library's defaults
    for the rest, or the reduced overrides); reduced mode writes no training files
    (checkpoint, loss curves: about 1.3 s a training)."""
    parameters = dict(n_s=n_s, n_past=n_past, n_future=n_future, train_fraction=train_fraction, seed=ctx.seed)
    if ctx.model != "lstm":
        parameters["model"] = ctx.model
    if n_cond_repeat:
        parameters["n_cond_repeat"] = n_cond_repeat
    n_runs = len(trajectories) if isinstance(trajectories, (list, tuple)) else 1
    if n_runs > 1 and not ctx.settings.reduced and ctx.model == "lstm":
        # n_runs times the windows of one run: the library's schedule counted in gradient
        # steps (epochs / n_runs, the per-epoch decay gamma ** n_runs), not in epochs, which
        # would make it n_runs times longer (about 25 minutes for 10 runs on 2 cores)
        default = TrainConfig()
        parameters["config"] = TrainConfig(n_epochs=math.ceil(default.n_epochs / n_runs),
                                           gamma=default.gamma ** n_runs,
                                           patience=math.ceil(default.patience / n_runs))
    return experiments.train(trajectories, parameters,
                             overrides=ctx.settings.train_overrides if ctx.model == "lstm" else {},
                             folder=None if ctx.settings.reduced else folder, progress=ctx.progress)


def online_run(ctx: Context, problem, parts, surrogates, n_steps: int, n_cri: int, save_every: int,
               load_jumps: str = "synchronize"):
    """The synchronization-avoiding run and its record."""
    online, seconds = timed(jaxsync.simulate_sync_avoiding, problem, n_steps, partitions=parts,
                            surrogates=surrogates, n_cri=n_cri, save=save_every, load_jumps=load_jumps,
                            executor=ctx.executor())
    return online, run_stats(online, seconds)


def surrogates_of(trained, load_parameter=None):
    """What the online run predicts with: the surrogate file's record (its shared nodes are
    checked against the partition), or for a conditional network its surrogate with the
    test run's label."""
    if load_parameter is None:
        return trained.saved
    return Surrogate.from_saved(trained.saved, load_parameter)


def variant_entry(name: str, parameters: dict, training: dict | None, online: dict, metrics: dict, kind: str,
                  extra: dict | None = None) -> dict:
    out = {"name": name, "parameters": parameters, "training": training, "online": online, "metrics": metrics,
           "targets": targets(metrics, kind)}
    out.update(extra or {})
    return out


def add_series(series: dict, variant: str, times, reference, predicted, tip: int, components=(2,)) -> None:
    """The time series of one online run: times, the free-end components, both fields."""
    series[f"{variant}__times"] = np.asarray(times, np.float64)
    for c in components:
        axis = "xyz"[c]
        series[f"{variant}__{axis}_reference"] = np.asarray(reference[:, tip, c], np.float64)
        series[f"{variant}__{axis}_predicted"] = np.asarray(predicted[:, tip, c], np.float64)
    series[f"{variant}__field_reference"] = np.asarray(reference, np.float64)
    series[f"{variant}__field_predicted"] = np.asarray(predicted, np.float64)


# ----------------------------------------------------------------------------- cases


@dataclasses.dataclass(frozen=True)
class FixedLoad:
    """A case of one synchronized reference and, per variant (name, n_p, n_f, n_ts), a
    training and an online run compared with it (:func:`fixed_load_case`).

    Attributes:
        name: the case.
        problem, parts: the problem and its partition.
        variants: (name, n_p, n_f, n_ts) of every variant.
        n_steps, n_s: total steps; the sampling stride.
        save: the reference's snapshots (the full field every ``save.every`` steps, the
            shared nodes every ``save.shared_every``); the online runs save every
            ``save.every`` steps.
        final_relative_to: the final free-end error relative to the "final value" or to
            the "amplitude" (:func:`experiments.run_metrics`).
        components: the free-end components reported (2 = z, the targets' one).
        notes: the case's notes.
        reference_key: cases with the same key (the default cantilever) share the
            reference computed first in this process, and the training and online run of
            variants of the same settings.
        compare_raw_refill: the same networks also run with the paper's raw refill
            (``Surrogate.smooth=False``), reported as ``raw_refill`` (the noise
            measurement).
        compare_load_jumps: the same networks also predict through the load jumps (the
            paper's way, ``load_jumps="predict"``), reported as
            ``predicted_through_load_jumps``.
    """

    name: str
    problem: object
    parts: object
    variants: tuple
    n_steps: int
    n_s: int
    save: jaxsync.SaveAt
    final_relative_to: str = "final value"
    components: tuple = (2,)
    notes: tuple = ()
    reference_key: str | None = None
    compare_raw_refill: bool = False
    compare_load_jumps: bool = False


def fixed_load_case(ctx: Context, case: FixedLoad):
    """The reference and every variant of ``case``: (the record's entries, the series)."""
    name, problem, parts, n_steps, n_s = case.name, case.problem, case.parts, case.n_steps, case.n_s
    save_every = case.save.every
    key = (case.reference_key, n_steps, save_every, case.save.shared_every, ctx.seed, parts.n_parts)
    if case.reference_key is not None and key in ctx.references:
        reference, stats, parts = ctx.references[key]  # and its partition, whatever METIS gives now
        stats = {**stats, "reused_from_case": stats.get("reused_from_case", stats["case"])}
        log(ctx, f"[{name}] synchronized reference: the one of case {stats['reused_from_case']}")
    else:
        log(ctx, f"[{name}] synchronized reference: {n_steps} steps, dt {problem.dt:.4e} s, {parts.n_parts} parts")
        reference, seconds = timed(jaxsync.simulate, problem, n_steps, partitions=parts, save=case.save,
                                   executor=ctx.executor())
        stats = {**run_stats(reference, seconds), "case": name}
        if case.reference_key is not None:
            ctx.references[key] = (reference, stats, parts)
    tip = check_tip(problem.mesh, parts)
    out = {"reference": stats, "variants": [], "tip_node": tip}
    series = {}
    excluded = excluded_nodes(problem, parts)

    def metrics_of(predicted, component=2):
        return run_metrics(reference.displacement, predicted.displacement, tip, excluded,
                           final_relative_to=case.final_relative_to, component=component)

    for variant, n_p, n_f, fraction in case.variants:
        n_cri = n_s * n_p
        run_key = (key, n_s, n_p, n_f, fraction)
        if case.reference_key is not None and run_key in ctx.online_runs:
            # the same training (same data, settings and seed: bit-identical) and online run
            online, training, stats, origin, trained = ctx.online_runs[run_key]
            training, stats = {**training, "reused_from": origin}, {**stats, "reused_from": origin}
            log(ctx, f"[{name}/{variant}] training and online run: those of {origin}")
        else:
            log(ctx, f"[{name}/{variant}] training (n_s {n_s}, n_p {n_p}, n_f {n_f}, n_ts {fraction})")
            trained, training = train(ctx, reference, os.path.join(ctx.out, name, "training", variant), n_s=n_s,
                                      n_past=n_p, n_future=n_f, train_fraction=fraction)
            log(ctx, f"[{name}/{variant}] online run from n_cri {n_cri}")
            online, stats = online_run(ctx, problem, parts, surrogates_of(trained), n_steps, n_cri, save_every)
            if case.reference_key is not None:
                ctx.online_runs[run_key] = (online, training, stats, f"{name}/{variant}", trained)
        metrics = metrics_of(online)
        extra = {}
        if case.compare_raw_refill:
            raw_surrogate = dataclasses.replace(Surrogate.from_saved(trained.saved), smooth=False)
            log(ctx, f"[{name}/{variant}] online run with the raw refill")
            raw, raw_stats = online_run(ctx, problem, parts, raw_surrogate, n_steps, n_cri, save_every)
            extra["raw_refill"] = {
                "metrics": metrics_of(raw), "online": raw_stats,
                "high_frequency": {"raw": high_frequency_error(reference.displacement, raw.displacement, excluded),
                                   "smooth": high_frequency_error(reference.displacement, online.displacement,
                                                                  excluded)}}
            series[f"{variant}__field_predicted_raw_refill"] = np.asarray(raw.displacement, np.float64)
        if case.compare_load_jumps:
            log(ctx, f"[{name}/{variant}] online run predicting through the load jumps")
            through, through_stats = online_run(ctx, problem, parts, surrogates_of(trained), n_steps, n_cri,
                                                save_every, load_jumps="predict")
            through_metrics = metrics_of(through)
            extra["predicted_through_load_jumps"] = {"metrics": through_metrics, "online": through_stats,
                                                     "targets": targets(through_metrics, "fixed")}
            series[f"{variant}__z_predicted_through_load_jumps"] = np.asarray(through.displacement[:, tip, 2],
                                                                              np.float64)
        for c in case.components:
            if c != 2:
                extra[f"tip_{'xyz'[c]}"] = metrics_of(online, component=c)
        out["variants"].append(variant_entry(
            variant, {"n_s": n_s, "n_past": n_p, "n_future": n_f, "train_fraction": fraction, "n_cri": n_cri},
            training, stats, metrics, "fixed", extra))
        add_series(series, variant, reference.times, reference.displacement, online.displacement, tip,
                   case.components)
    out["notes"] = list(case.notes)
    return out, series


def coarse_cantilever(ctx: Context):
    """(settings, the default cantilever on the coarse mesh, its partition, total steps)."""
    s = ctx.settings
    mesh = ctx.coarse_mesh()
    return s, jaxsync.cantilever(mesh), jaxsync.partition(mesh, s.n_parts, seed=ctx.seed), ctx.n_steps(s.n_steps)


def case_default(ctx: Context):
    s, problem, parts, n_steps = coarse_cantilever(ctx)
    params = {"n_steps": n_steps, "n_s": s.n_s, "n_past": s.n_past, "n_future": s.n_future,
              "train_fraction": s.train_fraction, "n_parts": s.n_parts, "save_every": s.save_every, "shared_every": 1,
              "n_cri": s.n_s * s.n_past, "body_force": list(BODY_FORCES["default"]), "t_off": None}
    out, series = fixed_load_case(ctx, FixedLoad(
        "default", problem, parts, (("default", s.n_past, s.n_future, s.train_fraction),), n_steps, s.n_s,
        jaxsync.SaveAt(s.save_every, 1), reference_key="default cantilever", compare_raw_refill=True))
    return params, problem, parts, out, series


def case_sequence_length(ctx: Context):
    s, problem, parts, n_steps = coarse_cantilever(ctx)
    variants = tuple((f"np{p}_nf{f}", p, f, s.train_fraction) for p, f in s.sequence_variants)
    params = {"n_steps": n_steps, "n_s": s.n_s, "variants": [[p, f] for p, f in s.sequence_variants],
              "train_fraction": s.train_fraction, "n_parts": s.n_parts, "save_every": s.save_every, "shared_every": 1,
              "body_force": list(BODY_FORCES["default"])}
    out, series = fixed_load_case(ctx, FixedLoad(
        "sequence_length", problem, parts, variants, n_steps, s.n_s, jaxsync.SaveAt(s.save_every, 1),
        reference_key="default cantilever", notes=("n_cri = n_s n_p differs between the variants",)))
    return params, problem, parts, out, series


def case_training_size(ctx: Context):
    s, problem, parts, n_steps = coarse_cantilever(ctx)
    variants = tuple((f"nts{f:.2f}", s.n_past, s.n_future, f) for f in s.training_fractions)
    params = {"n_steps": n_steps, "n_s": s.n_s, "n_past": s.n_past, "n_future": s.n_future,
              "train_fractions": list(s.training_fractions), "n_parts": s.n_parts, "save_every": s.save_every,
              "shared_every": 1, "n_cri": s.n_s * s.n_past, "body_force": list(BODY_FORCES["default"])}
    out, series = fixed_load_case(ctx, FixedLoad("training_size", problem, parts, variants, n_steps, s.n_s,
                                                 jaxsync.SaveAt(s.save_every, 1), reference_key="default cantilever"))
    return params, problem, parts, out, series


def case_refined(ctx: Context):
    s = ctx.settings
    mesh = jaxsync.box_beam(divisions=s.refined_divisions)
    problem = jaxsync.cantilever(mesh)
    n_parts = s.refined_parts
    parts = jaxsync.partition(mesh, n_parts, seed=ctx.seed)
    n_steps = ctx.n_steps(s.refined_steps)
    n_s, save_every = s.refined_n_s, s.refined_save_every
    # the shared nodes at every step would take GBs over 5e5 steps: keep them at the
    # largest stride that divides both n_s and save_every (the offline rollout check,
    # which reads every step, is then skipped; training reads every n_s-th step only)
    shared_every = 1 if s.reduced else math.gcd(n_s, save_every)
    notes = []
    if len(jax.devices()) < N_DEVICES:
        notes.append(f"{len(jax.devices())} devices available: {n_parts} parts"
                     + (" (reduced mode: as many parts as devices, up to 6)" if s.reduced
                        else " share them (the paper: 6 parts on 6 processors)"))
    notes.append(f"CFL dt of this mesh {problem.dt:.4e} s; the paper's refined mesh (4 615 tets) has 6.2e-5 s: "
                 "the generated box mesh's shortest edges differ (its coarse mesh gives 3.50e-4 s against the "
                 "paper's 2.48e-4 s, the same factor sqrt(2))")
    if shared_every > 1:
        notes.append(f"shared nodes kept every {shared_every} steps (memory): no offline rollout check")
    params = {"n_steps": n_steps, "n_s": n_s, "n_past": s.n_past, "n_future": s.n_future,
              "train_fraction": s.train_fraction, "n_parts": n_parts, "n_parts_paper": 6,
              "divisions": list(s.refined_divisions), "save_every": save_every, "shared_every": shared_every,
              "n_cri": n_s * s.n_past, "n_predicted_steps": n_steps - n_s * s.n_past, "dt": problem.dt,
              "dt_paper": 6.2e-5, "body_force": list(BODY_FORCES["default"])}
    out, series = fixed_load_case(ctx, FixedLoad(
        "refined_6_parts", problem, parts, (("refined", s.n_past, s.n_future, s.train_fraction),), n_steps, n_s,
        jaxsync.SaveAt(save_every, shared_every), notes=tuple(notes)))
    return params, problem, parts, out, series


def case_skewed(ctx: Context):
    s = ctx.settings
    mesh = ctx.coarse_mesh()
    force = BODY_FORCES["skewed"]
    problem = jaxsync.cantilever(mesh, body_force=force)
    parts = jaxsync.partition(mesh, s.n_parts, seed=ctx.seed)
    n_steps = ctx.n_steps(s.n_steps)
    params = {"n_steps": n_steps, "n_s": s.n_s, "n_past": s.n_past, "n_future": s.n_future,
              "train_fraction": s.train_fraction, "n_parts": s.n_parts, "save_every": s.save_every, "shared_every": 1,
              "n_cri": s.n_s * s.n_past, "body_force": list(force)}
    out, series = fixed_load_case(ctx, FixedLoad(
        "skewed", problem, parts, (("skewed", s.n_past, s.n_future, s.train_fraction),), n_steps, s.n_s,
        jaxsync.SaveAt(s.save_every, 1), components=(1, 2),
        notes=("z is the target component; y is reported under tip_y",)))
    return params, problem, parts, out, series


def case_step_off(ctx: Context):
    s = ctx.settings
    mesh = ctx.coarse_mesh()
    problem = jaxsync.cantilever(mesh, t_off=s.t_off)
    parts = jaxsync.partition(mesh, s.n_parts, seed=ctx.seed)
    n_steps = ctx.n_steps(s.n_steps)
    params = {"n_steps": n_steps, "n_s": s.n_s, "n_past": s.n_past, "n_future": s.n_future,
              "train_fraction": s.train_fraction, "n_parts": s.n_parts, "save_every": s.save_every, "shared_every": 1,
              "n_cri": s.n_s * s.n_past, "body_force": list(BODY_FORCES["default"]), "t_off": s.t_off}
    notes = ["final error relative to the free end's amplitude, not to its final value: after the load is "
             "switched off the beam decays towards rest, so the final reference value is close to 0 and an "
             "error relative to it would be meaningless",
             "the online run stays synchronized through the load jump (simulate_sync_avoiding's default "
             "load_jumps='synchronize') until the networks' whole input history follows it; the same networks "
             "predicting through it from n_cri, as the paper did, are reported as predicted_through_load_jumps"]
    if s.reduced:
        notes.append("reduced mode: t_off 0.5 s so that the load is switched off within the short run")
    out, series = fixed_load_case(ctx, FixedLoad(
        "step_off", problem, parts, (("step_off", s.n_past, s.n_future, s.train_fraction),), n_steps, s.n_s,
        jaxsync.SaveAt(s.save_every, 1), final_relative_to="amplitude", notes=tuple(notes),
        compare_load_jumps=True))
    return params, problem, parts, out, series


def draw_labels(rng, n: int, low: float, high: float):
    """n training labels and one test label from U(low, high), the test not among them."""
    train_labels = rng.uniform(low, high, size=n)
    test = float(rng.uniform(low, high))
    while np.isclose(train_labels, test, rtol=0, atol=1e-9).any():
        test = float(rng.uniform(low, high))
    return [float(v) for v in train_labels], test


def ensemble_case(ctx: Context, name: str, make_problem, train_labels, test_label, label_name: str, variants):
    """Training runs of one ensemble call (labels stored as the load parameter), a test run
    of an unseen label computed by jaxsync.simulate, and per variant (name, q) a training
    on all runs and an online run of the test problem."""
    s = ctx.settings
    problems = [make_problem(v) for v in train_labels]
    test_problem = make_problem(test_label)
    mesh = test_problem.mesh
    parts = jaxsync.partition(mesh, s.n_parts, seed=ctx.seed)
    tip = check_tip(mesh, parts)
    n_steps = ctx.n_steps(s.n_steps)
    log(ctx, f"[{name}] ensemble of {len(problems)} training runs ({label_name} = "
        + ", ".join(f"{v:.4g}" for v in train_labels) + ")")
    runs, seconds = timed(jaxsync.ensemble, problems, n_steps, partitions=parts, labels=train_labels,
                          save=jaxsync.SaveAt(s.save_every, 1), executor=ctx.executor())
    ensemble_stats = run_stats(runs[0], seconds)
    log(ctx, f"[{name}] test run, unseen {label_name} = {test_label:.4g}")
    reference, ref_seconds = timed(jaxsync.simulate, test_problem, n_steps, partitions=parts, save=s.save_every,
                                   executor=ctx.executor())
    out = {"tip_node": tip, "reference": run_stats(reference, ref_seconds),
           "training_data": {"generated_by": "jaxsync.ensemble (one call)", "n_runs": len(runs),
                             "label_name": label_name, "labels": list(train_labels), "test_label": test_label,
                             "test_label_unseen": test_label not in train_labels, "ensemble": ensemble_stats,
                             "labels_stored": [t.parameters.get("load_parameter") for t in runs]},
           "variants": [], "notes": []}
    series = {"training__times": np.asarray(runs[0].times), "training__labels": np.asarray(train_labels),
              "training__z": np.stack([np.asarray(t.displacement[:, tip, 2]) for t in runs])}
    excluded = excluded_nodes(test_problem, parts)
    n_cri = s.n_s * s.n_past
    if ctx.model != "lstm":  # unconditional only
        variants = [(ctx.model, 0)]
    for variant, q in variants:
        log(ctx, f"[{name}/{variant}] training on {len(runs)} runs" + (f", conditional (q = {q})" if q else ""))
        trained, training = train(ctx, list(runs), os.path.join(ctx.out, name, "training", variant), n_s=s.n_s,
                                  n_past=s.n_past, n_future=s.n_future, train_fraction=s.train_fraction,
                                  n_cond_repeat=q)
        log(ctx, f"[{name}/{variant}] online run from n_cri {n_cri}")
        online, stats = online_run(ctx, test_problem, parts, surrogates_of(trained, test_label if q else None),
                                   n_steps, n_cri, s.save_every)
        metrics = run_metrics(reference.displacement, online.displacement, tip, excluded)
        out["variants"].append(variant_entry(
            variant, {"n_s": s.n_s, "n_past": s.n_past, "n_future": s.n_future, "train_fraction": s.train_fraction,
                      "n_cri": n_cri, "n_cond_repeat": q, "conditional": bool(q),
                      "test_label": test_label}, training, stats, metrics, "unseen"))
        add_series(series, variant, reference.times, reference.displacement, online.displacement, tip)
    params = {"n_steps": n_steps, "n_s": s.n_s, "n_past": s.n_past, "n_future": s.n_future,
              "train_fraction": s.train_fraction, "n_parts": s.n_parts, "save_every": s.save_every, "shared_every": 1,
              "n_cri": n_cri, "n_runs": len(runs), "n_cond_repeat": s.n_cond_repeat, "label": label_name,
              "labels": list(train_labels), "test_label": test_label, "seed": ctx.seed}
    return params, test_problem, parts, out, series


def case_initial_conditions(ctx: Context):
    s = ctx.settings
    mesh = ctx.coarse_mesh()
    static = np.asarray(jaxsync.steady_state(jaxsync.cantilever(mesh)))
    rng = np.random.default_rng(ctx.seed)
    train_labels, test = draw_labels(rng, s.n_runs, -s.ic_range, s.ic_range)

    def make(u):
        return jaxsync.cantilever(mesh, initial_displacement=(1.0 + u) * static)

    params, problem, parts, out, series = ensemble_case(
        ctx, "initial_conditions", make, train_labels, test, "u",
        [("unconditional", 0), ("conditional", s.n_cond_repeat)])
    params.update(u_range=[-s.ic_range, s.ic_range], static_tip_z_cm=float(static[tip_node(mesh), 2]),
                  body_force=list(BODY_FORCES["default"]))
    out["notes"].append("initial displacement (1 + u) times the static solution of the default cantilever, "
                        "default ramped load; the paper ran the unconditional decoder only")
    return params, problem, parts, out, series


def case_loads(ctx: Context):
    s = ctx.settings
    mesh = ctx.coarse_mesh()
    rng = np.random.default_rng(ctx.seed)
    train_labels, test = draw_labels(rng, s.n_runs, *s.load_range)

    def make(fz):
        return jaxsync.cantilever(mesh, body_force=(0.0, 0.0, -fz))

    params, problem, parts, out, series = ensemble_case(ctx, "loads", make, train_labels, test, "f_z",
                                                        [("conditional", s.n_cond_repeat)])
    params.update(f_z_range=list(s.load_range))
    out["notes"].append("body force (0, 0, -f_z), ramped over 1 s; the label is f_z")
    return params, problem, parts, out, series


def case_full_system(ctx: Context):
    """One network over every dof of the serial problem (build_dataset, stack_replicas,
    train_replicas with the library's TrainConfig() and LSTMArchitecture defaults), the
    same offline rollout check as train_surrogates, then simulate_full_system."""
    s = ctx.settings
    mesh = ctx.coarse_mesh()
    problem = jaxsync.cantilever(mesh)
    n_steps = ctx.n_steps(s.n_steps)
    n_s, n_p, n_f = s.n_s, s.n_past, s.n_future
    n_cri = n_s * n_p
    tip = check_tip(mesh, None)
    log(ctx, f"[full_system] serial reference saved at every step: {n_steps} steps")
    reference, seconds = timed(jaxsync.simulate, problem, n_steps, save=1, executor=ctx.executor())
    history = np.asarray(reference.displacement).reshape(n_steps + 1, -1)
    data = stack_replicas([build_dataset([history], n_s, n_p, n_f, s.train_fraction, split_seed=ctx.seed)])
    overrides = ctx.settings.train_overrides
    arch = LSTMArchitecture(n_dof=data.n_dof_max, n_past=n_p, n_future=n_f,
                            **{k: overrides[k] for k in ("n_hidden", "n_layers") if k in overrides})
    config = overrides.get("config", TrainConfig())
    log(ctx, f"[full_system] training one {ctx.model} surrogate over {history.shape[1]} dofs")
    if ctx.model == "linear":
        result, train_seconds = timed(fit_linear, data)
        arch, config = result.arch, result.config
    else:
        result, train_seconds = timed(train_replicas, data, arch, config, jax.random.key(ctx.seed),
                                      progress=ctx.progress)
    surrogate = Surrogate.from_result(result, n_s)
    folder = None if s.reduced else os.path.join(ctx.out, "full_system", "training", "full_system")
    if folder is not None:
        os.makedirs(folder, exist_ok=True)
        surrogate.save(os.path.join(folder, "surrogate.h5"), metadata={"case": "full_system"})
    rollout = rollout_errors(surrogate, np.pad(history, ((0, 0), (0, arch.n_dof - history.shape[1])))[None])
    worst = float(rollout.relative.max())
    warning = None
    if worst > ROLLOUT_TOLERANCE:
        warning = (f"the full-system surrogate misses the offline check: rolled out without the truth over "
                   f"{rollout.n_steps} steps, off by up to {100 * worst:.2g} % of the amplitude (tolerance "
                   f"{100 * ROLLOUT_TOLERANCE:.2g} %)")
    training = {
        "case_parameters_passed": {"n_s": n_s, "n_past": n_p, "n_future": n_f, "train_fraction": s.train_fraction,
                                   "seed": ctx.seed},
        "overrides_passed": (sorted(k for k in overrides if k in ("config", "n_hidden", "n_layers"))
                             if ctx.model == "lstm" else []),
        "n_training_runs": 1, "train_seconds": train_seconds,
        "n_epochs_run": result.n_epochs_run, "rollout_relative": rollout.relative.tolist(),
        "rollout_passed": worst <= ROLLOUT_TOLERANCE, "rollout_warning": warning,
        "folder": None if folder is None else os.path.abspath(folder),
        "summary": {"model": ctx.model, "architecture": {"kind": arch.kind, **arch.to_dict()},
                    "training": {**config.to_dict(), "n_epochs_run": result.n_epochs_run,
                                 "stopped_at_epoch": result.stopped_epoch},
                    "n_train_windows": int(data.x_train.shape[1]), "n_val_windows": int(data.x_val.shape[1]),
                    "final_val_loss": result.best_val_loss.tolist(), "seconds_per_epoch": result.seconds_per_epoch,
                    "compile_seconds": result.compile_seconds, "train_seconds": train_seconds,
                    "rollout_check": {**rollout.to_dict(), "tolerance": ROLLOUT_TOLERANCE}},
    }
    if folder is not None:
        atomic_json(os.path.join(folder, "train_summary.json"), training["summary"])
    log(ctx, f"[full_system] predicting steps {n_cri + 1}..{n_steps} without the solver")
    predicted, online_seconds = timed(jaxsync.simulate_full_system, problem, reference, surrogate, n_cri=n_cri)
    stats = run_stats(predicted, online_seconds)
    # every case is compared at the snapshots every n_s steps (series.npz keeps those);
    # the free end is also checked at every step
    keep = slice(0, None, n_s)
    ref_field, pred_field = np.asarray(reference.displacement), np.asarray(predicted.displacement)
    metrics = run_metrics(ref_field[keep], pred_field[keep], tip, excluded_nodes(problem, None))
    metrics["tip_max_error_relative_every_step"] = node_error(ref_field, pred_field, tip, 2).relative
    fixed, values = problem.dirichlet_dofs()
    clamped = np.abs(pred_field.reshape(n_steps + 1, -1)[:, fixed] - np.asarray(values)).max(axis=1)
    metrics["dirichlet_max_abs_predicted_cm"] = predicted.stats.dirichlet_max_abs_predicted
    out = {"tip_node": tip, "reference": run_stats(reference, seconds),
           "variants": [variant_entry("full_system", {"n_s": n_s, "n_past": n_p, "n_future": n_f,
                                                       "train_fraction": s.train_fraction, "n_cri": n_cri},
                                      training, stats, metrics, "full_system")],
           "notes": ["metrics at the snapshots every n_s steps; tip_max_error_relative_every_step at every step",
                     "the network does not know the clamp, but the clamped dofs never move in its training "
                     "data, so their normalization has std 0 and they invert to their value whatever the "
                     "network says; dirichlet_max_abs_predicted_cm is the largest |predicted displacement| on "
                     "them (paper figure 20, where it is not 0)"]}
    series = {}
    add_series(series, "full_system", reference.times[keep], ref_field[keep], pred_field[keep], tip)
    series["full_system__every_step_times"] = np.asarray(reference.times)
    series["full_system__every_step_z_reference"] = ref_field[:, tip, 2].copy()
    series["full_system__every_step_z_predicted"] = pred_field[:, tip, 2].copy()
    series["full_system__clamped_max_abs_predicted"] = clamped
    params = {"n_steps": n_steps, "n_s": n_s, "n_past": n_p, "n_future": n_f, "train_fraction": s.train_fraction,
              "n_parts": 1, "save_every": 1, "metrics_every": n_s, "n_cri": n_cri,
              "n_predicted_steps": n_steps - n_cri, "n_dof": int(history.shape[1]),
              "body_force": list(BODY_FORCES["default"])}
    return params, problem, None, out, series


CASE_FUNCTIONS = {"default": case_default, "sequence_length": case_sequence_length,
                  "training_size": case_training_size, "refined_6_parts": case_refined, "skewed": case_skewed,
                  "step_off": case_step_off, "initial_conditions": case_initial_conditions, "loads": case_loads,
                  "full_system": case_full_system}


# ----------------------------------------------------------------------------- figure


def case_figure(name: str, record: dict, series: dict, path: str) -> None:
    """The paper's figure of a case: free-end displacement of the reference and of every
    variant (training runs faint), its error relative to the amplitude, e_l2, and for the
    full system the predicted displacement on the clamped end."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    variants = [v["name"] for v in record["variants"]]
    components = [c for c in "yz" if f"{variants[0]}__{c}_reference" in series]
    full = "full_system__clamped_max_abs_predicted" in series
    n_panels = len(components) + 2 + int(full)
    fig = Figure(figsize=(9, 2.6 * n_panels))
    FigureCanvasAgg(fig)
    axes = fig.subplots(n_panels, 1, sharex=True)
    # where each online run started predicting (later than n_cri when it synchronized through a load jump)
    n_cri_times = {v["name"]: (v["online"] or {}).get("n_cri", v["parameters"]["n_cri"]) * record["dt"]
                   for v in record["variants"]}
    for ax, c in zip(axes, components):
        if c == "z" and "training__z" in series:
            for k, z in enumerate(series["training__z"]):
                ax.plot(series["training__times"], z, color="0.75", lw=0.6,
                        label="training runs" if k == 0 else None)
        drawn = set()
        for v in variants:
            ref_key = f"{v}__{c}_reference"
            ref = series[ref_key]
            key = (len(ref), float(ref[-1]))
            if key not in drawn:  # variants compared with the same reference: draw it once
                ax.plot(series[f"{v}__times"], ref, "k-", lw=1.2, label="synchronized" if not drawn else None)
                drawn.add(key)
            ax.plot(series[f"{v}__times"], series[f"{v}__{c}_predicted"], "--", lw=1.0, label=f"{v} (predicted)")
            if c == "z" and f"{v}__z_predicted_through_load_jumps" in series:
                ax.plot(series[f"{v}__times"], series[f"{v}__z_predicted_through_load_jumps"], ":", lw=1.0,
                        label=f"{v} (predicted through the load jump)")
        ax.set_ylabel(f"free-end {c} [cm]")
        ax.legend(fontsize="x-small", ncol=2)
    ax = axes[len(components)]
    for v in variants:
        z_ref = series[f"{v}__z_reference"]
        error = 100 * np.abs(series[f"{v}__z_predicted"] - z_ref) / np.abs(z_ref).max()
        ax.plot(series[f"{v}__times"], error, lw=0.9, label=v)
        if f"{v}__z_predicted_through_load_jumps" in series:
            error = 100 * np.abs(series[f"{v}__z_predicted_through_load_jumps"] - z_ref) / np.abs(z_ref).max()
            ax.plot(series[f"{v}__times"], error, ":", lw=0.9, label=f"{v} (predicted through the load jump)")
    kind = record["variants"][0]["targets"]
    ax.axhline(kind["tip_max_within_percent"], color="r", ls=":", lw=1.0,
               label=f"target {kind['tip_max_within_percent']:g} %")
    ax.set_ylabel("free-end z error\n[% of amplitude]")
    ax.legend(fontsize="x-small", ncol=2)
    ax = axes[len(components) + 1]
    for v in variants:
        ax.plot(series[f"{v}__times"], l2_error(series[f"{v}__field_reference"], series[f"{v}__field_predicted"]),
                lw=0.9, label=v)
    ax.set_ylabel("e_l2 [cm]")
    ax.legend(fontsize="x-small", ncol=2)
    if full:
        ax = axes[-1]
        ax.plot(series["full_system__every_step_times"], series["full_system__clamped_max_abs_predicted"], lw=0.8)
        ax.set_ylabel("largest |predicted|\non the clamp [cm]")
    for ax in axes:
        for t in sorted(set(n_cri_times.values())):
            ax.axvline(t, color="0.5", ls=":", lw=0.7)
        ax.grid(True, alpha=0.3)
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(f"{name}: {record['description']} (paper figure {record['paper_figures']})"
                 + (" -- REDUCED smoke run" if record["reduced"] else ""), fontsize="small")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")


# ----------------------------------------------------------------------------- driver


DESCRIPTIONS = {
    "default": "coarse cantilever, 2 parts, the demo's pipeline (baseline)",
    "sequence_length": "input/output sequence lengths n_p, n_f",
    "training_size": "training fraction n_ts",
    "refined_6_parts": "refined cantilever, 6 parts, n_s 350",
    "skewed": "skewed body force (0, -0.5, -0.5)",
    "step_off": "load switched off at t_off",
    "initial_conditions": "initial displacement (1 + u) u_static, unseen u",
    "loads": "load magnitude f_z, conditional decoder, unseen f_z",
    "full_system": "one network over every dof, no solver after n_cri",
}


def run_case(ctx: Context, name: str) -> dict:
    start = time.perf_counter()
    folder = os.path.join(ctx.out, name)
    os.makedirs(folder, exist_ok=True)
    load_before = os.getloadavg()[0]
    params, problem, parts, out, series = CASE_FUNCTIONS[name](ctx)
    params = {**params, "seed": ctx.seed, "reduced": ctx.settings.reduced}
    mesh = problem.mesh
    record = {
        "case": name, "description": DESCRIPTIONS[name], "paper_figures": PAPER_FIGURES[name],
        "reduced": ctx.settings.reduced, "model": ctx.model, "parameters": params,
        "mesh": {"source": ("box_beam(divisions=%s)" % (tuple(ctx.settings.refined_divisions),)
                            if name == "refined_6_parts" else ctx.mesh_name()),
                 "n_nodes": int(mesh.n_nodes), "n_elements": int(mesh.n_elements)},
        "dt": float(problem.dt), "simulated_seconds": float(params["n_steps"] * problem.dt),
        "n_parts": 1 if parts is None else int(parts.n_parts),
        "n_shared_nodes": 0 if parts is None else int(parts.n_interface),
        **out,
        "settings": ctx.settings.to_dict(),
        "targets_met": all(v["targets"]["met"] for v in out["variants"]),
        "machine": {**experiments.machine(), "load_average_before": load_before},
    }
    record["wall_seconds"] = time.perf_counter() - start
    series_path = os.path.join(folder, "series.npz")
    with atomic_path(series_path) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **series)
    figure_path = os.path.join(folder, f"{name}.png")
    case_figure(name, record, series, figure_path)
    record["files"] = {"json": os.path.abspath(os.path.join(folder, f"{name}.json")),
                       "figure": os.path.abspath(figure_path), "series": os.path.abspath(series_path)}
    atomic_json(record["files"]["json"], record)
    return record


def percent(value) -> str:
    return "-" if value is None else f"{100 * value:.3g}"


def table_rows(out: str) -> list[dict]:
    records = []
    for path in sorted(glob.glob(os.path.join(out, "*", "*.json"))):
        if os.path.basename(path) != os.path.basename(os.path.dirname(path)) + ".json":
            continue
        with open(path) as f:
            records.append(json.load(f))
    order = {c: i for i, c in enumerate(CASES)}
    records.sort(key=lambda r: order.get(r.get("case"), len(order)))
    rows = []
    for r in records:
        # a run of the same networks predicting through the load jumps: its own row
        entries = [(v, v["name"], v["metrics"], v["online"], v["targets"]) for v in r["variants"]]
        entries += [(v, f"{v['name']}, predicted through the load jump", x["metrics"], x["online"], x["targets"])
                    for v in r["variants"] for x in [v.get("predicted_through_load_jumps")] if x]
        for v, variant, m, online, met in entries:
            tr = v["training"] or {}
            rollout = tr.get("rollout_relative")
            rows.append({
                "case": r["case"] + (" (reduced)" if r.get("reduced") else ""), "variant": variant,
                "model": r.get("model", "lstm"),
                "mesh": f"{r['mesh']['n_nodes']} nodes / {r['mesh']['n_elements']} tets", "parts": r["n_parts"],
                "steps": r["parameters"]["n_steps"],
                "n_s": tr.get("case_parameters_passed", {}).get("n_s", v["parameters"]["n_s"]),
                "n_p/n_f": f"{tr.get('case_parameters_passed', {}).get('n_past', v['parameters']['n_past'])}/"
                           f"{v['parameters']['n_future']}",
                "training runs": tr.get("n_training_runs", "-"), "epochs run": tr.get("n_epochs_run") or "-",
                "candidates": (((tr.get("summary") or {}).get("candidates") or {}).get("n_candidates", 1)
                               if tr and r.get("model", "lstm") == "lstm" else "-"),
                "training s": ("-" if tr.get("train_seconds") is None else f"{tr['train_seconds']:.1f}"
                               + (f" (that of {tr['reused_from']})" if tr.get("reused_from") else "")),
                "free-end max %": percent(m["tip_max_error_relative"]),
                "final %": percent(m["tip_final_error_relative"])
                + (" (of amplitude)" if m.get("tip_final_relative_to") == "amplitude" else ""),
                "l2 relative %": percent(m["l2_relative"]),
                "non-shared node max %": percent(m["interior_max_error_relative"]),
                "rollout check %": "-" if not rollout else percent(max(rollout)),
                "targets met": "yes" if met["met"] else "no",
                "synchronized steps": (online or {}).get("n_synchronized_steps", "-"),
                "n_ts": tr.get("case_parameters_passed", {}).get("train_fraction", v["parameters"].get(
                    "train_fraction")),
            })
    return rows


TABLE_COLUMNS = ("case", "variant", "model", "mesh", "steps", "parts", "n_s", "n_p/n_f", "n_ts", "training runs",
                 "candidates", "epochs run", "training s", "synchronized steps", "free-end max %", "final %",
                 "l2 relative %", "non-shared node max %", "rollout check %", "targets met")


def write_table(out: str) -> str:
    rows = table_rows(out)
    lines = ["# Paper section 5.1 experiment matrix (benchmarks/paper_experiments.py)", "",
             "Errors in % of the free end's largest |z| (final: of its final value, or of the amplitude where "
             "marked); l2 relative over all saved steps and dofs; non-shared node max: largest error at a node "
             "neither shared nor clamped, in % of the largest displacement in the model; rollout check: the "
             "offline rollout's largest shared-dof error in % of the part's amplitude (worst part); candidates: "
             "networks trained per part, the one of lowest validation loss kept; synchronized "
             "steps: of the online run (n_cri, and the steps kept synchronized through a load jump); training s: "
             "wall time of the training call, compilation included (a network shape compiled earlier in the same "
             "process is not compiled again, so same-shape trainings after the first look cheap). Targets: "
             "fixed loads 2 % max and 1 % final, unseen initial condition or load 5 % max, full system 2 % max.",
             "", "| " + " | ".join(TABLE_COLUMNS) + " |", "|" + "---|" * len(TABLE_COLUMNS)]
    for row in rows:
        lines.append("| " + " | ".join(str(row[c]) for c in TABLE_COLUMNS) + " |")
    path = os.path.join(out, "table.md")
    with atomic_path(path) as tmp:
        with open(tmp, "w") as f:
            f.write("\n".join(lines) + "\n")
    return path


def steps_problem(settings: Settings, name: str, steps: int) -> str | None:
    """Why ``--steps`` cannot serve case ``name`` (None: it can): it must be a multiple of
    the case's snapshot stride and leave steps to predict after the largest n_cri."""
    if name == "refined_6_parts":
        every, n_cri = settings.refined_save_every, settings.refined_n_s * settings.n_past
    else:
        every = settings.save_every
        n_past = settings.n_past
        if name == "sequence_length":
            n_past = max(p for p, _ in settings.sequence_variants)
        n_cri = settings.n_s * n_past
    if steps % every:
        return f"case {name} saves every {every} steps: --steps must be a multiple of it"
    if steps <= n_cri:
        return f"case {name} synchronizes up to step n_cri = {n_cri}: --steps must be larger"
    return None


def parse_args(argv):
    parser = argparse.ArgumentParser(prog="paper_experiments.py", description=__doc__.splitlines()[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog="cases: " + ", ".join(CASES))
    parser.add_argument("--case", nargs="+", choices=CASES, metavar="NAME",
                        help="case(s) to run: " + ", ".join(CASES))
    parser.add_argument("--all", action="store_true", help="run every case, then write the table")
    parser.add_argument("--table", action="store_true", help="(re)write <out>/table.md from the JSON files found")
    parser.add_argument("--reduced", action="store_true",
                        help="small smoke settings (the tests): short runs, 2 epochs, n_H 8, one encoder layer, "
                             "ensembles of 3")
    parser.add_argument("--mesh", default=None,
                        help="coarse mesh file for every case but refined_6_parts (e.g. the paper's "
                             "beam_coarse.vtk); default: the built-in 104-node box beam")
    parser.add_argument("--steps", type=int, default=None,
                        help="total steps of every case (default: the paper's, or the reduced ones)")
    parser.add_argument("--seed", type=int, default=0, help="METIS, training and label seed")
    parser.add_argument("--model", choices=choices(SurrogateModel), default="lstm",
                        help="the surrogate every case trains: the LSTM (default) or the linear autoregressive "
                             "baseline (least squares; unconditional)")
    parser.add_argument("--out", default=DEFAULT_OUT, help="root folder: each case writes <out>/<case>/")
    parser.add_argument("--quiet", action="store_true", help="no progress bars or stage messages")
    args = parser.parse_args(argv)
    if not (args.case or args.all or args.table):
        parser.error("nothing to do: give --case NAME, --all or --table")
    if args.case and args.all:
        parser.error("give --case or --all, not both")
    if args.steps is not None and args.steps < 1:
        parser.error(f"--steps must be >= 1, got {args.steps}")
    if args.mesh is not None and not os.path.isfile(args.mesh):
        parser.error(f"--mesh {args.mesh}: no such file")
    if args.steps is not None:
        settings = reduced_settings(len(jax.devices())) if args.reduced else paper_settings()
        for name in CASES if args.all else (args.case or []):
            problem = steps_problem(settings, name, args.steps)
            if problem:
                parser.error(problem)
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    settings = reduced_settings(len(jax.devices())) if args.reduced else paper_settings()
    ctx = Context(settings=settings, out=os.path.abspath(args.out), mesh_file=args.mesh, seed=args.seed,
                  progress=not args.quiet, steps=args.steps, model=args.model)
    cases = list(CASES) if args.all else list(dict.fromkeys(args.case or []))
    failed, times = [], {}
    for name in cases:
        start = time.perf_counter()
        if args.all:
            try:
                record = run_case(ctx, name)
            except Exception:  # keep going: one case's failure does not cost the others
                traceback.print_exc()
                failed.append(name)
                continue
        else:
            record = run_case(ctx, name)
        times[name] = time.perf_counter() - start
        for v in record["variants"]:
            m = v["metrics"]
            print(f"{name}/{v['name']}: free-end max {percent(m['tip_max_error_relative'])} %, final "
                  f"{percent(m['tip_final_error_relative'])} %, l2 {percent(m['l2_relative'])} %, targets "
                  f"{'met' if v['targets']['met'] else 'missed'} ({times[name]:.1f} s for the case)", flush=True)
    print(f"wrote {write_table(ctx.out)}", flush=True)  # after any case too: the table follows the JSONs
    if failed:
        print(f"FAILED cases: {', '.join(failed)}", file=sys.stderr, flush=True)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
