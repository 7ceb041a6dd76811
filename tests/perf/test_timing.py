"""Timing breakdowns (jaxsync.perf.timing): what they report, checked against the partition
and the arguments, never against the clock. That the separately timed stages add up to
the measured step is a measurement: ``benchmarks/bench_distributed.py`` prints it."""

import json

import pytest

import jaxsync
from jaxsync import CheckpointError, ProblemError
from jaxsync.fem.forces import Preassembled
from jaxsync.perf.reports import SpeedupReport, TimingReport
from jaxsync.perf.timing import speedup_breakdown, timing_breakdown


@pytest.fixture(scope="module")
def problem():
    return jaxsync.cantilever()  # the paper's coarse cantilever, 104 nodes


@pytest.fixture(scope="module")
def partition(problem):
    return jaxsync.partition(problem.mesh, 2, seed=0)


@pytest.mark.parametrize("mode", ["preassembled", "recompute", Preassembled(product="compact")],
                         ids=["preassembled", "recompute", "compact-product"])
def test_breakdown_reports_every_part(problem, partition, mode, tmp_path):
    # a force model times the form it computes (a short run's compact product) under its name
    report = timing_breakdown(problem, partition, mode=mode, n_steps=5, repeats=2)
    name = mode if isinstance(mode, str) else mode.name
    assert (report.mode, report.n_parts, report.n_steps, report.repeats) == (name, 2, 5, 2)
    assert report.n_shared_nodes == partition.n_interface > 0
    assert report.n_devices == 2 and "emulated" in report.device
    assert report.dt == pytest.approx(float(problem.dt))
    for r, part in zip(report.rows, partition.parts):
        assert (r.part, r.n_nodes, r.n_elements, r.n_shared) == (
            part.index, part.n_local, len(part.elements), part.n_shared)
        if name == "preassembled":
            assert r.t_e == 0.0  # K is assembled once; no element work per step
    assert sum(r.n_elements for r in report.rows) == problem.mesh.n_elements
    assert len(report.loadavg) == 3 and report.setup_s >= 0
    report.save_json(tmp_path / "report.json")
    assert TimingReport.load_json(tmp_path / "report.json") == report


def test_one_part_has_no_synchronization(problem):
    report = timing_breakdown(problem, 1, n_steps=5, repeats=2)
    assert report.n_parts == 1 and report.n_shared_nodes == 0
    (r,) = report.rows
    assert r.n_shared == 0 and r.t_s == 0.0 and report.n_devices == 1
    assert (r.n_nodes, r.n_elements) == (problem.mesh.n_nodes, problem.mesh.n_elements)
    assert "n_c=1" in report.table()


def test_bad_arguments_are_refused(problem):
    with pytest.raises(ProblemError, match="mode"):
        timing_breakdown(problem, 2, mode="explicit")
    with pytest.raises(ProblemError, match="n_steps"):
        timing_breakdown(problem, 2, n_steps=0)
    with pytest.raises(ProblemError, match="repeats"):
        timing_breakdown(problem, 2, repeats=0)
    with pytest.raises(jaxsync.PartitionError):
        timing_breakdown(problem, 0)


def test_breakdown_of_deep_halos_times_the_grown_parts(problem, partition):
    from jaxsync.parallel.exchange import halo_partition

    report = timing_breakdown(problem, partition, n_steps=5, repeats=2, sync=jaxsync.Halo(2))
    grown = halo_partition(partition, 2)
    assert report.n_steps == 6  # rounded up to whole exchange cycles
    assert [(r.n_nodes, r.n_elements, r.n_shared) for r in report.rows] == [
        (p.n_local, len(p.elements), p.n_shared) for p in grown.parts]
    assert sum(r.n_elements for r in report.rows) > problem.mesh.n_elements  # the redundant work
    assert report.t_step > 0 and report.rows[0].t_s == report.rows[1].t_s >= 0


def test_speedup_breakdown_times_both_solvers(problem, partition, tmp_path):
    from jaxsync.surrogate import Surrogate

    predictor = Surrogate.initialized(partition, 4, n_hidden=8, n_layers=1, n_past=3, n_future=5)
    report = speedup_breakdown(problem, partition, predictor, n_cycles=2, repeats=2, stage_repeats=2,
                               halo_depths=(1, 4))
    assert report.steps_per_prediction == 4 * 5 and report.n_steps == 2 * 4 * 5
    assert set(report.t_step_halo) == {1, 4} and all(t > 0 for t in report.t_step_halo.values())
    assert report.zeta_halo[4] == pytest.approx(report.t_step_synchronized / report.t_step_halo[4])
    assert "deep halos, depth 4" in report.table()
    assert (report.n_s, report.n_past, report.n_future) == (4, 3, 5)
    assert set(report.t_step_sync) == {"psum", "ppermute"} and report.sync in report.t_step_sync
    assert len(report.t_prediction) == 2
    for sync_row, avoid_row in zip(report.synchronized.rows, report.avoiding.rows):
        assert sync_row.t_d == 0.0 and avoid_row.t_s == 0.0
        # the avoiding solver's local step is the synchronized solver's, measured once
        assert (avoid_row.t_e, avoid_row.t_m, avoid_row.t_o, avoid_row.t_local) == (
            sync_row.t_e, sync_row.t_m, sync_row.t_o, sync_row.t_local)
    assert report.architecture["n_hidden"] == 8
    report.save_json(tmp_path / "speedup.json")
    assert SpeedupReport.load_json(tmp_path / "speedup.json") == report
    assert json.loads((tmp_path / "speedup.json").read_text())["kind"] == "jaxsync-speedup-report"
    with pytest.raises(CheckpointError):
        TimingReport.load_json(tmp_path / "speedup.json")
    with pytest.raises(ProblemError, match="syncs"):
        speedup_breakdown(problem, partition, predictor, syncs=("allgather",))
    with pytest.raises(ProblemError, match="halo depth 3 does not divide the 40 timed steps"):
        speedup_breakdown(problem, partition, predictor, n_cycles=2, halo_depths=(3,))
    with pytest.raises(ProblemError, match="2 parts"):
        speedup_breakdown(problem, 1, predictor)
    with pytest.raises(ProblemError, match="n_cycles"):
        speedup_breakdown(problem, partition, predictor, n_cycles=0)
