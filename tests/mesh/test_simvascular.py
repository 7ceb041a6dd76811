"""SimVascular mesh folders in (``read_mesh(folder)``, ``read_mesh(volume, faces=...)``),
VTU series out (``Trajectory.to_vtu``), and both through ``jaxsync simulate``.

The folders are written here: the box beam's volume with meshio (``GlobalNodeID``,
``GlobalElementID``), its six faces as VTK XML PolyData by :func:`write_vtp` below, an
encoder of its own (meshio writes no ``.vtp``), in the encodings VTK writes: appended raw
zlib-compressed data (what SimVascular writes), inline base64, ASCII, 32/64-bit headers,
either byte order. The node order of the volume and of every face is shuffled, so that a
wrong mapping cannot pass."""

import base64
import os
import xml.etree.ElementTree as ET
import zlib

import meshio
import numpy as np
import pytest

import jaxsync
from jaxsync import MeshError, OutputError
from jaxsync.cli import main
from jaxsync.mesh import simvascular

BLOCK = 48  # bytes per compressed block: small, so that arrays span several blocks


# ---------------------------------------------------------------------------------------
# writing SimVascular folders


def _encode(values: np.ndarray, fmt: str, compress: bool, header: str, order: str):
    """(header bytes, payload bytes) of one array as VTK writes it."""
    hdt = np.dtype(order + {"UInt32": "u4", "UInt64": "u8"}[header])
    raw = np.ascontiguousarray(values).tobytes()
    if not compress:
        return np.array([len(raw)], hdt).tobytes(), raw
    blocks = [raw[i:i + BLOCK] for i in range(0, len(raw), BLOCK)]
    packed = [zlib.compress(b) for b in blocks]
    last = len(blocks[-1]) if blocks else 0
    head = np.array([len(blocks), BLOCK, last] + [len(p) for p in packed], hdt).tobytes()
    return head, b"".join(packed)


_VTK_NAMES = {"i4": "Int32", "i8": "Int64", "f4": "Float32", "f8": "Float64", "u1": "UInt8"}


def write_vtp(path, points, polys, point_data=None, cell_data=None, *, fmt="appended",
              compress=True, header="UInt32", order="<", lines=None):
    """A VTK XML PolyData file: ``polys`` a list of node lists (triangles, quads...),
    optional ``lines``; ``fmt`` "ascii", "binary" (inline base64), "appended" (raw) or
    "appended64" (base64)."""
    appended, chunks = fmt.startswith("appended"), []
    offset = 0

    def array(name, values, components=1):
        nonlocal offset
        values = np.asarray(values)
        values = values.astype(values.dtype.newbyteorder(order))
        kind = _VTK_NAMES[values.dtype.str[1:]]
        attrs = f'type="{kind}" Name="{name}"' + (f' NumberOfComponents="{components}"' if components > 1 else "")
        if fmt == "ascii":
            text = " ".join(repr(v) for v in values.ravel().tolist())
            return f'<DataArray {attrs} format="ascii">{text}</DataArray>'
        head, body = _encode(values, fmt, compress, header, order)
        if fmt == "binary":
            text = base64.b64encode(head).decode() + base64.b64encode(body).decode()
            return f'<DataArray {attrs} format="binary">\n{text}\n</DataArray>'
        data = head + body if fmt == "appended" else base64.b64encode(head) + base64.b64encode(body)
        chunks.append(data)
        element = f'<DataArray {attrs} format="appended" offset="{offset}"/>'
        offset += len(data)
        return element

    def cells(tag, cell_list):
        conn = np.array([n for c in cell_list for n in c], dtype=np.int64)
        ends = np.cumsum([len(c) for c in cell_list]).astype(np.int64)
        return f"<{tag}>{array('connectivity', conn)}{array('offsets', ends)}</{tag}>"

    lines = lines or []
    n_lines = f' NumberOfLines="{len(lines)}"' if lines else ""
    parts = [f'<Piece NumberOfPoints="{len(points)}" NumberOfPolys="{len(polys)}"{n_lines}>']
    parts.append("<PointData>" + "".join(array(k, v) for k, v in (point_data or {}).items()) + "</PointData>")
    parts.append("<CellData>" + "".join(array(k, v) for k, v in (cell_data or {}).items()) + "</CellData>")
    parts.append("<Points>" + array("Points", np.asarray(points, np.float64).ravel(), 3) + "</Points>")
    parts.append(cells("Verts", []))  # empty sections, as VTK writes them
    if lines:
        parts.append(cells("Lines", lines))
    parts.append(cells("Polys", polys))
    parts.append("</Piece>")
    compressor = ' compressor="vtkZLibDataCompressor"' if compress and fmt != "ascii" else ""
    byte_order = "BigEndian" if order == ">" else "LittleEndian"
    head = (f'<?xml version="1.0"?>\n<VTKFile type="PolyData" version="1.0" byte_order="{byte_order}" '
            f'header_type="{header}"{compressor}>\n<PolyData>' + "".join(parts) + "</PolyData>\n")
    with open(path, "wb") as f:
        f.write(head.encode())
        if appended:
            encoding = "raw" if fmt == "appended" else "base64"
            f.write(f'<AppendedData encoding="{encoding}">\n_'.encode() + b"".join(chunks)
                    + b"\n</AppendedData>\n")
        f.write(b"</VTKFile>\n")


