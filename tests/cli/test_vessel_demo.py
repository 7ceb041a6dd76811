"""``jaxsync demo --case vessel``, reduced: a generated coronary tree of a few thousand
tets (near the fewest its thinnest branch allows) in 3 parts, 1000 steps, mass-scaled, a
short training, the synchronization-avoiding run and the report. The summary is checked
against the trajectories and independent computations (the shared-node errors recomputed
node by node, the mass scaling redone), not against the code's own definitions."""

import json

import numpy as np
import pytest
from test_cli_pipeline import run_cli

import jaxsync
from jaxsync.app.demo import SUMMARY_KEYS, VESSEL_KEYS, demo_defaults
from jaxsync.app.run_estimate import NOT_INCLUDED, format_duration
from jaxsync.cli import build_parser, parts_of
from jaxsync.errors import ConfigError

N_STEPS, N_S, N_P, N_PARTS, SIZE = 1000, 10, 5, 3, 3500
# the shared histories hold a row every N_S steps (rows 0 .. N_STEPS / N_S); training reads
# the first half of them, floor(0.5 rows)
TRAINED_ROWS = (N_STEPS // N_S + 1) // 2


@pytest.fixture(scope="module")
def vessel(tmp_path_factory):
    out = tmp_path_factory.mktemp("vessel") / "demo"
    run = run_cli(["demo", "--case", "vessel", "--size", SIZE, "--parts", N_PARTS, "--steps", N_STEPS,
                   "--n-s", N_S, "--n-past", N_P, "--n-future", N_P, "--epochs", "2", "--hidden", "8",
                   "--resync-tolerance", "none", "--out", out, "--no-progress"])
    assert run.code == 0, run.err
    summary = json.loads((out / "summary.json").read_text())
    reference = jaxsync.Trajectory.load(out / "synchronized.h5")
    online = jaxsync.Trajectory.load(out / "online.h5")
    return out, run, summary, reference, online


def test_vessel_summary_has_the_cantilever_keys_and_its_own(vessel):
    summary = vessel[2]
    for key in SUMMARY_KEYS + VESSEL_KEYS:
        assert key in summary, key
    for key in SUMMARY_KEYS + ("es_max", "es_hat_max", "interior_max_relative_error"):
        assert isinstance(summary[key], str) or np.isfinite(summary[key]), key
    # the tests' two emulated devices (conftest) hold the 3 parts
    assert summary["case"] == "vessel" and summary["n_parts"] == N_PARTS and summary["n_devices"] == 2
    assert summary["n_steps"] == N_STEPS
    assert summary["n_synchronized"] == N_S * N_P and summary["n_predicted"] == N_STEPS - N_S * N_P
    assert summary["component"] == "dominant"
    names = {row["interconnect"]["name"] for row in summary["projection"]["rows"]}
    assert {"infiniband-hdr", "nvlink-4", "ethernet-10g"} <= names
    assert summary["projection"]["pattern"]["n_parts"] == N_PARTS


def test_vessel_mesh_and_files(vessel):
    out, _, summary, reference, online = vessel
    mesh = reference.mesh
    assert summary["n_elements"] == mesh.n_elements and summary["n_dofs"] == 3 * mesh.n_nodes
    assert 3000 <= mesh.n_elements <= 4500
    assert {"inlet", "outlet", "lumen"} <= set(mesh.facet_sets)
    # the reference keeps the shared nodes every n_s steps only: what training reads
    assert reference.save_every == N_S and reference.shared_stride == N_S
    np.testing.assert_array_equal(reference.parts[0].shared_displacement,
                                  reference.displacement[:, reference.parts[0].shared_nodes].reshape(
                                      reference.n_saved, -1))
    assert online.n_saved == N_STEPS // N_S + 1
    for name in ("displacement_nodes.png", "l2_error.png", "shared_errors.png", "es_tracking.png",
                 "mass_scaling.png"):
        assert (out / "report" / name).stat().st_size > 1000, name
    assert (out / "surrogate" / "surrogate.h5").exists()


def test_vessel_shared_node_errors_recomputed_node_by_node(vessel):
    """es(t) (paper eq. 25): at each shared node, the mean over the parts that hold it of
    their component-mean absolute error, averaged over the shared nodes; es_hat (eq. 26)
    the same with the pairs of parts that hold a node. Recomputed here with loops."""
    _, _, summary, reference, online = vessel
    steps = np.flatnonzero(~np.asarray(online.synchronized, bool))
    truth = np.asarray(reference.displacement)[steps]
    per_node: dict[int, list[np.ndarray]] = {}
    for part in online.parts:
        values = np.asarray(part.predicted_shared_displacement).reshape(len(steps), -1, 3)
        for k, node in enumerate(part.shared_nodes):
            per_node.setdefault(int(node), []).append(values[:, k])
    es, es_hat = np.zeros(len(steps)), np.zeros(len(steps))
    for node, preds in per_node.items():
        es += np.mean([np.abs(p - truth[:, node]).mean(axis=1) for p in preds], axis=0)
        pairs = [np.abs(a - b).mean(axis=1) for i, a in enumerate(preds) for b in preds[i + 1:]]
        es_hat += np.mean(pairs, axis=0)
    es, es_hat = es / len(per_node), es_hat / len(per_node)
    assert summary["es_max"] == pytest.approx(es.max(), rel=1e-9)
    assert summary["es_hat_max"] == pytest.approx(es_hat.max(), rel=1e-9)
    assert summary["es_final"] == pytest.approx(es[-1], rel=1e-9)


def test_vessel_interior_nodes_in_their_dominant_component(vessel):
    """One monitored node per part, not shared and not clamped, each measured in its own
    dominant component; the worst relative error recomputed from the trajectories."""
    _, _, summary, reference, online = vessel
    ref, pred = np.asarray(reference.displacement), np.asarray(online.displacement)
    shared = set(np.concatenate([p.shared_nodes for p in online.parts]).tolist())
    problem = jaxsync.coronary(reference.mesh)
    clamped = set((problem.dirichlet_dofs()[0] // 3).tolist())
    rows = [row for row in summary["node_errors"] if not row["shared"]]
    assert len(rows) == N_PARTS
    worst = 0.0
    for part, row in zip(online.parts, rows):
        node = row["node"]
        assert node not in shared and node not in clamped
        amplitude = np.abs(ref[:, node]).max(axis=0)
        k = int(np.argmax(amplitude))
        assert row["component"] == "xyz"[k]
        relative = np.abs(pred[:, node, k] - ref[:, node, k]).max() / amplitude[k]
        assert row["relative_max_error"] == pytest.approx(relative, rel=1e-9)
        worst = max(worst, relative)
    assert summary["interior_max_relative_error"] == pytest.approx(worst, rel=1e-9)


def test_vessel_trains_on_the_first_half_and_measures_after_it(vessel):
    """Training ends at the last shared-history row of the first half (rows every
    save_every = 10 steps: 101 rows, the first 50 up to step 490); every out-of-sample
    error is recomputed from the trajectories over the snapshots after that step only."""
    _, run, summary, reference, online = vessel
    assert demo_defaults("vessel").train_fraction == 0.5
    assert TRAINED_ROWS == 50
    last = (TRAINED_ROWS - 1) * N_S
    assert summary["train_until_step"] == last == 490
    ref, pred = np.asarray(reference.displacement), np.asarray(online.displacement)
    steps = np.rint(np.asarray(online.times) / online.dt).astype(int)
    after = steps > last
    oos = summary["out_of_sample"]
    assert oos["from_step"] == last + N_S and oos["n_snapshots"] == after.sum() == (N_STEPS - last - N_S) // N_S + 1
    worst = 0.0
    for row in oos["node_errors"]:
        node, k = row["node"], "xyz".index(row["component"])
        error = np.abs(pred[after, node, k] - ref[after, node, k])
        amplitude = np.abs(ref[after, node, k]).max()
        assert row["max_abs_error"] == pytest.approx(error.max(), rel=1e-12)
        assert row["max_abs_displacement"] == pytest.approx(amplitude, rel=1e-12)
        if not row["shared"]:
            worst = max(worst, error.max() / amplitude)
    assert oos["interior_max_relative_error"] == pytest.approx(worst, rel=1e-9)
    l2 = np.sqrt(((pred[after] - ref[after]) ** 2).sum(axis=(1, 2)))  # e(t), paper eq. 24
    assert oos["l2_error_max"] == pytest.approx(l2.max(), rel=1e-9)
    assert f"out of sample (after step {last})" in run.out


def test_vessel_mass_scaling_check(vessel):
    """The step is 2.5 times the CFL step; the added mass is what jaxsync.mass_scaling
    adds on the same mesh; the node's motion changes only marginally (paper fig. 19)."""
    _, _, summary, reference, _ = vessel
    m = summary["mass_scaling"]
    problem = jaxsync.coronary(reference.mesh)
    _, added = jaxsync.mass_scaling(problem, beta=2.5, warn_above_percent=None)
    assert m["dt_cfl"] == pytest.approx(problem.dt, rel=1e-12)
    assert m["dt_scaled"] == pytest.approx(2.5 * problem.dt, rel=1e-12) == summary["dt"]
    assert m["added_mass_percent"] == pytest.approx(added, rel=1e-12) and added > 0
    assert m["n_steps_cfl"] * m["dt_cfl"] == pytest.approx(m["n_steps_scaled"] * m["dt_scaled"], rel=0.01)
    assert m["max_abs_displacement"] > 0 and m["relative_difference"] < 0.05


def test_vessel_demo_reports_the_pressure_diameter_loop(vessel):
    """The vessel section of the report (jaxsync.vessel_metrics) on the synchronized run:
    the lumen pressure at every snapshot is the pressure load's magnitude times its time
    function, evaluated here; the diameters are positive, the wall's peaks found, the
    figures written."""
    out, _, summary, reference, _ = vessel
    section = summary["vessel"]
    assert not section["skipped"]
    pressure = [load for load in jaxsync.coronary(reference.mesh).loads if isinstance(load, jaxsync.Pressure)]
    assert section["surface"] == pressure[0].surface
    expected = [sum(float(p.magnitude) * float(p.time(t)) for p in pressure) for t in reference.times]
    np.testing.assert_allclose(section["loop"]["pressure"], expected, rtol=1e-12)
    assert len(section["loop"]["diameter"]) == reference.n_saved and min(section["loop"]["diameter"]) > 0
    assert section["peaks"]["wall"]["von_mises"]["value"] > 0
    assert (out / "report" / "pressure_diameter.png").is_file() and (out / "report" / "wall_stress.png").is_file()


def test_vessel_demo_prints_its_table(vessel):
    text = vessel[1].out
    assert "coronary tree" in text and "mass scaling" in text and "es / es_hat" in text
    assert f"{N_STEPS} steps: {N_S * N_P} synchronized, {N_STEPS - N_S * N_P} predicted" in text


def test_vessel_defaults_and_devices():
    d = demo_defaults("vessel")
    assert (d.n_parts, d.resync_tolerance, d.component, d.shared_every_step) == (11, "1%", None, False)
    assert (d.n_hidden, d.epochs, d.n_candidates) == (32, 300, 1)  # its 11 parts keep the demo short
    assert parts_of(build_parser().parse_args(["demo", "--candidates", "3"])) == 2
    assert build_parser().parse_args(["demo", "--candidates", "3"]).n_candidates == 3
    assert demo_defaults("vessel", "paper").n_s == 1000 and demo_defaults("vessel", "paper").n_steps == 1_000_000
    parser = build_parser()
    assert parts_of(parser.parse_args(["demo", "--case", "vessel"])) == 11
    assert parts_of(parser.parse_args(["demo"])) == 2
    assert parts_of(parser.parse_args(["demo", "--case", "vessel", "--parts", "4"])) == 4


def test_vessel_bad_sizes_are_refused(tmp_path):
    with pytest.raises(ConfigError, match="vessel size 'huge'"):
        demo_defaults("vessel", "huge")
    with pytest.raises(ConfigError, match="the vessel case"):
        demo_defaults("cantilever", "paper")
    with pytest.raises(ConfigError, match="unknown demo case"):
        demo_defaults("aorta")
    run = run_cli(["demo", "--case", "vessel", "--size", "10", "--out", tmp_path / "x", "--no-progress"])
    assert run.code == 2 and "from 1000 to 2000000" in run.err
    run = run_cli(["demo", "--train-fraction", "1.5", "--out", tmp_path / "y", "--no-progress"])
    assert run.code == 2 and "train fraction must be in (0, 1], got 1.5" in run.err and not (tmp_path / "y").exists()


# The run-time estimate printed before the first stage (jaxsync.app.run_estimate; its
# arithmetic and text: tests/app/test_demo_estimate.py), on this fixture's run.
def test_the_estimate_comes_before_the_first_stage(vessel):
    run, summary = vessel[1], vessel[2]
    text = summary["estimate"]["text"]
    assert text.startswith("estimated time on this machine (cpu, 2 devices emulated in one process): about ")
    at = run.out.index(text)
    assert run.out.index("estimating the run time") < run.out.index("; timing a training epoch") < at
    assert at < run.out.index("[1/5] mass-scaling check") < run.out.index("[2/5] synchronized run")


def test_the_recorded_estimate_is_the_product_of_what_it_measured(vessel):
    """Each part is the count times the rate the code measured, both recorded; the total
    is their sum; the counts are the run's own."""
    summary = vessel[2]
    e = summary["estimate"]
    assert e["n_steps"] == summary["n_steps"] == N_STEPS and e["n_parts"] == N_PARTS
    assert e["n_devices"] == summary["n_devices"] == 2 and e["device_kind"] == summary["device_kind"]
    assert e["us_per_step_synchronized"] > 0 and e["calibration_steps"] >= 20
    assert e["synchronized_s"] == pytest.approx(N_STEPS * e["us_per_step_synchronized"] * 1e-6, rel=1e-12)
    assert e["sync_avoiding_s"] == e["synchronized_s"]
    assert e["epochs"] == 2 and e["training_s"] == pytest.approx(2 * e["seconds_per_epoch"], rel=1e-12)
    # both runs of the mass-scaling check, which trims each to whole sampling strides
    m = summary["mass_scaling"]
    assert 0 <= e["mass_scaling_steps"] - (m["n_steps_cfl"] + m["n_steps_scaled"]) <= 0.01 * e["mass_scaling_steps"]
    assert e["mass_scaling_s"] == pytest.approx(e["mass_scaling_steps"] * e["us_per_step_single_device"] * 1e-6,
                                                rel=1e-12)
    parts = ("mass_scaling_s", "synchronized_s", "sync_avoiding_s", "training_s")
    assert e["total_s"] == pytest.approx(sum(e[k] for k in parts), rel=1e-12)
    assert format_duration(e["total_s"]) in e["text"].splitlines()[0]
    assert e["measure_seconds"] > 0 and e["not_included"] == NOT_INCLUDED
