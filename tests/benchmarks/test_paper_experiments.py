"""benchmarks/paper_experiments.py: the paper's cantilever experiment matrix (section 5.1),
run in ``--reduced`` mode in-process (2 emulated devices); the errors in every JSON are
recomputed here from the time series the script saved.

The default run runs the matrix once, shortened (``--steps``, FAST_STEPS) and without the two
cases whose code paths other cases take too (training_size: a variant reusing the default
run, as sequence_length; initial_conditions: an ensemble case, as loads); the slow run
repeats every test on the whole matrix at the reduced settings (``--all``)."""

import json
from typing import NamedTuple

import jax
import numpy as np
import pytest

import jaxsync
from benchmark_scripts import load_benchmark

CASES = ("default", "sequence_length", "training_size", "refined_6_parts", "skewed", "step_off",
         "initial_conditions", "loads", "full_system")

# the reduced settings, written out (not read from the script)
COMMON = {"n_steps": 3000, "n_s": 10, "train_fraction": 0.5, "n_parts": 2, "seed": 0, "reduced": True}
EXPECTED = {
    "default": {**COMMON, "n_past": 5, "n_future": 5, "save_every": 10, "shared_every": 1, "n_cri": 50,
                "body_force": [0.0, 0.0, -0.5], "t_off": None},
    "sequence_length": {**COMMON, "variants": [[5, 5], [5, 2]], "save_every": 10, "shared_every": 1},
    "training_size": {**{k: v for k, v in COMMON.items() if k != "train_fraction"}, "n_past": 5, "n_future": 5,
                      "train_fractions": [0.25, 0.5], "n_cri": 50},
    "refined_6_parts": {"n_steps": 4000, "n_s": 20, "n_past": 5, "n_future": 5, "n_parts": 2, "n_parts_paper": 6,
                        "divisions": [12, 2, 2], "save_every": 20, "shared_every": 1, "n_cri": 100,
                        "n_predicted_steps": 3900, "seed": 0, "reduced": True},
    "skewed": {**COMMON, "n_past": 5, "n_future": 5, "n_cri": 50, "body_force": [0.0, -0.5, -0.5]},
    "step_off": {**COMMON, "n_past": 5, "n_future": 5, "n_cri": 50, "t_off": 0.5},
    "initial_conditions": {**COMMON, "n_past": 5, "n_future": 5, "n_cri": 50, "n_runs": 3, "n_cond_repeat": 12,
                           "label": "u", "u_range": [-0.25, 0.25]},
    "loads": {**COMMON, "n_past": 5, "n_future": 5, "n_cri": 50, "n_runs": 3, "n_cond_repeat": 12, "label": "f_z",
              "f_z_range": [0.3, 0.7]},
    "full_system": {**COMMON, "n_past": 5, "n_future": 5, "n_parts": 1, "save_every": 1, "metrics_every": 10,
                    "n_cri": 50, "n_predicted_steps": 2950, "n_dof": 312},
}
# the shortest run every case takes: step_off's load jump (t_off 0.5 s, step 1427) and the
# synchronized history after it (n_cri 1480) inside it, a multiple of every save stride
FAST_STEPS = 1600
FAST_CASES = tuple(c for c in CASES if c not in ("training_size", "initial_conditions"))
VARIANTS = {"default": ["default"], "sequence_length": ["np5_nf5", "np5_nf2"], "training_size": ["nts0.25", "nts0.50"],
            "refined_6_parts": ["refined"], "skewed": ["skewed"], "step_off": ["step_off"],
            "initial_conditions": ["unconditional", "conditional"], "loads": ["conditional"],
            "full_system": ["full_system"]}



def expected_parameters(case, n_steps):
    """EXPECTED[case], for a run of ``n_steps`` steps given with --steps (None: the reduced
    settings' own)."""
    expected = dict(EXPECTED[case])
    if n_steps is not None:
        expected["n_steps"] = n_steps
        if "n_predicted_steps" in expected:
            expected["n_predicted_steps"] = n_steps - expected["n_cri"]
    return expected


class Matrix(NamedTuple):
    out: object
    rc: int
    records: dict
    cases: tuple
    steps: int | None  # --steps, or None


@pytest.fixture(scope="module")
def script():
    return load_benchmark("paper_experiments")


def run_matrix(script, out, cases, steps):
    argv = ["--all"] if cases == CASES else ["--case", *cases]
    argv += ["--reduced", "--quiet", "--out", str(out)] + ([] if steps is None else ["--steps", str(steps)])
    rc = script.main(argv)
    records = {}
    for case in CASES:
        path = out / case / f"{case}.json"
        if path.exists():
            records[case] = json.loads(path.read_text())
    return Matrix(out, rc, records, cases, steps)