def write_face(path, triangles, points, volume_ids, rng, **kw):
    """One face file: ``triangles`` (volume positions) with their own points, shuffled,
    numbered by the volume's ``volume_ids``."""
    used = rng.permutation(np.unique(triangles))
    local = np.full(len(points), -1)
    local[used] = np.arange(len(used))
    write_vtp(path, points[used], local[triangles].tolist(),
              {"GlobalNodeID": volume_ids[used].astype(np.int32)},
              {"GlobalElementID": np.arange(1, len(triangles) + 1, dtype=np.int32),
               "ModelFaceID": np.ones(len(triangles), dtype=np.int32)}, **kw)


def write_folder(folder, beam, *, seed=0, own_ids=False, **kw):
    """The beam as a SimVascular folder. Returns ``perm``: file position j holds beam node
    perm[j]. ``own_ids``: the volume numbers its points in a scrambled order (GlobalNodeID
    not position + 1)."""
    rng = np.random.default_rng(seed)
    perm = rng.permutation(beam.n_nodes)
    position = np.argsort(perm)  # beam node -> file position
    points = beam.points[perm]
    ids = (rng.permutation(beam.n_nodes) * 3 + 7) if own_ids else np.arange(1, beam.n_nodes + 1)
    os.makedirs(os.path.join(folder, "mesh-surfaces"), exist_ok=True)
    meshio.write(os.path.join(folder, "mesh-complete.mesh.vtu"), meshio.Mesh(
        points, [("tetra", position[beam.tets])],
        point_data={"GlobalNodeID": ids.astype(np.int32)},
        cell_data={"GlobalElementID": [np.arange(1, beam.n_elements + 1, dtype=np.int32)]}))
    for name, tri in beam.facet_sets.items():
        write_face(os.path.join(folder, "mesh-surfaces", f"{name}.vtp"), position[tri], points, ids, rng,
                   **kw)
    return perm


def triangle_set(tri) -> set:
    return {tuple(sorted(t)) for t in np.asarray(tri).tolist()}


@pytest.fixture
def beam():
    return jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1))


@pytest.fixture
def folder(tmp_path, beam):
    path = tmp_path / "beam-mesh"
    perm = write_folder(path, beam)
    return path, perm


# ---------------------------------------------------------------------------------------
# reading


