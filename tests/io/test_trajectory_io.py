import os

import meshio
import numpy as np
import pytest

import jaxsync
from jaxsync import CheckpointError
from jaxsync.io import atomic_path
from jaxsync.io.trajectory import PartHistory


@pytest.fixture(scope="module")
def trajectory():
    return jaxsync.simulate(jaxsync.cantilever(), 500, save=50)


def test_hdf5_round_trip(trajectory, tmp_path):
    path = tmp_path / "t.h5"
    trajectory.save(path)
    back = jaxsync.Trajectory.load(path)
    np.testing.assert_array_equal(back.displacement, trajectory.displacement)
    np.testing.assert_array_equal(back.times, trajectory.times)
    np.testing.assert_array_equal(back.mesh.points, trajectory.mesh.points)
    np.testing.assert_array_equal(back.mesh.tets, trajectory.mesh.tets)
    assert set(back.mesh.facet_sets) == set(trajectory.mesh.facet_sets)
    assert back.dt == trajectory.dt and back.save_every == 50
    assert back.parameters == trajectory.parameters
    assert {k: back.parameters[k] for k in ("E", "nu", "rho", "damping")} == {
        "E": 1.0e6, "nu": 0.3, "rho": 1.0, "damping": 0.5}
    assert back.stats == trajectory.stats  # run statistics, apart from the physics
    assert back.stats.us_per_step > 0 and back.stats.n_devices == 1 and back.stats.n_processes == 1


def test_stats_of_a_file_written_before_process_counts_load(trajectory, tmp_path):
    """Files of a jaxsync that stored no ``stat_n_processes`` still load (it is None);
    a count of several processes round-trips."""
    import dataclasses

    import h5py

    path = tmp_path / "t.h5"
    dataclasses.replace(trajectory, stats=trajectory.stats.merged(n_devices=4, n_processes=2)).save(path)
    assert jaxsync.Trajectory.load(path).stats.n_processes == 2
    with h5py.File(path, "r+") as f:
        del f.attrs["stat_n_processes"]
    back = jaxsync.Trajectory.load(path)
    assert back.stats.n_processes is None and back.stats.n_devices == 4


def test_parts_round_trip(trajectory, tmp_path):
    import dataclasses

    parts = (PartHistory(np.array([3, 4]), np.array([0]), np.ones((11, 6))),
             PartHistory(np.array([4]), np.array([1]), np.zeros((11, 3))))
    with_parts = dataclasses.replace(trajectory, parts=parts)
    with_parts.save(tmp_path / "p.h5")
    back = jaxsync.Trajectory.load(tmp_path / "p.h5")
    assert len(back.parts) == 2
    np.testing.assert_array_equal(back.parts[0].shared_nodes, [3, 4])
    np.testing.assert_array_equal(back.parts[1].shared_displacement, np.zeros((11, 3)))


def test_failed_write_keeps_the_old_file(trajectory, tmp_path):
    import dataclasses

    path = tmp_path / "t.h5"
    trajectory.save(path)
    before = path.read_bytes()
    broken = dataclasses.replace(trajectory, displacement=np.array([object()]))
    with pytest.raises(Exception):
        broken.save(path)
    assert path.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["t.h5"]  # no temporary left behind


def test_atomic_path_removes_temporary_on_error(tmp_path):
    target = tmp_path / "x.txt"
    target.write_text("good")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            open(tmp, "w").write("half")
            raise RuntimeError("boom")
    assert target.read_text() == "good"
    assert os.listdir(tmp_path) == ["x.txt"]


def test_load_rejects_other_files(tmp_path):
    with pytest.raises(CheckpointError, match="does not exist"):
        jaxsync.Trajectory.load(tmp_path / "missing.h5")
    (tmp_path / "junk.h5").write_bytes(b"junk")
    with pytest.raises(CheckpointError, match="cannot read"):
        jaxsync.Trajectory.load(tmp_path / "junk.h5")
    import h5py

    with h5py.File(tmp_path / "other.h5", "w") as f:
        f["x"] = 1
    with pytest.raises(CheckpointError, match="not a jaxsync trajectory"):
        jaxsync.Trajectory.load(tmp_path / "other.h5")


def test_xdmf_time_series_is_readable_and_does_not_clobber(trajectory, tmp_path):
    trajectory.save(tmp_path / "run.h5")
    before = (tmp_path / "run.h5").read_bytes()
    data = trajectory.to_xdmf(tmp_path / "run.xdmf")
    assert (tmp_path / "run.h5").read_bytes() == before  # the trajectory file is untouched
    assert os.path.basename(data) == "run.xdmf.h5"
    assert sorted(os.listdir(tmp_path)) == ["run.h5", "run.xdmf", "run.xdmf.h5"]
    cwd = os.getcwd()
    os.chdir(tmp_path)  # meshio's reader resolves the data file relative to the cwd
    try:
        with meshio.xdmf.TimeSeriesReader("run.xdmf") as reader:
            points, cells = reader.read_points_cells()
            assert reader.num_steps == trajectory.n_saved
            for k in (0, 5, trajectory.n_saved - 1):
                t, point_data, _ = reader.read_data(k)
                assert t == pytest.approx(float(trajectory.times[k]))
                np.testing.assert_array_equal(point_data["displacement"], trajectory.displacement[k])
    finally:
        os.chdir(cwd)
    np.testing.assert_array_equal(points, trajectory.mesh.points)