@pytest.fixture(scope="module")
def fast_matrix(script, tmp_path_factory):
    """FAST_CASES, reduced and FAST_STEPS long, once."""
    return run_matrix(script, tmp_path_factory.mktemp("experiments"), FAST_CASES, FAST_STEPS)


@pytest.fixture(scope="module")
def full_matrix(script, tmp_path_factory):
    """The whole matrix, reduced (--all), once."""
    return run_matrix(script, tmp_path_factory.mktemp("experiments_full"), CASES, None)


# the default run checks every test on the fast matrix (FAST_CASES, FAST_STEPS)
@pytest.fixture(params=["fast", pytest.param("full", marks=pytest.mark.slow)])
def matrix(request):
    return request.getfixturevalue(f"{request.param}_matrix")


def case_runs(cases):
    """(matrix, case) parameters: each of ``cases`` in the fast matrix where it runs, and in
    the whole matrix (slow: the default run checks the fast ones)."""
    return ([pytest.param("fast", c, id=f"fast-{c}") for c in cases if c in FAST_CASES]
            + [pytest.param("full", c, id=f"full-{c}", marks=pytest.mark.slow) for c in cases])


def test_the_reduced_settings_are_the_written_ones(script):
    # what the slow run's matrix runs (the fast one gives --steps)
    settings = script.reduced_settings(2)
    assert settings.n_steps == EXPECTED["default"]["n_steps"] == 3000
    assert settings.refined_steps == EXPECTED["refined_6_parts"]["n_steps"] == 4000
    for case in CASES:
        assert script.steps_problem(settings, case, FAST_STEPS) is None, case