def assert_same_faces(mesh, beam, perm):
    assert sorted(mesh.facet_sets) == sorted(beam.facet_sets)
    np.testing.assert_array_equal(mesh.points, beam.points[perm])
    for name, tri in beam.facet_sets.items():
        assert triangle_set(perm[mesh.facet_sets[name]]) == triangle_set(tri), name


def test_a_folder_reads_with_one_facet_set_per_face(folder, beam):
    path, perm = folder
    mesh = jaxsync.read_mesh(path)
    assert (mesh.n_nodes, mesh.n_elements) == (beam.n_nodes, beam.n_elements)
    assert_same_faces(mesh, beam, perm)
    np.testing.assert_array_equal(mesh.source_node_ids, np.arange(beam.n_nodes))


@pytest.mark.parametrize("kw", [
    dict(fmt="appended", compress=True),
    dict(fmt="appended", compress=False, header="UInt64"),
    dict(fmt="appended64", compress=True, header="UInt64"),
    dict(fmt="binary", compress=False),
    dict(fmt="binary", compress=True, order=">"),
    dict(fmt="ascii"),
], ids=lambda kw: "-".join(str(v) for v in kw.values()))
def test_every_vtk_encoding_of_the_faces_reads_the_same(tmp_path, beam, kw):
    perm = write_folder(tmp_path / "m", beam, seed=3, **kw)
    assert_same_faces(jaxsync.read_mesh(tmp_path / "m"), beam, perm)


def test_faces_map_through_the_volumes_own_global_node_ids(tmp_path, beam):
    perm = write_folder(tmp_path / "m", beam, seed=5, own_ids=True)
    mesh = jaxsync.read_mesh(tmp_path / "m")
    assert_same_faces(mesh, beam, perm)
    ids = meshio.read(tmp_path / "m" / "mesh-complete.mesh.vtu").point_data["GlobalNodeID"]
    np.testing.assert_array_equal(mesh.source_node_ids + 1, ids)  # the user's numbering


def test_a_volume_file_with_explicit_faces(folder, beam):
    path, perm = folder
    surfaces = path / "mesh-surfaces"
    volume = path / "mesh-complete.mesh.vtu"
    mesh = jaxsync.read_mesh(volume, faces=[surfaces / "x0.vtp", surfaces / "x1.vtp"])
    assert sorted(mesh.facet_sets) == ["x0", "x1"]
    assert triangle_set(perm[mesh.facet_sets["x1"]]) == triangle_set(beam.facet_sets["x1"])
    named = jaxsync.read_mesh(volume, faces={"clamp": surfaces / "x0.vtp"})
    assert triangle_set(perm[named.facet_sets["clamp"]]) == triangle_set(beam.facet_sets["x0"])
    (tmp := path / "other").mkdir()
    (tmp / "x0.vtp").write_bytes((surfaces / "x0.vtp").read_bytes())
    with pytest.raises(MeshError, match="would both be the facet set 'x0'.*mapping"):
        jaxsync.read_mesh(volume, faces=[surfaces / "x0.vtp", tmp / "x0.vtp"])
    with pytest.raises(MeshError, match="only with a volume file"):
        jaxsync.read_mesh(path, faces=[surfaces / "x0.vtp"])
    with pytest.raises(MeshError, match=r"\.vtp surface .*not a volume mesh"):
        jaxsync.read_mesh(surfaces / "x0.vtp")


