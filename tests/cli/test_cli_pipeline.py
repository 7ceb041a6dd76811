"""The whole pipeline from the command line, reduced: ``jaxsync demo`` (synchronized run,
training, online run, report), then ``predict`` and ``report`` on its files, with and
without error control.

Each command runs once, in a module-scoped fixture that keeps its exit status and output;
every check is its own test, so one failure does not hide the others."""

import contextlib
import dataclasses
import io
import json
import warnings

import jax
import numpy as np
import pytest

import jaxsync
from jaxsync.cli import main

N_STEPS, N_S = 1500, 5
# the predict runs that check one option each run the first third of the demo's steps
SHORT = 500
# the --learn run: three rejected cycles (test_predict_learns_after_every_rejected_cycle)
LEARN_STEPS = 200


@dataclasses.dataclass
class Run:
    """A finished command: exit status, stdout, stderr, warnings."""

    code: int
    out: str
    err: str
    warnings: list


def run_cli(argv) -> Run:
    """``main(argv)`` with its output and warnings recorded (usable in module fixtures,
    where capsys is not)."""
    out, err = io.StringIO(), io.StringIO()
    with warnings.catch_warnings(record=True) as caught, contextlib.redirect_stdout(out), \
            contextlib.redirect_stderr(err):
        warnings.simplefilter("always")
        code = main([str(a) for a in argv])
    return Run(code, out.getvalue(), err.getvalue(), list(caught))


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """``jaxsync demo`` in a reduced mode; its folder and output."""
    folder = tmp_path_factory.mktemp("pipeline")
    out = folder / "demo"
    run = run_cli(["demo", "--steps", N_STEPS, "--epochs", "2", "--hidden", "8", "--n-s", N_S,
                   "--n-past", "5", "--n-future", "5", "--out", out, "--no-progress", "--resync-tolerance", "none"])
    assert run.code == 0, run.err
    return folder, out, run


@pytest.fixture(scope="module")
def summary(demo):
    return json.loads((demo[1] / "summary.json").read_text())


@pytest.fixture(scope="module")
def online(demo):
    return jaxsync.Trajectory.load(demo[1] / "online.h5")


@pytest.fixture(scope="module")
def reference(demo):
    return jaxsync.Trajectory.load(demo[1] / "synchronized.h5")


def predict_args(demo, output, *extra):
    _, out, _ = demo
    return ["predict", out / "synchronized.h5", out / "surrogate" / "surrogate.h5", "-o", output,
            "--no-progress", *extra]


@pytest.fixture(scope="module")
def predicted(demo):
    """``jaxsync predict`` on the demo's files: the same online run from the command line."""
    path = demo[0] / "again.h5"
    return path, run_cli(predict_args(demo, path, "--resync-tolerance", "none"))


@pytest.fixture(scope="module")
def resync(demo):
    """``jaxsync predict`` with error control: 2-epoch networks disagree at once, every
    cycle is rejected before use and the run falls back to the synchronized solver
    (stretches of 2, 4, 8... cycles)."""
    path = demo[0] / "resync.h5"
    return path, run_cli(predict_args(demo, path, "--resync-tolerance", "1e-12"))


# ----------------------------------------------------------------------------- demo


def test_demo_summary_has_the_documented_keys(summary):
    from jaxsync.app.demo import SUMMARY_KEYS

    for key in SUMMARY_KEYS:
        assert key in summary, key
        assert isinstance(summary[key], str) or np.isfinite(summary[key]), key


def test_demo_counts_agree_with_the_run(summary):
    assert summary["n_steps"] == N_STEPS
    # n_cri = n_s n_p; the counts agree with the run's statistics and flags
    assert summary["n_synchronized"] == 25 and summary["n_predicted"] == 1475
    assert summary["n_synchronized_steps"] == 25 and summary["n_predicted_steps"] == 1475
    # trained on the first half of the 1501 rows of shared history (steps 0 .. 749)
    assert summary["train_until_step"] == 749 and summary["out_of_sample"]["from_step"] > 749