def test_vtu_to_an_unwritable_location_is_an_output_error_naming_it(trajectory, tmp_path):
    """``to_vtu("/proc/x")`` raised a raw FileNotFoundError from making its staging folder."""
    from jaxsync.io import OutputError

    if os.path.isdir("/proc"):
        with pytest.raises(OutputError, match=r"could not write /proc/x.pvd: .*choose another location"):
            trajectory.to_vtu("/proc/x")
    (tmp_path / "afile").write_text("keep")
    with pytest.raises(OutputError, match="afile"):
        trajectory.to_vtu(tmp_path / "afile" / "run")
    assert os.listdir(tmp_path) == ["afile"] and (tmp_path / "afile").read_text() == "keep"


def test_xdmf_to_an_unwritable_location_is_an_output_error_naming_it(trajectory, tmp_path):
    """``to_xdmf("/proc/x.xdmf")`` raised a raw FileNotFoundError naming a temporary file."""
    from jaxsync.io import OutputError

    if os.path.isdir("/proc"):
        with pytest.raises(OutputError, match="/proc/x.xdmf") as caught:
            trajectory.to_xdmf("/proc/x.xdmf")
        assert ".xdmf." not in str(caught.value).replace("/proc/x.xdmf", "")  # no temporary name
    (tmp_path / "afile").write_text("keep")
    with pytest.raises(OutputError, match="afile is a file, not a folder"):
        trajectory.to_xdmf(tmp_path / "afile" / "run.xdmf")
    (tmp_path / "taken.xdmf").mkdir()
    with pytest.raises(OutputError, match="it is a folder"):
        trajectory.to_xdmf(tmp_path / "taken.xdmf")
    assert sorted(os.listdir(tmp_path)) == ["afile", "taken.xdmf"] and (tmp_path / "afile").read_text() == "keep"