def test_the_mesh_goes_through_the_usual_repairs(tmp_path, beam):
    """An unused node and inverted elements in a volume without GlobalNodeID (the faces'
    ids are then 1-based positions): dropped and re-oriented, with their warnings, and the
    facet sets renumbered."""
    rng = np.random.default_rng(1)
    points = np.vstack([[[9.0, 9.0, 9.0]], beam.points])  # an unused node first
    ids = np.arange(1, len(points) + 1)
    tets = beam.tets + 1
    tets[::2] = tets[::2][:, [0, 2, 1, 3]]  # inverted
    os.makedirs(tmp_path / "m" / "mesh-surfaces")
    meshio.write(tmp_path / "m" / "mesh-complete.mesh.vtu", meshio.Mesh(points, [("tetra", tets)]))
    for name, tri in beam.facet_sets.items():
        write_face(tmp_path / "m" / "mesh-surfaces" / f"{name}.vtp", tri + 1, points, ids, rng)
    with pytest.warns(jaxsync.MeshWarning) as caught:
        mesh = jaxsync.read_mesh(tmp_path / "m")
    text = " ".join(str(w.message) for w in caught)
    assert "inverted" in text and "used by no element" in text
    assert mesh.n_nodes == beam.n_nodes and (mesh.volumes() > 0).all()
    assert_same_faces(mesh, beam, np.arange(beam.n_nodes))
    np.testing.assert_array_equal(mesh.source_node_ids, np.arange(1, beam.n_nodes + 1))


def test_write_folder_writes_what_simvascular_writes(tmp_path, beam):
    folder = simvascular.write_folder(beam, tmp_path / "m")
    assert_same_faces(jaxsync.read_mesh(folder), beam, np.arange(beam.n_nodes))
    for number, name in enumerate(beam.facet_sets, start=1):
        face = simvascular.read_vtp(tmp_path / "m" / "mesh-surfaces" / f"{name}.vtp")
        nodes = face.point_data["GlobalNodeID"][face.cells[0].data] - 1
        elements = face.cell_data["GlobalElementID"][0] - 1  # the element each triangle bounds
        assert all(set(t) <= set(beam.tets[e]) for t, e in zip(nodes.tolist(), elements.tolist()))
        assert (face.cell_data["ModelFaceID"][0] == number).all()
    with pytest.raises(OutputError, match="not an empty folder"):
        simvascular.write_folder(beam, folder)


# ---------------------------------------------------------------------------------------
# refused folders


def _rewrite_face(folder, name, **changes):
    """Rewrite one face of ``folder`` from its current content with ``changes``."""
    path = folder / "mesh-surfaces" / f"{name}.vtp"
    face = simvascular.read_vtp(path)
    tri = np.concatenate([b.data for b in face.cells if b.type == "triangle"]).tolist()
    args = dict(points=face.points, polys=tri, point_data=dict(face.point_data))
    args.update(changes)
    write_vtp(path, args.pop("points"), args.pop("polys"), args.pop("point_data"), **args)
    return path


