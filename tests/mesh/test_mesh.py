import os
import warnings

import meshio
import numpy as np
import pytest

import jaxsync
from jaxsync import MeshError, MeshWarning
from jaxsync.mesh import tet_volumes, validated_mesh

REFERENCE = os.path.join(os.path.dirname(__file__), "..", "..", "..", "shared", "reference", "beam_coarse.vtk")


def unit_cube_tets():
    """Two cells of a structured mesh written by hand (6 tets per cube, Kuhn split)."""
    return jaxsync.box_beam(2.0, 1.0, 1.0, (2, 1, 1))


def test_box_beam_default_is_coarse_cantilever():
    mesh = jaxsync.box_beam()
    assert mesh.n_nodes == 104 and mesh.n_elements == 150
    assert mesh.points.dtype == np.float64 and mesh.tets.shape == (150, 4)
    vol = mesh.volumes()
    assert np.all(vol > 0)
    assert vol.sum() == pytest.approx(25.0, rel=1e-12)
    lo, hi = mesh.bounding_box
    np.testing.assert_allclose(lo, 0.0)
    np.testing.assert_allclose(hi, [25.0, 1.0, 1.0])


def test_box_beam_facet_sets_cover_the_faces():
    mesh = jaxsync.box_beam(3.0, 2.0, 1.0, (3, 2, 1))
    for name, axis, value, area in (("x0", 0, 0.0, 2.0), ("x1", 0, 3.0, 2.0), ("y0", 1, 0.0, 3.0),
                                    ("y1", 1, 2.0, 3.0), ("z0", 2, 0.0, 6.0), ("z1", 2, 1.0, 6.0)):
        tri = mesh.facet_set(name)
        np.testing.assert_allclose(mesh.points[tri][:, :, axis], value)
        p = mesh.points[tri]
        areas = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
        assert areas.sum() == pytest.approx(area)
    # the six sets together are the whole boundary
    total = sum(len(v) for v in mesh.facet_sets.values())
    assert total == len(mesh.boundary_facets())


def test_boundary_facets_point_outward():
    mesh = jaxsync.box_beam(2.0, 1.0, 1.0, (2, 2, 2))
    faces = mesh.boundary_facets()
    p = mesh.points[faces]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    outward = p.mean(axis=1) - mesh.points.mean(axis=0)
    assert np.all(np.einsum("ij,ij->i", normal, outward) > 0)


def test_box_beam_rejects_bad_divisions():
    with pytest.raises(MeshError, match="divisions"):
        jaxsync.box_beam(divisions=(0, 1, 1))


def write_mixed_vtk(path, mesh):
    """Legacy VTK with vertex, line, triangle and tetra blocks, as gmsh writes it."""
    cells = [("vertex", np.array([[0], [1]])), ("line", np.array([[0, 1], [1, 2]])),
             ("triangle", mesh.facet_set("x0")), ("tetra", mesh.tets)]
    meshio.write_points_cells(path, mesh.points, cells, file_format="vtk", binary=False)


def test_read_mixed_legacy_vtk(tmp_path):
    mesh = unit_cube_tets()
    path = tmp_path / "mixed.vtk"
    write_mixed_vtk(str(path), mesh)
    read = jaxsync.read_mesh(path)
    np.testing.assert_array_equal(read.tets, mesh.tets)
    np.testing.assert_allclose(read.points, mesh.points)
    # untagged triangles are kept as the "boundary" facet set
    np.testing.assert_array_equal(read.facet_sets["boundary"], mesh.facet_set("x0"))


@pytest.mark.parametrize("suffix", [".vtu", ".xdmf"])
def test_read_vtu_and_xdmf(tmp_path, suffix):
    mesh = unit_cube_tets()
    path = str(tmp_path / f"m{suffix}")
    meshio.write_points_cells(path, mesh.points, [("tetra", mesh.tets)])
    read = jaxsync.read_mesh(path)
    np.testing.assert_array_equal(read.tets, mesh.tets)
    np.testing.assert_allclose(read.points, mesh.points)