def test_demo_devices_and_speed(summary, reference, online):
    assert summary["n_devices"] == 2 and summary["device_kind"] == "cpu"
    # the summary reports the times the runs measured and saved with their trajectories
    assert summary["us_per_step_synchronized"] == reference.stats.us_per_step
    assert summary["us_per_step_predicted"] == online.stats.us_per_step_predicted
    assert summary["zeta_sync"] in ("psum", "ppermute") and summary["t_d_us"] > 0


def test_demo_writes_the_report_figures(demo):
    for name in ("displacement_nodes.png", "l2_error.png", "shared_errors.png", "et_histogram.png"):
        assert (demo[1] / "report" / name).stat().st_size > 1000


def test_demo_online_trajectory(online):
    assert online.save_every == 5 and online.n_saved == 301  # the full field every n_s steps
    assert online.synchronized.sum() == 25 // 5 + 1 and not online.synchronized[-1]


def test_demo_reference_keeps_every_step_at_the_shared_nodes(reference):
    assert reference.save_every == 5 and reference.parts[0].shared_displacement.shape[0] == 1501


def test_demo_prints_the_summary(demo):
    text = demo[2].out
    assert "speed-up" in text and "time per step, predicted" in text and "zeta, compiled steps" in text
    assert "1500 steps: 25 synchronized, 1475 predicted" in text


def test_demo_files_name_the_demo_folder_not_its_staging_folder(demo, summary):
    """The run is written beside the folder and moved in at the end: no path in what it
    wrote or printed names the staging folder, and none is left behind."""
    folder, out, run = demo
    assert sorted(p.name for p in folder.iterdir() if p.name.startswith("demo")) == ["demo"]
    assert summary["report"] == str(out / "report")
    trained = json.loads((out / "surrogate" / "train_summary.json").read_text())
    assert trained["trajectories"] == [str(out / "synchronized.h5")]
    assert trained["surrogate"] == str(out / "surrogate" / "surrogate.h5")
    for path in out.rglob("*.json"):
        assert ".partial-" not in path.read_text(), path
    assert ".partial-" not in run.out and str(out / "surrogate" / "surrogate.h5") in run.out


def test_a_second_demo_into_the_folder_is_refused_without_force(demo):
    _, out, _ = demo
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*")}
    run = run_cli(["demo", "--steps", N_STEPS, "--out", out, "--no-progress"])
    assert run.code == 2 and run.err.startswith("error:") and run.err.count("\n") == 1, run.err
    assert str(out) in run.err and "--force" in run.err
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*")} == before


def test_demo_folder_keeps_the_usual_permissions(demo):
    """The demo's folder is staged with tempfile.mkdtemp (0700) and renamed into place: it
    gets the usual permissions (the umask's) as every other output folder."""
    umask = os_umask()
    assert (demo[1].stat().st_mode & 0o7777) == 0o777 & ~umask


def os_umask() -> int:
    import os

    umask = os.umask(0)
    os.umask(umask)
    return umask


def test_demo_staging_keeps_the_permissions_of_the_folder_it_replaces(tmp_path):
    """``mkdir udir2`` (0755, or the user's own mode) then ``jaxsync demo -o udir2``: the
    folder that takes its place has its mode, not mkdtemp's 0700."""
    import os

    from jaxsync.app.demo import install_folder, staging_folder

    for mode in (0o755, 0o750, 0o2775):
        final = tmp_path / f"udir{mode:o}"
        final.mkdir()
        os.chmod(final, mode)
        (final / "notes.txt").write_text("mine")
        staging = staging_folder(str(final))
        open(os.path.join(staging, "summary.json"), "w").close()
        install_folder(staging, str(final))
        assert (final / "notes.txt").read_text() == "mine" and (final / "summary.json").exists()
        assert final.stat().st_mode & 0o777 == mode & 0o777
    new = staging_folder(str(tmp_path / "fresh"))
    install_folder(new, str(tmp_path / "fresh"))
    assert (tmp_path / "fresh").stat().st_mode & 0o7777 == 0o777 & ~os_umask()


