"""Where the commands write: locations that cannot be written are refused before anything
runs, a write that fails all the same (a full disk) ends in one ``error:`` line that names
what was kept, ``jaxsync demo`` replaces a finished demo only with ``--force`` and only
once the new run is complete, and the small things the command line prints (the package's
warnings as one line, help without a literal ``%%``, the steps of a resumed run).

Tests run as root, for whom permission bits do not count: an unwritable location is a
path under a regular file (``afile/out.h5``) or in /proc."""

import errno
import json
import os
import types

import numpy as np
import pytest

import jaxsync
from jaxsync.cli import build_parser, main
from jaxsync.io import OutputError, atomic_path, check_writable, recording_writes


def small_case(tmp_path):
    """A 4-element bar, 20 steps; returns the TOML path."""
    folder = tmp_path / "case"
    folder.mkdir(parents=True, exist_ok=True)
    cfg = folder / "bar.toml"
    cfg.write_text("[mesh]\nlength = 4.0\ndivisions = [4, 1, 1]\n[run]\nn_steps = 20\nsave_every = 10\n")
    return cfg


@pytest.fixture
def afile(tmp_path):
    """A regular file: nothing can be written under it."""
    path = tmp_path / "afile"
    path.write_text("not a folder")
    return path


def files_under(folder):
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def must_not_run(*args, **kwargs):
    raise AssertionError("the computation ran although an output location is unusable")


def assert_one_error_line(err, *needles):
    assert err.startswith("error:") and err.count("\n") == 1, err
    assert "Traceback" not in err
    for needle in needles:
        assert str(needle) in err, (needle, err)


# ----------------------------------------------------------------------------- before the run


@pytest.mark.parametrize("option, name", [("-o", "out.h5"), ("--xdmf", "out.xdmf"),
                                          ("--checkpoint", "ck.h5"), ("--timings", "t.json")])
def test_simulate_refuses_an_unwritable_output_before_running(tmp_path, afile, capsys, monkeypatch, option, name):
    import jaxsync.perf.timing

    monkeypatch.setattr("jaxsync.solve._solver.simulate", must_not_run)
    monkeypatch.setattr(jaxsync.perf.timing, "timing_breakdown", must_not_run)
    cfg = small_case(tmp_path)
    target = afile / name
    args = ["simulate", str(cfg), option, str(target), "--no-progress"]
    if option != "-o":
        args += ["-o", str(tmp_path / "run.h5")]
    before = files_under(tmp_path)
    assert main(args) == 2
    assert_one_error_line(capsys.readouterr().err, target, "is a file, not a folder", option)
    assert files_under(tmp_path) == before  # no output file, no temporary


