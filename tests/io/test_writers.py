"""Output writers: the registry (jaxsync.io.writers), the staged multi-file writes every writer
gets (jaxsync.io.staged_outputs), XDMF without os.chdir, the guide's worked example, and
jaxsync simulate writing its formats through the registry."""

from __future__ import annotations

import os
import re
import threading
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import h5py
import meshio
import numpy as np
import pytest

import jaxsync
from jaxsync.cli import main
from jaxsync.errors import OutputError
from jaxsync.io import OutputFile, claim_output, claimed_outputs, host_tag
from jaxsync.io.writers import (
    Hdf5Writer,
    OutputWriter,
    VtuWriter,
    XdmfWriter,
    register_writer,
    registered_writers,
    unregister_writer,
    write_output,
    writer_for,
)

GUIDE = Path(__file__).resolve().parents[2] / "docs" / "guides" / "extending-output.md"


@pytest.fixture(scope="module")
def trajectory():
    problem = jaxsync.cantilever(jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1)), body_force=(0.0, 0.0, -50.0),
                                 t_ramp=0.01)
    return jaxsync.simulate(problem, 60, save=20)


@pytest.fixture
def registry():
    """The registry as it was, restored after the test (the tests register writers)."""
    before = registered_writers()
    yield
    for name in set(registered_writers()) - set(before):
        unregister_writer(name)
    for name, writer in before.items():
        register_writer(name, writer, replace=True)


class TextWriter(OutputWriter):
    """Writes the given lines to one file, optionally failing after the first part."""

    suffixes = (".txt",)
    description = "text"

    def __init__(self, text="new", fail=False):
        self.text, self.fail = text, fail

    def write(self, trajectory, path, staged):
        with open(staged.path(path), "w") as f:
            f.write(self.text[:2])
            if self.fail:
                raise OSError(28, "No space left on device")
            f.write(self.text[2:])


class PairWriter:
    """Two files, the index naming the data file; fails on the index if asked."""

    suffixes = (".idx",)
    description = "index and data"

    def __init__(self, fail_on_index=False, stray=None):
        self.fail_on_index, self.stray = fail_on_index, stray

    def outputs(self, path):
        return OutputFile(path + ".dat", "data"), OutputFile(path, "index")

    def write(self, trajectory, path, staged):
        with open(staged.path(path + ".dat"), "w") as f:
            f.write(f"{trajectory.n_saved}")
        if self.stray:
            staged.path(self.stray)
        if self.fail_on_index:
            raise OSError(28, "No space left on device")
        with open(staged.path(path), "w") as f:
            f.write(os.path.basename(path) + ".dat")


# --- the registry -------------------------------------------------------------------------

def test_builtin_writers_by_name_and_by_suffix():
    assert isinstance(writer_for("xdmf"), XdmfWriter) and isinstance(writer_for("out/run.xdmf"), XdmfWriter)
    assert isinstance(writer_for("vtu"), VtuWriter) and isinstance(writer_for("out/run.pvd"), VtuWriter)
    assert isinstance(writer_for("hdf5"), Hdf5Writer) and isinstance(writer_for("run.h5"), Hdf5Writer)
    assert writer_for("run.hdf5") is writer_for("hdf5")
    mine = XdmfWriter(every=2)
    assert writer_for(mine) is mine
    with pytest.raises(OutputError, match=r"no output writer for 'run\.csv'.*xdmf \(\.xdmf\).*vtu \(\.pvd\)"):
        writer_for("run.csv")


def test_registration_refuses_clashes_and_non_writers(registry):
    with pytest.raises(OutputError, match="'xdmf' is registered already"):
        register_writer("xdmf", TextWriter())
    with pytest.raises(OutputError, match=r"the suffix \.pvd is claimed by the writer 'vtu'"):
        register_writer("paraview", VtuWriter())
    with pytest.raises(OutputError, match="is not a writer"):
        register_writer("nothing", object())
    with pytest.raises(OutputError, match="a word"):
        register_writer("a.b", TextWriter())
    register_writer("text", TextWriter())
    assert isinstance(writer_for("notes.txt"), TextWriter) and "text" in registered_writers()
    unregister_writer("text")
    with pytest.raises(OutputError, match="no output writer"):
        writer_for("notes.txt")


def test_the_longest_claimed_suffix_wins(registry):
    class XdmfData(TextWriter):
        suffixes = (".xdmf.h5",)

    register_writer("xdmf-data", XdmfData())
    assert isinstance(writer_for("run.xdmf.h5"), XdmfData) and isinstance(writer_for("run.h5"), Hdf5Writer)


