import json
import os
import subprocess
import sys

import numpy as np
import pytest

import jaxsync
from jaxsync.cli import build_parser, main


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
    out = subprocess.run([sys.executable, "-m", "jaxsync.cli", "--help"], capture_output=True,
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
                 "-o", str(out), "--no-progress"])
    assert code == 2
    assert "above the stability bound" in capsys.readouterr().err
    assert out.read_bytes() == b"previous good result"


def test_demo_end_to_end_reduced(tmp_path, capsys):
    """The whole pipeline (synchronized run, training, online run, report) in a reduced
    mode; the summary has the documented keys and the figures exist."""
    from jaxsync.demo import SUMMARY_KEYS

    out = tmp_path / "demo"
    assert main(["demo", "--steps", "1500", "--epochs", "2", "--hidden", "8", "--n-s", "5",
                 "--n-past", "5", "--n-future", "5", "--out", str(out), "--no-progress"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    for key in SUMMARY_KEYS:
        assert key in summary and np.isfinite(summary[key]), key
    assert summary["n_steps"] == 1500
    assert summary["n_synchronized"] == 26 and summary["n_predicted"] == 1474
    assert summary["speedup"] == pytest.approx(summary["us_per_step_synchronized"]
                                               / summary["us_per_step_predicted"])
    for name in ("displacement_nodes.png", "l2_error.png", "shared_errors.png", "et_histogram.png"):
        assert (out / "report" / name).stat().st_size > 1000
    online = jaxsync.Trajectory.load(out / "online.h5")
    assert online.synchronized.sum() == 27 and not online.synchronized[-1]
    text = capsys.readouterr().out
    assert "speed-up" in text and "time per step, predicted" in text and "zeta, compiled steps" in text
    assert summary["zeta_sync"] in ("psum", "ppermute") and summary["t_d_us"] > 0

    # the same online run from the command line, and its report
    assert main(["predict", str(out / "synchronized.h5"), str(out / "surrogate" / "surrogate.h5"),
                 "-o", str(tmp_path / "again.h5"), "--no-progress"]) == 0
    again = jaxsync.Trajectory.load(tmp_path / "again.h5")
    np.testing.assert_allclose(again.displacement, online.displacement, rtol=0, atol=1e-12)
    assert main(["report", str(out / "synchronized.h5"), str(tmp_path / "again.h5"),
                 "-o", str(tmp_path / "report")]) == 0
    again_summary = json.loads((tmp_path / "report" / "summary.json").read_text())
    assert again_summary["tip_max_abs_error"] == pytest.approx(summary["tip_max_abs_error"], rel=1e-9)

    # with the es_hat monitor: 2-epoch networks disagree, so every cycle is followed by
    # n_p n_s re-synchronized steps; the report handles the interleaved segments
    capsys.readouterr()
    assert main(["predict", str(out / "synchronized.h5"), str(out / "surrogate" / "surrogate.h5"),
                 "--resync-tolerance", "1e-12", "-o", str(tmp_path / "resync.h5"), "--no-progress"]) == 0
    assert "re-synchronized" in capsys.readouterr().out
    resync = jaxsync.Trajectory.load(tmp_path / "resync.h5")
    at = resync.parameters["resynchronized_at"]
    assert len(at) >= 2 and at[1] - at[0] == 2 * 25  # a 25-step cycle, then 25 synchronized steps
    assert resync.synchronized.sum() > online.synchronized.sum()
    assert main(["report", str(out / "synchronized.h5"), str(tmp_path / "resync.h5"),
                 "-o", str(tmp_path / "report_resync")]) == 0


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
    import jaxsync.solver

    def diverging(problem, n_steps, **kwargs):
        err = jaxsync.StabilityError("the run diverged by step 7")
        err.trajectory = jaxsync.simulate(problem, 10, save_every=5)
        raise err

    monkeypatch.setattr(jaxsync.solver, "simulate", diverging)
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
