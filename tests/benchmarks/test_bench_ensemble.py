"""benchmarks/bench_ensemble.py runs (its quick settings): the members' vectorised set-up,
the same members as problems (equal trajectories) and the batched speed are measured, on
the cantilever and on the demo's vessel, whose checked member equals its own
jaxsync.simulate run to round-off."""

import json

from benchmark_scripts import load_benchmark


def test_bench_ensemble_quick(tmp_path):
    bench = load_benchmark("bench_ensemble")
    out = tmp_path / "ensemble.json"
    assert bench.main(["--quick", "--members", "4", "--steps", "20", "--case", "E", "--own-systems-members", "2",
                       "--out", str(out)]) == 0
    record = json.loads(out.read_text())
    rows = record["rows"]
    assert [(r["problem"], r["case"], r["members"]) for r in rows] == [("cantilever", "E", 4), ("vessel", "E", 2)]
    cantilever, vessel = rows
    assert cantilever["problems_ms_per_member"] > 0 and cantilever["own_systems_ms_per_member"] > 0
    assert cantilever["max_rel_diff_members_vs_problems"] <= 1e-12
    for r in rows:
        assert r["setup_ms_per_member"]["warm"] > 0 and r["run_steps_per_s"] > 0
        assert r["run_steps_per_s"] == r["members"] * 1e6 / r["us_per_batched_step"]
    assert vessel["steps"] == 20 and vessel["dofs"] > 3000 and vessel["member_checked"] == 1
    assert vessel["max_rel_diff_member_vs_simulate"] <= 1e-12
    assert "| vessel (" in record["table"]
    assert record["command"].startswith("python benchmarks/bench_ensemble.py --quick")
