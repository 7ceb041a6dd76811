"""benchmarks/bench_finetune.py runs end to end (its quick smoke settings) and writes the
before/after errors it reports."""

import json

import pytest

from benchmark_scripts import load_benchmark


@pytest.mark.slow
def test_bench_finetune_quick(tmp_path):
    bench = load_benchmark("bench_finetune")
    out = tmp_path / "finetune.json"
    assert bench.main(["--quick", "--case", "default", "--quiet", "--out", str(out)]) == 0
    data = json.loads(out.read_text())
    (row,) = data["rows"]
    assert row["case"] == "default" and data["quick"]
    for when in ("before", "after"):
        assert 0 <= row[when]["tip_max_error_relative"] < 10
    tuned = row["fine_tune"]
    assert len(row["fine_tune_loss_history"]) == data["config"]["n_iterations"] == 4
    # the kept weights are the best validated ones (the start's when none was better)
    losses = [v for _, v in tuned["validation"]]
    assert tuned["improvement"] == pytest.approx(min(losses) / losses[0])
    assert "| default |" in data["table"]
