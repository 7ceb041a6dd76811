"""benchmarks/bench_predicted_step.py runs (its quick settings): every surrogate's row,
its parts consistent with one another, and the untrained LSTM with a highway it times."""

import json

import numpy as np
import pytest

import jaxsync
from benchmark_scripts import load_benchmark
from jaxsync.errors import ConfigError
from jaxsync.surrogate import Surrogate


def test_bench_predicted_step_quick(tmp_path):
    bench = load_benchmark("bench_predicted_step")
    out = tmp_path / "predicted_step.json"
    assert bench.main(["--quick", "--highway-rank", "6", "--linear-rank", "5", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    rows = {r["surrogate"]: r for r in result["rows"]}
    assert set(rows) == {"lstm", "lstm-all", "lstm-bare", "linear"} and result["case"] == "cantilever"
    assert (rows["lstm"]["rank"], rows["lstm-all"]["rank"], rows["lstm-bare"]["rank"], rows["linear"]["rank"]) == \
        (6, 6, 0, 5)
    # n_s = 10 <= the default 16 samples: every refill calls the network on all 10 applications
    assert {r["refill_calls"] for r in rows.values()} == {10}
    for r in rows.values():
        assert min(r["t_sync_us"], r["t_nosync_us"], r["t_avoid_us"]) > 0
        # the refill's per-step time is its program's time less that of a call without a
        # step, clipped at 0 (jaxsync.perf.measure.per_step_times): on the quick cantilever
        # the difference is within the timer's noise and can be clipped
        assert r["t_d_us"] >= 0
        assert r["rest_us"] == pytest.approx(r["t_avoid_us"] - r["t_nosync_us"] - r["t_d_us"])
        assert r["zeta"] == pytest.approx(r["t_sync_us"] / r["t_avoid_us"])
        assert r["t_d_over_t_sync"] == pytest.approx(r["t_d_us"] / r["t_sync_us"])
    assert result["table"].count("\n") == 5


def test_an_untrained_lstm_with_a_highway_has_its_shape_and_cost():
    problem = jaxsync.cantilever()
    partition = jaxsync.partition(problem.mesh, 2, seed=0)
    bare = Surrogate.initialized(partition, 10, n_hidden=4, n_layers=1)
    wide = Surrogate.initialized(partition, 10, n_hidden=4, n_layers=1, highway_rank=7)
    assert wide.arch.highway and wide.arch.highway_rank == 7
    assert bare.arch.highway_rank == 0 and "highway" not in bare.params  # a highway is set by a fit
    assert np.asarray(wide.params["highway"]["w_in"]).shape == (2, 20, wide.n_dof, 7)
    # the highway's flops: 2 n_p n_dof r + 2 r n_f n_dof and its addition, per window
    d = wide.n_dof
    extra = wide.arch.prediction_cost(10).flops - bare.arch.prediction_cost(10).flops
    assert extra == 10 * (2 * 20 * d * 7 + 2 * 7 * 20 * d + 2 * 20 * d)
    with pytest.raises(ConfigError, match="highway_rank"):
        Surrogate.initialized(partition, 10, model="linear", highway_rank=3)
