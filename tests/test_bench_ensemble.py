"""benchmarks/bench_ensemble.py runs (its quick settings): the members' vectorised set-up,
the same members as problems (equal trajectories) and the batched speed are measured."""

import json

from benchmark_scripts import load_benchmark


def test_bench_ensemble_quick(tmp_path):
    bench = load_benchmark("bench_ensemble")
    out = tmp_path / "ensemble.json"
    assert bench.main(["--quick", "--members", "4", "--steps", "20", "--case", "E", "--own-systems-members", "2",
                       "--out", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert [(r["case"], r["members"]) for r in rows] == [("E", 4)]
    for r in rows:
        assert r["setup_ms_per_member"]["warm"] > 0 and r["problems_ms_per_member"] > 0
        assert r["own_systems_ms_per_member"] > 0 and r["run_steps_per_s"] > 0
        assert r["max_rel_diff_members_vs_problems"] <= 1e-12