def test_demo_options_are_checked_before_the_synchronized_run(tmp_path):
    """``jaxsync demo --epochs 0`` ran the whole synchronized run before its error, and
    ``--parts 1`` crashed in training after it: every option is checked before [1/4]."""
    small = ["--steps", N_STEPS, "--n-s", N_S, "--n-past", "5", "--n-future", "5", "--epochs", "2", "--no-progress"]
    cases = [
        (["--epochs", "0"], "n_epochs must be >= 1"),
        (["--parts", "1"], "a 1-part run has no shared nodes, so there is nothing for the surrogates to predict; "
                           "use --parts 2 or more"),
        (["--hidden", "0"], "n_hidden"),
        (["--candidates", "0"], "n_candidates must be an integer >= 1"),
        (["--eta0", "-1"], "eta0 must be > 0"),
        (["--n-past", "0"], "Sampling.n_past must be an integer >= 1"),
        (["--steps", "0"], "n_steps must be an integer >= 1"),
        (["--steps", "40"], "40 steps give 4 training snapshots"),
        (["--save-every", "7"], "n_steps=1500 is not a multiple of save_every=7"),
        (["--save-every", "3"], "--save-every 3 must divide n_s = 5"),
        (["--resync-tolerance", "abc"], "neither a length in cm"),
        (["--seed", "-1"], "seed must be an integer >= 0"),
        (["--case", "vessel", "--size", "1000", "--epochs", "0"], "n_epochs must be >= 1"),
    ]
    for k, (extra, message) in enumerate(cases):
        out = tmp_path / f"d{k}"
        run = run_cli(["demo", *small, *extra, "--out", out])
        assert run.code == 2 and run.err.startswith("error: ") and run.err.count("\n") == 1, (extra, run.err)
        assert message in run.err, (extra, run.err)
        assert "[1/" not in run.out and "synchronized run" not in run.out, (extra, run.out)
        assert not any(tmp_path.iterdir()), extra  # no output, no staging folder


# ----------------------------------------------------------------------------- predict


def test_predict_prints_the_counts(predicted):
    _, run = predicted
    assert run.code == 0, run.err
    assert "1500 steps: 25 synchronized, 1475 predicted" in run.out


