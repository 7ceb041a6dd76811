"""benchmarks/bench_ensemble_inverse.py runs (its quick settings): the moduli of several
vessels, fitted at once through the gradient of their batched run, are within a few
Cramer-Rao standard deviations of the moduli that made their noisy data, and the
gradient equals central differences of the loss."""

import json

from benchmark_scripts import load_benchmark


def test_bench_ensemble_inverse_quick(tmp_path):
    bench = load_benchmark("bench_ensemble_inverse")
    out = tmp_path / "ensemble_inverse.json"
    assert bench.main(["--quick", "--out", str(out)]) == 0
    record = json.loads(out.read_text())
    assert record["settings"]["members"] == 3 and record["problem"]["dofs"] > 3000
    members = record["members"]
    truth = [m["E_true"] for m in members]
    assert max(truth) / min(truth) > 1.1  # the members do differ
    for m in members:
        # the estimate's error, in units of its Cramer-Rao standard deviation: ~N(0, 1)
        assert abs(m["z"]) <= 4.0, m
        assert abs(m["relative_error"]) <= 4.0 * m["cramer_rao_relative_std"] + 1e-12, m
        assert m["cramer_rao_relative_std"] < 0.01  # the data do pin E down
    steps = record["gauss_newton_steps"]
    assert steps[0] > 0.05 and steps[-1] < 1e-8  # from 5 % or more away, to convergence
    for check in record["gradient_check"]:
        assert check["relative_difference"] <= 1e-6, check
    assert record["command"].startswith("python benchmarks/bench_ensemble_inverse.py --quick")
    assert "| member | E true |" in record["table"]
