"""benchmarks/regime_map.py: the cost-model regime map on a synthetic bench_sync JSON, and
its model checked against the alpha-beta formula by hand."""

import json
import math

import pytest

from benchmark_scripts import load_benchmark
from jaxsync.perf.costmodel import CommunicationPattern


def synthetic_sync_json(path):
    rows = [{"kind": "solver", "method": "psum-gloo", "n_doubles": 12, "steps": 64, "us_per_step_best": 300.0},
            {"kind": "solver", "method": "mpi4jax", "n_doubles": 12, "steps": 64, "us_per_step_best": 12.0},
            {"kind": "speedup", "method": "nosync", "steps": 64, "us_per_step_best": 4.0},
            {"kind": "speedup", "method": "avoid-lstm-paper", "steps": 64, "us_per_step_best": 24.0},
            {"kind": "speedup", "method": "avoid-lstm-default", "steps": 64, "us_per_step_best": 14.0},
            {"kind": "speedup", "method": "avoid-linear", "steps": 64, "us_per_step_best": 4.01}]
    path.write_text(json.dumps({"benchmark": "synthetic", "rows": rows}))


def test_main_writes_png_and_json_from_measured_rows(tmp_path, capsys):
    script = load_benchmark("regime_map")
    sync = tmp_path / "sync.json"
    synthetic_sync_json(sync)
    assert script.main(["--sync-json", str(sync), "--out-dir", str(tmp_path)]) == 0
    assert (tmp_path / "regime_map.png").stat().st_size > 10_000
    record = json.loads((tmp_path / "regime_map.json").read_text())
    inputs = record["inputs"]
    assert inputs["t_c_us"] == 4.0
    assert inputs["t_d_us"] == pytest.approx({"avoid-lstm-paper": 20.0, "avoid-lstm-default": 10.0,
                                              "avoid-linear": 0.05})  # 0.01 clipped at 0.05
    assert inputs["solver_t_s_us"] == pytest.approx({"mpi4jax": 8.0, "psum-gloo": 296.0})
    assert not any("fall" in n for n in record["notes"])
    assert record["pattern"]["n_parts"] == 8 and record["mesh_nodes"] == 2525
    assert {r["interconnect"] for r in record["presets"]} >= {"infiniband-hdr", "ethernet-10g"}
    for r in record["presets"]:  # break-even surrogate cost = t_s
        assert r["break_even_t_d_allreduce_us"] == r["t_s_allreduce_us"] > 0
    # deeper halos hold more elements
    reds = [record["halos"][k]["redundancy"] for k in ("1", "2", "4", "8")]
    assert 1.0 < reds[0] < reds[1] < reds[2] < reds[3]
    out = capsys.readouterr().out
    assert "ethernet-10g" in out and "break-even" in out


def test_missing_sync_json_falls_back_with_a_note(tmp_path, capsys):
    script = load_benchmark("regime_map")
    assert script.main(["--sync-json", str(tmp_path / "absent.json"), "--out-dir", str(tmp_path)]) == 0
    record = json.loads((tmp_path / "regime_map.json").read_text())
    assert record["inputs"]["t_d_us"] == script.FALLBACK_T_D_US
    assert record["inputs"]["solver_t_s_us"] == {}
    assert any("not found" in n for n in record["notes"])
    assert any("fall" in n and "back" in n for n in record["notes"])
    assert "fall" in capsys.readouterr().out
    assert (tmp_path / "regime_map.png").exists()


def test_surrogate_break_even_latency_on_two_parts_by_hand():
    script = load_benchmark("regime_map")
    # 2 parts sharing 4 nodes: S = 4 * 3 * 8 = 96 bytes; allreduce on 2 parts = one
    # message of S (recursive doubling, 1 round; the ring's 2 messages of S/2 cost more)
    pattern = CommunicationPattern(n_parts=2, n_interface=4, neighbours=(((1, 4),), ((0, 4),)))
    bandwidth, t_d, t_c = 12.5e9, 10e-6, 3e-6
    latency = script.break_even_latency(pattern, t_d, bandwidth, "allreduce")
    assert latency == pytest.approx(t_d - 96 / bandwidth, rel=1e-9)
    t_s = latency + 96 / bandwidth  # alpha-beta, by hand
    assert script.zeta_surrogate(t_c, t_s, t_d) == pytest.approx(1.0, rel=1e-9)
    t_s_model = script.t_sync(pattern, [latency, 2 * latency], bandwidth, "allreduce")
    assert script.zeta_surrogate(t_c, t_s_model[0], t_d) == pytest.approx(1.0, rel=1e-9)
    assert script.zeta_surrogate(t_c, t_s_model[1], t_d) > 1.0
    # a surrogate cheaper than the bandwidth term pays at any latency
    assert script.break_even_latency(pattern, 1e-9, bandwidth, "allreduce") == 0.0


def test_deep_halo_zeta_limits():
    script = load_benchmark("regime_map")
    pattern = CommunicationPattern(n_parts=2, n_interface=4, neighbours=(((1, 4),), ((0, 4),)))
    halo = CommunicationPattern(n_parts=2, n_interface=12, neighbours=(((1, 12),), ((0, 12),)),
                                dofs_per_node=6)
    bandwidth, r_k, k = 12.5e9, 1.5, 4
    # large t_c: the redundant work dominates, zeta -> 1 / r_k < 1
    lat = 1e-6
    t_s = script.t_sync(pattern, lat, bandwidth, "neighbour")[0]
    t_sh = script.t_sync(halo, lat, bandwidth, "neighbour")[0]
    assert t_s == pytest.approx(lat + 96 / bandwidth)
    assert t_sh == pytest.approx(lat + 12 * 6 * 8 / bandwidth)
    z_big = script.zeta_halo(1.0, t_s, r_k, t_sh, k)
    assert z_big < 1.0 and z_big == pytest.approx(1 / r_k, rel=1e-4)
    # large latency at a moderate t_c: one exchange in k steps wins, zeta -> k
    lat = 1e-2
    t_s = script.t_sync(pattern, lat, bandwidth, "neighbour")[0]
    t_sh = script.t_sync(halo, lat, bandwidth, "neighbour")[0]
    z_lat = script.zeta_halo(1e-6, t_s, r_k, t_sh, k)
    assert z_lat > 1.0 and z_lat == pytest.approx(k, rel=1e-3)
    assert math.isfinite(z_lat)
