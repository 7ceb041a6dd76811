"""Timing reports (jaxsync.perf.reports) on hand-made numbers: ratios, the paper's
max-average row, the speed-up quantities, tables and JSON round trips."""

import dataclasses
import json

import numpy as np
import pytest

from jaxsync import CheckpointError, ProblemError
from jaxsync.perf.reports import PartTiming, SpeedupReport, TimingReport, max_average


def row(part, t_e, t_m, t_s, t_o, t_local, **kw):
    values = dict(part=part, n_nodes=10, n_elements=20, n_shared=3, t_e=t_e, t_m=t_m, t_s=t_s,
                  t_o=t_o, t_local=t_local, t_t=t_local + t_s)
    values.update(kw)
    return PartTiming(**values)


def report_of(rows, **kw):
    values = dict(mode="preassembled", n_parts=len(rows), n_shared_nodes=7, n_nodes=30,
                  n_elements=60, n_steps=100, repeats=3, dt=2.5e-4, device="test",
                  n_devices=2, rows=tuple(rows), t_step=5e-6, t_step_nosync=4e-6, setup_s=0.1,
                  loadavg=(1.0, 2.0, 3.0))
    values.update(kw)
    return TimingReport(**values)


def speedup_of(**kw):
    sync = report_of([row(0, 0.0, 2e-6, 12e-6, 1e-6, 3e-6), row(1, 0.0, 1e-6, 12e-6, 1e-6, 2e-6)])
    avoid = report_of([row(0, 0.0, 2e-6, 0.0, 1e-6, 3e-6, t_d=1e-6, t_t=4e-6),
                       row(1, 0.0, 1e-6, 0.0, 1e-6, 2e-6, t_d=1e-6, t_t=3e-6)])
    values = dict(synchronized=sync, avoiding=avoid, sync="ppermute",
                  t_step_sync={"psum": 30e-6, "ppermute": 20e-6}, t_step_nosync=8e-6,
                  t_step_avoiding=10e-6, t_prediction=(0.9e-3, 1.1e-3), t_prediction_spmd=1.6e-3,
                  n_s=80, n_past=20, n_future=20, architecture={"n_hidden": 32},
                  n_steps=1600, repeats=4)
    values.update(kw)
    return SpeedupReport(**values)


def test_ratios_by_hand():
    r = row(0, t_e=1e-6, t_m=2e-6, t_s=3e-6, t_o=4e-6, t_local=7e-6)  # t_t = 10 us
    assert r.ratios == pytest.approx({"r_e": 0.1, "r_m": 0.2, "r_s": 0.3, "r_d": 0.0, "r_o": 0.4})
    assert r.r_sum == pytest.approx(1.0)
    # stages measured apart may miss the whole: 2 us of stages in a 4 us step
    assert row(0, 0.0, 1e-6, 0.0, 1e-6, 4e-6).r_sum == pytest.approx(0.5)
    assert row(0, 0.0, 0.0, 0.0, 0.0, 0.0).r_sum == 0.0
    assert row(0, 1e-6, 2e-6, 3e-6, 4e-6, 7e-6).to_dict()["r_o"] == pytest.approx(0.4)
    with pytest.raises(ProblemError, match="t_x"):
        r.ratio("t_x")
    with pytest.raises(ProblemError, match="t_m"):
        row(0, 0.0, -1e-6, 0.0, 1e-6, 2e-6)
    with pytest.raises(ProblemError, match="t_o"):
        row(0, 0.0, 1e-6, 0.0, np.nan, 2e-6)


def test_max_average_picks_the_part_with_the_largest_total():
    rows = [row(0, 0.0, 9e-6, 1e-6, 1e-6, 10e-6),   # largest t_m, not the largest t_t
            row(1, 2e-6, 3e-6, 8e-6, 1e-6, 6e-6),   # largest t_s and t_t = 14 us
            row(2, 0.0, 5e-6, 1e-6, 6e-6, 11e-6)]
    assert max_average(rows).part == 1
    report = report_of(rows)
    assert report.max_average is report.rows[1]
    assert "max@1" in report.table()
    assert report.to_dict()["max_average"]["r_s"] == pytest.approx(8 / 14)
    with pytest.raises(ProblemError):
        max_average([])
    with pytest.raises(ProblemError, match="rows"):
        report_of(rows, n_parts=2)
    with pytest.raises(dataclasses.FrozenInstanceError):
        report.mode = "recompute"


def test_timing_report_json_round_trip(tmp_path):
    report = report_of([row(0, 1e-6, 2e-6, 3e-6, 4e-6, 7e-6), row(1, 0.0, 1e-6, 3e-6, 1e-6, 2e-6)])
    path = tmp_path / "timing.json"
    report.save_json(path)
    assert TimingReport.load_json(path) == report
    data = json.loads(path.read_text())
    assert data["rows"][0]["r_m"] == pytest.approx(0.2) and data["rows"][0]["r_sum"] == pytest.approx(1.0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["timing.json"]  # no temporaries left
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"kind": "something else"}))
    with pytest.raises(CheckpointError, match="not a jaxsync timing report"):
        TimingReport.load_json(other)
    broken = report.to_dict()
    del broken["rows"]
    (tmp_path / "broken.json").write_text(json.dumps(broken))
    with pytest.raises(CheckpointError):
        TimingReport.load_json(tmp_path / "broken.json")


def test_speedup_quantities_by_hand():
    report = speedup_of()
    assert report.steps_per_prediction == 1600
    assert report.t_step_synchronized == pytest.approx(20e-6)  # the faster, ppermute
    assert report.zeta == pytest.approx(2.0)  # 20 us / 10 us
    assert report.t_s == pytest.approx(12e-6)  # 20 us - 8 us
    assert report.t_d == pytest.approx(1e-6)  # 1.6 ms over 1600 steps
    assert report.surrogate_pays
    assert not speedup_of(t_prediction_spmd=32e-3).surrogate_pays  # 20 us per step > t_s
    assert speedup_of(t_step_nosync=25e-6).t_s == 0.0  # noise: clipped
    text = report.table()
    assert "zeta = t_t / t_t' = 2.000" in text and "<- baseline" in text
    with pytest.raises(ProblemError, match="allgather"):
        speedup_of(sync="allgather")


def test_speedup_report_json_round_trip(tmp_path):
    report = speedup_of()
    report.save_json(tmp_path / "speedup.json")
    assert SpeedupReport.load_json(tmp_path / "speedup.json") == report
    data = json.loads((tmp_path / "speedup.json").read_text())
    assert data["zeta"] == pytest.approx(2.0)
    assert data["avoiding"]["max_average"]["t_d"] == pytest.approx(1e-6)
    with pytest.raises(CheckpointError, match="speed-up report"):
        SpeedupReport.load_json(tmp_path / "missing.json")
