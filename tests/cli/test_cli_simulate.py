"""``jaxsync simulate``: problems from TOML files, outputs that are never overwritten by
accident, diverged and interrupted runs, mass scaling, distributed runs and timings.

Where a run must fail or must not start, the test replaces the public
``jaxsync.solve.simulate`` (what the command calls) and checks what the command
does around it."""

import json

import numpy as np
import pytest

import jaxsync
from jaxsync.app.config import load_config, problem_from_config
from jaxsync.cli import main


def test_simulate_from_the_packaged_config(tmp_path, capsys):
    out = tmp_path / "c.h5"
    assert main(["simulate", "--steps", "400", "--save-every", "100", "-o", str(out),
                 "--xdmf", str(tmp_path / "c.xdmf"), "--no-progress"]) == 0
    traj = jaxsync.Trajectory.load(out)
    assert traj.displacement.shape == (5, 104, 3)
    expected = jaxsync.simulate(jaxsync.cantilever(), 400, save=100)
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


def test_print_config(capsys):
    assert main(["simulate", "--print-config"]) == 0
    assert "[material]" in capsys.readouterr().out


def test_simulate_distributed(tmp_path):
    out = tmp_path / "d.h5"
    assert main(["simulate", "--steps", "200", "--save-every", "1", "--parts", "2",
                 "--mode", "recompute", "-o", str(out), "--no-progress"]) == 0
    traj = jaxsync.Trajectory.load(out)
    assert len(traj.parts) == 2
    single = jaxsync.simulate(jaxsync.cantilever(), 200, mode="recompute")
    np.testing.assert_allclose(traj.displacement, single.displacement, rtol=0, atol=1e-14)


def test_cli_keeps_snapshots_of_a_diverged_run(tmp_path, monkeypatch, capsys):
    """When a run diverges, the snapshots before are written next to the output."""
    def diverging(problem, n_steps, **kwargs):
        err = jaxsync.StabilityError("the run diverged by step 7")
        err.trajectory = jaxsync.simulate(problem, 10, save=5)
        raise err

    monkeypatch.setattr("jaxsync.solve._solver.simulate", diverging)
    out = tmp_path / "run.h5"
    assert main(["simulate", "--steps", "100", "--save-every", "5", "-o", str(out),
                 "--no-progress"]) == 2
    assert not out.exists()
    partial = jaxsync.Trajectory.load(tmp_path / "run.partial.h5")
    assert partial.n_saved == 3
    assert "diverged" in capsys.readouterr().err


def test_simulate_with_deep_halos(tmp_path, capsys):
    out = tmp_path / "h.h5"
    assert main(["simulate", "--steps", "200", "--save-every", "10", "--parts", "2", "--sync", "halo",
                 "--halo-depth", "5", "-o", str(out), "--no-progress"]) == 0
    single = jaxsync.simulate(jaxsync.cantilever(), 200, save=10)
    scale = np.abs(single.displacement).max()
    assert np.abs(jaxsync.Trajectory.load(out).displacement - single.displacement).max() <= 1e-12 * scale
    # save_every and the depth must divide one another: a one-line error with the fix
    assert main(["simulate", "--steps", "200", "--save-every", "10", "--parts", "2", "--sync", "halo",
                 "--halo-depth", "3", "-o", str(tmp_path / "bad.h5"), "--no-progress"]) != 0
    assert "halo_depth=1 or save_every=30" in capsys.readouterr().err
    assert not (tmp_path / "bad.h5").exists()


def test_simulate_timings(tmp_path, capsys):
    path = tmp_path / "t.json"
    assert main(["simulate", "--parts", "2", "--timings", str(path)]) == 0
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
    cfg = small_case(tmp_path)
    (tmp_path / existing).write_bytes(b"another run's result")
    args = ["simulate", str(cfg), "-o", str(tmp_path / "run.h5"), "--xdmf",
            str(tmp_path / "run.xdmf"), "--no-progress"]

    def must_not_run(*a, **k):
        raise AssertionError("simulate ran although an output exists")

    monkeypatch.setattr("jaxsync.solve._solver.simulate", must_not_run)
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
    direct = jaxsync.simulate(problem, 40, save=10)
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


def test_negative_numbers_are_joined_to_their_option():
    """What lets ``--dt -1e-4`` through argparse (public parse_known_args, no private
    setting): a negative number after an option becomes its ``=`` value."""
    from jaxsync.cli.common import join_negative_values

    assert join_negative_values(["--dt", "-1e-4", "-o", "-.5", "--steps", "10"]) == [
        "--dt=-1e-4", "-o=-.5", "--steps", "10"]
    assert join_negative_values(["--dt=-1e-4", "-1e-4"]) == ["--dt=-1e-4", "-1e-4"]  # already given
    assert join_negative_values(["--", "--dt", "-1"]) == ["--", "--dt", "-1"]  # positionals after --
    assert join_negative_values(["--dt", "-x"]) == ["--dt", "-x"]  # not a number


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
    capsys.readouterr()
    # a target below the CFL step adds nothing, and the run says it keeps the larger step
    assert main(["simulate", str(cfg), "-o", str(tmp_path / "m3.h5"), "--mass-scaling-dt",
                 str(0.5 * problem.dt), "--no-progress", "--steps", "100"]) == 0
    assert (f"mass scaling to dt {0.5 * problem.dt:.4e} s: added mass 0.00 % of the total (every element is "
            f"stable at a larger step); the run takes the CFL step {problem.dt:.4e} s") in capsys.readouterr().out
    assert jaxsync.Trajectory.load(tmp_path / "m3.h5").dt == pytest.approx(problem.dt, rel=1e-12)
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
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("jaxsync.solve._solver.simulate", interrupted)
    out = tmp_path / "k.h5"
    try:
        code = main(["simulate", str(small_case(tmp_path)), "-o", str(out), "--no-progress"])
    except KeyboardInterrupt:  # would stop pytest itself
        pytest.fail("Ctrl-C escaped jaxsync's main: the user gets a traceback")
    assert code == 130
    err = capsys.readouterr().err
    assert err.startswith("interrupted") and err.count("\n") == 1 and "Traceback" not in err
    assert "checkpoint" in err and not out.exists()


def test_simulate_element_and_float32_blocks_options(tmp_path, capsys):
    """--element P2 runs quadratic tetrahedra (the library's P2 run, bit for bit);
    --float32-blocks stays within 1e-6 of float64 and is refused with --mode recompute."""
    p2 = tmp_path / "p2.h5"
    assert main(["simulate", "--element", "P2", "--steps", "200", "--save-every", "100", "-o", str(p2),
                 "--no-progress"]) == 0
    traj = jaxsync.Trajectory.load(p2)
    expected = jaxsync.simulate(jaxsync.cantilever(element="P2"), 200, save=100)
    assert traj.element == "P2"
    np.testing.assert_array_equal(traj.displacement, expected.displacement)
    f32 = tmp_path / "f32.h5"
    assert main(["simulate", "--float32-blocks", "--steps", "2000", "--save-every", "1000", "-o", str(f32),
                 "--no-progress"]) == 0
    single = jaxsync.Trajectory.load(f32).displacement
    double = jaxsync.simulate(jaxsync.cantilever(), 2000, save=1000).displacement
    difference = np.abs(single - double).max() / np.abs(double).max()
    assert 0 < difference < 1e-6
    assert main(["simulate", "--mode", "recompute", "--float32-blocks", "--steps", "10", "-o",
                 str(tmp_path / "x.h5"), "--no-progress"]) == 2
    assert "--mode preassembled" in capsys.readouterr().err