# --- the guarantees every writer gets --------------------------------------------------------

def test_a_writer_that_fails_leaves_the_earlier_file_and_no_temporary(trajectory, tmp_path):
    target = tmp_path / "notes.txt"
    assert write_output(trajectory, tmp_path / "notes", TextWriter("first")) == str(target)  # suffix added
    assert target.read_text() == "first"
    with pytest.raises(OutputError, match=r"could not write .*notes\.txt: No space left on device"):
        write_output(trajectory, target, TextWriter("second", fail=True))
    assert target.read_text() == "first" and os.listdir(tmp_path) == ["notes.txt"]
    with pytest.raises(KeyboardInterrupt):
        write_output(trajectory, target, _Interrupting())
    assert target.read_text() == "first" and os.listdir(tmp_path) == ["notes.txt"]


class _Interrupting(TextWriter):
    def write(self, trajectory, path, staged):
        open(staged.path(path), "w").write("half")
        raise KeyboardInterrupt


def test_overwrite_false_keeps_the_existing_file_and_writes_beside_it(trajectory, tmp_path):
    target = tmp_path / "notes.txt"
    target.write_text("mine")
    with pytest.raises(OutputError, match=r"notes\.txt exists and overwrite=False.*notes\.conflict-1\.txt"):
        write_output(trajectory, target, TextWriter("new"), overwrite=False)
    assert target.read_text() == "mine" and (tmp_path / "notes.conflict-1.txt").read_text() == "new"
    write_output(trajectory, target, TextWriter("newer"))  # the default replaces
    assert target.read_text() == "newer"


def test_several_files_appear_together_or_not_at_all(trajectory, tmp_path):
    index = tmp_path / "run.idx"
    write_output(trajectory, index, PairWriter())
    assert index.read_text() == "run.idx.dat" and (tmp_path / "run.idx.dat").read_text() == str(trajectory.n_saved)
    index.write_text("earlier index")
    (tmp_path / "run.idx.dat").write_text("earlier data")
    with pytest.raises(OutputError, match=r"could not write .*run\.idx: No space"):
        write_output(trajectory, index, PairWriter(fail_on_index=True))
    assert index.read_text() == "earlier index" and (tmp_path / "run.idx.dat").read_text() == "earlier data"
    assert sorted(os.listdir(tmp_path)) == ["run.idx", "run.idx.dat"]


def test_a_failed_commit_puts_back_what_it_replaced(trajectory, tmp_path, monkeypatch):
    """The data file is in place when the index cannot be renamed: the earlier data come back."""
    import jaxsync.io.atomic as io_module

    index = tmp_path / "run.idx"
    index.write_text("earlier index")
    (tmp_path / "run.idx.dat").write_text("earlier data")
    real = io_module._commit

    def failing_commit(tmp, path, replace=True):
        if path.endswith(".idx"):
            raise OSError(28, "No space left on device")
        real(tmp, path, replace)

    monkeypatch.setattr(io_module, "_commit", failing_commit)
    with pytest.raises(OutputError, match="No space"):
        write_output(trajectory, index, PairWriter())
    assert index.read_text() == "earlier index" and (tmp_path / "run.idx.dat").read_text() == "earlier data"
    assert sorted(os.listdir(tmp_path)) == ["run.idx", "run.idx.dat"]


def test_a_writer_may_write_only_what_it_declares(trajectory, tmp_path):
    with pytest.raises(OutputError, match=r"other\.bin is not an output of this write"):
        write_output(trajectory, tmp_path / "run.idx", PairWriter(stray=str(tmp_path / "other.bin")))
    assert os.listdir(tmp_path) == []


def test_claimed_outputs_are_not_replaced_when_they_appear_meanwhile(trajectory, tmp_path):
    """As atomic_path: a file another program wrote after the command claimed it is kept."""
    target = tmp_path / "notes.txt"
    with claimed_outputs():
        claim_output(target, replace=False)
        target.write_text("another program's")
        with pytest.raises(OutputError, match="appeared while this command ran"):
            write_output(trajectory, target, TextWriter("ours"))
    assert target.read_text() == "another program's"
    assert (tmp_path / "notes.conflict-1.txt").read_text() == "ours"


