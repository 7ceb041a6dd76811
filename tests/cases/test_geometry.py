"""The generated vessel (jaxsync.cases.vessel_mesh): tags, geometry, orientation, a
static lumen-pressure solve against the thick-walled cylinder (Lame), errors."""

import math

import numpy as np
import pytest

import jaxsync
from jaxsync.cases import estimated_elements, vessel_centerline, vessel_mesh
from jaxsync.errors import MeshError

R_I, WALL, LENGTH, SIZE = 0.175, 0.05, 3.0, 0.06
R_O = R_I + WALL


@pytest.fixture(scope="module")
def tube():
    return vessel_mesh(length=LENGTH, radius=R_I, wall=WALL, size=SIZE)


@pytest.fixture(scope="module")
def bifurcation():
    return vessel_mesh(length=LENGTH, radius=R_I, wall=WALL, branch=True, size=SIZE)


def distance_to_centerline(points, segments):
    best = np.full(len(points), np.inf)
    for a, b in segments:
        ab = b - a
        s = np.clip((points - a) @ ab / (ab @ ab), 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(points - (a + s[:, None] * ab), axis=1))
    return best


def closest_on_centerline(points, segments):
    best, where = np.full(len(points), np.inf), np.zeros_like(points)
    for a, b in segments:
        ab = b - a
        s = np.clip((points - a) @ ab / (ab @ ab), 0.0, 1.0)
        q = a + s[:, None] * ab
        d = np.linalg.norm(points - q, axis=1)
        closer = d < best
        best[closer], where[closer] = d[closer], q[closer]
    return where


def outward_normals(mesh, triangles):
    """Unit normals of boundary triangles pointing out of the solid (away from the
    fourth node of the element they belong to)."""
    local = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
    faces = np.sort(mesh.tets[:, local].reshape(-1, 3), axis=1)
    lookup = {tuple(f): i for i, f in enumerate(faces)}
    owner = np.array([lookup[tuple(t)] for t in np.sort(triangles, axis=1)]) // 4
    p = mesh.points
    a, b, c = (p[triangles[:, k]] for k in range(3))
    n = np.cross(b - a, c - a)
    opposite = p[mesh.tets[owner]].sum(axis=1) - a - b - c  # the element's fourth node
    n *= -np.sign(np.einsum("ij,ij->i", opposite - a, n))[:, None]
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def test_tags_exist_and_are_nonempty(tube, bifurcation):
    for name in ("inlet", "outlet", "lumen", "outer"):
        assert len(tube.facet_set(name)) > 0
    for name in ("inlet", "outlet", "outlet_1", "outlet_2", "lumen", "outer"):
        assert len(bifurcation.facet_set(name)) > 0
    out = bifurcation.facet_sets
    both = np.sort(np.concatenate([out["outlet_1"], out["outlet_2"]]), axis=1)
    assert np.array_equal(np.unique(both, axis=0), np.unique(np.sort(out["outlet"], axis=1), axis=0))
    # every tagged triangle is a boundary face, and the tags cover the whole boundary
    for mesh, names in ((tube, ("inlet", "outlet", "lumen", "outer")),
                        (bifurcation, ("inlet", "outlet", "lumen", "outer"))):
        boundary = {tuple(f) for f in np.sort(mesh.boundary_facets(), axis=1)}
        tagged = np.sort(np.concatenate([mesh.facet_sets[n] for n in names]), axis=1)
        assert {tuple(f) for f in tagged} == boundary
        assert len(tagged) == len(boundary)  # no triangle in two of these sets


def test_straight_tube_volume_and_radii(tube):
    exact = math.pi * (R_O**2 - R_I**2) * LENGTH
    # inscribed polygons lose a little volume; a few percent at this coarse size
    assert tube.volumes().sum() == pytest.approx(exact, rel=0.03)
    assert np.all(tube.volumes() > 0)
    r = np.hypot(tube.points[:, 0], tube.points[:, 1])
    assert np.allclose(r[tube.facet_nodes("lumen")], R_I, rtol=1e-6)
    assert np.allclose(r[tube.facet_nodes("outer")], R_O, rtol=1e-6)
    assert np.allclose(tube.points[tube.facet_nodes("inlet"), 2], 0.0, atol=1e-9)
    assert np.allclose(tube.points[tube.facet_nodes("outlet"), 2], LENGTH, atol=1e-9)
    assert tube.points[:, 2].min() == pytest.approx(0.0, abs=1e-9)
    assert tube.points[:, 2].max() == pytest.approx(LENGTH, abs=1e-9)