def test_read_gmsh_with_physical_groups(tmp_path):
    gmsh = pytest.importorskip("gmsh")
    path = str(tmp_path / "box.msh")
    gmsh.initialize(["", "-noenv"])
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("box")
        gmsh.model.occ.addBox(0, 0, 0, 4, 1, 1)
        gmsh.model.occ.synchronize()
        left = [tag for dim, tag in gmsh.model.getEntities(2)
                if abs(gmsh.model.occ.getCenterOfMass(dim, tag)[0]) < 1e-9]
        right = [tag for dim, tag in gmsh.model.getEntities(2)
                 if abs(gmsh.model.occ.getCenterOfMass(dim, tag)[0] - 4) < 1e-9]
        gmsh.model.addPhysicalGroup(2, left, 11, name="clamp")
        gmsh.model.addPhysicalGroup(2, right, 12, name="tip")
        gmsh.model.addPhysicalGroup(3, [1], 1, name="solid")
        gmsh.option.setNumber("Mesh.MeshSizeMax", 0.5)
        gmsh.model.mesh.generate(3)
        gmsh.write(path)
    finally:
        gmsh.finalize()
    mesh = jaxsync.read_mesh(path)
    assert mesh.volumes().sum() == pytest.approx(4.0, rel=1e-10)
    assert set(mesh.facet_sets) >= {"clamp", "tip"}
    np.testing.assert_allclose(mesh.points[mesh.facet_set("clamp")][..., 0], 0.0, atol=1e-12)
    np.testing.assert_allclose(mesh.points[mesh.facet_set("tip")][..., 0], 4.0, atol=1e-12)
    p = mesh.points[mesh.facet_set("tip")]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()
    assert area == pytest.approx(1.0)


def test_no_tetra_is_an_error(tmp_path):
    path = str(tmp_path / "surface.vtk")
    mesh = unit_cube_tets()
    meshio.write_points_cells(path, mesh.points, [("triangle", mesh.boundary_facets())])
    with pytest.raises(MeshError, match="no tetrahedra"):
        jaxsync.read_mesh(path)


def test_missing_file_is_an_error(tmp_path):
    with pytest.raises(MeshError, match="does not exist"):
        jaxsync.read_mesh(tmp_path / "nope.msh")


def test_nan_coordinates_name_the_node():
    mesh = unit_cube_tets()
    points = mesh.points.copy()
    points[5, 1] = np.nan
    with pytest.raises(MeshError, match="node 5"):
        validated_mesh(points, mesh.tets)


def test_out_of_range_index_names_the_element():
    mesh = unit_cube_tets()
    tets = mesh.tets.copy()
    tets[3, 2] = mesh.n_nodes + 7
    with pytest.raises(MeshError, match="element 3"):
        validated_mesh(mesh.points, tets)


def test_zero_volume_element_is_named():
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0]], float)
    tets = np.array([[0, 1, 2, 3], [0, 1, 4, 2]])  # second one is flat (z = 0)
    with pytest.raises(MeshError, match="element 1"):
        validated_mesh(points, tets)


def test_repeated_node_is_an_error():
    points = np.eye(4, 3)
    with pytest.raises(MeshError, match="element 0"):
        validated_mesh(points, np.array([[0, 1, 1, 3]]))


def test_inverted_elements_are_reoriented_and_reported():
    mesh = unit_cube_tets()
    tets = mesh.tets.copy()
    tets[[1, 4]] = tets[[1, 4]][:, [1, 0, 2, 3]]
    assert np.sum(tet_volumes(mesh.points, tets) < 0) == 2
    with pytest.warns(MeshWarning, match="2 inverted"):
        fixed = validated_mesh(mesh.points, tets)
    assert np.all(fixed.volumes() > 0)
    np.testing.assert_allclose(fixed.volumes(), mesh.volumes())


def test_unused_nodes_are_dropped_and_reported():
    mesh = unit_cube_tets()
    extra = np.vstack([[9.0, 9.0, 9.0], mesh.points])  # node 0 is unused
    with pytest.warns(MeshWarning, match="1 nodes are used by no element"):
        fixed = validated_mesh(extra, mesh.tets + 1, {"x0": mesh.facet_set("x0") + 1})
    np.testing.assert_allclose(fixed.points, mesh.points)
    np.testing.assert_array_equal(fixed.tets, mesh.tets)
    np.testing.assert_array_equal(fixed.source_node_ids, np.arange(1, mesh.n_nodes + 1))
    np.testing.assert_array_equal(fixed.facet_set("x0"), mesh.facet_set("x0"))


def test_unknown_facet_set_lists_known_names():
    with pytest.raises(MeshError, match="known: x0, x1"):
        jaxsync.box_beam().facet_set("lumen")


def test_clean_mesh_reads_without_warnings(tmp_path):
    mesh = unit_cube_tets()
    path = str(tmp_path / "m.vtu")
    meshio.write_points_cells(path, mesh.points, [("tetra", mesh.tets)])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        jaxsync.read_mesh(path)


