"""Writing a :class:`jaxsync.Mesh` to a file that :func:`jaxsync.read_mesh` reads back with
its facet sets (:func:`write_mesh`)."""

from __future__ import annotations

import os

import numpy as np

from ..errors import MeshError

__all__ = ["write_mesh", "MESH_FORMATS", "FACET_SET_PREFIX"]

FACET_SET_PREFIX = "facet_set:"
"""The cell data of a VTK file that :func:`write_mesh` writes for each facet set (1 on its
triangles), which :func:`jaxsync.read_mesh` reads back as the set of that name."""

MESH_FORMATS = {".vtu": "vtu", ".msh": "gmsh22", ".vtk": "vtk"}
"""The extensions :func:`write_mesh` writes, and meshio's name of each format."""


def write_mesh(mesh, path: str | os.PathLike, *, replace: bool = False) -> str:
    """Write ``mesh`` to ``path`` (``.vtu``, ``.msh`` gmsh 2.2 or legacy ``.vtk``, by its
    extension) atomically (:func:`jaxsync.io.atomic_path`): the tetrahedra (``tetra``, or
    ``tetra10`` with a quadratic mesh's mid nodes), and each facet set as a block of
    triangles: in a gmsh file tagged by the cell data ``gmsh:physical`` with the set's name
    in the field data (gmsh's physical groups), in a VTK file marked by the cell data
    ``facet_set:<name>`` (:data:`FACET_SET_PREFIX`); :func:`jaxsync.read_mesh` reads either
    back as the facet sets. VTK files also hold the point data ``GlobalNodeID``
    (``source_node_ids + 1``).

    Args:
        replace: replace an existing file (default: refuse it).

    Returns:
        The path written.

    Raises:
        MeshError: an extension it does not write.
        OutputError: ``path`` exists and ``replace`` is False, or the write failed.
    """
    import meshio

    from ..errors import OutputError
    from ..io.atomic import atomic_path

    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower()
    if ext not in MESH_FORMATS:
        raise MeshError(f"cannot write a mesh as {ext or '(no extension)'!r}: choose one of "
                        f"{', '.join(MESH_FORMATS)} (facet sets kept)")
    if os.path.exists(path) and not replace:
        raise OutputError(f"{path} already exists: choose another name, or replace it explicitly")
    if mesh.mid_nodes is None:
        points, cells = mesh.points, [("tetra", mesh.tets)]
    else:  # tetra10: one node per edge after the vertices, in VTK's edge order
        order = ((0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3))
        pairs = np.sort(np.stack([mesh.tets[:, list(e)] for e in order], axis=1), axis=2).reshape(-1, 2)
        edges, first, inverse = np.unique(pairs, axis=0, return_index=True, return_inverse=True)
        mids = np.asarray(mesh.mid_nodes).reshape(-1, 3)[first]
        points = np.concatenate([mesh.points, mids])
        cells = [("tetra10", np.concatenate([mesh.tets, mesh.n_nodes + inverse.reshape(-1, 6)], axis=1))]
    names = list(mesh.facet_sets)
    for name in names:
        cells.append(("triangle", np.asarray(mesh.facet_sets[name], dtype=np.int64)))
    sizes = [len(c) for _, c in cells]
    if ext == ".msh":  # gmsh's physical groups: a tag per block, the names in the field data
        physical = [np.full(n, k + 1, dtype=np.int32) for k, n in enumerate(sizes)]
        cell_data = {"gmsh:physical": physical, "gmsh:geometrical": physical}
        field_data = {"wall": np.array([1, 3]), **{name: np.array([k + 2, 2]) for k, name in enumerate(names)}}
        point_data = {}  # gmsh files keep no point data that meshio reads back
    else:  # VTK keeps no names of tags: one 0/1 cell array per facet set, FACET_SET_PREFIX + name
        cell_data = {FACET_SET_PREFIX + name: [np.full(n, int(b == k + 1), dtype=np.int8) for b, n in enumerate(sizes)]
                     for k, name in enumerate(names)}
        field_data = {}
        node_ids = np.concatenate([np.asarray(mesh.source_node_ids) + 1,
                                   np.zeros(len(points) - mesh.n_nodes, dtype=np.int64)]).astype(np.int32)
        point_data = {"GlobalNodeID": node_ids}
    written = meshio.Mesh(points, cells, point_data=point_data, cell_data=cell_data, field_data=field_data)
    with atomic_path(path, replace=replace) as tmp:
        kwargs = {"binary": False} if ext == ".msh" else {}
        meshio.write(tmp, written, file_format=MESH_FORMATS[ext], **kwargs)
    return path
