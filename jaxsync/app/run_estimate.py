"""How long a demo will take on this machine, measured before its long work starts.

``jaxsync demo --case vessel`` runs for minutes (``--size small``) to days (``--size
paper`` on a laptop). Before its first long stage it times short compiled pieces of the
actual work and prints what the whole run will take (:func:`measure_demo_estimate`):

- the synchronized step: the distributed program of the actual problem, partition and
  devices (the run's own SPMD program, :class:`jaxsync.solve.executors.DistributedRunner`,
  chunks of :data:`CHUNK_STEPS` steps), called after its compilation until about
  ``target_seconds`` [s] have passed; the mean wall time per step [us];
- the single-device step of the mass-scaling check (the same, one device, whole mesh);
- one training epoch: the run's training program (:func:`jaxsync.surrogate.train_surrogates`'s
  model, replicas, windows, batch size, with and without load signals as the run) on
  random windows of the shapes the synchronized run will give, one epoch after its
  compilation [s].

The estimate (:func:`estimate_parts`, plain arithmetic) is steps times the time per step
for the runs (the synchronization-avoiding run at the synchronized step: it runs the same
steps; its predicted steps skip the exchange but add the surrogates' refill predictions,
which cannot be timed before the surrogates exist) and epochs times the time per epoch for
the training (an upper bound when early stopping ends it sooner). Not included:
compilation, the timing stage and the report (seconds to minutes).
"""

from __future__ import annotations

import math
import time

import numpy as np

__all__ = ["CHUNK_STEPS", "format_duration", "format_step_time", "estimate_parts", "format_estimate",
           "mass_scaling_steps", "TRAINING_TIMED_ELEMENTS", "time_distributed_step", "time_single_device_step",
           "time_training_epoch",
           "measure_demo_estimate", "NOT_INCLUDED"]

CHUNK_STEPS = 20
"""Steps per timed call of the step programs."""

TRAINING_TIMED_ELEMENTS = 20_000
"""Meshes up to this many tetrahedra have a training epoch timed; above it the estimate
leaves the training out and says so: an epoch of the run's own training program holds its
windows' least-squares highway fit in memory (8 GB at 30 000 tets; the paper's size does
not fit a 24 GB machine), and the estimate must not need more than the run's steps do."""

NOT_INCLUDED = "compilation, the timing stage and the report"
"""What the estimate leaves out (seconds to minutes)."""


def format_duration(seconds: float) -> str:
    """A duration for people: ``"about 45 s"``, ``"about 12 min"``, ``"about 3 h 10 min"``
    (from one hour on, to the nearest 5 minutes), ``"about 2 days 5 h"`` (from two days
    on, to the nearest hour).

    Raises:
        ConfigError: ``seconds`` negative, NaN or infinite.
    """
    from ..errors import ConfigError

    if isinstance(seconds, bool) or not isinstance(seconds, (int, float, np.integer, np.floating)) \
            or not math.isfinite(seconds) or seconds < 0:
        raise ConfigError(f"a duration must be a finite number of seconds >= 0, got {seconds!r}")
    if seconds < 59.5:
        return f"about {max(1, round(seconds))} s"
    if seconds < 3600 - 30:
        return f"about {round(seconds / 60)} min"
    if seconds < 48 * 3600:
        minutes = 5 * round(seconds / 300)
        hours, minutes = divmod(minutes, 60)
        return f"about {hours} h" + (f" {minutes} min" if minutes else "")
    hours = round(seconds / 3600)
    days, hours = divmod(hours, 24)
    return f"about {days} days" + (f" {hours} h" if hours else "")


def format_step_time(us: float) -> str:
    """A time per step [us] as ``"850 us"`` or ``"8.2 ms"``."""
    return f"{us:.0f} us" if us < 999.5 else f"{us / 1000:.3g} ms"


def _count(n: int) -> str:
    """``1000000`` as ``"1 000 000"``."""
    return f"{int(n):,}".replace(",", " ")


