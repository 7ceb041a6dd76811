"""benchmarks/gpu_projection.py on a small stand-in mesh: it writes its JSON and table, and
its rows agree with the alpha-beta model computed by hand."""

import json
import math

import pytest

from benchmark_scripts import load_benchmark

T_1, T_C_ONE, T_SYNC_ONE, FLOOR = 115.0, 156.0, 163.0, 10.0  # us: the H200 figures and t_0


@pytest.fixture(scope="module")
def projection(tmp_path_factory):
    out = tmp_path_factory.mktemp("gpu_projection")
    script = load_benchmark("gpu_projection")
    assert script.main(["--out-dir", str(out), "--stand-in-elements", "4000", "--max-parts", "16"]) == 0
    record = json.loads((out / "gpu_projection.json").read_text())
    return script, record


def test_writes_json_with_the_small_scenarios(projection):
    _, record = projection
    keys = [r["key"] for r in record["scenarios"]]
    assert keys == ["one-gpu", "nvlink-3us", "nvlink-6us", "nodes-16", "xla-16"]  # --max-parts 16
    assert record["stand_in"]["n_elements"] < 6000
    for r in record["scenarios"]:
        assert set(r["halos"]) == {"1", "2", "4", "8"}
        reds = [r["halos"][k]["redundancy"] for k in ("1", "2", "4", "8")]
        assert 1.0 < reds[0] < reds[1] < reds[2] < reds[3]  # deeper halos hold more elements
        assert r["break_even_t_d_vs_synchronized_us"] == r["t_s_us"]
        assert r["best_exact"]["t_step_us"] <= min([r["t_sync_us"], T_1]
                                                   + [h["t_step_us"] for h in r["halos"].values()])


def test_one_gpu_row_by_hand(projection):
    _, record = projection
    row = next(r for r in record["scenarios"] if r["key"] == "one-gpu")
    assert row["t_c_us"] == T_C_ONE
    assert row["t_s_us"] == pytest.approx(T_SYNC_ONE - T_C_ONE, rel=1e-9)  # fitted to the measured exchange
    assert row["t_sync_us"] == pytest.approx(T_SYNC_ONE, rel=1e-9)
    # the whole mesh on the one GPU (115 us) beats any 11-part step: the learned method never wins
    assert row["best_exact"]["method"] == "whole mesh on one GPU"
    assert row["break_even_t_d_vs_best_exact_us"] == pytest.approx(T_1 - T_C_ONE)
    assert row["surrogates"]["lstm"]["rate_needed_vs_best_exact_GFlops"] is None
    # the LSTM at the CPU rate: 11 refills of the widest part, each the measured CPU time of a
    # refill of all n_s windows scaled to the 16 calls of the default smooth refill (the LSTM's
    # flops are affine in the windows: the normalization of the mean and std is per window too)
    vessel = record["vessel"]
    assert record["surrogate_cost"]["refill_calls"] == 16
    t_d = 11 * 1e6 * vessel["refill_seconds_widest_alone"] * (16 / vessel["n_s"]) / (vessel["n_s"]
                                                                                    * vessel["n_future"])
    lstm = row["surrogates"]["lstm"]
    assert lstm["t_d_cpu_rate_us"] == pytest.approx(t_d, rel=1e-9)
    assert lstm["zeta"] == pytest.approx(T_SYNC_ONE / (T_C_ONE + t_d), rel=1e-9)


def exchange_us(latency, bandwidth, p, vector_nodes, busiest_nodes, values_per_node):
    """The alpha-beta exchange by hand: the cheaper of a ring allreduce of the whole
    vector (2 (p - 1) / p of its bytes per GPU) and one grouped neighbour exchange of the
    busiest part's values."""
    ring = latency + 2 * (p - 1) / p * vector_nodes * values_per_node * 8 / bandwidth
    grouped = latency + busiest_nodes * values_per_node * 8 / bandwidth
    return 1e6 * min(ring, grouped)


def test_nvlink_row_by_hand(projection):
    """zeta of the synchronized, halo and linear steps from the alpha-beta formulas."""
    _, record = projection
    row = next(r for r in record["scenarios"] if r["key"] == "nvlink-3us")
    p, latency, bandwidth = 8, 3e-6, 450e9  # NVLink 4, one NCCL call
    site = record["stand_in"]["partitions"]
    c = record["vessel"]["n_interface"] / site["11"]["n_interface"]
    n_a = round(c * site["8"]["n_interface"])
    assert row["n_interface"] == n_a
    t_c = FLOOR + (T_1 - FLOOR) / p
    t_s = exchange_us(latency, bandwidth, p, n_a, round(c * site["8"]["busiest"]), 3)
    assert row["t_c_us"] == pytest.approx(t_c, rel=1e-12)
    assert row["t_s_us"] == pytest.approx(t_s, rel=1e-9)
    t_sync = t_c + t_s
    ratio = record["stand_in"]["n_elements"] / record["vessel"]["n_elements"]
    for k in (1, 2, 4, 8):
        stand_in = site["8"]["halos"][str(k)]
        r_k = 1 + c * (stand_in["redundancy"] - 1) * ratio
        t_sh = exchange_us(latency, bandwidth, p, round(c * stand_in["n_halo"]), round(c * stand_in["busiest"]), 6)
        t_halo = FLOOR + r_k * (t_c - FLOOR) + t_sh / k
        assert row["halos"][str(k)]["t_step_us"] == pytest.approx(t_halo, rel=1e-9)
        assert row["halos"][str(k)]["zeta"] == pytest.approx(t_sync / t_halo, rel=1e-9)
    # the linear surrogate: 2 n_p D r + 2 r n_f D + bias, normalization and mask per window
    d, rank, n_p, n_f = row["shared_dofs_widest"], record["vessel"]["n_train_windows"], 20, 20
    n_s, calls = record["vessel"]["n_s"], 16  # the smooth refill's calls over the n_s n_f steps a refill serves
    flops = (2 * n_p * d * rank + 2 * rank * n_f * d + n_f * d + 2 * d * (n_p + n_f) + n_f * d) * calls / (n_s * n_f)
    linear = row["surrogates"]["linear"]
    assert linear["flops_per_step"] == pytest.approx(flops, rel=1e-12)
    t_d = 1e6 * flops / (1e9 * record["surrogate_cost"]["cpu_rate_GFlops"])
    assert linear["zeta"] == pytest.approx(t_sync / (t_c + t_d), rel=1e-9)
    best = min([t_sync] + [h["t_step_us"] for h in row["halos"].values()])
    assert row["break_even_t_d_vs_best_exact_us"] == pytest.approx(best - t_c, rel=1e-9)
    assert linear["rate_needed_vs_best_exact_GFlops"] == pytest.approx(flops / (1e3 * (best - t_c)), rel=1e-9)


def test_table_printed(projection):
    script, record = projection
    text = script.format_table(record)
    assert "11 parts on one GPU" in text and "halo k=8" in text and "never / never" in text
    assert math.isfinite(record["surrogate_cost"]["cpu_rate_GFlops"])