def _break(case, path, beam):
    surfaces = path / "mesh-surfaces"
    if case == "no volume":
        os.remove(path / "mesh-complete.mesh.vtu")
        return str(path), "without mesh-complete.mesh.vtu"
    if case == "no mesh-surfaces":
        for f in surfaces.iterdir():
            f.unlink()
        surfaces.rmdir()
        return str(path), "no mesh-surfaces/ folder"
    if case == "empty mesh-surfaces":
        for f in surfaces.iterdir():
            f.unlink()
        return str(surfaces), "holds no .vtp face files"
    if case == "no GlobalNodeID":
        n_points = len(simvascular.read_vtp(surfaces / "y1.vtp").points)
        f = _rewrite_face(path, "y1", point_data={"Other": np.zeros(n_points)})
        return str(f), "no point data GlobalNodeID.*Other"
    if case == "id out of range":
        face = simvascular.read_vtp(surfaces / "z0.vtp")
        ids = face.point_data["GlobalNodeID"].copy()
        ids[0] = beam.n_nodes + 5
        f = _rewrite_face(path, "z0", point_data={"GlobalNodeID": ids})
        return str(f), f"1 GlobalNodeID values .*\\({beam.n_nodes + 5}\\) are not nodes of the volume"
    if case == "quads":
        face = simvascular.read_vtp(surfaces / "x1.vtp")
        tri = np.concatenate([b.data for b in face.cells]).tolist()
        f = _rewrite_face(path, "x1", polys=tri + [[0, 1, 2, 3]])
        return str(f), r"cells other than triangles \(1 quad, beside 2 triangles\)"
    if case == "lines":
        f = _rewrite_face(path, "x1", lines=[[0, 1]])
        return str(f), r"cells other than triangles \(1 line"
    if case == "interior triangle":
        # a triangle through the middle of the beam: a face of two tetrahedra
        mesh = jaxsync.read_mesh(path)
        keys = np.sort(mesh.tets[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]].reshape(-1, 3), axis=1)
        uniq, counts = np.unique(keys, axis=0, return_counts=True)
        inner = uniq[counts == 2][:3]
        ids = np.arange(1, mesh.n_nodes + 1)
        write_face(surfaces / "y0.vtp", np.vstack([mesh.facet_sets["y0"], inner]), mesh.points, ids,
                   np.random.default_rng(0))
        return str(surfaces / "y0.vtp"), ("3 of its 11 triangles are not on the boundary.*0 are faces of no "
                                          "tetrahedron, 3 are interior")
    if case == "face of another mesh":
        other = jaxsync.box_beam(4.0, 1.0, 1.0, (2, 1, 1))  # same coordinates, other nodes
        ids = np.arange(1, other.n_nodes + 1)
        write_face(surfaces / "x1.vtp", other.facet_sets["y1"], other.points, ids, np.random.default_rng(0))
        return str(surfaces / "x1.vtp"), "triangles are not on the boundary of the volume.*faces of no tetrahedron"
    if case == "truncated":
        f = surfaces / "z1.vtp"
        f.write_bytes(f.read_bytes()[:300])
        return str(f), "could not read face file .*z1.vtp"
    raise AssertionError(case)


@pytest.mark.parametrize("case", ["no volume", "no mesh-surfaces", "empty mesh-surfaces", "no GlobalNodeID",
                                  "id out of range", "quads", "lines", "interior triangle",
                                  "face of another mesh", "truncated"])
def test_a_bad_folder_is_refused_naming_the_file_and_the_fix(folder, beam, case):
    path, _ = folder
    where, message = _break(case, path, beam)
    with pytest.raises(MeshError, match=message) as info:
        jaxsync.read_mesh(path)
    assert where in str(info.value)


def test_ids_missing_from_the_volumes_own_numbering_are_refused(tmp_path, beam):
    write_folder(tmp_path / "m", beam, own_ids=True)
    face = tmp_path / "m" / "mesh-surfaces" / "x0.vtp"
    content = simvascular.read_vtp(face)
    ids = content.point_data["GlobalNodeID"].copy()
    ids[1] = 2  # the scrambled numbering is 7, 10, 13, ...: 2 is no node
    tri = np.concatenate([b.data for b in content.cells]).tolist()
    write_vtp(face, content.points, tri, {"GlobalNodeID": ids})
    with pytest.raises(MeshError, match=r"x0.vtp: 1 GlobalNodeID values of its triangles \(2\) are not nodes "
                                        r"of the volume .*its own GlobalNodeID"):
        jaxsync.read_mesh(tmp_path / "m")


# ---------------------------------------------------------------------------------------
# running on it, VTU output


def _problem(mesh):
    return jaxsync.Problem(mesh, jaxsync.LinearElastic(E=1.0e3, nu=0.3, rho=1.0),
                           dirichlet=[jaxsync.Dirichlet("x0")],
                           loads=[jaxsync.Pressure(2.0, jaxsync.Ramp(0.05), surface="x1")],
                           damping=5.0)


def test_a_problem_on_the_folder_equals_the_same_problem_on_the_beam(folder, beam):
    path, perm = folder
    on_beam = jaxsync.simulate(_problem(beam), 60, save=20)
    problem = _problem(jaxsync.read_mesh(path))
    assert problem.dt == pytest.approx(_problem(beam).dt, rel=1e-12)
    on_folder = jaxsync.simulate(problem, 60, save=20, dt=on_beam.dt)
    expected = np.asarray(on_beam.displacement)[:, perm]
    assert np.abs(expected).max() > 0
    np.testing.assert_allclose(on_folder.displacement, expected, rtol=0, atol=1e-12 * np.abs(expected).max())