def estimate_parts(n_steps: int, us_per_step: float, *, epochs: int = 0, seconds_per_epoch: float | None = None,
                   mass_scaling_steps: int = 0, us_per_step_single: float | None = None) -> dict:
    """The estimate's arithmetic: each stage's seconds and their total.

    Args:
        n_steps: time steps of the synchronized run (and of the synchronization-avoiding one).
        us_per_step: the synchronized distributed step [us].
        epochs, seconds_per_epoch: the training's epochs and one epoch [s] (None: not
            measured, the training left out of the total).
        mass_scaling_steps, us_per_step_single: the mass-scaling check's single-device steps
            (both of its runs) and one such step [us] (None or 0 steps: no check).

    Returns:
        {``"mass_scaling_s"``, ``"synchronized_s"``, ``"sync_avoiding_s"``,
        ``"training_s"`` (each [s], None where not estimated), ``"total_s"`` (the sum of
        those estimated)}.

    Raises:
        ConfigError: a negative or non-finite count or time.
    """
    from ..errors import ConfigError

    for name, value in (("n_steps", n_steps), ("us_per_step", us_per_step), ("epochs", epochs),
                        ("seconds_per_epoch", seconds_per_epoch), ("mass_scaling_steps", mass_scaling_steps),
                        ("us_per_step_single", us_per_step_single)):
        if value is not None and (not math.isfinite(value) or value < 0):
            raise ConfigError(f"{name} must be a finite number >= 0 for a run-time estimate, got {value!r}")
    synchronized = n_steps * us_per_step * 1e-6
    parts = {
        "mass_scaling_s": (mass_scaling_steps * us_per_step_single * 1e-6
                           if mass_scaling_steps and us_per_step_single is not None else None),
        "synchronized_s": synchronized,
        "sync_avoiding_s": synchronized,  # the same steps, at the synchronized step (module docstring)
        "training_s": None if seconds_per_epoch is None else epochs * seconds_per_epoch,
    }
    parts["total_s"] = sum(v for v in parts.values() if v is not None)
    return parts


def format_estimate(estimate: dict) -> str:
    """The lines ``jaxsync demo`` prints from :func:`measure_demo_estimate`'s dict: the
    total, then one line per stage with its basis, then what is not included."""
    e = estimate
    where = (f"{e['device_kind']}, {e['n_devices']} device{'s' if e['n_devices'] != 1 else ''}"
             + (" emulated in one process" if e.get("devices_emulated") else ""))
    rows = []
    if e.get("mass_scaling_s") is not None:
        rows.append(("mass-scaling check", f"{_count(e['mass_scaling_steps'])} single-device steps at "
                                           f"{format_step_time(e['us_per_step_single_device'])}",
                     e["mass_scaling_s"]))
    rows.append(("synchronized run", f"{_count(e['n_steps'])} steps at "
                                     f"{format_step_time(e['us_per_step_synchronized'])} (timed over "
                                     f"{_count(e['calibration_steps'])} steps, {e['n_parts']} parts)",
                 e["synchronized_s"]))
    rows.append(("sync-avoiding run", f"{_count(e['n_steps'])} steps, taken at the synchronized step",
                 e["sync_avoiding_s"]))
    if e.get("training_s") is not None:
        rows.append(("training", f"{_count(e['epochs'])} epochs at {e['seconds_per_epoch']:.3g} s (one epoch "
                                 f"timed on windows of the run's shapes)", e["training_s"]))
    else:
        rows.append(("training", f"not timed above {_count(TRAINING_TIMED_ELEMENTS)} tets (one epoch's "
                                 f"memory), not included", None))
    width = max(len(name) for name, _, _ in rows)
    lines = [f"estimated time on this machine ({where}): {format_duration(e['total_s'])}"]
    lines += [f"  {name:<{width}}  {basis}" + ("" if s is None else f": {format_duration(s)}")
              for name, basis, s in rows]
    lines.append(f"  not included: {e['not_included']}")
    return "\n".join(lines)


def mass_scaling_steps(seconds: float, dt_cfl: float, dt_scaled: float) -> int:
    """Steps of both single-device runs of the mass-scaling check over ``seconds`` [s]
    (as :func:`jaxsync.app.mass_scaling.mass_scaling_check` counts them, to a few steps)."""
    n_scaled = max(1, int(round(seconds / dt_scaled)))
    return n_scaled + max(1, int(round(n_scaled * dt_scaled / dt_cfl)))


def _timed_calls(call, state, steps_per_call: int, target_seconds: float, max_steps: int) -> tuple[float, int]:
    """(mean wall time per step [us], steps timed) of ``state = call(state)``: one untimed
    call (compilation), then calls until ``target_seconds`` [s] or ``max_steps`` steps."""
    import jax

    state = jax.block_until_ready(call(state))
    steps, start = 0, time.perf_counter()
    while True:
        state = jax.block_until_ready(call(state))
        steps += steps_per_call
        elapsed = time.perf_counter() - start
        if elapsed >= target_seconds or steps >= max_steps:
            return 1e6 * elapsed / steps, steps


def _zero_state(problem):
    """A start of zero displacement: the speed of a step does not depend on the values."""
    import jax.numpy as jnp

    from ..fem._stepper import SolverState

    zeros = np.zeros((problem.n_nodes, 3))
    return SolverState(zeros, zeros.copy(), jnp.asarray(0, dtype=jnp.int32))