def test_a_staging_folder_of_a_dead_writer_is_removed_by_the_next_write(trajectory, tmp_path):
    import subprocess
    import sys

    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    stale = tmp_path / f".notes.txt.{child.pid}@{host_tag()}.abcd1234.stage"
    live = tmp_path / f".notes.txt.{os.getpid()}@{host_tag()}.efgh5678.stage"
    for folder in (stale, live):
        folder.mkdir()
        (folder / "notes.txt").write_text("half")
    write_output(trajectory, tmp_path / "notes.txt", TextWriter("new"))
    assert not stale.exists() and live.exists()
    assert (tmp_path / "notes.txt").read_text() == "new"


# --- the built-in writers through the registry -------------------------------------------------

def test_hdf5_writer_writes_what_load_reads(trajectory, tmp_path):
    path = write_output(trajectory, tmp_path / "run.h5")
    back = jaxsync.Trajectory.load(path)
    np.testing.assert_array_equal(back.displacement, trajectory.displacement)
    np.testing.assert_array_equal(back.times, trajectory.times)
    with h5py.File(path) as f:
        assert f["displacement"].compression == "gzip"
    write_output(trajectory, tmp_path / "plain.h5", Hdf5Writer(compression=None))
    with h5py.File(tmp_path / "plain.h5") as f:
        assert f["displacement"].compression is None


def test_vtu_writer_through_the_registry_reads_back(trajectory, tmp_path):
    pvd = write_output(trajectory, tmp_path / "out" / "run", "vtu")
    assert pvd == str(tmp_path / "out" / "run.pvd")
    assert sorted(os.listdir(tmp_path / "out")) == ["run", "run.pvd"]
    files = [d.get("file") for d in ET.parse(pvd).getroot().iter("DataSet")]
    assert len(files) == trajectory.n_saved
    for i, name in enumerate(files):
        step = meshio.read(tmp_path / "out" / name)
        np.testing.assert_array_equal(step.points, trajectory.mesh.points)
        np.testing.assert_array_equal(step.point_data["displacement"], trajectory.displacement[i])


def _read_xdmf(path):
    with meshio.xdmf.TimeSeriesReader(str(path)) as reader:
        points, cells = reader.read_points_cells()
        steps = [reader.read_data(k) for k in range(reader.num_steps)]
    return points, cells, steps


def _assert_xdmf_holds(path, trajectory, every=1):
    points, cells, steps = _read_xdmf(path)
    np.testing.assert_array_equal(points, trajectory.mesh.points)
    assert [(c.type, c.data.tolist()) for c in cells] == [("tetra", trajectory.mesh.tets.tolist())]
    kept = range(0, trajectory.n_saved, every)
    assert len(steps) == len(kept)
    for (t, point_data, _), i in zip(steps, kept):
        assert t == float(trajectory.times[i])
        np.testing.assert_array_equal(point_data["displacement"], trajectory.displacement[i])


def test_xdmf_never_changes_the_working_directory(trajectory, tmp_path, monkeypatch):
    def no_chdir(path):
        raise AssertionError(f"os.chdir({path!r}) during an XDMF write")

    (tmp_path / "cwd").mkdir()
    monkeypatch.chdir(tmp_path / "cwd")  # where meshio's own writer would put run.h5
    cwd = os.getcwd()
    monkeypatch.setattr(os, "chdir", no_chdir)
    data = trajectory.to_xdmf(tmp_path / "a" / "run.xdmf")
    assert write_output(trajectory, tmp_path / "b" / "run", "xdmf") == str(tmp_path / "b" / "run.xdmf")
    write_output(trajectory, tmp_path / "c" / "thin.xdmf", XdmfWriter(every=2))
    assert os.getcwd() == cwd and os.listdir(cwd) == [] and data == str(tmp_path / "a" / "run.xdmf.h5")
    for folder in "ab":
        assert sorted(os.listdir(tmp_path / folder)) == ["run.xdmf", "run.xdmf.h5"]
        _assert_xdmf_holds(tmp_path / folder / "run.xdmf", trajectory)
    _assert_xdmf_holds(tmp_path / "c" / "thin.xdmf", trajectory, every=2)


def test_xdmf_in_a_thread_while_the_main_thread_watches_the_working_directory(trajectory, tmp_path):
    cwd, seen, errors = os.getcwd(), set(), []

    def write():
        try:
            for k in range(3):
                trajectory.to_xdmf(tmp_path / f"run{k}.xdmf")
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    thread = threading.Thread(target=write)
    thread.start()
    while thread.is_alive():
        seen.add(os.getcwd())
        time.sleep(0)
    thread.join()
    assert not errors and seen <= {cwd}
    _assert_xdmf_holds(tmp_path / "run2.xdmf", trajectory)