def _pvd(path):
    root = ET.parse(path).getroot()
    return [(float(d.get("timestep")), d.get("file")) for d in root.iter("DataSet")]


def test_vtu_series_reads_back_with_meshio(tmp_path):
    write_folder(tmp_path / "m", jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1)), own_ids=True)
    mesh = jaxsync.read_mesh(tmp_path / "m")
    traj = jaxsync.simulate(_problem(mesh), 60, save=20)
    pvd = traj.to_vtu(tmp_path / "out" / "run")
    assert pvd == str(tmp_path / "out" / "run.pvd")
    assert sorted(os.listdir(tmp_path / "out")) == ["run", "run.pvd"]
    entries = _pvd(pvd)
    assert [t for t, _ in entries] == [float(t) for t in traj.times]  # exactly
    ids = meshio.read(tmp_path / "m" / "mesh-complete.mesh.vtu").point_data["GlobalNodeID"]
    for i, (_, name) in enumerate(entries):
        step = meshio.read(tmp_path / "out" / name)
        np.testing.assert_array_equal(step.points, mesh.points)
        assert [(c.type, c.data.tolist()) for c in step.cells] == [("tetra", mesh.tets.tolist())]
        np.testing.assert_array_equal(step.point_data["displacement"], traj.displacement[i])
        np.testing.assert_array_equal(step.point_data["GlobalNodeID"], ids)
    # thinned, into the same place (the earlier series replaced), spelled as a folder
    traj.to_vtu(str(tmp_path / "out" / "run") + os.sep, every=2)
    assert [t for t, _ in _pvd(pvd)] == [float(traj.times[0]), float(traj.times[2])]
    assert sorted(os.listdir(tmp_path / "out" / "run")) == ["run_000000.vtu", "run_000002.vtu"]


def test_the_cell_writer_takes_any_cell_type(tmp_path):
    """tetra10 goes through the same writer (quadratic elements, later)."""
    from jaxsync.io.trajectory import write_vtu

    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    mid = np.array([(points[a] + points[b]) / 2 for a, b in [(0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3)]])
    write_vtu(tmp_path / "q.vtu", np.vstack([points, mid]), np.arange(10)[None], "tetra10",
              point_data={"displacement": np.zeros((10, 3))})
    back = meshio.read(tmp_path / "q.vtu")
    assert back.cells[0].type == "tetra10" and back.cells[0].data.tolist() == [list(range(10))]


def test_a_failed_vtu_write_leaves_the_earlier_series(tmp_path, monkeypatch):
    import jaxsync.io.trajectory as trajectory_module

    traj = jaxsync.simulate(_problem(jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1))), 40, save=20)
    pvd = traj.to_vtu(tmp_path / "run")
    before = {p: p.read_bytes() for p in [tmp_path / "run.pvd", *(tmp_path / "run").iterdir()]}
    calls, write = [], trajectory_module.write_vtu

    def full_disk(path, *args, **kwargs):  # the second step file fails
        calls.append(path)
        if len(calls) == 2:
            raise OSError(28, "No space left on device")
        write(path, *args, **kwargs)

    monkeypatch.setattr(trajectory_module, "write_vtu", full_disk)
    with pytest.raises(OutputError, match=r"could not write .*run.pvd: No space left.*free space"):
        traj.to_vtu(tmp_path / "run", every=1)
    assert {p: p.read_bytes() for p in [tmp_path / "run.pvd", *(tmp_path / "run").iterdir()]} == before
    assert sorted(os.listdir(tmp_path)) == ["run", "run.pvd"]  # no staging folder left
    assert pvd == str(tmp_path / "run.pvd")