def test_bifurcation_radii_and_outlets(bifurcation):
    segments = vessel_centerline(length=LENGTH, branch=True)
    d = distance_to_centerline(bifurcation.points, segments)
    assert np.allclose(d[bifurcation.facet_nodes("lumen")], R_I, rtol=1e-5)
    assert np.allclose(d[bifurcation.facet_nodes("outer")], R_O, rtol=1e-5)
    assert np.all(d > R_I - 1e-6) and np.all(d < R_O + 1e-6)  # all inside the wall
    for name, (start, end) in (("outlet_1", segments[1]), ("outlet_2", segments[2])):
        pts = bifurcation.points[bifurcation.facet_nodes(name)]
        axis = (end - start) / np.linalg.norm(end - start)
        assert np.allclose((pts - end) @ axis, 0.0, atol=1e-9)       # in the end plane
        assert np.linalg.norm(pts - end, axis=1).max() <= R_O + 1e-9
    assert bifurcation.points[bifurcation.facet_nodes("outlet_1"), 0].min() > 0
    assert bifurcation.points[bifurcation.facet_nodes("outlet_2"), 0].max() < 0
    assert np.all(bifurcation.volumes() > 0)


@pytest.mark.parametrize("which", ["tube", "bifurcation"])
def test_lumen_normals_point_into_the_lumen(which, request):
    mesh = request.getfixturevalue(which)
    segments = vessel_centerline(length=LENGTH, branch=which == "bifurcation")
    for name, sign in (("lumen", -1.0), ("outer", 1.0)):
        tri = mesh.facet_set(name)
        centres = mesh.points[tri].mean(axis=1)
        radial = centres - closest_on_centerline(centres, segments)
        radial /= np.linalg.norm(radial, axis=1, keepdims=True)
        cosine = np.einsum("ij,ij->i", outward_normals(mesh, tri), radial)
        # lumen: the solid's outward normal points towards the centerline; outer: away
        assert np.all(sign * cosine > 0.5), name


def test_lumen_pressure_inflates_like_lame():
    """Clamped long tube under lumen pressure: at mid-length the state is plane strain
    (eps_zz = 0), so the radial displacement is the thick-walled cylinder's (Lame)."""
    length, p0 = 2.0, 1.0e5
    E, nu = 6.26e6, 0.4
    mesh = vessel_mesh(length=length, radius=R_I, wall=WALL, size=0.05)
    problem = jaxsync.Problem(
        mesh, jaxsync.LinearElastic(E=E, nu=nu, rho=1.0),
        dirichlet=[jaxsync.Dirichlet("inlet"), jaxsync.Dirichlet("outlet")],
        loads=[jaxsync.Pressure(p0, surface="lumen")])
    u = np.asarray(jaxsync.steady_state(problem))
    x = mesh.points
    r = np.hypot(x[:, 0], x[:, 1])
    u_r = (u[:, 0] * x[:, 0] + u[:, 1] * x[:, 1]) / r
    a = p0 * R_I**2 / (R_O**2 - R_I**2)
    b = a * R_O**2
    lame = (1 + nu) / E * ((1 - 2 * nu) * a * r + b / r)
    mid = np.abs(x[:, 2] - length / 2) < 0.25
    for name in ("lumen", "outer"):
        nodes = np.intersect1d(mesh.facet_nodes(name), np.flatnonzero(mid))
        assert np.all(u_r[nodes] > 0), f"{name} moves inwards"
        # P1 tetrahedra with one to two elements across the wall are a little stiff
        assert np.mean(u_r[nodes] / lame[nodes]) == pytest.approx(1.0, rel=0.15), name
    assert np.abs(u[mid, 2]).max() < 0.1 * lame.max()   # plane strain: no axial motion


@pytest.mark.parametrize("size", [0.0, -0.05, float("nan"), float("inf"), "fine"])
def test_bad_size_is_refused(size):
    with pytest.raises(MeshError, match="size"):
        vessel_mesh(size=size)


