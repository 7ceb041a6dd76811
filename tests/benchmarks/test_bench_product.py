"""benchmarks/bench_product.py runs (its quick settings) and records both forms of the
stiffness product with the break-even run length computed from its own numbers."""

import json

from benchmark_scripts import load_benchmark


def test_bench_product_quick(tmp_path):
    bench = load_benchmark("bench_product")
    out = tmp_path / "product.json"
    record = bench.main(["--quick", "--out", str(out)])
    assert json.loads(out.read_text()) == json.loads(json.dumps(record))
    (row,) = record["rows"]
    assert row["case"] == "cantilever" and row["parts"] == 1 and row["n_steps"] == 200
    assert row["slots"] == 104 * 9  # the coarse cantilever's nodes times its widest row
    for form in ("fused", "compact"):
        m = row[form]
        assert m["wall_s"] > m["compile_s"] > 0 and m["us_per_step"] > 0
    f, c = row["fused"], row["compact"]
    if row["break_even_steps"] is None:  # no saving, or no penalty: nothing to repay
        assert f["wall_s"] <= c["wall_s"] or c["us_per_step"] <= f["us_per_step"]
    else:
        expected = 200 + 1e6 * (f["wall_s"] - c["wall_s"]) / (c["us_per_step"] - f["us_per_step"])
        assert abs(row["break_even_steps"] - expected) <= 1e-9 * expected
        assert row["break_even_slot_steps"] == row["break_even_steps"] * row["slots"]