@pytest.mark.slow
@pytest.mark.skipif(not os.path.exists(REFERENCE), reason="paper's reference mesh not available")
def test_paper_reference_mesh():
    """The paper's own coarse cantilever mesh (shared/reference): CFL dt, mass, static tip
    deflection and first frequency as computed independently (see its README)."""
    import scipy.sparse.linalg as spla

    mesh = jaxsync.read_mesh(REFERENCE)
    assert mesh.n_nodes == 110 and mesh.n_elements == 256
    problem = jaxsync.cantilever(mesh)
    assert problem.dt == pytest.approx(2.4784e-4, rel=1e-4)
    assert float(np.sum(problem.lumped_mass())) == pytest.approx(25.0, rel=1e-12)
    u = jaxsync.steady_state(problem)
    assert u[:, 2].min() == pytest.approx(-0.0739, rel=0.01)
    m = problem.material
    K = problem.operators.stiffness(m.lam, m.mu)
    fixed, _ = problem.dirichlet_dofs()
    free = np.setdiff1d(np.arange(K.shape[0]), fixed)
    M = np.repeat(np.asarray(problem.lumped_mass()), 3)[free]
    import scipy.sparse as sp

    w2 = spla.eigsh(K[free][:, free].tocsc(), k=1, M=sp.diags(M).tocsc(), sigma=0, which="LM")[0][0]
    assert np.sqrt(w2) / (2 * np.pi) == pytest.approx(0.483, rel=0.01)


@pytest.mark.parametrize("content", [b"", b"\n  \n"])
def test_empty_file_is_a_mesh_error_naming_the_file(tmp_path, content):
    path = tmp_path / "empty.msh"
    path.write_bytes(content)
    with pytest.raises(MeshError, match=r"empty\.msh.* is empty; re-export"):
        jaxsync.read_mesh(path)


@pytest.mark.parametrize("name, content", [
    ("garbage.msh", b"this is not a mesh\n1 2 3\n"),
    ("garbage.vtu", b"<not xml"),
])
def test_garbage_file_is_a_mesh_error_not_system_exit(tmp_path, capfd, name, content):
    """meshio calls sys.exit(1) when no reader accepts a file; read_mesh must raise a
    catchable MeshError naming the file, and keep meshio's printing off the terminal."""
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(MeshError, match=rf"could not read mesh file .*{name}.*not a valid"):
        jaxsync.read_mesh(path)
    out, err = capfd.readouterr()
    assert out == "" and err == ""


def test_truncated_gmsh_file_names_the_file(tmp_path):
    path = tmp_path / "cut.msh"
    path.write_text("$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Nodes\n1 2")
    with pytest.raises(MeshError, match=r"cut\.msh.*damaged, truncated"):
        jaxsync.read_mesh(path)


def test_unknown_extension_and_folder_are_mesh_errors(tmp_path):
    path = tmp_path / "beam.foo"
    path.write_text("whatever")
    with pytest.raises(MeshError, match=r"beam\.foo.*unknown extension '\.foo'.*\.msh"):
        jaxsync.read_mesh(path)
    with pytest.raises(MeshError, match="is a folder"):
        jaxsync.read_mesh(tmp_path)


def test_keyboard_interrupt_while_reading_is_not_swallowed(tmp_path, monkeypatch):
    import meshio

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(meshio, "read", interrupted)
    path = tmp_path / "m.msh"
    path.write_text("x")
    with pytest.raises(KeyboardInterrupt):
        jaxsync.read_mesh(path)


def test_a_surface_in_two_physical_groups_is_in_both_facet_sets(tmp_path):
    """meshio keeps only an element's first physical tag in gmsh:physical; the facet sets
    come from the complete physical groups."""
    import gmsh

    path = tmp_path / "box.msh"
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("box")
        gmsh.model.occ.addBox(0, 0, 0, 2, 1, 1)
        gmsh.model.occ.synchronize()
        surfaces = [tag for _, tag in gmsh.model.getEntities(2)]
        left = [s for s in surfaces
                if abs(gmsh.model.occ.getCenterOfMass(2, s)[0]) < 1e-9]
        right = [s for s in surfaces
                 if abs(gmsh.model.occ.getCenterOfMass(2, s)[0] - 2) < 1e-9]
        gmsh.model.addPhysicalGroup(2, left, name="left")
        gmsh.model.addPhysicalGroup(2, left + right, name="ends")
        gmsh.model.addPhysicalGroup(3, [1], name="solid")
        gmsh.option.setNumber("Mesh.MeshSizeMax", 0.4)
        gmsh.model.mesh.generate(3)
        gmsh.write(str(path))
    finally:
        gmsh.finalize()
    mesh = jaxsync.read_mesh(path)
    ends = mesh.facet_nodes("ends")
    left_nodes = mesh.facet_nodes("left")
    x = mesh.points[:, 0]
    assert np.all(x[left_nodes] == 0.0)
    assert set(np.flatnonzero(np.isclose(x, 0.0))) == set(left_nodes)
    assert set(np.flatnonzero(np.isclose(x, 0.0) | np.isclose(x, 2.0))) == set(ends)


