"""Timing breakdown (jaxsync.perf.timing): consistency of the measured stages, the paper's
definitions (ratios, max-average), JSON round trip. No test asserts a speed."""

import dataclasses
import json

import jax
import numpy as np
import pytest

import jaxsync
from jaxsync import CheckpointError, ProblemError
from jaxsync.perf.timing import PartTiming, TimingReport, max_average, timing_breakdown


@pytest.fixture(scope="module")
def small_problem():
    return jaxsync.cantilever(jaxsync.box_beam(25, 1, 1, (25, 2, 2)))  # 234 nodes, 600 tets


def measure(problem, mode):
    # short calls (~0.5 ms), many repeats: the best repeat is a call nobody preempted
    return timing_breakdown(problem, 2, mode=mode, n_steps=50, repeats=150)


@pytest.fixture(scope="module")
def reports(small_problem):
    return {mode: measure(small_problem, mode) for mode in ("preassembled", "recompute")}


def worst_mismatch(report):
    """Largest |(t_e + t_m + t_o) / t_local - 1| over the parts."""
    return max(abs((r.t_e + r.t_m + r.t_o) / r.t_local - 1.0) for r in report.rows)


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


@pytest.mark.parametrize("mode", ["preassembled", "recompute"])
def test_stages_add_up_to_the_total(reports, small_problem, mode):
    """t_e + t_m + t_o, measured as separate programs (T_force - T_other, the scatter
    alone, T_other), add up to the separately measured real local step T_full within
    10 % in both modes. This fails when a variant stops representing the real step
    (XLA folding the zero-scaled force away, or the force timed outside the update loop,
    where it is 10-15 % cheaper than in the fused step) or when stages overlap."""
    report = reports[mode]
    for _ in range(2):
        if worst_mismatch(report) <= 0.10:
            break
        # The VM's timings vary by up to 1.7x between runs; a burst of load during one
        # measurement is not a defect of the method, three misses in a row would be.
        report = measure(small_problem, mode)
    assert worst_mismatch(report) <= 0.10, report.table()


@pytest.mark.parametrize("mode", ["preassembled", "recompute"])
def test_report_structure(reports, small_problem, mode):
    report = reports[mode]
    assert report.n_parts == 2 and len(report.rows) == 2
    assert report.n_shared_nodes > 0
    for r in report.rows:
        assert r.t_t == pytest.approx(r.t_local + r.t_s)
        assert r.t_m > 0 and r.t_o > 0
        assert r.t_s > 0  # a psum between two devices costs something
        if mode == "preassembled":
            assert r.t_e == 0.0  # K is assembled once; no element work per step
        else:
            assert r.t_e > 0
    assert report.setup_s >= 0 and report.n_devices == 2
    assert report.t_step == pytest.approx(report.t_step_nosync + report.rows[0].t_s)
    assert sum(r.n_elements for r in report.rows) == small_problem.mesh.n_elements
    assert len(report.loadavg) == 3


def test_ratios_are_stage_over_total():
    r = row(0, t_e=1e-6, t_m=2e-6, t_s=3e-6, t_o=4e-6, t_local=7e-6)
    assert r.t_t == pytest.approx(10e-6)
    assert r.ratios == pytest.approx({"r_e": 0.1, "r_m": 0.2, "r_s": 0.3, "r_d": 0.0, "r_o": 0.4})
    assert r.ratio("t_m") == pytest.approx(0.2)
    assert r.r_sum == pytest.approx(1.0)
    # stages measured apart may miss the whole: r_sum shows it
    assert row(0, 0.0, 1e-6, 0.0, 1e-6, 4e-6).r_sum == pytest.approx(0.5)
    assert row(0, 0.0, 0.0, 0.0, 0.0, 0.0).ratios == {"r_e": 0.0, "r_m": 0.0, "r_s": 0.0, "r_d": 0.0, "r_o": 0.0}
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
    assert report.to_dict()["max_average"]["part"] == 1
    assert report.to_dict()["max_average"]["r_s"] == pytest.approx(8 / 14)
    with pytest.raises(ProblemError):
        max_average([])
    with pytest.raises(ProblemError, match="rows"):
        report_of(rows, n_parts=2)


def test_json_round_trip(tmp_path, reports):
    for report in (report_of([row(0, 1e-6, 2e-6, 3e-6, 4e-6, 7e-6)]), reports["recompute"]):
        path = tmp_path / f"{report.mode}.json"
        report.save_json(path)
        back = TimingReport.load_json(path)
        assert back == report
        data = json.loads(path.read_text())
        assert data["rows"][0]["r_m"] == pytest.approx(report.rows[0].ratio("t_m"))
        assert data["n_shared_nodes"] == report.n_shared_nodes
    assert sorted(p.name for p in tmp_path.iterdir()) == ["preassembled.json", "recompute.json"]
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"kind": "something else"}))
    with pytest.raises(CheckpointError, match="not a jaxsync timing report"):
        TimingReport.load_json(other)
    broken = dict(report_of([row(0, 0.0, 1e-6, 0.0, 1e-6, 2e-6)]).to_dict())
    del broken["rows"]
    (tmp_path / "broken.json").write_text(json.dumps(broken))
    with pytest.raises(CheckpointError):
        TimingReport.load_json(tmp_path / "broken.json")