def test_the_xdmf_names_its_data_relative_so_the_pair_moves_together(trajectory, tmp_path):
    trajectory.to_xdmf(tmp_path / "run.xdmf")
    references = set(re.findall(r">([^<>]*):/", (tmp_path / "run.xdmf").read_text()))
    assert references == {"run.xdmf.h5"}
    moved = tmp_path / "elsewhere"
    moved.mkdir()
    for name in ("run.xdmf", "run.xdmf.h5"):
        os.rename(tmp_path / name, moved / name)
    _assert_xdmf_holds(moved / "run.xdmf", trajectory)


def test_a_failed_xdmf_write_leaves_the_earlier_pair(trajectory, tmp_path, monkeypatch):
    import sys

    import jaxsync.io.writers

    # the module that holds the XDMF writer (white box: its series writer fails half-way)
    xdmf_module = sys.modules[jaxsync.io.writers.XdmfWriter.__module__]
    trajectory.to_xdmf(tmp_path / "run.xdmf")
    before = {n: (tmp_path / n).read_bytes() for n in ("run.xdmf", "run.xdmf.h5")}

    def full_disk(path, data_path, *args, **kwargs):
        open(data_path, "wb").write(b"half")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(xdmf_module, "write_xdmf_series", full_disk)
    with pytest.raises(OutputError, match=r"could not write .*run\.xdmf: No space left on device"):
        write_output(trajectory, tmp_path / "run.xdmf")
    assert {n: (tmp_path / n).read_bytes() for n in ("run.xdmf", "run.xdmf.h5")} == before
    assert sorted(os.listdir(tmp_path)) == ["run.xdmf", "run.xdmf.h5"]


# --- the guide's worked example -----------------------------------------------------------

def _guide_writer_block() -> str:
    """The guide's first python block that defines a writer (the code, as the page shows it)."""
    blocks = re.findall(r"```python\n(.*?)```", GUIDE.read_text(), re.S)
    return next(b for b in blocks if "register_writer(" in b)


def test_the_guides_npz_writer_writes_the_trajectory(registry, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(_guide_writer_block(), str(GUIDE), "exec"), namespace)  # registers "npz", writes one
    trajectory = namespace["trajectory"]
    assert isinstance(writer_for("npz"), namespace["NpzWriter"])
    archive = np.load(tmp_path / "cantilever.npz")
    np.testing.assert_array_equal(archive["times"], np.asarray(trajectory.times))
    np.testing.assert_array_equal(archive["points"], np.asarray(trajectory.mesh.points))
    np.testing.assert_array_equal(archive["displacement"], np.asarray(trajectory.displacement))
    # by name, with the suffix added, and with the guarantees: a failed write keeps the file
    assert write_output(trajectory, "again", "npz") == "again.npz"
    assert os.path.exists("again.npz")
    before = Path("cantilever.npz").read_bytes()
    monkeypatch.setattr(np, "savez", lambda *a, **k: (_ for _ in ()).throw(OSError(28, "No space left on device")))
    with pytest.raises(OutputError, match="cantilever.npz: No space"):
        write_output(trajectory, "cantilever.npz")
    assert Path("cantilever.npz").read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["again.npz", "cantilever.npz"]


# --- the command line writes its formats through the registry -----------------------------------

def test_simulate_writes_xdmf_and_vtu_through_the_registry(registry, tmp_path, capsys):
    calls = []

    class RecordingXdmf(XdmfWriter):
        def write(self, trajectory, path, staged):
            calls.append(path)
            super().write(trajectory, path, staged)

    register_writer("xdmf", RecordingXdmf(), replace=True)
    cfg = tmp_path / "bar.toml"
    cfg.write_text("[mesh]\nlength = 4.0\ndivisions = [4, 1, 1]\n[run]\nn_steps = 20\nsave_every = 10\n")
    assert main(["simulate", str(cfg), "-o", str(tmp_path / "run.h5"), "--xdmf", str(tmp_path / "run"),
                 "--vtu", str(tmp_path / "series"), "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert calls == [str(tmp_path / "run.xdmf")]
    assert f"wrote {tmp_path / 'run.xdmf'} (with {tmp_path / 'run.xdmf.h5'})" in out
    assert f"wrote {tmp_path / 'series.pvd'} (with {tmp_path / 'series'})" in out
    traj = jaxsync.Trajectory.load(tmp_path / "run.h5")
    _assert_xdmf_holds(tmp_path / "run.xdmf", traj)
    assert sorted(os.listdir(tmp_path / "series")) == ["series_000000.vtu", "series_000001.vtu",
                                                       "series_000002.vtu"]