def split_beam():
    """The box beam with its nodes at x = 12 doubled: the elements beyond x = 12 use the
    copies, so the two halves touch without being connected."""
    beam = jaxsync.box_beam(25.0, 1.0, 1.0, (25, 2, 2))
    points, tets = beam.points, beam.tets
    at_cut = np.flatnonzero(np.isclose(points[:, 0], 12.0))
    copy_of = np.full(len(points), -1)
    copy_of[at_cut] = len(points) + np.arange(len(at_cut))
    beyond = points[tets].mean(axis=1)[:, 0] > 12.0
    split = tets.copy()
    on_cut = beyond[:, None] & (copy_of[tets] >= 0)
    split[on_cut] = copy_of[tets][on_cut]
    return beam, np.vstack([points, points[at_cut]]), split, len(at_cut)


def test_a_mesh_cut_by_coincident_nodes_is_flagged_and_can_be_merged(tmp_path):
    beam, points, tets, n_copies = split_beam()
    with pytest.warns(MeshWarning) as caught:
        cut = validated_mesh(points, tets)
    messages = [str(w.message) for w in caught]
    assert any(f"{n_copies} pairs of coincident nodes" in m for m in messages)
    assert any("2 disconnected pieces" in m for m in messages)
    assert int(jaxsync.mesh.connected_components(cut).max()) == 1
    # read from a file as a user would
    path = tmp_path / "split.vtu"
    meshio.write(str(path), meshio.Mesh(points, [("tetra", tets)]))
    with pytest.warns(MeshWarning) as caught:
        read = jaxsync.read_mesh(path)
    assert any("the mesh is cut there" in str(w.message) for w in caught)
    # merged: the original beam (same nodes, same elements), one piece, no warning
    merged = jaxsync.mesh.merge_coincident_nodes(read)
    assert merged.n_nodes == beam.n_nodes
    np.testing.assert_array_equal(merged.points, beam.points)
    np.testing.assert_array_equal(merged.tets, beam.tets)
    assert np.all(jaxsync.mesh.connected_components(merged) == 0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        validated_mesh(merged.points, merged.tets)


def test_merging_keeps_facet_sets():
    beam, points, tets, _ = split_beam()
    # the end face x = 25 lies beyond the cut: its triangles use copied nodes only if on the cut
    with pytest.warns(MeshWarning):
        cut = validated_mesh(points, tets, facet_sets={"x1": beam.facet_sets["x1"]})
    merged = jaxsync.mesh.merge_coincident_nodes(cut)
    np.testing.assert_array_equal(merged.facet_sets["x1"], beam.facet_sets["x1"])


def test_separate_pieces_are_flagged():
    cube = unit_cube_tets()
    points, tets = cube.points, cube.tets
    far = points + np.array([5.0, 0.0, 0.0])
    with pytest.warns(MeshWarning, match="2 disconnected pieces") as caught:
        validated_mesh(np.vstack([points, far]), np.vstack([tets, tets + len(points)]))
    assert not any("coincident" in str(w.message) for w in caught)


def test_generated_meshes_raise_no_topology_warning():
    for mesh in (jaxsync.box_beam(), jaxsync.box_beam(25.0, 1.0, 1.0, (50, 4, 4))):
        assert len(jaxsync.mesh.coincident_nodes(mesh)) == 0
        assert np.all(jaxsync.mesh.connected_components(mesh) == 0)


def test_merging_drops_the_faces_of_the_cut_and_refuses_to_collapse_elements():
    beam, points, tets, n_copies = split_beam()
    # a facet set holding both faces of the cut: the triangles at x = 12 on either side
    x = points[:, 0]
    faces = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
    tris = np.sort(tets[:, faces].reshape(-1, 3), axis=1)
    on_cut = np.isclose(x[tris], 12.0).all(axis=1)
    cut_faces = np.unique(tris[on_cut], axis=0)
    assert len(cut_faces) == 2 * 2 * 2 * 2  # 2 x 2 quads, 2 triangles each, on both sides
    with pytest.warns(MeshWarning):
        cut = validated_mesh(points, tets, facet_sets={"cut": cut_faces})
    assert len(cut.facet_sets["cut"]) == 16
    merged = jaxsync.merge_coincident_nodes(cut)
    assert len(merged.facet_sets["cut"]) == 0  # interior after the merge
    # a tolerance so large that an element's own nodes merge: refused
    with pytest.raises(MeshError, match="collapse element"):
        jaxsync.merge_coincident_nodes(merged, tol=2.0)
    with pytest.raises(MeshError, match="tolerance"):
        jaxsync.mesh.coincident_nodes(merged, tol=-1.0)


# ----------------------------------------------------------------------------- arrays, as files are checked


TET = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("points, tets, match", [
    (TET, [[0, 2, 1, 3]], r"element 0 .* is inverted .*jaxsync\.Mesh\.from_arrays"),
    (TET[:, :2], [[0, 1, 2, 3]], "points are 2-D"),
    (TET, [[0, 1, 2, 7]], r"element 0 refers to node indices \[0, 1, 2, 7\] outside 0..3"),
    (np.where(np.eye(4, 3, -1) == 1, np.nan, TET), [[0, 1, 2, 3]], "node 1 has non-finite coordinates"),
    (np.vstack([TET, [[5.0, 5.0, 5.0]]]), [[0, 1, 2, 3]], r"1 nodes are used by no element \(first: node 4\)"),
    (TET, [[0, 1, 1, 3]], "repeats a node"),
    (TET, np.zeros((0, 4), int), "no tetrahedra"),
    (TET, [[0.0, 1.0, 2.0, 3.0]], "must be integers"),
    ([["a", "b", "c"]] * 4, [[0, 1, 2, 3]], "points must be an"),
])
def test_a_mesh_built_from_arrays_is_checked_as_a_file_is(points, tets, match):
    with pytest.raises(MeshError, match=match):
        jaxsync.Mesh(points, tets)


def test_a_mesh_from_arrays_with_facets_off_the_node_list_is_refused():
    with pytest.raises(MeshError, match="facet 0 of the set 'top' refers to node indices"):
        jaxsync.Mesh(TET, [[0, 1, 2, 3]], facet_sets={"top": [[1, 2, 9]]})
    with pytest.raises(MeshError, match="shape \\(n_facets, 3\\)"):
        jaxsync.Mesh(TET, [[0, 1, 2, 3]], facet_sets={"top": [[1, 2, 3, 0]]})


def test_from_arrays_repairs_what_read_mesh_repairs(tmp_path):
    points = np.vstack([TET, [[5.0, 5.0, 5.0]]])
    with pytest.warns(MeshWarning) as caught:
        mesh = jaxsync.Mesh.from_arrays(points, [[0, 2, 1, 3]], facet_sets={"base": [[0, 1, 2]]})
    assert {"inverted" in str(w.message) or "used by no element" in str(w.message) for w in caught} == {True}
    assert mesh.n_nodes == 4 and mesh.volumes()[0] == pytest.approx(1 / 6)
    np.testing.assert_array_equal(mesh.source_node_ids, [0, 1, 2, 3])
    # the same arrays through a file give the same mesh
    path = tmp_path / "m.vtu"
    meshio.write(path, meshio.Mesh(points, [("tetra", np.array([[0, 2, 1, 3]]))]))
    with pytest.warns(MeshWarning):
        read = jaxsync.read_mesh(path)
    np.testing.assert_array_equal(read.tets, mesh.tets)
    np.testing.assert_array_equal(read.points, mesh.points)


def test_box_beam_refuses_what_it_cannot_make():
    for divisions in ((4.5, 1, 1), (4, 1), (0, 1, 1), ("4", 1, 1.0000001)):
        with pytest.raises(MeshError, match="three whole numbers >= 1"):
            jaxsync.box_beam(4.0, 1.0, 1.0, divisions)
    assert jaxsync.box_beam(4.0, 1.0, 1.0, (4.0, 1, np.int64(1))).n_elements == 24
    with pytest.raises(MeshError, match="positive finite lengths"):
        jaxsync.box_beam(float("inf"), 1.0, 1.0, (4, 1, 1))


def test_a_file_with_other_volume_cells_beside_tetrahedra_is_refused(tmp_path):
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1], [1, 1, 1],
                       [0.5, 0.5, 2.0]], dtype=float)
    path = tmp_path / "mixed.vtu"
    meshio.write(path, meshio.Mesh(points, [("tetra", np.array([[4, 5, 6, 8]])),
                                            ("hexahedron", np.array([[0, 1, 3, 2, 4, 5, 7, 6]]))]))
    with pytest.raises(MeshError, match=r"1 volume cells that are not tetrahedra \(hexahedron\)"):
        jaxsync.read_mesh(path)