def test_a_folder_given_as_a_file_to_read_is_one_clear_line(tmp_path, capsys):
    """A folder as a trajectory (``Trajectory.load``, ``jaxsync report``, ``jaxsync train``),
    a surrogate file, a training state or a solver checkpoint: one line that says so, not
    h5py's two-line reason."""
    from jaxsync.cli import main
    from jaxsync.io.checkpoint import load_checkpoint
    from jaxsync.io.surrogate_file import load_surrogate
    from jaxsync.surrogate.training import load_training_state

    folder = tmp_path / "adir"
    folder.mkdir()
    with pytest.raises(CheckpointError) as caught:
        jaxsync.Trajectory.load(folder)
    assert str(caught.value) == f"trajectory {str(folder)!r} is a folder; give a .h5 file"
    for call, what in ((lambda: load_surrogate(folder), "surrogate file"),
                       (lambda: load_training_state(folder, {}, None), "training state"),
                       (lambda: load_checkpoint(folder, "key", 10), "checkpoint")):
        with pytest.raises(CheckpointError, match=f"^{what} .* is a folder; give a .h5 file") as caught:
            call()
        assert "\n" not in str(caught.value)
    capsys.readouterr()
    for argv in (["report", str(folder), str(folder), "-o", str(tmp_path / "r")],
                 ["train", str(folder), "-o", str(tmp_path / "sur"), "--no-progress"]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err == f"error: trajectory {str(folder)!r} is a folder; give a .h5 file\n", err
    assert sorted(os.listdir(tmp_path)) == ["adir"]


def dead_pid():
    import subprocess
    import sys

    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def test_stale_temporaries_of_dead_writers_are_removed(tmp_path):
    import time

    from jaxsync.io import STALE_TEMP_AGE_S, host_tag

    host = host_tag()
    files = {
        # (name, age in s) -> kept?
        (f".t.h5.{dead_pid()}@{host}.abcd1234.tmp", 0): False,  # writer gone
        (f".t.h5.{os.getpid()}@{host}.abcd1234.tmp", 0): True,  # live writer (this one)
        (f".t.h5.{os.getppid()}@{host}.abcd1234.tmp", 2 * STALE_TEMP_AGE_S): True,  # live, idle
        (".t.h5.1234@another-host.abcd1234.tmp", 0): True,  # cannot check: recent, kept
        (".t.h5.1234@another-host.efgh5678.tmp", 2 * STALE_TEMP_AGE_S): False,  # abandoned
        (".t.h5.k2j4h1x_.tmp", 2 * STALE_TEMP_AGE_S): False,  # older jaxsync, abandoned
        (".t.h5.q9w8e7r6.tmp", 0): True,  # older jaxsync, maybe still writing
        (f".t.h5.x.{dead_pid()}@{host}.abcd1234.tmp", 0): True,  # target "t.h5.x"
        (f".u.h5.{dead_pid()}@{host}.abcd1234.tmp", 0): True,  # another target
    }
    for (name, age), _ in files.items():
        (tmp_path / name).write_bytes(b"half a file")
        if age:
            os.utime(tmp_path / name, (time.time() - age, time.time() - age))
    with atomic_path(tmp_path / "t.h5") as tmp:
        assert f".t.h5.{os.getpid()}@{host}." in os.path.basename(tmp)
        open(tmp, "w").write("new")
    left = set(os.listdir(tmp_path))
    assert (tmp_path / "t.h5").read_text() == "new"
    for (name, _), kept in files.items():
        assert (name in left) == kept, name


def test_temporary_of_a_killed_writer_is_removed_by_the_next_write(tmp_path):
    import signal
    import subprocess
    import sys

    target = tmp_path / "big.h5"
    target.write_text("good")
    script = ("import sys, time\n"
              "from jaxsync.io import atomic_path\n"
              "with atomic_path(sys.argv[1]) as tmp:\n"
              "    open(tmp, 'wb').write(b'x' * 100000)\n"
              "    print('writing', flush=True)\n"
              "    time.sleep(120)\n")
    child = subprocess.Popen([sys.executable, "-c", script, str(target)], stdout=subprocess.PIPE,
                             text=True)
    try:
        assert child.stdout.readline().strip() == "writing"
    finally:
        child.send_signal(signal.SIGKILL)
        child.wait(timeout=60)
    stale = [n for n in os.listdir(tmp_path) if n.endswith(".tmp")]
    assert len(stale) == 1 and stale[0].startswith(f".big.h5.{child.pid}@")
    assert target.read_text() == "good"  # the killed write did not touch the target
    with atomic_path(target) as tmp:
        open(tmp, "w").write("newer")
    assert sorted(os.listdir(tmp_path)) == ["big.h5"]
    assert target.read_text() == "newer"


@pytest.mark.parametrize("compression", ["gzip", "lzf", None])
def test_compression_options_round_trip(tmp_path, compression):
    import h5py

    problem = jaxsync.cantilever()
    traj = jaxsync.simulate(problem, 400, save=jaxsync.SaveAt(10, 1), partitions=2)
    path = tmp_path / f"{compression}.h5"
    traj.save(path, compression=compression)
    back = jaxsync.Trajectory.load(path)
    np.testing.assert_array_equal(back.displacement, traj.displacement)
    np.testing.assert_array_equal(back.parts[0].shared_displacement, traj.parts[0].shared_displacement)
    assert back.shared_every == 1 and back.stats.n_devices == traj.stats.n_devices
    with h5py.File(path) as f:
        assert f["displacement"].compression == compression


def test_bad_compression_is_refused(tmp_path):
    traj = jaxsync.simulate(jaxsync.cantilever(), 10)
    with pytest.raises(jaxsync.CheckpointError, match="compression"):
        traj.save(tmp_path / "x.h5", compression="zip")
    with pytest.raises(jaxsync.CheckpointError, match="level"):
        traj.save(tmp_path / "x.h5", level=12)
    assert not (tmp_path / "x.h5").exists()


def test_a_diverged_runs_snapshots_can_be_saved(tmp_path):
    problem = jaxsync.cantilever(jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1)), body_force=(0.0, 0.0, -1.0e12),
                                 t_ramp=1e-3)
    for partitions in (None, 2):
        with pytest.raises(jaxsync.StabilityError) as caught:
            jaxsync.simulate(problem, 400, save=10, partitions=partitions)
        kept = caught.value.trajectory
        assert kept.result == jaxsync.Result.DIVERGED and kept.n_saved >= 1
        path = tmp_path / f"kept-{partitions}.h5"
        kept.save(path)  # the snapshots the message promises
        back = jaxsync.Trajectory.load(path)
        np.testing.assert_array_equal(back.displacement, kept.displacement)
        assert back.result == jaxsync.Result.DIVERGED and np.isfinite(back.displacement).all()
    assert jaxsync.Trajectory(times=np.zeros(1), displacement=np.zeros((1, 20, 3)), mesh=problem.mesh, dt=1e-4,
                              stats=None).stats == jaxsync.RunStats()


def test_save_replaces_by_default_and_refuses_with_overwrite_false(trajectory, tmp_path):
    from jaxsync.io import OutputError

    path = tmp_path / "t.h5"
    trajectory.save(path)
    first = path.read_bytes()
    trajectory.save(path)  # documented: replaces, atomically
    with pytest.raises(OutputError, match="exists and overwrite=False"):
        trajectory.save(path, overwrite=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.h5"] and path.read_bytes() == first
    # a file that another process writes while this one writes is kept; ours goes beside it
    from jaxsync.io import atomic_path

    other = tmp_path / "o.h5"
    with pytest.raises(OutputError, match="o.conflict-1.h5"):
        with atomic_path(other, replace=False) as tmp:
            open(tmp, "w").write("ours")
            other.write_text("theirs")
    assert other.read_text() == "theirs" and (tmp_path / "o.conflict-1.h5").read_text() == "ours"