def test_every_case_writes_its_json_figure_and_series(matrix):
    out, rc, records, cases, _ = matrix
    assert rc == 0
    assert sorted(records) == sorted(cases)
    for case in cases:
        folder = out / case
        assert (folder / f"{case}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert (folder / "series.npz").is_file()
        record = records[case]
        assert record["case"] == case and record["reduced"] is True
        assert [v["name"] for v in record["variants"]] == VARIANTS[case]
        for key in ("parameters", "mesh", "dt", "machine", "wall_seconds", "targets_met", "reference", "files"):
            assert key in record, (case, key)
        assert record["machine"]["n_devices"] == len(jax.devices())
        assert not list(folder.glob(".*.tmp")), "no temporary files left behind"


@pytest.mark.parametrize("which, case", case_runs(CASES))
def test_parameters_are_the_reduced_settings(request, which, case):
    matrix = request.getfixturevalue(f"{which}_matrix")
    params = matrix.records[case]["parameters"]
    for key, value in expected_parameters(case, matrix.steps).items():
        assert params[key] == value, (key, params[key], value)


def test_refined_case_uses_the_available_devices(matrix):
    record = matrix[2]["refined_6_parts"]
    assert record["n_parts"] == min(6, len(jax.devices())) == 2
    assert record["mesh"]["n_elements"] == 12 * 2 * 2 * 6
    assert any("devices available" in note for note in record["notes"])
    assert record["dt"] == pytest.approx(jaxsync.cantilever(jaxsync.box_beam(divisions=(12, 2, 2))).dt)


def excluded_nodes(case, record):
    """Shared and clamped nodes, rebuilt here from the mesh and METIS (seed 0)."""
    mesh = (jaxsync.box_beam(divisions=(12, 2, 2)) if case == "refined_6_parts" else jaxsync.box_beam())
    clamped = np.flatnonzero(np.isclose(mesh.points[:, 0], mesh.points[:, 0].min()))
    if case == "full_system":
        return clamped
    shared = jaxsync.partition(mesh, record["n_parts"], seed=0).shared_nodes
    return np.union1d(clamped, shared)


@pytest.mark.parametrize("which, case", case_runs(CASES))
def test_errors_recomputed_from_the_series(request, which, case):
    matrix = request.getfixturevalue(f"{which}_matrix")
    check_errors_from_series(matrix.out, matrix.records[case], case)


def check_errors_from_series(out, record, case):
    series = np.load(out / case / "series.npz")
    tip = record["tip_node"]
    excluded = excluded_nodes(case, record)
    for variant in record["variants"]:
        v, m = variant["name"], variant["metrics"]
        ref, pred = series[f"{v}__field_reference"], series[f"{v}__field_predicted"]
        times = series[f"{v}__times"]
        assert ref.shape == pred.shape == (len(times), record["mesh"]["n_nodes"], 3) and m["n_saved"] == len(times)
        z_ref, z = series[f"{v}__z_reference"], series[f"{v}__z_predicted"]
        np.testing.assert_array_equal(z_ref, ref[:, tip, 2])
        np.testing.assert_array_equal(z, pred[:, tip, 2])
        every = record["parameters"].get("metrics_every", record["parameters"]["save_every"])
        np.testing.assert_allclose(times, np.arange(len(times)) * every * record["dt"], rtol=1e-12, atol=1e-15)
        # before n_cri the online run is the synchronized one
        n_sync = variant["parameters"]["n_cri"] // every + 1
        np.testing.assert_allclose(pred[:n_sync], ref[:n_sync], rtol=0, atol=1e-12 * np.abs(ref).max())
        amplitude = np.abs(z_ref).max()
        final_scale = amplitude if m["tip_final_relative_to"] == "amplitude" else abs(z_ref[-1])
        diff = pred - ref
        e_l2 = np.sqrt((diff ** 2).reshape(len(diff), -1).sum(axis=1))
        interior = np.setdiff1d(np.arange(ref.shape[1]), excluded)
        expected = {
            "tip_amplitude_cm": amplitude,
            "tip_max_error_relative": np.abs(z - z_ref).max() / amplitude,
            "tip_final_error_relative": abs(z[-1] - z_ref[-1]) / final_scale,
            "l2_relative": np.sqrt((diff ** 2).sum() / (ref ** 2).sum()),
            "l2_relative_final": np.sqrt((diff[-1] ** 2).sum() / (ref[-1] ** 2).sum()),
            "e_l2_max_cm": e_l2.max(), "e_l2_final_cm": e_l2[-1],
            "interior_max_error_relative": (np.sqrt((diff[:, interior] ** 2).sum(axis=2)).max()
                                            / np.sqrt((ref ** 2).sum(axis=2)).max()),
        }
        for key, value in expected.items():
            assert m[key] == pytest.approx(value, rel=1e-10, abs=1e-300), (v, key)
        goal = {"initial_conditions": 0.05, "loads": 0.05}.get(case, 0.02)
        assert variant["targets"]["tip_max_met"] == (m["tip_max_error_relative"] <= goal)
        assert variant["targets"]["met"] in (True, False)
    assert record["targets_met"] == all(v["targets"]["met"] for v in record["variants"])


def test_variants_with_the_default_settings_reuse_the_default_run(matrix):
    records = matrix[2]
    default = records["default"]["variants"][0]
    assert "reused_from" not in default["training"] and "case" in records["default"]["reference"]
    reusing = [(c, v) for c, v in (("sequence_length", "np5_nf5"), ("training_size", "nts0.50"))
               if c in matrix.cases]
    assert reusing
    for case, variant in reusing:
        record = records[case]
        assert record["reference"]["reused_from_case"] == "default"
        same = next(v for v in record["variants"] if v["name"] == variant)
        assert same["training"]["reused_from"] == same["online"]["reused_from"] == "default/default"
        assert same["metrics"] == default["metrics"]
        other = next(v for v in record["variants"] if v["name"] != variant)
        assert "reused_from" not in other["training"]


def test_final_errors_and_extra_components(matrix):
    records = matrix[2]
    assert records["step_off"]["variants"][0]["metrics"]["tip_final_relative_to"] == "amplitude"
    assert any("amplitude" in note for note in records["step_off"]["notes"])
    assert records["default"]["variants"][0]["metrics"]["tip_final_relative_to"] == "final value"
    assert "tip_final_met" in records["default"]["variants"][0]["targets"]
    assert "tip_final_met" not in records["loads"]["variants"][0]["targets"]  # unseen load: 5 % max only
    skewed = records["skewed"]["variants"][0]
    assert skewed["metrics"]["component"] == "z" and skewed["tip_y"]["component"] == "y"
    series = np.load(matrix[0] / "skewed" / "series.npz")
    y_ref, y = series["skewed__y_reference"], series["skewed__y_predicted"]
    assert skewed["tip_y"]["tip_max_error_relative"] == pytest.approx(np.abs(y - y_ref).max() / np.abs(y_ref).max())


def test_full_system_reports_the_clamped_end(matrix):
    out, _, records = matrix[:3]
    variant = records["full_system"]["variants"][0]
    series = np.load(out / "full_system" / "series.npz")
    clamped = series["full_system__clamped_max_abs_predicted"]
    n_steps = records["full_system"]["parameters"]["n_steps"]
    assert n_steps == (matrix.steps or 3000)
    assert len(clamped) == n_steps + 1 and not clamped[:51].any()
    # the clamped dofs never move in the training data: their normalization has std 0, so
    # even a 2-epoch network predicts them at exactly their value (the paper's did not)
    assert clamped.max() == 0.0
    assert variant["metrics"]["dirichlet_max_abs_predicted_cm"] == pytest.approx(clamped.max())
    assert variant["online"]["dirichlet_max_abs_predicted"] == pytest.approx(clamped.max())
    every_z = series["full_system__every_step_z_predicted"] - series["full_system__every_step_z_reference"]
    assert variant["metrics"]["tip_max_error_relative_every_step"] == pytest.approx(
        np.abs(every_z).max() / np.abs(series["full_system__every_step_z_reference"]).max())
    assert variant["targets"]["kind"] == "full_system"
    assert variant["training"]["summary"]["architecture"]["n_dof"] == 312


@pytest.mark.parametrize("which, case", case_runs(("initial_conditions", "loads")))
def test_ensemble_cases_record_their_training_runs(request, which, case):
    matrix = request.getfixturevalue(f"{which}_matrix")
    low, high = {"initial_conditions": (-0.25, 0.25), "loads": (0.3, 0.7)}[case]
    record = matrix[2][case]
    data = record["training_data"]
    labels = data["labels"]
    assert data["n_runs"] == len(labels) == 3 and len(set(labels)) == 3
    assert data["labels_stored"] == labels  # what jaxsync.ensemble stored as the load parameter
    assert data["test_label"] not in labels and data["test_label_unseen"] is True
    assert all(low <= x <= high for x in labels + [data["test_label"]])
    np.testing.assert_allclose(labels, np.random.default_rng(0).uniform(low, high, size=3), rtol=0, atol=0)
    for variant in record["variants"]:
        training = variant["training"]
        assert training["n_training_runs"] == 3
        conditional = variant["parameters"]["conditional"]
        assert variant["parameters"]["test_label"] == data["test_label"]
        assert training["summary"]["architecture"]["n_cond_repeat"] == (12 if conditional else 0)
        assert training["summary"]["load_parameters"] == (labels if conditional else None)
        assert variant["targets"]["kind"] == "unseen"
    series = np.load(matrix[0] / case / "series.npz")
    n_steps = record["parameters"]["n_steps"]
    assert n_steps == (matrix.steps or 3000)
    assert series["training__z"].shape == (3, n_steps // 10 + 1)
    np.testing.assert_array_equal(series["training__labels"], labels)


def test_training_passes_only_case_parameters(matrix):
    allowed = {"n_s", "n_past", "n_future", "train_fraction", "seed", "n_cond_repeat"}
    for case, record in matrix[2].items():
        for variant in record["variants"]:
            training = variant["training"]
            assert set(training["case_parameters_passed"]) <= allowed, case
            # reduced mode only
            assert training["overrides_passed"] in (["config", "emse_applications", "n_hidden", "n_layers"],
                                                    ["config", "n_hidden", "n_layers"])  # (full system)
            summary = training["summary"]
            assert summary["architecture"]["n_hidden"] == 8 and summary["architecture"]["n_layers"] == 1
            assert summary["training"]["n_epochs"] == 2 and training["n_epochs_run"] == 2
            assert training["train_seconds"] > 0
            rollout = training["rollout_relative"]
            assert rollout is None or len(rollout) == record["n_parts"]
            # 2 epochs cannot pass the offline check: the warning is recorded, not raised
            if rollout is not None and max(rollout) > 0.02:
                assert training["rollout_warning"] and "offline check" in training["rollout_warning"]
                assert training["rollout_passed"] is False


def test_table_has_a_row_per_case_and_variant(matrix, script):
    out, _, records, cases, _ = matrix
    table = out / "table.md"
    table.unlink()
    assert script.main(["--table", "--out", str(out)]) == 0
    rows = [line for line in table.read_text().splitlines() if line.startswith("| ") and "---" not in line]
    header, rows = rows[0], rows[1:]
    assert "free-end max %" in header and "targets met" in header and "rollout check %" in header
    # and one for the step-off networks predicting through the load jump
    assert len(rows) == sum(len(VARIANTS[c]) for c in cases) + 1
    assert sum(row.startswith("| step_off (reduced) | step_off, predicted through the load jump |")
               for row in rows) == 1
    assert "synchronized steps" in header
    for case in cases:
        for variant in VARIANTS[case]:
            assert sum(row.startswith(f"| {case} (reduced) | {variant} |") for row in rows) == 1, (case, variant)
    default = next(row for row in rows if row.startswith("| default (reduced) |"))
    max_error = 100 * records["default"]["variants"][0]["metrics"]["tip_max_error_relative"]
    assert f"| {max_error:.3g} |" in default


def test_step_off_stays_synchronized_through_the_load_jump(matrix):
    """The step-off online run keeps synchronizing until the networks' input history
    (n_p n_s steps) follows the jump; the same networks predicting through it from n_cri
    are reported beside it. The jump step is read here from the load schedule itself."""
    out, _, records = matrix[:3]
    record = records["step_off"]
    variant = record["variants"][0]
    dt, every = record["dt"], record["parameters"]["save_every"]
    g = np.where(np.arange(record["parameters"]["n_steps"] + 1) * dt < record["parameters"]["t_off"], 1.0, 0.0)
    jump = int(np.flatnonzero(np.diff(g))[0]) + 1
    history = record["parameters"]["n_s"] * record["parameters"]["n_past"]
    n_cri = -(-(jump + history - 1) // every) * every
    assert variant["online"]["load_jumps"] == [jump]
    assert variant["online"]["n_cri"] == variant["online"]["n_synchronized_steps"] == n_cri
    through = variant["predicted_through_load_jumps"]
    assert through["online"]["n_synchronized_steps"] == record["parameters"]["n_cri"] == 50
    assert "load_jumps" not in through["online"]
    series = np.load(out / "step_off" / "series.npz")
    z_ref, z = series["step_off__z_reference"], series["step_off__z_predicted_through_load_jumps"]
    assert through["metrics"]["tip_max_error_relative"] == pytest.approx(np.abs(z - z_ref).max() / np.abs(z_ref).max())
    # synchronized up to n_cri: the kept run equals the reference there
    z_kept = series["step_off__z_predicted"]
    np.testing.assert_allclose(z_kept[:n_cri // every + 1], z_ref[:n_cri // every + 1], rtol=0, atol=1e-12)


def test_unknown_case_is_a_clear_argparse_error(script, capsys):
    with pytest.raises(SystemExit) as exc:
        script.main(["--case", "cantilever_9"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "invalid choice: 'cantilever_9'" in err and "full_system" in err


def test_nothing_to_do_is_an_argparse_error(script, capsys):
    with pytest.raises(SystemExit) as exc:
        script.main(["--reduced"])
    assert exc.value.code == 2
    assert "give --case NAME, --all or --table" in capsys.readouterr().err


def test_steps_that_do_not_fit_a_case_are_refused(script, capsys):
    with pytest.raises(SystemExit) as exc:
        script.main(["--case", "default", "--steps", "1234"])
    assert exc.value.code == 2 and f"saves every {script.paper_settings().save_every} steps" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        script.main(["--case", "sequence_length", "--reduced", "--steps", "50"])
    assert "n_cri = 50" in capsys.readouterr().err


@pytest.fixture(scope="module")
def linear_matrix(script, tmp_path_factory):
    """Two cases, reduced, with the linear surrogate: (output root, exit code, {case: record}).
    ``loads`` goes through train_surrogates (as every partitioned case), ``full_system``
    through fit_linear."""
    out = tmp_path_factory.mktemp("experiments_linear")
    cases = ("loads", "full_system")
    rc = script.main(["--case", *cases, "--reduced", "--quiet", "--model", "linear", "--out", str(out),
                      "--steps", str(FAST_STEPS)])
    return out, rc, {case: json.loads((out / case / f"{case}.json").read_text()) for case in cases}


def test_the_linear_model_runs_the_cases_and_says_so(linear_matrix):
    out, rc, records = linear_matrix
    assert rc == 0
    for case, record in records.items():
        assert record["model"] == "linear"
        for variant in record["variants"]:
            summary = variant["training"]["summary"]
            assert summary["model"] == "linear" and summary["architecture"]["kind"] == "linear", case
            # the reduced LSTM overrides (n_H 8, 2 epochs) are not passed to a least-squares fit
            assert variant["training"]["overrides_passed"] == []
        check_errors_from_series(out, record, case)
    # unconditional: the ensemble case trains one variant, without the load parameter
    (loads,) = records["loads"]["variants"]
    assert loads["name"] == "linear" and loads["parameters"]["n_cond_repeat"] == 0
    assert loads["training"]["summary"]["load_parameters"] is None
    assert records["full_system"]["variants"][0]["training"]["summary"]["architecture"]["n_dof"] == 312
    rows = [line for line in (out / "table.md").read_text().splitlines() if line.startswith("| ")]
    assert rows[0].startswith("| case | variant | model |")
    assert any(row.startswith("| loads (reduced) | linear | linear |") for row in rows)