def test_too_fine_is_refused_before_meshing(tmp_path):
    assert estimated_elements(size=1e-3) > 2_000_000
    with pytest.raises(MeshError, match="max_elements"):
        vessel_mesh(tmp_path / "fine.msh", size=1e-3)
    assert not (tmp_path / "fine.msh").exists()
    with pytest.raises(MeshError, match="max_elements"):
        vessel_mesh(size=SIZE, max_elements=100)


@pytest.mark.parametrize("kwargs", [dict(radius=0.0), dict(wall=-0.01), dict(length=0.1),
                                    dict(branch=True, angle=89.0),
                                    dict(branch=True, length=1.0)])
def test_bad_geometry_is_refused(kwargs):
    with pytest.raises(MeshError):
        vessel_mesh(size=SIZE, **kwargs)


def test_gmsh_failure_is_a_mesh_error_and_gmsh_is_closed(monkeypatch, tmp_path):
    import gmsh

    def broken(*args, **kwargs):
        raise Exception("simulated meshing failure")

    monkeypatch.setattr(gmsh.model.mesh, "generate", broken)
    target = tmp_path / "vessel.msh"
    target.write_text("good old file")
    with pytest.raises(MeshError, match="simulated meshing failure"):
        vessel_mesh(target, size=SIZE)
    assert not gmsh.isInitialized()
    assert target.read_text() == "good old file"      # a failed run overwrites nothing
    assert [p.name for p in tmp_path.iterdir()] == ["vessel.msh"]  # no temporary left


def test_file_written_read_back_deterministic_and_quiet(tmp_path, capfd, tube):
    path = tmp_path / "sub" / "vessel.msh"
    mesh = vessel_mesh(path, length=LENGTH, radius=R_I, wall=WALL, size=SIZE)
    assert capfd.readouterr().out == ""                 # gmsh prints nothing unless verbose
    assert path.exists() and path.read_text().startswith("$MeshFormat\n4.1")
    again = jaxsync.read_mesh(path)
    for m in (mesh, again):
        assert np.array_equal(m.points, tube.points) and np.array_equal(m.tets, tube.tets)
        assert sorted(m.facet_sets) == sorted(tube.facet_sets)
        for name in tube.facet_sets:
            assert np.array_equal(m.facet_sets[name], tube.facet_sets[name])
    assert [p.name for p in path.parent.iterdir()] == ["vessel.msh"]


def test_caller_gmsh_session_is_left_as_it_was():
    import gmsh

    gmsh.initialize(readConfigFiles=False, interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("mine")
        gmsh.model.occ.addBox(0, 0, 0, 1, 1, 1)
        gmsh.model.occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMax", 0.7)
        models = gmsh.model.list()
        mesh = vessel_mesh(size=0.08)
        assert mesh.n_elements > 0
        assert gmsh.isInitialized()
        assert gmsh.model.getCurrent() == "mine"
        assert gmsh.model.list() == models
        assert gmsh.model.getEntities(3) == [(3, 1)]
        assert gmsh.option.getNumber("Mesh.MeshSizeMax") == 0.7
    finally:
        gmsh.finalize()


def test_vessel_example_script_runs(tmp_path, capsys):
    """notebooks/vessel_example.py, shortened: the pulse inflates the vessel."""
    import importlib.util
    from pathlib import Path

    script = Path(__file__).resolve().parents[2] / "notebooks" / "vessel_example.py"
    spec = importlib.util.spec_from_file_location("vessel_example", script)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    assert example.PULSE_VALUES.min() == pytest.approx(1.067e5, rel=1e-3)   # 80 mmHg
    assert example.PULSE_VALUES.max() == pytest.approx(1.6e5, rel=1e-3)     # 120 mmHg
    out = example.main(["-o", str(tmp_path), "--size", "0.08", "--steps", "400",
                        "--save-every", "200"])
    assert capsys.readouterr().out.count("\n") > 3
    for name in ("vessel.msh", "vessel.h5", "vessel.xdmf"):
        assert (tmp_path / name).exists()
    u_r = out["lumen_radial_displacement"]
    assert u_r[0] == 0.0 and np.all(u_r[1:] > 0) and u_r[-1] > u_r[1]   # ramped inflation
    assert out["mass_increase_percent"] >= 0.0
