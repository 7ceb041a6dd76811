"""benchmarks/untuned_vessel.py on a coarse bifurcating vessel (the linear model, a short
run): the pipeline of jaxsync commands runs, and the JSON's counts and errors are those of
the two trajectories it kept, recomputed here."""

import json

import numpy as np
import pytest

import jaxsync
from benchmark_scripts import load_benchmark


def test_untuned_vessel_quick_run_reports_what_its_trajectories_hold(tmp_path):
    bench = load_benchmark("untuned_vessel")
    out = tmp_path / "untuned"
    bench.main(["--size", "0.15", "--steps", "3000", "--n-s", "15", "--models", "linear", "--no-progress",
                "--keep", "--out", str(out)])
    record = json.loads((out / "untuned_vessel.json").read_text())
    assert record["n_parts"] == 4 and record["n_steps"] == 3000 and record["tolerance"] == "1%"
    (row,) = record["models"]
    assert row["model"] == "linear"
    assert [c["command"].split()[1] for c in record["commands"]] == ["simulate", "train", "predict"]
    reference = jaxsync.Trajectory.load(out / "run" / "sync.h5")
    online = jaxsync.Trajectory.load(out / "run" / "online_linear.h5")
    stats = online.stats
    assert row["n_cri"] == stats.n_cri == 20 * 15
    assert row["n_predicted"] + row["n_synchronized"] == 3000
    assert row["predicted_fraction_after_n_cri"] == row["n_predicted"] / (3000 - stats.n_cri)
    # the largest nodal error after n_cri, recomputed from the saved fields
    assert np.array_equal(np.asarray(reference.times), np.asarray(online.times))
    steps = np.rint(np.asarray(online.times) / float(online.dt)).astype(int)
    error = np.sqrt(((np.asarray(online.displacement) - np.asarray(reference.displacement)) ** 2).sum(-1))
    assert row["max_nodal_error_cm"] == pytest.approx(error[steps > stats.n_cri].max(), rel=1e-12)
    assert row["max_nodal_error_out_of_sample_cm"] == pytest.approx(error[steps > 1500].max(), rel=1e-12)
    # 1 % of the shared amplitude of the trained steps (the surrogate file records it), at every re-synchronization
    trained = jaxsync.surrogate.load_surrogate(out / "run" / "surrogate_linear" / "surrogate.h5")
    rows = reference.parts[0].shared_displacement.shape[0]
    amplitude = max(np.abs(p.shared_displacement[:rows // 2]).max() for p in reference.parts)
    assert trained.metadata["shared_amplitude_cm"] == amplitude
    assert row["tolerance_cm"] == pytest.approx(0.01 * amplitude, rel=1e-12)
    assert all(t == pytest.approx(row["tolerance_cm"], rel=1e-12) for t in stats.tolerance_cm or ())
    assert row["tolerance_cm"] > 0 and row["error_over_tolerance"] == row["max_nodal_error_cm"] / row["tolerance_cm"]
    assert row["meets_target"] == (row["predicted_fraction_after_n_cri"] >= 0.8 and row["error_over_tolerance"] <= 2)
