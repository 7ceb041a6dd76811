import json
import os
import subprocess
import sys

import numpy as np
import pytest

import jaxsync
from jaxsync.app.cli import build_parser, main
from jaxsync.app.config import load_config, problem_from_config


def option_strings(parser):
    return {s for action in parser._actions for s in action.option_strings}


def test_every_option_is_documented():
    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    assert {"demo", "simulate"} <= set(sub.choices)
    for name, p in sub.choices.items():
        text = p.format_help()
        for action in p._actions:
            if action.option_strings and "-h" not in action.option_strings:
                assert action.help, f"{name} {action.option_strings} has no help"
                assert action.option_strings[0] in text


def test_console_script_help():
    out = subprocess.run([sys.executable, "-m", "jaxsync.app.cli", "--help"], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0
    assert "simulate" in out.stdout and "demo" in out.stdout


def test_simulate_from_the_packaged_config(tmp_path, capsys):
    out = tmp_path / "c.h5"
    assert main(["simulate", "--steps", "400", "--save-every", "100", "-o", str(out),
                 "--xdmf", str(tmp_path / "c.xdmf"), "--no-progress"]) == 0
    traj = jaxsync.Trajectory.load(out)
    assert traj.displacement.shape == (5, 104, 3)
    expected = jaxsync.simulate(jaxsync.cantilever(), 400, save_every=100)
    np.testing.assert_array_equal(traj.displacement, expected.displacement)
    assert (tmp_path / "c.xdmf").exists()
    assert "wrote" in capsys.readouterr().out


def test_simulate_general_problem_from_toml(tmp_path):
    cfg = tmp_path / "bar.toml"
    cfg.write_text("""
[mesh]
length = 4.0
divisions = [4, 1, 1]
[material]
E = 1.0e3
nu = 0.0
rho = 1.0
[problem]
kind = "general"
damping = 5.0
[[dirichlet]]
facet = "x0"
[[pressure]]
surface = "x1"
magnitude = 2.0
t_ramp = 0.5
[run]
n_steps = 200
save_every = 100
""")
    out = tmp_path / "bar.h5"
    assert main(["simulate", str(cfg), "-o", str(out), "--no-progress"]) == 0
    traj = jaxsync.Trajectory.load(out)
    assert traj.n_saved == 3 and np.all(np.isfinite(traj.displacement))
    assert traj.displacement[-1, :, 0].min() < 0  # pushed in -x


@pytest.mark.parametrize("text, message", [
    ("[mesh]\nfoo = 1\n", "unknown key"),
    ("[meshes]\n", "unknown table"),
    ("[problem]\nkind = 'tube'\n", "kind must be"),
    ("[material]\nnu = 0.7\n", "Poisson"),
    ("[run]\nn_steps = 101\nsave_every = 10\n", "multiple of save_every"),
    ("this is = = not toml", "invalid TOML"),
    ("[problem]\nkind = 'general'\n[[pressure]]\nsurface = 'lumen'\n", "no facet set named 'lumen'"),
])
def test_bad_configuration_gives_a_one_line_error(tmp_path, capsys, text, message):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(text)
    assert main(["simulate", str(cfg), "-o", str(tmp_path / "x.h5"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and message in err
    assert not (tmp_path / "x.h5").exists()


def test_diverging_run_keeps_what_was_saved(tmp_path, capsys):
    out = tmp_path / "run.h5"
    out.write_bytes(b"previous good result")
    code = main(["simulate", "--steps", "20000", "--save-every", "100", "--dt", "2e-3",
                 "-o", str(out), "--no-progress", "--force"])
    assert code == 2
    assert "above the stability bound" in capsys.readouterr().err
    assert out.read_bytes() == b"previous good result"


def test_demo_end_to_end_reduced(tmp_path, capsys):
    """The whole pipeline (synchronized run, training, online run, report) in a reduced
    mode; the summary has the documented keys and the figures exist."""
    from jaxsync.app.demo import SUMMARY_KEYS

    out = tmp_path / "demo"
    assert main(["demo", "--steps", "1500", "--epochs", "2", "--hidden", "8", "--n-s", "5",
                 "--n-past", "5", "--n-future", "5", "--out", str(out), "--no-progress"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    for key in SUMMARY_KEYS:
        assert key in summary, key
        assert isinstance(summary[key], str) or np.isfinite(summary[key]), key
    assert summary["n_steps"] == 1500
    # n_cri = n_s n_p; the counts agree with the run's statistics and flags
    assert summary["n_synchronized"] == 25 and summary["n_predicted"] == 1475
    assert summary["n_synchronized_steps"] == 25 and summary["n_predicted_steps"] == 1475
    assert summary["n_devices"] == 2 and summary["device_kind"] == "cpu"
    assert summary["speedup"] == pytest.approx(summary["us_per_step_synchronized"]
                                               / summary["us_per_step_predicted"])
    for name in ("displacement_nodes.png", "l2_error.png", "shared_errors.png", "et_histogram.png"):
        assert (out / "report" / name).stat().st_size > 1000
    online = jaxsync.Trajectory.load(out / "online.h5")
    assert online.save_every == 5 and online.n_saved == 301  # the full field every n_s steps
    assert online.synchronized.sum() == 25 // 5 + 1 and not online.synchronized[-1]
    reference = jaxsync.Trajectory.load(out / "synchronized.h5")
    assert reference.save_every == 5 and reference.parts[0].shared_displacement.shape[0] == 1501
    text = capsys.readouterr().out
    assert "speed-up" in text and "time per step, predicted" in text and "zeta, compiled steps" in text
    assert "1500 steps: 25 synchronized, 1475 predicted" in text
    assert summary["zeta_sync"] in ("psum", "ppermute") and summary["t_d_us"] > 0

    # the same online run from the command line, and its report
    capsys.readouterr()
    assert main(["predict", str(out / "synchronized.h5"), str(out / "surrogate" / "surrogate.h5"),
                 "-o", str(tmp_path / "again.h5"), "--no-progress"]) == 0
    assert "1500 steps: 25 synchronized, 1475 predicted" in capsys.readouterr().out
    again = jaxsync.Trajectory.load(tmp_path / "again.h5")
    np.testing.assert_allclose(again.displacement, online.displacement, rtol=0, atol=1e-12)
    # an existing output is not overwritten without --force (refused before running)
    before = (tmp_path / "again.h5").stat().st_mtime_ns
    assert main(["predict", str(out / "synchronized.h5"), str(out / "surrogate" / "surrogate.h5"),
                 "-o", str(tmp_path / "again.h5"), "--no-progress"]) == 2
    assert "--force" in capsys.readouterr().err
    assert (tmp_path / "again.h5").stat().st_mtime_ns == before
    assert main(["report", str(out / "synchronized.h5"), str(tmp_path / "again.h5"),
                 "-o", str(tmp_path / "report")]) == 0
    again_summary = json.loads((tmp_path / "report" / "summary.json").read_text())
    assert again_summary["tip_max_abs_error"] == pytest.approx(summary["tip_max_abs_error"], rel=1e-9)

    # with error control: 2-epoch networks disagree at once, every cycle is rejected
    # before use and the run falls back to the synchronized solver (stretches of 2, 4,
    # 8... cycles); printed, saved and reported counts agree
    capsys.readouterr()
    with pytest.warns(RuntimeWarning, match="retrain the surrogates or loosen the tolerance"):
        assert main(["predict", str(out / "synchronized.h5"), str(out / "surrogate" / "surrogate.h5"),
                     "--resync-tolerance", "1e-12", "-o", str(tmp_path / "resync.h5"),
                     "--no-progress"]) == 0
    printed = capsys.readouterr().out
    resync = jaxsync.Trajectory.load(tmp_path / "resync.h5")
    st = resync.stats
    at = list(st.resynchronized_at)
    assert at[:3] == [25, 75, 175]  # a 25-step cycle; synchronized for 2, then 4 cycles
    assert st.n_synchronized_steps == 1500 and st.n_predicted_steps == 0
    assert f"1500 steps: 1500 synchronized, 0 predicted (n_cri = 25); tolerance 1e-12 cm: {len(at)} " in printed
    assert resync.synchronized.all()
    np.testing.assert_allclose(resync.displacement, reference.displacement, rtol=0,
                               atol=1e-12 * np.abs(reference.displacement).max())
    capsys.readouterr()
    assert main(["report", str(out / "synchronized.h5"), str(tmp_path / "resync.h5"),
                 "-o", str(tmp_path / "report_resync")]) == 0
    reported = json.loads((tmp_path / "report_resync" / "summary.json").read_text())
    assert reported["n_synchronized"] == 1500 and reported["n_predicted"] == 0
    assert "1500 steps: 1500 synchronized, 0 predicted" in capsys.readouterr().out


def test_predict_refuses_a_checkpoint_of_another_partition(tmp_path, capsys):
    from jaxsync.surrogate import SurrogateCheckpoint, save_checkpoint

    problem = jaxsync.cantilever()
    sync = jaxsync.simulate(problem, 200, partitions=2)
    sync.save(tmp_path / "s.h5")
    other = jaxsync.partition(problem.mesh, 4)
    import jax

    from jaxsync.surrogate import LSTMArchitecture, init_replicas
    counts = tuple(3 * p.n_shared for p in other.parts)
    arch = LSTMArchitecture(n_dof=max(counts), n_hidden=4, n_layers=1, n_past=2, n_future=2)
    params = jax.tree_util.tree_map(np.asarray, init_replicas(jax.random.key(0), arch, counts))
    ckpt = SurrogateCheckpoint(arch=arch, params=params, mean=np.zeros((4, arch.n_dof), np.float32),
                               std=np.ones((4, arch.n_dof), np.float32), dof_counts=counts, n_s=2,
                               shared_nodes=tuple(p.shared_nodes for p in other.parts))
    save_checkpoint(tmp_path / "c.h5", ckpt)
    assert main(["predict", str(tmp_path / "s.h5"), str(tmp_path / "c.h5"), "-o",
                 str(tmp_path / "o.h5"), "--no-progress"]) == 2
    assert "partition has 2 parts" in capsys.readouterr().err
    assert not (tmp_path / "o.h5").exists()


def test_print_config(capsys):
    assert main(["simulate", "--print-config"]) == 0
    assert "[material]" in capsys.readouterr().out


def test_simulate_distributed(tmp_path):
    out = tmp_path / "d.h5"
    assert main(["simulate", "--steps", "200", "--save-every", "1", "--partitions", "2",
                 "--mode", "recompute", "-o", str(out), "--no-progress"]) == 0
    traj = jaxsync.Trajectory.load(out)
    assert len(traj.parts) == 2
    single = jaxsync.simulate(jaxsync.cantilever(), 200, mode="recompute")
    np.testing.assert_allclose(traj.displacement, single.displacement, rtol=0, atol=1e-14)


def test_cli_keeps_snapshots_of_a_diverged_run(tmp_path, monkeypatch, capsys):
    """When a run diverges, the snapshots before are written next to the output."""
    import jaxsync.solve.solver

    def diverging(problem, n_steps, **kwargs):
        err = jaxsync.StabilityError("the run diverged by step 7")
        err.trajectory = jaxsync.simulate(problem, 10, save_every=5)
        raise err

    monkeypatch.setattr(jaxsync.solve.solver, "simulate", diverging)
    out = tmp_path / "run.h5"
    assert main(["simulate", "--steps", "100", "--save-every", "5", "-o", str(out),
                 "--no-progress"]) == 2
    assert not out.exists()
    partial = jaxsync.Trajectory.load(tmp_path / "run.partial.h5")
    assert partial.n_saved == 3
    assert "diverged" in capsys.readouterr().err


def test_simulate_timings(tmp_path, capsys):
    path = tmp_path / "t.json"
    assert main(["simulate", "--partitions", "2", "--timings", str(path)]) == 0
    out = capsys.readouterr().out
    assert "t_s" in out
    data = json.loads(path.read_text())
    assert data["n_parts"] == 2 and len(data["rows"]) == 2


def small_case(tmp_path, run_extra=""):
    """A 4-element bar in its own folder, 20 steps; returns the TOML path."""
    folder = tmp_path / "case"
    folder.mkdir(parents=True, exist_ok=True)
    cfg = folder / "bar.toml"
    cfg.write_text(f"""
[mesh]
length = 4.0
divisions = [4, 1, 1]
[run]
n_steps = 20
save_every = 10
{run_extra}
""")
    return cfg


def test_xdmf_requested_by_the_config_follows_dash_o(tmp_path, capsys):
    """Two runs of one config with different -o must not share (overwrite) one xdmf."""
    cfg = small_case(tmp_path, 'xdmf = "shared.xdmf"')
    for name in ("one", "two"):
        assert main(["simulate", str(cfg), "-o", str(tmp_path / f"{name}.h5"), "--no-progress"]) == 0
        assert (tmp_path / f"{name}.xdmf").exists() and (tmp_path / f"{name}.xdmf.h5").exists()
    assert not (tmp_path / "case" / "shared.xdmf").exists()
    # an explicit --xdmf still wins
    assert main(["simulate", str(cfg), "-o", str(tmp_path / "three.h5"), "--xdmf",
                 str(tmp_path / "mine.xdmf"), "--no-progress"]) == 0
    assert (tmp_path / "mine.xdmf").exists() and not (tmp_path / "three.xdmf").exists()


@pytest.mark.parametrize("existing", ["run.h5", "run.xdmf", "run.xdmf.h5"])
def test_existing_outputs_are_refused_before_running_unless_forced(tmp_path, capsys, monkeypatch,
                                                                   existing):
    import jaxsync.solve.solver

    cfg = small_case(tmp_path)
    (tmp_path / existing).write_bytes(b"another run's result")
    args = ["simulate", str(cfg), "-o", str(tmp_path / "run.h5"), "--xdmf",
            str(tmp_path / "run.xdmf"), "--no-progress"]

    def must_not_run(*a, **k):
        raise AssertionError("simulate ran although an output exists")

    monkeypatch.setattr(jaxsync.solve.solver, "simulate", must_not_run)
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and existing in err and "--force" in err
    assert (tmp_path / existing).read_bytes() == b"another run's result"
    monkeypatch.undo()
    assert main(args + ["--force"]) == 0
    assert jaxsync.Trajectory.load(tmp_path / "run.h5").n_saved == 3
    assert (tmp_path / existing).read_bytes() != b"another run's result"


def test_existing_timings_json_is_refused_unless_forced(tmp_path, capsys):
    cfg = small_case(tmp_path)
    path = tmp_path / "t.json"
    path.write_text("{}")
    assert main(["simulate", str(cfg), "--timings", str(path)]) == 2
    assert "t.json already exists" in capsys.readouterr().err and path.read_text() == "{}"
    assert main(["simulate", str(cfg), "--timings", str(path), "--force"]) == 0
    assert json.loads(path.read_text())["n_parts"] == 1


def test_resumed_run_replaces_its_own_output_without_force(tmp_path):
    cfg = small_case(tmp_path)
    out, ckpt = tmp_path / "r.h5", tmp_path / "r.ckpt.h5"
    base = ["simulate", str(cfg), "-o", str(out), "--checkpoint", str(ckpt), "--no-progress"]
    assert main(base) == 0
    assert main(base + ["--steps", "40"]) == 0  # continues from the checkpoint
    problem, _ = problem_from_config(load_config(cfg))
    direct = jaxsync.simulate(problem, 40, save_every=10)
    np.testing.assert_array_equal(jaxsync.Trajectory.load(out).displacement, direct.displacement)
    # the checkpoint must not be one of the outputs
    assert main(["simulate", str(cfg), "-o", str(tmp_path / "x.h5"), "--checkpoint",
                 str(tmp_path / "x.h5"), "--no-progress"]) == 2


@pytest.mark.parametrize("dt", [["--dt", "-1e-4"], ["--dt=-1e-4"], ["--dt", "-0.5"]])
def test_negative_dt_reaches_the_package_check(tmp_path, capsys, dt):
    cfg = small_case(tmp_path)
    assert main(["simulate", str(cfg), "-o", str(tmp_path / "n.h5"), "--no-progress"] + dt) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: time step must be positive") and "expected one argument" not in err
    assert not (tmp_path / "n.h5").exists()


def test_mass_scaling_from_the_command_line(tmp_path, capsys):
    cfg = small_case(tmp_path)
    problem, _ = problem_from_config(load_config(cfg))
    out = tmp_path / "m.h5"
    assert main(["simulate", str(cfg), "-o", str(out), "--mass-scaling-beta", "2",
                 "--no-progress"]) == 0
    captured = capsys.readouterr()
    # uniform elements: all of them get 4 times the density
    assert "added mass 300.00 %" in captured.out
    assert captured.err.startswith("warning: mass scaling") and "300.0 %" in captured.err
    traj = jaxsync.Trajectory.load(out)
    assert traj.dt == pytest.approx(2 * problem.dt, rel=1e-12)
    assert traj.parameters["added_mass_percent"] == pytest.approx(300.0)
    target = 1.5 * problem.dt
    assert main(["simulate", str(cfg), "-o", str(tmp_path / "m2.h5"), "--mass-scaling-dt",
                 str(target), "--no-progress"]) == 0
    assert jaxsync.Trajectory.load(tmp_path / "m2.h5").dt == pytest.approx(target, rel=1e-12)
    with pytest.raises(SystemExit):  # argparse: not allowed with
        main(["simulate", "--mass-scaling-dt", "1e-4", "--mass-scaling-beta", "2"])
    assert "not allowed with" in capsys.readouterr().err


def test_mass_scaling_from_toml(tmp_path, capsys):
    cfg = small_case(tmp_path, "mass_scaling_beta = 1.5")
    problem, _ = problem_from_config(load_config(small_case(tmp_path / "x")))
    assert main(["simulate", str(cfg), "-o", str(tmp_path / "s.h5"), "--no-progress"]) == 0
    assert "added mass 125.00 %" in capsys.readouterr().out
    assert jaxsync.Trajectory.load(tmp_path / "s.h5").dt == pytest.approx(1.5 * problem.dt, rel=1e-12)
    # the command line replaces the file's setting
    assert main(["simulate", str(cfg), "-o", str(tmp_path / "t.h5"), "--mass-scaling-beta", "1.2",
                 "--no-progress"]) == 0
    assert jaxsync.Trajectory.load(tmp_path / "t.h5").dt == pytest.approx(1.2 * problem.dt, rel=1e-12)
    both = small_case(tmp_path / "y", "mass_scaling_beta = 1.5\nmass_scaling_dt = 1e-3")
    assert main(["simulate", str(both), "-o", str(tmp_path / "u.h5"), "--no-progress"]) == 2
    assert "both mass_scaling_dt and mass_scaling_beta" in capsys.readouterr().err


def test_ctrl_c_prints_one_line_and_exits_130(tmp_path, capsys, monkeypatch):
    import jaxsync.solve.solver

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(jaxsync.solve.solver, "simulate", interrupted)
    out = tmp_path / "k.h5"
    try:
        code = main(["simulate", str(small_case(tmp_path)), "-o", str(out), "--no-progress"])
    except KeyboardInterrupt:  # would stop pytest itself
        pytest.fail("Ctrl-C escaped jaxsync's main: the user gets a traceback")
    assert code == 130
    err = capsys.readouterr().err
    assert err.startswith("interrupted") and err.count("\n") == 1 and "Traceback" not in err
    assert "checkpoint" in err and not out.exists()
