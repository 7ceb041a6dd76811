"""The run-time estimate ``jaxsync demo --case vessel`` prints before its first stage
(jaxsync.app.run_estimate): its formatting and arithmetic as pure functions, and one run
of the reduced vessel demo (the arguments of tests/cli/test_vessel_demo.py), where it must
come before the first stage and be recorded in summary.json as the product of the
numbers it measured."""

import dataclasses
import math
import re

import pytest

from jaxsync.app.demo import SUMMARY_KEYS, VESSEL_KEYS
from jaxsync.app.run_estimate import (
    NOT_INCLUDED,
    estimate_parts,
    format_duration,
    format_estimate,
    format_step_time,
    mass_scaling_steps,
    measure_demo_estimate,
)
from jaxsync.errors import ConfigError

PARTS = ("mass_scaling_s", "synchronized_s", "sync_avoiding_s", "training_s")


@pytest.mark.parametrize("seconds, text", [
    (0.2, "about 1 s"), (45.4, "about 45 s"), (59.4, "about 59 s"), (59.6, "about 1 min"),
    (725, "about 12 min"), (3569, "about 59 min"), (3580, "about 1 h"), (3 * 3600 + 10 * 60, "about 3 h 10 min"),
    (3 * 3600 + 11 * 60, "about 3 h 10 min"), (3 * 3600 + 58 * 60, "about 4 h"),
    (47 * 3600, "about 47 h"), (2 * 86400 + 5 * 3600 + 600, "about 2 days 5 h"), (3 * 86400, "about 3 days"),
])
def test_durations_read_as_people_say_them(seconds, text):
    assert format_duration(seconds) == text


@pytest.mark.parametrize("bad", [-1.0, math.nan, math.inf, None, "1 h", True])
def test_bad_durations_are_refused(bad):
    with pytest.raises(ConfigError, match="finite number of seconds >= 0"):
        format_duration(bad)


def test_step_times():
    assert format_step_time(850.2) == "850 us" and format_step_time(8200.0) == "8.2 ms"
    assert format_step_time(12_345.0) == "12.3 ms"


def test_the_total_is_the_sum_of_the_parts():
    e = estimate_parts(1_000_000, 8200.0, epochs=300, seconds_per_epoch=4.0, mass_scaling_steps=35_000,
                       us_per_step_single=20_000.0)
    assert e["synchronized_s"] == pytest.approx(8200.0) == e["sync_avoiding_s"]
    assert e["training_s"] == pytest.approx(1200.0) and e["mass_scaling_s"] == pytest.approx(700.0)
    assert e["total_s"] == pytest.approx(sum(e[k] for k in PARTS)) == pytest.approx(18_300.0)
    assert format_duration(e["total_s"]) == "about 5 h 5 min"
    # what is not measured is None and not in the total
    e = estimate_parts(100, 10.0)
    assert e["training_s"] is None and e["mass_scaling_s"] is None
    assert e["total_s"] == pytest.approx(2 * 100 * 10.0 * 1e-6)
    with pytest.raises(ConfigError, match="us_per_step must be a finite number >= 0"):
        estimate_parts(100, math.nan)


def test_mass_scaling_steps_count_both_runs():
    # 0.01 s at 4e-6 s (2500 steps) and at the CFL step 1.6e-6 s (6250 steps)
    assert mass_scaling_steps(0.01, 1.6e-6, 4e-6) == 2500 + 6250


def test_the_printed_estimate_names_every_stage_and_its_total():
    e = estimate_parts(1_000_000, 8200.0, epochs=300, seconds_per_epoch=4.0, mass_scaling_steps=35_000,
                       us_per_step_single=20_000.0)
    e.update(us_per_step_synchronized=8200.0, calibration_steps=140, us_per_step_single_device=20_000.0,
             mass_scaling_steps=35_000, seconds_per_epoch=4.0, epochs=300, n_steps=1_000_000, n_parts=11,
             n_devices=2, device_kind="cpu", devices_emulated=True, not_included=NOT_INCLUDED)
    text = format_estimate(e)
    first, *rows = text.splitlines()
    assert first == "estimated time on this machine (cpu, 2 devices emulated in one process): about 5 h 5 min"
    assert "1 000 000 steps at 8.2 ms (timed over 140 steps, 11 parts): about 2 h 15 min" in rows[1]
    assert "35 000 single-device steps at 20 ms: about 12 min" in rows[0]
    assert "300 epochs at 4 s" in rows[3] and rows[3].endswith("about 20 min")
    assert rows[-1] == f"  not included: {NOT_INCLUDED}"


def test_the_estimate_is_a_vessel_key():
    assert "estimate" in VESSEL_KEYS and "estimate" not in SUMMARY_KEYS


def test_above_the_size_limit_the_training_is_left_out_and_said(monkeypatch):
    """A mesh above TRAINING_TIMED_ELEMENTS: the steps are timed, the training epoch is
    not (its memory), and the total and the text say so."""
    import jaxsync
    from jaxsync.app import run_estimate
    from jaxsync.app.demo import demo_defaults

    problem = jaxsync.cantilever()
    monkeypatch.setattr(run_estimate, "TRAINING_TIMED_ELEMENTS", problem.mesh.n_elements - 1)
    d = dataclasses.replace(demo_defaults("cantilever"), n_steps=400)
    e = measure_demo_estimate(problem, jaxsync.partition(problem.mesh, 2, seed=0), d, shared_every=1,
                              target_seconds=0.05)
    assert e["training_s"] is None and e["seconds_per_epoch"] is None and e["us_per_step_synchronized"] > 0
    assert e["total_s"] == pytest.approx(e["synchronized_s"] + e["sync_avoiding_s"], rel=1e-12)
    assert re.search(rf"\n  training +not timed above {problem.mesh.n_elements - 1} tets", e["text"]), e["text"]