def test_one_part_has_no_synchronization():
    problem = jaxsync.cantilever()
    report = timing_breakdown(problem, 1, n_steps=50, repeats=3)
    assert report.n_parts == 1 and report.n_shared_nodes == 0
    (r,) = report.rows
    assert r.n_shared == 0 and r.t_s == 0.0 and r.ratio("t_s") == 0.0
    assert r.t_t == r.t_local == report.t_step
    assert r.n_nodes == problem.mesh.n_nodes and r.n_elements == problem.mesh.n_elements
    assert "n_c=1" in report.table()


def test_timed_distributed_program_is_the_solver_step(small_problem):
    """The synchronized variant that t_step and t_s come from computes the same states as
    the distributed solver, so the timing measures the real step."""
    from jaxsync.solve.distributed import DistributedRunner
    from jaxsync.solve.solver import build_system, initial_state
    from jaxsync.perf.timing import _distributed_program

    system = build_system(small_problem, small_problem.dt, "preassembled")
    state = initial_state(small_problem, system)
    runner = DistributedRunner(small_problem, system, 2, save_every=30)
    start = runner.from_global(state)
    expected, _, _ = runner.advance(start, 1)
    timed, _ = _distributed_program(runner, 30, synchronize=True)(runner.parts, start)
    np.testing.assert_array_equal(np.asarray(timed.displacement), np.asarray(expected.displacement))
    unsynchronized, _ = _distributed_program(runner, 30, synchronize=False)(runner.parts, start)
    assert not np.array_equal(np.asarray(unsynchronized.displacement), np.asarray(expected.displacement))


def test_bad_arguments_are_refused():
    problem = jaxsync.cantilever()
    with pytest.raises(ProblemError, match="mode"):
        timing_breakdown(problem, 2, mode="explicit")
    with pytest.raises(ProblemError, match="n_steps"):
        timing_breakdown(problem, 2, n_steps=0)
    with pytest.raises(ProblemError, match="repeats"):
        timing_breakdown(problem, 2, repeats=0)
    with pytest.raises(jaxsync.PartitionError):
        timing_breakdown(problem, 0)


def test_report_is_frozen():
    report = report_of([row(0, 0.0, 1e-6, 0.0, 1e-6, 2e-6)])
    with pytest.raises(dataclasses.FrozenInstanceError):
        report.mode = "recompute"
    assert len(jax.devices()) == 2


def test_speedup_breakdown_measures_both_solvers_in_one_run(tmp_path):
    """Synchronized (psum and ppermute) and synchronization-avoiding programs timed in one
    run; zeta, t_s, t_d and the avoiding rows follow from the measured times."""
    from jaxsync.solve.syncavoid import SurrogatePredictor
    from jaxsync.perf.timing import speedup_breakdown

    problem = jaxsync.cantilever()
    part = jaxsync.partition(problem.mesh, 2, seed=0)
    predictor = SurrogatePredictor.initialized(part, 4, n_hidden=8, n_layers=1, n_past=3, n_future=5)
    report = speedup_breakdown(problem, part, predictor, n_cycles=2, repeats=3, stage_repeats=5)
    assert report.steps_per_prediction == 20 and report.n_steps == 40
    assert set(report.t_step_sync) == {"psum", "ppermute"}
    assert report.sync == min(report.t_step_sync, key=report.t_step_sync.get)
    assert report.zeta == pytest.approx(report.t_step_sync[report.sync] / report.t_step_avoiding)
    assert report.t_s == pytest.approx(max(report.t_step_synchronized - report.t_step_nosync, 0.0))
    assert len(report.t_prediction) == 2 and all(t > 0 for t in report.t_prediction)
    assert report.t_prediction_spmd > 0
    assert report.t_d == pytest.approx(report.t_prediction_spmd / 20)
    assert report.surrogate_pays == (report.t_d < report.t_s)
    for sync_row, row_ in zip(report.synchronized.rows, report.avoiding.rows):
        assert row_.t_s == 0.0 and sync_row.t_d == 0.0
        assert row_.t_d == pytest.approx(report.t_d)
        assert row_.t_t == pytest.approx(sync_row.t_local + row_.t_d)
        assert (row_.t_e, row_.t_m, row_.t_o) == (sync_row.t_e, sync_row.t_m, sync_row.t_o)
    assert report.architecture["n_hidden"] == 8
    assert "zeta" in report.table()
    report.save_json(tmp_path / "speedup.json")
    data = json.loads((tmp_path / "speedup.json").read_text())
    assert data["zeta"] == pytest.approx(report.zeta)
    assert data["avoiding"]["max_average"]["t_d"] == pytest.approx(report.avoiding.max_average.t_d)
    with pytest.raises(ProblemError, match="syncs"):
        speedup_breakdown(problem, part, predictor, syncs=("allgather",))
    with pytest.raises(ProblemError, match="2 parts"):
        speedup_breakdown(problem, 1, predictor)
