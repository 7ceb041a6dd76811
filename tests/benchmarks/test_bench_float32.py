"""benchmarks/bench_float32.py runs (its quick settings) and measures float32 blocks
against float64: a small, nonzero difference."""

import json

from benchmark_scripts import load_benchmark


def test_bench_float32_quick(tmp_path):
    bench = load_benchmark("bench_float32")
    out = tmp_path / "float32.json"
    assert bench.main(["--quick", "--steps", "400", "--out", str(out)]) == 0
    rows = {r["case"]: r for r in json.loads(out.read_text())["rows"]}
    assert set(rows) == {"cantilever", "vessel-rough"}
    for r in rows.values():
        assert r["steps"] == 400 and 0 < r["error"] < 1e-5
        assert r["at_quarters"][-1] <= r["error"]