def test_vtu_output_never_replaces_a_folder_of_other_files(tmp_path):
    traj = jaxsync.simulate(_problem(jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1))), 20, save=20)
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "notes.txt").write_text("mine")
    with pytest.raises(OutputError, match="not a VTU series"):
        traj.to_vtu(tmp_path / "run")
    assert (tmp_path / "run" / "notes.txt").read_text() == "mine"
    with pytest.raises(OutputError, match="positive integer"):
        traj.to_vtu(tmp_path / "other", every=0)


# ---------------------------------------------------------------------------------------
# the command line


CASE = """
[material]
E = 1.0e3
nu = 0.3
rho = 1.0
[problem]
kind = "general"
damping = 5.0
[[dirichlet]]
facet = "x0"
[[pressure]]
surface = "x1"
magnitude = 2.0
t_ramp = 0.05
[run]
n_steps = 40
save_every = 20
"""


def test_simulate_on_a_folder_with_vtu_output(folder, tmp_path, beam, capsys):
    path, perm = folder
    (tmp_path / "case.toml").write_text(CASE)
    out = tmp_path / "out"
    args = ["simulate", str(tmp_path / "case.toml"), "--mesh", str(path), "-o", str(out / "run.h5"),
            "--vtu", str(out / "run"), "--no-progress"]
    assert main(args) == 0
    assert "wrote " + str(out / "run.pvd") in capsys.readouterr().out
    traj = jaxsync.Trajectory.load(out / "run.h5")
    assert sorted(traj.mesh.facet_sets) == sorted(beam.facet_sets)
    entries = _pvd(out / "run.pvd")
    assert [t for t, _ in entries] == [float(t) for t in traj.times]
    last = meshio.read(out / entries[-1][1])
    np.testing.assert_array_equal(last.point_data["displacement"], traj.displacement[-1])
    expected = jaxsync.simulate(_problem(beam), 40, save=20).displacement[:, perm]
    np.testing.assert_allclose(traj.displacement, expected, rtol=0, atol=1e-12 * np.abs(expected).max())
    # an existing series is refused before anything runs, and replaced with --force
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and "run.pvd" in err and "--force" in err
    assert main(args + ["--force"]) == 0


def test_the_toml_file_names_the_folder_and_the_series(folder, tmp_path):
    path, _ = folder
    case = tmp_path / "case"
    case.mkdir()
    os.rename(path, case / "beam-mesh")
    (case / "run.toml").write_text(CASE.replace("[material]", '[mesh]\nfile = "beam-mesh"\n[material]')
                                   + 'output = "run.h5"\nvtu = "series/run"\n')
    assert main(["simulate", str(case / "run.toml"), "--no-progress"]) == 0
    assert (case / "series" / "run.pvd").exists() and len(os.listdir(case / "series" / "run")) == 3
    # with -o, the series the file asks for is named after it (as --xdmf)
    assert main(["simulate", str(case / "run.toml"), "-o", str(tmp_path / "two.h5"), "--no-progress"]) == 0
    assert (tmp_path / "two.pvd").exists() and (tmp_path / "two").is_dir()


def test_a_vtu_prefix_taken_by_other_files_is_refused_before_running(tmp_path, capsys, monkeypatch):
    beam = "[mesh]\nlength = 4.0\ndivisions = [4, 1, 1]\n[material]"
    (tmp_path / "case.toml").write_text(CASE.replace("[material]", beam))
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "notes.txt").write_text("mine")

    def must_not_run(*a, **k):
        raise AssertionError("simulate ran although the output cannot be written")

    monkeypatch.setattr("jaxsync.solve._solver.simulate", must_not_run)
    assert main(["simulate", str(tmp_path / "case.toml"), "-o", str(tmp_path / "run.h5"), "--vtu",
                 str(tmp_path / "run"), "--force", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and "not a VTU series" in err