def test_predict_holds_the_run_to_1_percent_by_default(demo, reference, tmp_path):
    """Without --resync-tolerance the run is held to 1 % of the largest shared-node
    displacement in the steps the surrogates were trained on (the trajectory's first half:
    the rows training read, floor(0.5 rows)); the 2-epoch networks fail it: the run falls
    back to the synchronized solver, and says so."""
    path = tmp_path / "default.h5"
    run = run_cli(predict_args(demo, path))  # the whole run: its first 500 steps are all held to 1 %
    assert run.code == 0, run.err
    rows = reference.parts[0].shared_displacement.shape[0]
    amplitude = max(np.abs(p.shared_displacement[:rows // 2]).max() for p in reference.parts)
    st = jaxsync.Trajectory.load(path).stats
    assert st.resync_tolerance == f"1 % of {amplitude:.4g} cm"
    assert np.allclose(st.tolerance_cm, 0.01 * amplitude) and st.n_resynchronizations >= 1
    assert f"tolerance 1 % of {amplitude:.4g} cm:" in run.out
    assert "retrain the surrogates or loosen the tolerance" in run.err


def test_predict_repeats_the_demo_online_run(predicted, online):
    path, _ = predicted
    again = jaxsync.Trajectory.load(path)
    np.testing.assert_allclose(again.displacement, online.displacement, rtol=0, atol=1e-12)


def test_predict_raw_refill_writes_the_networks_own_values(demo, reference, online):
    """--raw-refill writes the n_s interleaved network applications as they are; the
    default writes their smooth curve from the last known value; --refill-samples 2 the
    curve through the means of two applications. Checked on the first predicted cycle
    against the network applied to the synchronized history."""
    from jaxsync.surrogate import Surrogate, smooth_refill

    path = demo[0] / "raw.h5"
    run = run_cli(predict_args(demo, path, "--raw-refill", "--resync-tolerance", "none", "--steps", SHORT))
    assert run.code == 0, run.err
    raw = jaxsync.Trajectory.load(path)
    run = run_cli(predict_args(demo, demo[0] / "sampled.h5", "--refill-samples", "2", "--resync-tolerance", "none",
                               "--steps", SHORT))
    assert run.code == 0, run.err
    sampled = jaxsync.Trajectory.load(demo[0] / "sampled.h5")
    for bad in ("0", "x"):  # refused by the parser
        with pytest.raises(SystemExit) as refused:
            run_cli(predict_args(demo, demo[0] / "bad.h5", "--refill-samples", bad))
        assert refused.value.code == 2
    assert not (demo[0] / "bad.h5").exists()
    # the demo's surrogates read the load signals (its default): bound to its problem, the cantilever
    surrogate = Surrogate.load(demo[1] / "surrogate" / "surrogate.h5").for_problem(jaxsync.cantilever(), reference.dt)
    n_cri, history, every = N_S * 5, N_S * 5, online.save_every
    for p, part in enumerate(reference.parts):
        width = part.shared_displacement.shape[1]
        buffer = np.pad(part.shared_displacement[n_cri + 1 - history:n_cri + 1],
                        ((0, 0), (0, surrogate.n_dof - width)))
        network = np.asarray(dataclasses.replace(surrogate, smooth=False).part(p).predict(buffer, n_cri))
        saved = slice(every - 1, None, every)
        n = network[saved].shape[0]
        # the networks run in float32: compiled and eager agree to its round-off
        scale = np.abs(network).max()
        np.testing.assert_allclose(raw.parts[p].predicted_shared_displacement[:n], network[saved, :width],
                                   rtol=1e-5, atol=1e-6 * scale)
        smooth = np.asarray(smooth_refill(network, buffer[-1], N_S))
        np.testing.assert_allclose(online.parts[p].predicted_shared_displacement[:n], smooth[saved, :width],
                                   rtol=1e-5, atol=1e-6 * scale)
        assert np.abs(network[saved, :width] - smooth[saved, :width]).max() > 1e-3 * scale
        # --refill-samples 2: the curve through the block means of applications 1 and 3 of the 5
        means = network.reshape(-1, N_S, network.shape[1])[:, [1, 3]].mean(axis=1)
        few = np.asarray(smooth_refill(np.repeat(means, N_S, axis=0), buffer[-1], N_S))
        # (two windows compile a program of their own: float32 round-off of the normalized values, up to 2e-6)
        np.testing.assert_allclose(sampled.parts[p].predicted_shared_displacement[:n], few[saved, :width],
                                   rtol=1e-5, atol=1e-5 * scale)
        assert np.abs(few[saved, :width] - smooth[saved, :width]).max() > 1e-3 * scale


def test_predict_stays_synchronized_through_a_load_jump(demo, reference, tmp_path):
    """A config whose load is switched off between steps 249 and 250: predict (the first
    500 steps) stays synchronized until the networks' 25 input steps follow the jump (step
    274, saved at 275); ``--load-jumps predict`` predicts from n_cri = 25 through it. The demo's
    surrogates, trained with the load input on a ramped load, are refused on the
    switched-off one (another time-function form); load-blind ones, trained with
    --no-load-input, run there."""
    from importlib import resources

    text = resources.files("jaxsync").joinpath("data/cantilever.toml").read_text()
    config = tmp_path / "step_off.toml"
    config.write_text(text.replace("# t_off = 3.0", f"t_off = {249.5 * reference.dt!r}"))
    refused = run_cli(predict_args(demo, tmp_path / "refused.h5", "--config", config))
    assert refused.code == 2 and "trained with loads[0] a BodyForce of time function form Ramp" in refused.err
    assert "form StepOff(Ramp)" in refused.err
    blind = run_cli(["train", demo[1] / "synchronized.h5", "-o", tmp_path / "blind", "--no-load-input",
                     "--epochs", "2", "--hidden", "8", "--n-s", N_S, "--n-past", "5", "--n-future", "5",
                     "--rollout-tolerance", "100", "--no-progress"])
    assert blind.code == 0, blind.err

    def predict_blind(output, *extra):
        return ["predict", demo[1] / "synchronized.h5", tmp_path / "blind" / "surrogate.h5", "-o", output,
                "--no-progress", "--resync-tolerance", "none", "--steps", str(SHORT), *extra]

    kept = run_cli(predict_blind(tmp_path / "kept.h5", "--config", config))
    assert kept.code == 0, kept.err
    assert "500 steps: 275 synchronized, 225 predicted (n_cri = 275)" in kept.out
    assert "synchronized through the load jump at step 250" in kept.out
    stats = jaxsync.Trajectory.load(tmp_path / "kept.h5").stats
    assert stats.load_jumps == (250,) and stats.n_cri == 275
    through = run_cli(predict_blind(tmp_path / "through.h5", "--config", config, "--load-jumps", "predict"))
    assert through.code == 0, through.err
    assert "500 steps: 25 synchronized, 475 predicted" in through.out
    assert jaxsync.Trajectory.load(tmp_path / "through.h5").stats.load_jumps is None


def test_predict_refuses_an_existing_output(demo, predicted):
    """An existing output is not overwritten without --force (refused before running)."""
    path, _ = predicted
    before = path.stat().st_mtime_ns, path.read_bytes()
    run = run_cli(predict_args(demo, path))
    assert run.code == 2
    assert "--force" in run.err
    assert (path.stat().st_mtime_ns, path.read_bytes()) == before


def test_report_of_the_predicted_run_matches_the_demo(demo, predicted, summary):
    path, _ = predicted
    report = demo[0] / "report"
    run = run_cli(["report", demo[1] / "synchronized.h5", path, "-o", report,
                   "--train-until-step", summary["train_until_step"]])
    assert run.code == 0, run.err
    again_summary = json.loads((report / "summary.json").read_text())
    assert again_summary["tip_max_abs_error"] == pytest.approx(summary["tip_max_abs_error"], rel=1e-9)
    assert again_summary["train_until_step"] == summary["train_until_step"]
    assert again_summary["out_of_sample"]["interior_max_relative_error"] == pytest.approx(
        summary["out_of_sample"]["interior_max_relative_error"], rel=1e-9)
    late = run_cli(["report", demo[1] / "synchronized.h5", path, "-o", report, "--train-until-step", 10 ** 6,
                    "--force"])
    assert late.code == 2 and "no saved snapshot comes after train_until_step=1000000" in late.err
    assert json.loads((report / "summary.json").read_text()) == again_summary  # a failed run keeps the report


# ----------------------------------------------------------------------------- error control


def test_resync_warns_that_every_cycle_was_rejected(resync):
    _, run = resync
    assert run.code == 0, run.err
    # one line on stderr (the command line shows every warning so), naming what was held
    lines = [line for line in run.err.splitlines() if "retrain the surrogates or loosen the tolerance" in line]
    assert len(lines) == 1 and lines[0].startswith("warning: the surrogates kept es_hat and the estimated error "
                                                   "within the tolerance"), run.err


def test_resync_statistics_and_printed_counts_agree(resync):
    path, run = resync
    st = jaxsync.Trajectory.load(path).stats
    at = list(st.resynchronized_at)
    assert at[:3] == [25, 75, 175]  # a 25-step cycle; synchronized for 2, then 4 cycles
    assert st.n_synchronized_steps == 1500 and st.n_predicted_steps == 0
    assert f"1500 steps: 1500 synchronized, 0 predicted (n_cri = 25); tolerance 1e-12 cm: {len(at)} " in run.out


def test_resync_run_is_the_synchronized_run(resync, reference):
    path, _ = resync
    result = jaxsync.Trajectory.load(path)
    assert result.synchronized.all()
    np.testing.assert_allclose(result.displacement, reference.displacement, rtol=0,
                               atol=1e-12 * np.abs(reference.displacement).max())


def test_predict_learns_after_every_rejected_cycle(demo, reference, tmp_path):
    """``--learn``: an update after every re-synchronized stretch, said in the printed
    counts; a tolerance of 1e-12 cm still gives the synchronized run (the first LEARN_STEPS =
    200 steps: rejected at 25, 75 and 175; each update is 100 Adam iterations, the run's
    cost, so the run is shorter than the other predict runs' SHORT = 500 steps)."""
    path, learned = tmp_path / "learn.h5", tmp_path / "learned.h5"
    run = run_cli(predict_args(demo, path, "--resync-tolerance", "1e-12", "--learn", "--learn-budget", "600",
                               "--learn-save", learned, "--steps", LEARN_STEPS))
    assert run.code == 0, run.err
    result = jaxsync.Trajectory.load(path)
    st = result.stats
    assert len(st.surrogate_updated_at) == st.n_resynchronizations >= 2 and st.seconds_updating > 0
    assert f"{len(st.surrogate_updated_at)} surrogate updates" in run.out
    assert f"the learned surrogates to {learned}" in run.out
    assert result.n_saved == LEARN_STEPS // 5 + 1
    np.testing.assert_allclose(result.displacement, reference.displacement[:result.n_saved], rtol=0,
                               atol=1e-12 * np.abs(reference.displacement).max())
    # --learn-save: the surrogates as learned, a surrogate file that predicts the last stretch it
    # learned from (the synchronized run: the truth) better than the trained one
    from jaxsync.io.surrogate_file import load_surrogate
    from jaxsync.surrogate import Surrogate
    from jaxsync.surrogate.training import rollout_errors

    saved = load_surrogate(learned)
    updates = saved.metadata["online_learning"]["updated_at"]
    assert updates and set(updates) <= set(st.surrogate_updated_at)
    assert [list(n) for n in saved.shared_nodes] == [list(p.shared_nodes) for p in reference.parts]
    trained = Surrogate.load(demo[1] / "surrogate" / "surrogate.h5")
    problem = jaxsync.cantilever()
    histories = np.stack([np.pad(p.shared_displacement, [(0, 0), (0, trained.n_dof - p.shared_displacement.shape[1])])
                          for p in reference.parts])
    start = updates[-1] - trained.n_s * trained.n_future  # the last refill cycle before the last update
    error = {name: rollout_errors(s.for_problem(problem, reference.dt), histories, 1, start).mse.sum()
             for name, s in (("trained", trained), ("learned", Surrogate.from_saved(saved)))}
    assert error["learned"] < 0.5 * error["trained"], error
    for extra, message in ((["--learn", "--resync-tolerance", "none"], "give --resync-tolerance too"),
                           (["--learn-budget", "5"], "give --learn too"),
                           (["--learn-save", str(tmp_path / "x.h5")], "give --learn too"),
                           (["--learn", "--resync-tolerance", "1e-12", "--learn-save", str(path)], "exists")):
        bad = run_cli(predict_args(demo, tmp_path / "bad.h5", *extra))
        assert bad.code != 0 and message in bad.err, bad.err
        assert not (tmp_path / "bad.h5").exists()


def test_report_of_the_resync_run(demo, resync):
    path, _ = resync
    report = demo[0] / "report_resync"
    run = run_cli(["report", demo[1] / "synchronized.h5", path, "-o", report])
    assert run.code == 0, run.err
    reported = json.loads((report / "summary.json").read_text())
    assert reported["n_synchronized"] == 1500 and reported["n_predicted"] == 0
    assert "1500 steps: 1500 synchronized, 0 predicted" in run.out


# ----------------------------------------------------------------------------- partitions


def test_predict_refuses_a_checkpoint_of_another_partition(tmp_path, capsys):
    from jaxsync.surrogate import Surrogate

    problem = jaxsync.cantilever()
    sync = jaxsync.simulate(problem, 200, partitions=2)
    sync.save(tmp_path / "s.h5")
    other = jaxsync.partition(problem.mesh, 4)
    untrained = Surrogate.initialized(other, 2, n_hidden=4, n_layers=1, n_past=2, n_future=2)
    untrained.save(tmp_path / "c.h5", shared_nodes=tuple(p.shared_nodes for p in other.parts))
    assert main(["predict", str(tmp_path / "s.h5"), str(tmp_path / "c.h5"), "-o",
                 str(tmp_path / "o.h5"), "--no-progress"]) == 2
    assert "partition has 2 parts" in capsys.readouterr().err
    assert not (tmp_path / "o.h5").exists()


def test_predict_in_bfloat16_is_checked_first_and_follows_the_float32_run(demo, predicted, tmp_path):
    path, first = predicted
    assert first.code == 0, first.err
    run = run_cli(predict_args(demo, tmp_path / "bf16.h5", "--inference-dtype", "bfloat16",
                                   "--resync-tolerance", "none", "--steps", SHORT))
    assert run.code == 0, run.err
    line = next(line for line in run.out.splitlines() if line.startswith("bfloat16 inference"))
    assert "bound 1 %" in line
    deviation = float(line.split("by at most ")[1].split(" %")[0])
    assert 0 < deviation <= 1.0
    # the same run up to n_cri (synchronized: no network involved), then the networks computing
    # in bfloat16 make it differ from the float32 run (over the first 500 steps here)
    full, reduced = jaxsync.Trajectory.load(path), jaxsync.Trajectory.load(tmp_path / "bf16.h5")
    synchronized, n = full.stats.n_cri // full.save_every + 1, reduced.n_saved
    assert n == SHORT // full.save_every + 1
    np.testing.assert_array_equal(reduced.displacement[:synchronized], full.displacement[:synchronized])
    assert np.abs(reduced.displacement[synchronized:] - full.displacement[synchronized:n]).max() > 0


# ----------------------------------------------------------------------------- fine-tuning


def test_finetune_writes_a_checkpoint_that_predict_runs(demo, tmp_path):
    """``jaxsync finetune`` on the demo's files: windows within the training half, the best
    validated weights written with the partition and a record of the fine-tuning; refuses
    to overwrite; ``jaxsync predict`` runs the new checkpoint."""
    from jaxsync.io.surrogate_file import load_surrogate

    _, out, _ = demo
    trained = out / "surrogate" / "surrogate.h5"
    tuned = tmp_path / "tuned.h5"
    args = ["finetune", out / "synchronized.h5", trained, "-o", tuned, "--iterations", "3",
            "--window-cycles", "1", "--learning-rate", "1e-2", "--no-progress"]
    run = run_cli(args)
    assert run.code == 0, run.err
    assert "validation loss x" in run.out and f"first {N_STEPS // 2} steps" in run.out
    before, after = load_surrogate(trained), load_surrogate(tuned)
    record = after.metadata["fine_tuned"]
    assert record["span_steps"] == N_STEPS // 2 and record["config"]["n_iterations"] == 3
    assert record["config"]["window_cycles"] == 1 and record["config"]["learning_rate"] == 1e-2
    # every window lies within the training half: start + n_s n_p + one cycle <= 750
    assert max(record["window_starts"]) + 2 * N_S * 5 <= N_STEPS // 2
    losses = [v for _, v in record["validation"]]
    assert record["improvement"] == pytest.approx(min(losses) / losses[0])
    changed = any(not np.array_equal(a, b) for a, b in zip(jax.tree_util.tree_leaves(before.params),
                                                           jax.tree_util.tree_leaves(after.params)))
    assert changed == (record["best_iteration"] > 0)
    for a, b in zip((before.mean, before.std), (after.mean, after.std)):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(before.shared_nodes, after.shared_nodes):
        np.testing.assert_array_equal(a, b)
    assert after.metadata["sampling"] == before.metadata["sampling"]
    # an existing output is refused before any work
    written = tuned.read_bytes()
    again = run_cli(args)
    assert again.code == 2 and "--force" in again.err
    assert tuned.read_bytes() == written
    predict = predict_args(demo, tmp_path / "tuned_online.h5", "--resync-tolerance", "none", "--steps", SHORT)
    predict[2] = tuned
    online = run_cli(predict)
    assert online.code == 0, online.err