def _run_form(problem, n_steps: int | None):
    """The force model a run of ``n_steps`` steps compiles
    (:func:`jaxsync.fem.forces.run_force_model`)."""
    from ..fem.forces._internal_force import run_force_model

    return "preassembled" if n_steps is None else run_force_model("preassembled", problem, n_steps)


def time_distributed_step(problem, parts, *, n_steps: int | None = None, target_seconds: float = 1.0,
                          max_steps: int = 10_000) -> tuple[float, int]:
    """(wall time of one synchronized distributed step [us], steps timed): the run's own
    SPMD program (:class:`jaxsync.solve.executors.DistributedRunner`, the default
    exchange and devices of :func:`jaxsync.simulate`) on ``problem`` split as ``parts``,
    :data:`CHUNK_STEPS` steps per call, compilation excluded. ``n_steps``: the run's
    length, which chooses the product's form as :func:`jaxsync.simulate` does (None: the
    fused form of a run of unknown length)."""
    from ..fem._stepper import build_system
    from ..perf.kernels import distributed_step
    from ..solve.executors._distributed import DistributedRunner

    mode = _run_form(problem, n_steps)
    runner = DistributedRunner(problem, build_system(problem, problem.dt, mode), parts, save_every=CHUNK_STEPS,
                               mode=mode)
    program = distributed_step(runner, CHUNK_STEPS, True)
    return _timed_calls(lambda s: program(runner.parts, s)[0], runner.from_global(_zero_state(problem)),
                        CHUNK_STEPS, target_seconds, max_steps)


def time_single_device_step(problem, *, n_steps: int | None = None, target_seconds: float = 1.0,
                            max_steps: int = 10_000) -> tuple[float, int]:
    """(wall time of one step of the whole mesh on one device [us], steps timed), compilation
    excluded (the mass-scaling check's runs); ``n_steps`` as :func:`time_distributed_step`."""
    import jax

    from ..fem._stepper import build_system
    from ..solve.executors._phases import synchronized_steps

    system = jax.device_put(build_system(problem, problem.dt, _run_form(problem, n_steps)))
    program = jax.jit(lambda system, state: synchronized_steps(system, state, 1, CHUNK_STEPS)[0])
    return _timed_calls(lambda s: program(system, s), jax.device_put(_zero_state(problem)), CHUNK_STEPS,
                        target_seconds, max_steps)


def time_training_epoch(parts, n_rows: int, row_stride: int, *, sampling, architecture, optimizer,
                        load_inputs: tuple = ()) -> float:
    """Seconds of one training epoch, compilation excluded: the model of ``architecture``
    trained by its own ``fit`` as :func:`jaxsync.surrogate.train_surrogates` trains it (its
    candidates per part, ``optimizer``'s batch size and schedule) on random windows of the
    shapes a run gives: per part of ``parts`` 3 x its shared nodes dofs, ``n_rows`` rows of
    shared history, ``row_stride`` rows per n_s (:class:`~jaxsync.surrogate.Sampling`
    ``sampling``), a load signal per entry of ``load_inputs``
    (:func:`jaxsync.fem.load_inputs_of` the problem; () without load input)."""
    import dataclasses

    import jax

    from ..surrogate.models._protocol import FitSettings
    from ..surrogate.training._data import build_dataset, stack_replicas, trained_rows

    rng = np.random.default_rng(sampling.seed)
    rows = trained_rows(n_rows, sampling.train_fraction)
    signals = [rng.standard_normal((rows, len(load_inputs)))] if load_inputs else None
    datasets = [build_dataset([rng.standard_normal((rows, 3 * part.n_shared))], row_stride, sampling.n_past,
                              sampling.n_future, 1.0, sampling.val_fraction, sampling.seed,
                              n_offsets=sampling.n_offsets, split=sampling.split, signals=signals)
                for part in parts.parts]
    model = architecture.model_class
    data = stack_replicas(datasets * model.candidates_per_part(optimizer), tuple(load_inputs))
    arch = model.from_choice(architecture, data.n_dof_max, sampling.n_past, sampling.n_future, data.n_load)
    one_epoch = dataclasses.replace(optimizer, n_epochs=1, patience=None)
    result = arch.fit(data, FitSettings(architecture=architecture, optimizer=one_epoch,
                                        key=jax.random.key(sampling.seed), progress=False))
    return float(result.seconds_per_epoch)


