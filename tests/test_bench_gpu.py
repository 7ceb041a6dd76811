"""benchmarks/bench_gpu.py, the prepared GPU check, dry-run on the CPU: it must keep
working between the rare sessions that have a GPU."""

import json
import os

import pytest

from benchmark_scripts import load_benchmark


@pytest.mark.slow  # 30 s of compilation; the programs it runs are tested on their own elsewhere
def test_dry_run_on_the_cpu_checks_the_programs_and_writes_json(tmp_path, capsys):
    bench = load_benchmark("bench_gpu")
    out = tmp_path / "gpu.json"
    assert bench.main(["--platform", "cpu", "--quick", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["platform"] == "cpu" and result["n_devices"] >= 1
    assert [r["dofs"] for r in result["stepper"]] == [312, 14823]
    assert all(r["us_per_step"] > 0 and r["scipy_us_per_step"] > 0 for r in result["stepper"])
    assert {r["sync"] for r in result["distributed"]} == {"psum", "ppermute", "halo"}
    assert all(r["max_rel_diff_vs_single"] <= 1e-12 for r in result["distributed"])
    assert [r["surrogate"] for r in result["speedup"]] == ["linear"]
    assert all(set(r["zeta_halo"]) == {"1", "4"} for r in result["speedup"])
    assert "wrote" in capsys.readouterr().out


def test_without_the_platform_it_says_so_and_exits_3(capsys):
    bench = load_benchmark("bench_gpu")
    assert bench.main(["--platform", "tpu", "--out", os.devnull]) == 3
    assert "no tpu devices here" in capsys.readouterr().out