def test_simulate_refuses_a_folder_it_cannot_write_in(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("jaxsync.solve._solver.simulate", must_not_run)
    assert main(["simulate", str(small_case(tmp_path)), "-o", "/proc/jaxsync-test/out.h5", "--no-progress"]) == 2
    assert_one_error_line(capsys.readouterr().err, "/proc/jaxsync-test/out.h5", "-o")


def test_simulate_refuses_a_folder_as_output_file(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("jaxsync.solve._solver.simulate", must_not_run)
    (tmp_path / "folder.h5").mkdir()
    assert main(["simulate", str(small_case(tmp_path)), "-o", str(tmp_path / "folder.h5"), "--force",
                 "--no-progress"]) == 2
    assert_one_error_line(capsys.readouterr().err, "is a folder")


def test_missing_folders_count_as_writable(tmp_path):
    check_writable(tmp_path / "new" / "deeper" / "out.h5")  # the writers create them
    check_writable(tmp_path / "new" / "folder", folder=True)
    assert not (tmp_path / "new").exists()
    assert os.listdir(tmp_path) == []  # the probe file is gone
    with pytest.raises(OutputError, match="is a file, not a folder"):
        (tmp_path / "f").write_text("")
        check_writable(tmp_path / "f", folder=True)


def test_train_refuses_an_unwritable_output_folder(tmp_path, afile, capsys, monkeypatch):
    import jaxsync.cli.train
    from oscillator_trajectories import write_trajectory

    monkeypatch.setattr(jaxsync.cli.train, "train_surrogates", must_not_run)
    traj = write_trajectory(tmp_path / "run.h5", n_steps=60)
    assert main(["train", str(traj), "-o", str(afile / "out"), "--no-progress"]) == 2
    assert_one_error_line(capsys.readouterr().err, afile / "out", "-o")
    assert main(["train", str(traj), "-o", str(afile), "--no-progress"]) == 2  # a file, not a folder
    assert_one_error_line(capsys.readouterr().err, "is a file, not a folder")


@pytest.mark.parametrize("argv", [
    ["predict", "s.h5", "c.h5", "-o", "{bad}/online.h5"],
    ["finetune", "s.h5", "c.h5", "-o", "{bad}/tuned.h5"],
    ["report", "s.h5", "o.h5", "-o", "{bad}/report"],
    ["demo", "-o", "{bad}/demo", "--steps", "100"],
])
def test_other_commands_refuse_an_unwritable_output_before_reading_anything(afile, capsys, argv):
    # the inputs do not even exist: the output location is checked first
    argv = [a.format(bad=afile) for a in argv]
    assert main(argv) == 2
    assert_one_error_line(capsys.readouterr().err, afile, "-o")


# ----------------------------------------------------------------------------- at write time


def no_space(*args, **kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_a_full_disk_at_the_xdmf_keeps_the_trajectory_and_says_so(tmp_path, capsys, monkeypatch):
    """The issue's case: the trajectory and the XDMF's .h5 written, then the .xdmf fails."""
    def half_xdmf(self, path, every=1):
        (tmp_path / "run.xdmf.h5").write_bytes(b"heavy data")
        no_space()

    monkeypatch.setattr(jaxsync.Trajectory, "to_xdmf", half_xdmf)
    code = main(["simulate", str(small_case(tmp_path)), "-o", str(tmp_path / "run.h5"), "--xdmf",
                 str(tmp_path / "run.xdmf"), "--no-progress"])
    assert code == 2
    err = capsys.readouterr().err
    assert_one_error_line(err, "could not write", "run.xdmf:", "No space left on device",
                          "kept: " + str(tmp_path / "run.h5"), str(tmp_path / "run.xdmf.h5"))
    assert jaxsync.Trajectory.load(tmp_path / "run.h5").n_saved == 3  # kept, whole


def test_a_full_disk_at_the_trajectory_writes_nothing(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(jaxsync.Trajectory, "save", no_space)
    assert main(["simulate", str(small_case(tmp_path)), "-o", str(tmp_path / "run.h5"), "--no-progress"]) == 2
    assert_one_error_line(capsys.readouterr().err, "could not write " + str(tmp_path / "run.h5"),
                          "No space left on device", "no output file was written")
    assert not (tmp_path / "run.h5").exists()


def test_a_full_disk_inside_an_atomic_write_is_one_error_line(tmp_path, capsys, monkeypatch):
    """An OSError from the HDF5 writer itself, in a resumable run: the checkpoint written
    during the run is named as kept, the previous trajectory is left as it was."""
    import h5py

    cfg = small_case(tmp_path)
    out, ckpt = tmp_path / "run.h5", tmp_path / "run.ckpt.h5"
    real = jaxsync.Trajectory.save

    def failing_save(self, path, **kwargs):
        monkeypatch.setattr(h5py.Group, "create_dataset", no_space)
        try:
            return real(self, path, **kwargs)
        finally:
            monkeypatch.undo()

    monkeypatch.setattr(jaxsync.Trajectory, "save", failing_save)
    assert main(["simulate", str(cfg), "-o", str(out), "--checkpoint", str(ckpt), "--no-progress"]) == 2
    assert_one_error_line(capsys.readouterr().err, f"could not write {out}", "No space left on device",
                          f"kept: {ckpt}")
    assert sorted(os.listdir(tmp_path)) == ["case", "run.ckpt.h5"]  # no temporary left behind


def test_ctrl_c_between_two_writes_names_the_file_kept(tmp_path, capsys, monkeypatch):
    def interrupted(self, path, every=1):
        raise KeyboardInterrupt

    monkeypatch.setattr(jaxsync.Trajectory, "to_xdmf", interrupted)
    assert main(["simulate", str(small_case(tmp_path)), "-o", str(tmp_path / "run.h5"), "--xdmf",
                 str(tmp_path / "run.xdmf"), "--no-progress"]) == 130
    err = capsys.readouterr().err
    assert err.startswith("interrupted: the files completed before were kept (" + str(tmp_path / "run.h5"))
    assert err.count("\n") == 1

def test_atomic_path_failures_are_output_errors_and_oserrors(tmp_path):
    with recording_writes() as written:
        with atomic_path(tmp_path / "a.txt") as tmp:
            open(tmp, "w").write("a")
        with pytest.raises(OutputError, match="No space left") as info:
            with atomic_path(tmp_path / "b.txt"):
                no_space()
    assert isinstance(info.value, OSError) and isinstance(info.value, jaxsync.JaxsyncError)
    assert written == [str(tmp_path / "a.txt")]
    assert sorted(os.listdir(tmp_path)) == ["a.txt"]


# ----------------------------------------------------------------------------- demo


def test_demo_refuses_a_folder_that_holds_a_demo(tmp_path, capsys, monkeypatch):
    import jaxsync.app.demo

    monkeypatch.setattr(jaxsync.app.demo, "_pipeline", must_not_run)
    out = tmp_path / "demo"
    out.mkdir()
    (out / "summary.json").write_text('{"old": true}')
    assert main(["demo", "-o", str(out), "--steps", "100", "--no-progress"]) == 2
    assert_one_error_line(capsys.readouterr().err, out, "--force", "-o")
    assert files_under(tmp_path) == ["demo", "demo/summary.json"]
    assert (out / "summary.json").read_text() == '{"old": true}'


def test_demo_into_a_folder_of_other_files_keeps_them(tmp_path, capsys, monkeypatch):
    """Not a demo's folder: not refused; an interrupted run leaves it as it was."""
    import jaxsync.app.demo

    def interrupted(staging, final, *args, **kwargs):
        assert os.path.dirname(staging) == str(tmp_path) and final == str(tmp_path / "mine")
        (tmp_path / staging / "synchronized.h5").write_bytes(b"new")
        raise KeyboardInterrupt

    monkeypatch.setattr(jaxsync.app.demo, "_pipeline", interrupted)
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("mine")
    assert main(["demo", "-o", str(tmp_path / "mine"), "--steps", "100", "--n-s", "5", "--n-past", "5",
                 "--n-future", "5", "--no-progress"]) == 130
    assert files_under(tmp_path) == ["mine", "mine/notes.txt"]


def test_interrupted_demo_leaves_the_old_folder_and_no_staging(tmp_path, monkeypatch):
    """A real run (100 steps) interrupted once the synchronized run is written: the old
    demo is untouched, the new files are gone with their staging folder."""
    from jaxsync.app.demo import DemoSettings, run_demo

    out = tmp_path / "demo"
    (out / "surrogate").mkdir(parents=True)
    old = {"summary.json": b'{"old": true}', "synchronized.h5": b"old run", "surrogate/surrogate.h5": b"old nets"}
    for name, data in old.items():
        (out / name).write_bytes(data)
    seen = {}

    def interrupt(reference_path, **kwargs):
        seen["reference"] = reference_path
        seen["written"] = jaxsync.Trajectory.load(reference_path).n_saved
        raise KeyboardInterrupt

    monkeypatch.setattr("jaxsync.surrogate.training._fit.train_surrogates", interrupt)
    with pytest.raises(KeyboardInterrupt):
        run_demo(str(out), DemoSettings(n_steps=100, n_s=5, n_past=2, n_future=2, epochs=1, n_hidden=4),
                 progress=False, log=lambda *a: None, force=True)
    staging = os.path.dirname(seen["reference"])
    assert os.path.dirname(staging) == str(tmp_path) and os.path.basename(staging).startswith("demo.partial-")
    assert seen["written"] > 1  # the new synchronized run was complete, in the staging folder
    assert sorted(os.listdir(tmp_path)) == ["demo"]
    assert {name: (out / name).read_bytes() for name in old} == old
    assert files_under(out) == ["summary.json", "surrogate", "surrogate/surrogate.h5", "synchronized.h5"]


def test_failed_demo_write_is_one_line_and_keeps_the_old_folder(tmp_path, capsys, monkeypatch):
    import jaxsync.app.demo

    def full(staging, final, *args, **kwargs):
        with atomic_path(os.path.join(staging, "online.h5")):
            no_space()

    monkeypatch.setattr(jaxsync.app.demo, "_pipeline", full)
    out = tmp_path / "demo"
    out.mkdir()
    (out / "summary.json").write_text("old")
    assert main(["demo", "-o", str(out), "--force", "--steps", "100", "--n-s", "5", "--n-past", "5", "--n-future", "5",
                 "--no-progress"]) == 2
    assert_one_error_line(capsys.readouterr().err, f"could not write {out / 'online.h5'}",
                          "No space left on device", f"{out} is left as it was")
    assert files_under(tmp_path) == ["demo", "demo/summary.json"]


def test_install_folder_replaces_a_demo_and_keeps_a_users_files(tmp_path):
    from jaxsync.app.demo import install_folder

    final, staging = tmp_path / "demo", tmp_path / "demo.partial-1@host.abc"
    (final / "report").mkdir(parents=True)
    (final / "report" / "old.png").write_text("old")
    (final / "summary.json").write_text("old")
    (final / "notes.txt").write_text("mine")
    (staging / "report").mkdir(parents=True)
    (staging / "report" / "new.png").write_text("new")
    (staging / "summary.json").write_text("new")
    install_folder(str(staging), str(final))
    assert sorted(os.listdir(tmp_path)) == ["demo"]
    assert files_under(final) == ["notes.txt", "report", "report/new.png", "summary.json"]
    assert (final / "summary.json").read_text() == "new" and (final / "notes.txt").read_text() == "mine"
    # into a folder that does not exist: one rename
    install_folder(str(final), str(tmp_path / "other"))
    assert sorted(os.listdir(tmp_path)) == ["other"]


def test_paths_stored_in_the_staged_json_name_the_final_folder(tmp_path):
    from jaxsync.app.demo import retarget_paths

    staging, final = str(tmp_path / "d.partial-1@h.x"), str(tmp_path / "d")
    os.makedirs(os.path.join(staging, "surrogate"))
    data = {"trajectories": [os.path.join(staging, "synchronized.h5")], "n": 1, "other": staging + "x",
            "checkpoint": os.path.join(staging, "surrogate", "surrogate.h5")}
    with open(os.path.join(staging, "surrogate", "train_summary.json"), "w") as f:
        json.dump(data, f)
    retarget_paths(staging, final)
    with open(os.path.join(staging, "surrogate", "train_summary.json")) as f:
        assert json.load(f) == {"trajectories": [os.path.join(final, "synchronized.h5")], "n": 1,
                                "other": staging + "x",
                                "checkpoint": os.path.join(final, "surrogate", "surrogate.h5")}


def test_stale_staging_folders_of_dead_runs_are_removed(tmp_path):
    from jaxsync.app.demo import staging_folder
    from jaxsync.io import host_tag

    dead = tmp_path / f"demo.partial-999999999@{host_tag()}.abc"
    other_host = tmp_path / "demo.partial-999999999@elsewhere.abc"
    dead.mkdir()
    other_host.mkdir()
    staging = staging_folder(str(tmp_path / "demo"))
    assert sorted(os.listdir(tmp_path)) == sorted([os.path.basename(staging), other_host.name])


# ----------------------------------------------------------------------------- printed lines


@pytest.mark.parametrize("value", ["0", "0%", "-1e-4", "-1%"])
def test_a_resync_tolerance_that_is_not_positive_is_one_line_naming_it(value, tmp_path, capsys):
    """``--resync-tolerance 0`` (or 0%, =-1e-4, =-1%) said "'0' is neither a length in cm nor
    a percentage": the value is a number; what is wrong is that it is not > 0."""
    from jaxsync import ProblemError, ResyncTolerance
    from jaxsync.cli.common import resync_tolerance_of

    with pytest.raises(ProblemError, match="> 0") as caught:
        ResyncTolerance.parse(value)
    assert "neither" not in str(caught.value) and "\n" not in str(caught.value)
    args = build_parser().parse_args(["predict", "run.h5", "sur.h5", f"--resync-tolerance={value}"])
    with pytest.raises(ProblemError, match="> 0") as caught:
        resync_tolerance_of(args)  # what jaxsync predict reads the option with
    assert "neither" not in str(caught.value)
    # jaxsync demo checks it with its other options, before anything runs
    assert main(["demo", "-o", str(tmp_path / "demo"), f"--resync-tolerance={value}", "--no-progress"]) == 2
    assert_one_error_line(capsys.readouterr().err, "resync_tolerance must be a tolerance > 0")
    assert not (tmp_path / "demo").exists()


def test_no_help_text_shows_a_literal_double_percent():
    parser = build_parser()
    texts = [parser.format_help()]
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    texts += [p.format_help() for p in sub.choices.values()]
    assert set(sub.choices) == {"demo", "simulate", "train", "predict", "finetune", "report", "unload"}
    assert len(texts) == 8
    for text in texts:
        assert "%%" not in text
    assert "error control at 1 %;" in " ".join(sub.choices["demo"].format_help().split())


def test_resumed_run_says_how_many_steps_it_ran_and_from_where(tmp_path, capsys):
    cfg = small_case(tmp_path)
    out, ckpt = tmp_path / "r.h5", tmp_path / "r.ckpt.h5"
    base = ["simulate", str(cfg), "-o", str(out), "--checkpoint", str(ckpt), "--no-progress"]
    assert main(base) == 0
    assert capsys.readouterr().out.splitlines()[-1].startswith("20 steps in ")
    assert main(base + ["--steps", "50"]) == 0
    last = capsys.readouterr().out.splitlines()[-1]
    assert last.startswith(f"resumed from step 20 of 50 (checkpoint {ckpt}): 30 steps in "), last
    assert jaxsync.Trajectory.load(out).n_saved == 6


@pytest.mark.parametrize("stats, parts, text", [
    (dict(n_devices=2, n_processes=2, device_kind="cpu", emulated=False), 4,
     "2 cpu devices in 2 processes, 2 parts per device"),
    (dict(n_devices=2, device_kind="cpu", emulated=True), 2, "2 cpu devices, emulated"),  # before n_processes
    (dict(n_devices=1, n_processes=1, device_kind="cpu", emulated=False), None, "1 cpu device"),
])
def test_devices_are_counted_over_all_processes(stats, parts, text):
    from jaxsync.cli.simulate import devices_text

    assert devices_text(types.SimpleNamespace(**stats), parts) == text


def test_train_shows_the_rollout_warning_as_one_line(tmp_path, capsys):
    from oscillator_trajectories import write_trajectory

    traj = write_trajectory(tmp_path / "run.h5", n_steps=120)
    assert main(["train", str(traj), "-o", str(tmp_path / "out"), "--n-s", "2", "--n-past", "4", "--n-future", "3",
                 "--n-hidden", "4", "--n-layers", "1", "--epochs", "2", "--candidates", "1",
                 "--emse-applications", "0", "--no-progress"]) == 0
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert lines and lines[0].startswith("warning: the trained surrogates miss the offline check"), err
    assert len(lines) == 1 and "RolloutWarning" not in err and "warnings.warn" not in err, err


def test_every_warning_is_one_line(capsys):
    import warnings

    from jaxsync.cli.common import is_package_warning, package_warnings
    from jaxsync.errors import SynchronizedRunWarning
    from jaxsync.fem import MassScalingWarning
    from jaxsync.mesh import MeshWarning
    from jaxsync.surrogate import ReducedPrecisionWarning
    from jaxsync.surrogate.training import RolloutWarning

    for category in (MeshWarning, MassScalingWarning, RolloutWarning, ReducedPrecisionWarning):
        assert is_package_warning(category)
    assert not is_package_warning(RuntimeWarning) and not is_package_warning(UserWarning)
    assert is_package_warning(SynchronizedRunWarning) and issubclass(SynchronizedRunWarning, RuntimeWarning)
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        with package_warnings():
            warnings.warn("two\n  lines", MeshWarning)
            warnings.warn("mostly\n synchronized", SynchronizedRunWarning)
            warnings.warn("not ours", RuntimeWarning)  # another library's: one line too, with its kind
    assert capsys.readouterr().err == ("warning: two lines\nwarning: mostly synchronized\n"
                                       "warning: not ours (RuntimeWarning)\n")


# ----------------------------------------------------------------------------- a new user's faults


def diverging_case(tmp_path, model="linear-elastic"):
    """A 4-element bar under a body force that blows it up within its 40 steps."""
    cfg = tmp_path / f"div-{model}.toml"
    cfg.write_text(f'[mesh]\nlength = 4.0\ndivisions = [4, 1, 1]\n[material]\nmodel = "{model}"\n'
                   "[problem]\nbody_force = [0.0, 0.0, -1.0e12]\nt_ramp = 1.0e-3\n"
                   "[run]\nn_steps = 400\nsave_every = 10\n")
    return cfg


@pytest.mark.parametrize("model, parts", [("linear-elastic", None), ("neo-hookean", None), ("linear-elastic", "2")])
def test_a_diverging_run_keeps_its_snapshots_in_a_partial_file(tmp_path, capsys, model, parts):
    cfg = diverging_case(tmp_path, model)
    out = tmp_path / "div.h5"
    argv = ["simulate", str(cfg), "-o", str(out), "--no-progress"] + (["--parts", parts] if parts else [])
    assert main(argv) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[0].startswith("saved the ") and err[0].endswith(f"before divergence to {tmp_path / 'div.partial.h5'}")
    assert err[-1].startswith("error: ") and "Traceback" not in "\n".join(err)
    kept = jaxsync.Trajectory.load(tmp_path / "div.partial.h5")
    assert kept.result == jaxsync.Result.DIVERGED and kept.n_saved >= 1 and not out.exists()
    assert bool(np.isfinite(kept.displacement).all())
    # a second failure keeps the first one's snapshots and writes beside them
    first = (tmp_path / "div.partial.h5").read_bytes()
    assert main(argv) == 2
    assert (tmp_path / "div.partial.h5").read_bytes() == first and (tmp_path / "div.partial-2.h5").exists()


def test_train_and_report_refuse_earlier_results_without_force(tmp_path, capsys):
    from oscillator_trajectories import write_trajectory

    traj = write_trajectory(tmp_path / "run.h5", n_steps=120)
    train = ["train", str(traj), "-o", str(tmp_path / "out"), "--model", "linear", "--n-s", "2", "--n-past", "4",
             "--n-future", "3", "--emse-applications", "0", "--rollout-tolerance", "0", "--no-progress"]
    assert main(train) == 0
    capsys.readouterr()
    surrogate = (tmp_path / "out" / "surrogate.h5").read_bytes()
    assert main(train) == 2
    assert_one_error_line(capsys.readouterr().err, "surrogate.h5", "already exist", "--force")
    assert (tmp_path / "out" / "surrogate.h5").read_bytes() == surrogate
    assert main(train + ["--force"]) == 0
    # report: summary.json marks an earlier report; refused before the trajectories are read
    report = tmp_path / "report"
    report.mkdir()
    (report / "summary.json").write_text("{}")
    argv = ["report", str(tmp_path / "missing-ref.h5"), str(tmp_path / "missing-online.h5"), "-o", str(report)]
    assert main(argv) == 2
    assert_one_error_line(capsys.readouterr().err, "summary.json", "already exist", "--force")
    assert main(argv + ["--force"]) == 2  # now it gets as far as reading the (missing) trajectories
    assert_one_error_line(capsys.readouterr().err, "missing-ref.h5")
    assert (report / "summary.json").read_text() == "{}"


def test_an_output_is_never_one_of_the_commands_inputs(tmp_path, capsys):
    import meshio

    mesh = jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1))
    path = tmp_path / "beam.msh"
    meshio.write(path, meshio.Mesh(mesh.points, [("tetra", mesh.tets)]), file_format="gmsh")
    before = path.read_bytes()
    for target in (path, tmp_path / "." / "beam.msh"):
        assert main(["simulate", "--mesh", str(path), "-o", str(target), "--force", "--steps", "10"]) == 2
        assert_one_error_line(capsys.readouterr().err, "is also an input", "even with --force")
    cfg = small_case(tmp_path)
    assert main(["simulate", str(cfg), "-o", str(cfg), "--force"]) == 2
    assert_one_error_line(capsys.readouterr().err, "is also an input")
    assert main(["predict", str(tmp_path / "t.h5"), str(tmp_path / "s.h5"), "-o", str(tmp_path / "s.h5"),
                 "--force"]) == 2
    assert_one_error_line(capsys.readouterr().err, "is also an input")
    assert path.read_bytes() == before and cfg.exists()


def test_a_second_process_writing_the_same_output_stops_at_once(tmp_path, capsys, monkeypatch):
    import subprocess
    import sys

    cfg = small_case(tmp_path)
    out = tmp_path / "same.h5"
    owner = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:  # the lock of a live jaxsync process on this host
        from jaxsync.io import host_tag

        (tmp_path / ".same.h5.lock").write_text(f"{owner.pid}@{host_tag()}")
        monkeypatch.setattr("jaxsync.solve._solver.simulate", must_not_run)
        assert main(["simulate", str(cfg), "-o", str(out), "--no-progress"]) == 2
        assert_one_error_line(capsys.readouterr().err, "same.h5 is being written by another jaxsync process",
                              f"pid {owner.pid}")
        assert not out.exists() and (tmp_path / ".same.h5.lock").exists()  # the other's lock is left alone
    finally:
        owner.kill()
        owner.wait()
    monkeypatch.undo()
    # the lock of a process that is gone is taken over, and removed at the end
    assert main(["simulate", str(cfg), "-o", str(out), "--no-progress"]) == 0
    assert out.exists() and not (tmp_path / ".same.h5.lock").exists()


def test_a_file_that_appears_while_the_command_runs_is_never_replaced(tmp_path, capsys, monkeypatch):
    cfg = small_case(tmp_path)
    out = tmp_path / "r.h5"
    simulate = jaxsync.solve.simulate

    def another_writer_meanwhile(*args, **kwargs):
        out.write_text("another program's result")
        return simulate(*args, **kwargs)

    monkeypatch.setattr("jaxsync.solve._solver.simulate", another_writer_meanwhile)
    assert main(["simulate", str(cfg), "-o", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert_one_error_line(err, f"{out} appeared while this command ran", "r.conflict-1.h5")
    assert out.read_text() == "another program's result"
    assert jaxsync.Trajectory.load(tmp_path / "r.conflict-1.h5").n_saved == 3
    # with --force the command replaces it, as asked
    assert main(["simulate", str(cfg), "-o", str(out), "--no-progress", "--force"]) == 0
    assert jaxsync.Trajectory.load(out).n_saved == 3


def test_a_binary_file_given_as_configuration_is_one_error_line(tmp_path, capsys):
    binary = tmp_path / "sync.h5"
    binary.write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(range(256)))
    assert main(["simulate", str(binary)]) == 2
    assert_one_error_line(capsys.readouterr().err, "not a TOML text file")
    assert main(["predict", str(binary), str(binary), "--config", str(binary), "-o", str(tmp_path / "o.h5")]) == 2
    assert "Traceback" not in capsys.readouterr().err


def test_the_header_shows_the_step_the_run_uses(tmp_path, capsys):
    cfg = small_case(tmp_path)
    assert main(["simulate", str(cfg), "-o", str(tmp_path / "a.h5"), "--no-progress", "--dt", "1e-4"]) == 0
    out = capsys.readouterr().out
    default = float(jaxsync.cantilever(jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1))).dt)
    assert f"dt 1.0000e-04 s (given; the default would be {default:.4e} s" in out, out
    assert jaxsync.Trajectory.load(tmp_path / "a.h5").dt == 1e-4
    cfg.write_text(cfg.read_text().replace("[run]\n", "[run]\ndt = 2.0e-4\n"))
    assert main(["simulate", str(cfg), "-o", str(tmp_path / "b.h5"), "--no-progress"]) == 0
    assert "dt 2.0000e-04 s (given;" in capsys.readouterr().out


def test_options_that_would_be_ignored_are_refused(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("jaxsync.solve._solver.simulate", must_not_run)
    cfg = small_case(tmp_path)
    assert main(["simulate", str(cfg), "-o", str(tmp_path / "a.h5"), "--checkpoint-every", "100"]) == 2
    assert_one_error_line(capsys.readouterr().err, "--checkpoint-every 100 needs a checkpoint file")
    assert main(["simulate", str(cfg), "-o", str(tmp_path / "a.h5"), "--checkpoint", str(tmp_path / "c.h5"),
                 "--checkpoint-every", "0"]) == 2
    assert_one_error_line(capsys.readouterr().err, "SolverCheckpoint.every")
    monkeypatch.undo()
    hyper = tmp_path / "nh.toml"
    hyper.write_text(cfg.read_text() + '[material]\nmodel = "neo-hookean"\n')
    assert main(["simulate", str(hyper), "-o", str(tmp_path / "b.h5"), "--float32-blocks", "--no-progress"]) == 2
    assert_one_error_line(capsys.readouterr().err, "float32 stiffness blocks", "NeoHookean")


def test_an_output_under_a_file_is_said_as_such(tmp_path, capsys, afile):
    assert main(["simulate", str(small_case(tmp_path)), "-o", str(afile / "x.h5")]) == 2
    assert_one_error_line(capsys.readouterr().err, f"{afile} is a file, not a folder")


def test_a_trajectory_given_as_checkpoint_is_not_called_deletable(tmp_path, capsys):
    cfg = small_case(tmp_path)
    run = tmp_path / "run.h5"
    assert main(["simulate", str(cfg), "-o", str(run), "--no-progress"]) == 0
    capsys.readouterr()
    before = run.read_bytes()
    assert main(["simulate", str(cfg), "-o", str(tmp_path / "b.h5"), "--checkpoint", str(run), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert_one_error_line(err, "is a jaxsync trajectory (a run's output), not a solver checkpoint")
    assert "delete" not in err and run.read_bytes() == before


def test_a_failed_command_removes_only_the_folders_it_made(tmp_path, capsys, monkeypatch):
    work = tmp_path / "empty" / "work"
    work.mkdir(parents=True)  # empty folders of the user's: they stay
    monkeypatch.chdir(work)
    assert main(["report", "missing.h5", "missing.h5", "-o", "rep/sub"]) == 2
    assert_one_error_line(capsys.readouterr().err, "missing.h5")
    assert work.is_dir() and not any(work.iterdir())


def test_ctrl_c_says_how_each_command_resumes_and_only_where_it_can():
    from jaxsync.cli import resume_hint

    parse = build_parser().parse_args
    assert "resumes from the checkpoint c.h5" in resume_hint(parse(["simulate", "--checkpoint", "c.h5"]))
    assert "--checkpoint PATH" in resume_hint(parse(["simulate"]))
    assert resume_hint(parse(["predict", "t.h5", "s.h5"])) == ""
    assert resume_hint(parse(["report", "a.h5", "b.h5"])) == ""
    assert "training_state.h5" in resume_hint(parse(["train", "t.h5", "-o", "out", "--state-every", "5"]))
    assert resume_hint(parse(["train", "t.h5", "-o", "out", "--state-every", "0"])) == ""


def test_a_second_demo_into_the_same_folder_stops_at_once(tmp_path, capsys):
    import subprocess
    import sys

    from jaxsync.io import host_tag

    owner = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (tmp_path / ".demo.lock").write_text(f"{owner.pid}@{host_tag()}")
        assert main(["demo", "-o", str(tmp_path / "demo"), "--no-progress"]) == 2
        assert_one_error_line(capsys.readouterr().err, "demo is being written by another jaxsync process")
        assert not (tmp_path / "demo").exists()
    finally:
        owner.kill()
        owner.wait()