def measure_demo_estimate(problem, parts, d, *, shared_every: int, mass_scaling=None, seed: int = 0,
                          load_input: bool | None = None, highway: bool | None = None,
                          target_seconds: float = 1.0, log=None) -> dict:
    """Measure and estimate a demo run (module docstring).

    Args:
        problem: the run's :class:`jaxsync.Problem` (the vessel's mass-scaled one).
        parts: its :class:`jaxsync.Partition`.
        d: the run's :class:`jaxsync.app.demo.DemoDefaults` (steps, sampling, network,
            schedule).
        shared_every: the synchronized run's shared-history stride [steps].
        mass_scaling: (seconds [s], dt_cfl [s]) of the vessel's mass-scaling check, or None.
        seed: the run's seed; load_input, highway: as the run's
            :class:`~jaxsync.surrogate.ArchitectureChoice` takes them.
        target_seconds: wall time [s] each step program is timed for, after its compilation.
        log: where a line goes once the steps are timed, before the training epoch (which
            takes longest to compile and measure); None: nowhere.

    Returns:
        A JSON-ready dict: :func:`estimate_parts`'s seconds, ``us_per_step_synchronized``
        and ``calibration_steps`` (the distributed step and the steps timed),
        ``us_per_step_single_device`` and ``mass_scaling_steps`` (the check, or None and
        0), ``seconds_per_epoch`` and ``epochs``, ``n_steps``, ``n_parts``, the devices
        (``n_devices``, ``device_kind``, ``platform``, ``devices_emulated``),
        ``measure_seconds`` (what measuring took, compilations included),
        ``not_included`` (:data:`NOT_INCLUDED`) and ``text`` (:func:`format_estimate`).
    """
    from ..fem._load_signals import load_inputs_of
    from ..parallel.devices import device_summary
    from ..surrogate import ArchitectureChoice, Sampling
    from ..surrogate.training._train import TrainConfig

    started = time.perf_counter()
    # each program in the form its run compiles (a short run's compact product)
    us_sync, calibration_steps = time_distributed_step(problem, parts, n_steps=d.n_steps,
                                                       target_seconds=target_seconds)
    us_single, n_check = None, 0
    if mass_scaling is not None:
        seconds, dt_cfl = mass_scaling
        n_check = mass_scaling_steps(seconds, dt_cfl, problem.dt)
        us_single, _ = time_single_device_step(problem, n_steps=n_check, target_seconds=target_seconds)
    timed_training = problem.mesh.n_elements <= TRAINING_TIMED_ELEMENTS
    if log is not None:
        log(f"  synchronized step {format_step_time(us_sync)} ({_count(d.n_steps)} steps: "
            f"{format_duration(d.n_steps * us_sync * 1e-6)})"
            + ("" if us_single is None else f", single-device step {format_step_time(us_single)}")
            + ("; timing a training epoch" if timed_training else ""))
    choice = ArchitectureChoice(n_hidden=d.n_hidden, n_layers=d.n_layers, load_input=load_input,
                                **({} if highway is None else {"highway": highway}))
    sampling = Sampling(n_s=d.n_s, n_past=d.n_past, n_future=d.n_future, train_fraction=d.train_fraction, seed=seed)
    optimizer = TrainConfig(batch_size=d.batch_size, eta0=d.eta0, gamma=d.gamma, n_epochs=d.epochs,
                            n_candidates=d.n_candidates)
    # the run's windows carry the problem's load signals unless load_input is False
    # (train_surrogates: None is on when the run records them, as the demo's run does)
    inputs = () if load_input is False else load_inputs_of(problem)
    per_epoch = None
    if timed_training:
        per_epoch = time_training_epoch(parts, d.n_steps // shared_every + 1, d.n_s // shared_every,
                                        sampling=sampling.for_model(choice.model_class), architecture=choice,
                                        optimizer=optimizer, load_inputs=inputs)
    devices = device_summary()
    estimate = estimate_parts(d.n_steps, us_sync, epochs=optimizer.resolved_epochs, seconds_per_epoch=per_epoch,
                              mass_scaling_steps=n_check, us_per_step_single=us_single)
    estimate.update({
        "us_per_step_synchronized": us_sync, "calibration_steps": calibration_steps,
        "us_per_step_single_device": us_single, "mass_scaling_steps": n_check,
        "seconds_per_epoch": per_epoch, "epochs": optimizer.resolved_epochs, "n_steps": d.n_steps,
        "n_parts": parts.n_parts, "n_devices": devices["n_devices"], "device_kind": devices["device_kind"],
        "platform": devices["platform"], "devices_emulated": devices["emulated"],
        "not_included": NOT_INCLUDED, "measure_seconds": time.perf_counter() - started})
    estimate["text"] = format_estimate(estimate)
    return estimate
