import os

import meshio
import numpy as np
import pytest

import jaxsync
from jaxsync import CheckpointError
from jaxsync.trajectory import atomic_path


@pytest.fixture(scope="module")
def trajectory():
    return jaxsync.simulate(jaxsync.cantilever(), 500, save_every=50)


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
    assert back.parameters["us_per_step"] > 0


def test_parts_round_trip(trajectory, tmp_path):
    import dataclasses

    parts = ({"shared_nodes": np.array([3, 4]), "shared_displacement": np.ones((11, 6))},
             {"shared_nodes": np.array([4]), "shared_displacement": np.zeros((11, 3))})
    with_parts = dataclasses.replace(trajectory, parts=parts)
    with_parts.save(tmp_path / "p.h5")
    back = jaxsync.Trajectory.load(tmp_path / "p.h5")
    assert len(back.parts) == 2
    np.testing.assert_array_equal(back.parts[0]["shared_nodes"], [3, 4])
    np.testing.assert_array_equal(back.parts[1]["shared_displacement"], np.zeros((11, 3)))


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
