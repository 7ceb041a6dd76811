"""benchmarks/bench_gpu.py, the one prepared accelerator check, dry-run on the CPU: it must
keep working between the rare sessions that have a GPU."""

import json
import math
import os

from benchmark_scripts import load_benchmark

# the measured numbers of each section's rows: positive and finite
TIMED = {
    "copy": ("GB_per_s", "call_ms"),
    "stepper": ("us_per_step", "us_per_step_median", "bytes_per_step", "GB_per_s", "percent_of_copy", "call_ms"),
    "hyperelastic": ("us_per_force", "elements_per_s", "bytes_per_element", "GB_per_s", "bound_elements_per_s",
                     "percent_of_bound", "call_ms"),
    "vessel": ("us_per_step", "us_per_step_median", "call_ms"),
    "training": ("seconds_per_epoch", "ms_per_gradient_step", "compile_s", "call_ms"),
    "ensemble": ("us_per_batched_step", "run_steps_per_s", "call_ms", "setup_s_per_member"),
}


def _positive(value) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value) and value > 0


def test_dry_run_on_the_cpu_runs_every_section_and_writes_json(tmp_path, capsys):
    bench = load_benchmark("bench_gpu")
    out, mesh = tmp_path / "gpu.json", tmp_path / "vessel.npz"
    assert bench.main(["--platform", "cpu", "--quick", "--vessel-mesh", str(mesh), "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["platform"] == "cpu" and result["quick"] and result["jax"] and "cpu" in result["devices"]
    assert list(result["sections"]) == list(bench.SECTIONS) == list(TIMED)
    for name, section in result["sections"].items():
        assert section["rows"], name
        assert not section["errors"] and not section["skipped"], (name, section["errors"], section["skipped"])
        for row in section["rows"]:
            assert set(bench.ROW_KEYS[name]) <= set(row), (name, set(bench.ROW_KEYS[name]) - set(row))
            assert all(_positive(row[key]) for key in TIMED[name]), (name, row)
            assert row.get("steps_per_call", 1) >= 1

    stepper = result["sections"]["stepper"]["rows"]
    assert {r["blocks"] for r in stepper if r["variant"] == "advance"} == {"float64", "float32"}
    unrolled = [r for r in stepper if r["variant"] != "advance"]
    assert sorted(r["unroll"] for r in unrolled) == list(bench.UNROLLS)
    # the same steps, several per loop iteration: the displacements of advance to round-off
    assert all(r["max_rel_diff_vs_advance"] <= 1e-10 for r in unrolled)
    assert {r["law"] for r in result["sections"]["hyperelastic"]["rows"]} == {"NeoHookean", "HolzapfelGasserOgden"}
    vessel = result["sections"]["vessel"]["rows"]
    assert [r["n_parts"] for r in vessel] == [1, bench.QUICK.n_parts, bench.QUICK.n_parts]
    assert vessel[1]["max_rel_diff_vs_one_device"] <= 1e-10
    # the generated mesh was kept, and a later run reads it instead of meshing again
    assert result["sections"]["vessel"]["mesh_source"] == "gmsh"
    again, source = bench.vessel_mesh(bench.QUICK.vessel_target, str(mesh))
    assert source.startswith("read") and again.n_elements == vessel[0]["elements"]
    training = result["sections"]["training"]["rows"]
    assert [r["case"] for r in training] == ["demo", "paper-nH100", "vessel-paper"]
    assert [r["replicas"] for r in training] == [2, 2, bench.QUICK.n_parts]
    (ensemble,) = result["sections"]["ensemble"]["rows"]
    assert ensemble["members"] == bench.QUICK.members and ensemble["max_rel_diff_vs_ensemble"] <= 1e-10
    assert all(_positive(t) for t in result["summary"]["floor_us_per_step"].values())
    assert "wrote" in capsys.readouterr().out


def test_host_inputs_come_back_from_a_background_process():
    bench = load_benchmark("bench_gpu")
    prepared = bench.Prepared(1)
    try:
        prepared.submit("name", bench.beam_name, (60, 8, 8))
        value, waited = prepared.get("name")
    finally:
        prepared.close()
    assert value == "beam-60x8x8" and waited >= 0


def test_without_the_platform_it_says_so_and_exits_3(capsys):
    bench = load_benchmark("bench_gpu")
    assert bench.main(["--platform", "tpu", "--out", os.devnull]) == 3
    assert "no tpu devices here" in capsys.readouterr().out
