"""benchmarks/bench_surrogates.py --quick, reduced to one case and 600 steps: it runs the
three surrogates online, times them and writes the JSON the README table is made from."""

import json
import math

from benchmark_scripts import load_benchmark


def test_quick_run_writes_every_surrogate_and_timing(tmp_path, capsys):
    script = load_benchmark("bench_surrogates")
    out = tmp_path / "bench_surrogates.json"
    assert script.main(["--quick", "--case", "default", "--steps", "600", "--quiet", "--out", str(out)]) == 0
    record = json.loads(out.read_text())
    assert {"benchmark", "settings", "seed", "bf16_bound", "cases", "machine", "wall_seconds"} <= set(record)
    assert record["settings"]["quick"] is True and record["settings"]["n_steps"] == 600
    (case,) = record["cases"]
    assert case["case"] == "default"
    assert {"reference", "variants", "timing", "break_even", "bf16_check", "tip_node"} <= set(case)
    assert set(case["variants"]) == {"lstm", "lstm_bf16", "linear"}
    for name, variant in case["variants"].items():
        metrics = variant["metrics"]["z"]
        for key in ("tip_max_error_relative", "tip_final_error_relative", "e_l2_max_cm", "e_l2_final_cm",
                    "l2_relative"):
            assert metrics[key] >= 0, (name, key)
        # timings are measurements (never asserted): on a loaded machine a tiny network's
        # time after the call cost can be 0 or below, and zeta then None
        assert math.isfinite(variant["t_d"]) and (variant["zeta"] is None or variant["zeta"] > 0)
        assert variant["online"]["n_predicted_steps"] > 0
    assert case["variants"]["lstm_bf16"]["inference_dtype"] == "bfloat16"
    assert case["variants"]["linear"]["kind"] == "linear" and case["variants"]["lstm"]["kind"] == "lstm"
    assert set(case["timing"]["t_s"]) == {"psum", "ppermute"}
    assert {"lstm_bf16", "linear_bf16"} == set(case["bf16_check"])
    assert case["bf16_check"]["lstm_bf16"]["bound"] == record["bf16_bound"]
    assert "infiniband-hdr" in case["break_even"]
    assert set(case["break_even"]["infiniband-hdr"]["pays_off"]) == {"lstm", "lstm_bf16", "linear"}
    printed = capsys.readouterr().out
    assert "lstm_bf16" in printed and "break-even" in printed
    # a time that came out at or below the call cost (zeta None) is printed as "-"
    case["variants"]["linear"]["zeta"] = None
    row = next(line for line in script.table([case]).splitlines() if line.split()[:2] == ["default", "linear"])
    assert row.split()[-1] == "-"
