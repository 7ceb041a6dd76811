"""SimVascular mesh folders: the volume ``mesh-complete.mesh.vtu`` and one surface file per
face, ``mesh-surfaces/<face>.vtp``; :func:`jaxsync.read_mesh` reads them through this
module.

The layout, as SimVascular's mesher writes it:

- ``mesh-complete.mesh.vtu``: the volume, tetrahedra (cell data ``GlobalElementID``,
  point data ``GlobalNodeID``, the 1-based node numbers);
- ``mesh-surfaces/<face>.vtp``: one VTK XML PolyData file per face (triangles; point data
  ``GlobalNodeID``, the volume node of each surface point; cell data ``GlobalElementID``,
  the volume element of each triangle, often ``ModelFaceID``). The file stem names the
  face: ``mesh-surfaces/wall_outer.vtp`` becomes the facet set ``wall_outer``;
- often also ``mesh-complete.exterior.vtp`` and ``walls_combined.vtp`` at the top: unions
  of faces, not read.

A face's triangles are mapped onto volume nodes through ``GlobalNodeID``: through the
volume's own ``GlobalNodeID`` when its points carry one, else as 1-based positions in the
volume's point list. Every triangle must be a face of exactly one tetrahedron (a face on
the volume's boundary); anything else is a :class:`~jaxsync.MeshError` naming the file.

:func:`write_folder` writes a mesh in this layout (a generated vessel for SimVascular's
solvers, or a folder to try the reader on).

meshio (5.3) reads the volume but no ``.vtp`` file, so :func:`read_vtp` reads VTK XML
PolyData itself: ASCII, inline binary and appended (raw or base64) data, uncompressed or
compressed (zlib, LZMA; LZ4 with the ``lz4`` package), 32- or 64-bit headers, either byte
order, several pieces.
"""

from __future__ import annotations

import os
import pathlib
from typing import Any, Mapping

import numpy as np

from ..errors import MeshError
from ._vtp import CellBlock, PolyData, read_vtp

__all__ = ["VOLUME_FILE", "SURFACES_FOLDER", "PolyData", "CellBlock", "read_vtp",
           "folder_layout", "named_faces", "VolumeNodes", "face_triangles", "check_on_boundary",
           "write_folder"]

VOLUME_FILE = "mesh-complete.mesh.vtu"
"""The volume mesh of a SimVascular mesh folder."""

SURFACES_FOLDER = "mesh-surfaces"
"""The folder of a SimVascular mesh folder that holds one ``.vtp`` file per face."""

NODE_IDS = "GlobalNodeID"
"""Point data that numbers the volume's nodes (1-based) and maps surface points onto them."""

_EXPORT_FIX = ("export the volume and its faces together (SimVascular: Meshing, then 'Write "
               "Mesh'), so that mesh-surfaces/ belongs to mesh-complete.mesh.vtu")


def folder_layout(folder: str | os.PathLike) -> tuple[str, dict[str, str]]:
    """(volume file, face name -> face file) of a SimVascular mesh folder.

    Raises:
        MeshError: no ``mesh-complete.mesh.vtu`` in the folder, no ``mesh-surfaces/``
            folder, or no ``.vtp`` file in it.
    """
    folder = os.fspath(folder)
    volume = os.path.join(folder, VOLUME_FILE)
    if not os.path.isfile(volume):
        others = sorted(p.name for p in pathlib.Path(folder).glob("*.vtu"))
        held = (f" (it holds {', '.join(others)}: to read one of them, give its path, with "
                "faces=[...] for its .vtp faces)" if others else "")
        raise MeshError(
            f"{folder!r} is a folder without {VOLUME_FILE}{held}; read_mesh reads a folder in "
            f"SimVascular's layout ({VOLUME_FILE} and {SURFACES_FOLDER}/*.vtp): give the path of "
            "a mesh file, or of a SimVascular mesh folder")
    surfaces = os.path.join(folder, SURFACES_FOLDER)
    if not os.path.isdir(surfaces):
        raise MeshError(
            f"{folder!r}: no {SURFACES_FOLDER}/ folder beside {VOLUME_FILE}, so the mesh has no "
            f"named faces; {_EXPORT_FIX}, or read the volume alone with read_mesh({volume!r})")
    faces = {p.stem: str(p) for p in sorted(pathlib.Path(surfaces).glob("*.vtp")) if p.is_file()}
    if not faces:
        raise MeshError(
            f"{surfaces!r} holds no .vtp face files; {_EXPORT_FIX}, or read the volume alone "
            f"with read_mesh({volume!r})")
    return volume, faces


def named_faces(faces) -> dict[str, str]:
    """Face name -> file of ``read_mesh(..., faces=...)``: a mapping name -> path as given,
    or paths named after their stems (``walls/inner.vtp`` -> ``inner``).

    Raises:
        MeshError: two paths with the same stem, or a name that is not a non-empty string.
    """
    if isinstance(faces, (str, os.PathLike)):
        faces = [faces]
    if isinstance(faces, Mapping):
        named = {}
        for name, path in faces.items():
            if not isinstance(name, str) or not name:
                raise MeshError(f"faces: the name {name!r} of {os.fspath(path)!r} must be a "
                                "non-empty string")
            named[name] = os.fspath(path)
        return named
    named, seen = {}, {}
    for path in faces:
        path = os.fspath(path)
        name = pathlib.Path(path).stem
        if name in seen:
            raise MeshError(f"faces: {seen[name]!r} and {path!r} would both be the facet set "
                            f"{name!r}; pass a mapping {{name: path}} to name them")
        seen[name] = path
        named[name] = path
    return named


class VolumeNodes:
    """Maps ``GlobalNodeID`` values onto positions in the volume's point list: through
    the volume's own ``GlobalNodeID`` (``ids``) when it has one, else id - 1.

    Args:
        ids: the volume's ``GlobalNodeID`` point data, or None.
        n_points: number of points of the volume.
        path: the volume file (for messages).
    """

    def __init__(self, ids, n_points: int, path: str):
        self.n_points, self.path = int(n_points), path
        self.ids = None if ids is None else _integers(ids, f"{path}: point data {NODE_IDS}")
        if self.ids is not None:
            if len(self.ids) != self.n_points:
                raise MeshError(f"{path}: point data {NODE_IDS} has {len(self.ids)} values for "
                                f"{self.n_points} points; the volume file is damaged: re-export it")
            order = np.argsort(self.ids, kind="stable")
            repeated = np.flatnonzero(np.diff(self.ids[order]) == 0)
            if repeated.size:
                raise MeshError(
                    f"{path}: point data {NODE_IDS} gives the number {int(self.ids[order][repeated[0]])} "
                    f"to several points ({repeated.size} repeats); the faces cannot be mapped onto "
                    "it: re-export the mesh, or remove GlobalNodeID to map the faces by position")
            self.order, self.sorted = order, self.ids[order]

    @property
    def source_node_ids(self) -> np.ndarray | None:
        """The volume's ``GlobalNodeID`` - 1 (None: it has none): each node's number in
        the user's own numbering, 0-based (:attr:`jaxsync.Mesh.source_node_ids`)."""
        return None if self.ids is None else self.ids - 1

    def describe(self) -> str:
        if self.ids is None:
            return f"1..{self.n_points}, the 1-based positions of its {self.n_points} points"
        return f"{int(self.sorted[0])}..{int(self.sorted[-1])}, its own {NODE_IDS} of {self.n_points} points"

    def positions(self, ids: np.ndarray, face_path: str) -> np.ndarray:
        """Positions of ``ids`` (any shape) in the volume's point list."""
        ids = np.asarray(ids, dtype=np.int64)
        if self.ids is None:
            found = (ids >= 1) & (ids <= self.n_points)
            where = ids - 1
        else:
            at = np.minimum(np.searchsorted(self.sorted, ids), max(self.n_points - 1, 0))
            found = self.sorted[at] == ids if self.n_points else np.zeros(ids.shape, bool)
            where = self.order[at] if self.n_points else at
        if not found.all():
            bad = np.unique(ids[~found])
            shown = ", ".join(str(int(v)) for v in bad[:5]) + (", ..." if bad.size > 5 else "")
            raise MeshError(
                f"{face_path}: {bad.size} {NODE_IDS} values of its triangles ({shown}) are not "
                f"nodes of the volume {self.path} (its nodes are {self.describe()}); the face "
                f"belongs to another mesh: {_EXPORT_FIX}")
        return np.asarray(where, dtype=np.int64)

    def numbers(self, positions: np.ndarray) -> np.ndarray:
        """The ``GlobalNodeID`` of volume positions (position + 1 without one)."""
        positions = np.asarray(positions, dtype=np.int64)
        return positions + 1 if self.ids is None else self.ids[positions]


def _integers(values, what: str) -> np.ndarray:
    values = np.asarray(values).reshape(-1)
    if values.dtype.kind in "iu":
        return values.astype(np.int64)
    if values.dtype.kind == "f" and np.all(np.isfinite(values)) and np.all(values == np.round(values)):
        return values.astype(np.int64)
    raise MeshError(f"{what} must hold integer node numbers, got {values.dtype} values")


def face_triangles(face: Any, path: str, nodes: VolumeNodes) -> np.ndarray:
    """(n_triangles, 3) volume node positions of the triangles of one face file.

    ``face`` is what :func:`read_vtp` (or meshio) read: ``points``, ``cells`` (blocks with
    ``type`` and ``data``) and ``point_data`` with ``GlobalNodeID``. Triangles repeated in
    the file are kept once.

    Raises:
        MeshError: cells other than triangles, no triangles, no ``GlobalNodeID``, or ids
            that are not nodes of the volume.
    """
    counts: dict[str, int] = {}
    for block in face.cells:
        counts[block.type] = counts.get(block.type, 0) + len(block.data)
    others = {k: v for k, v in counts.items() if k != "triangle" and v}
    n_triangles = counts.get("triangle", 0)
    if others:
        listed = ", ".join(f"{v} {k}" for k, v in others.items())
        raise MeshError(
            f"{path}: the face has cells other than triangles ({listed}, beside {n_triangles} "
            "triangles); jaxsync's faces are the triangles of linear tetrahedra: export the "
            "surface as triangles (and the volume as linear tetrahedra)")
    if n_triangles == 0:
        raise MeshError(f"{path}: the face has no triangles; {_EXPORT_FIX}, or leave the file out")
    triangles = np.concatenate([np.asarray(b.data, dtype=np.int64).reshape(-1, 3)
                                for b in face.cells if b.type == "triangle"])
    ids = face.point_data.get(NODE_IDS)
    if ids is None:
        has = ", ".join(sorted(face.point_data)) or "none"
        raise MeshError(
            f"{path}: the face has no point data {NODE_IDS} (its point data: {has}); jaxsync "
            f"maps a face onto the volume through {NODE_IDS}, each point's 1-based volume node: "
            "export the faces with the volume (SimVascular's mesh-surfaces/), or add it")
    ids = _integers(ids, f"{path}: point data {NODE_IDS}")
    n_points = len(face.points)
    if len(ids) != n_points:
        raise MeshError(f"{path}: point data {NODE_IDS} has {len(ids)} values for {n_points} "
                        "points; the file is damaged: re-export it")
    if triangles.size and (triangles.min() < 0 or triangles.max() >= n_points):
        raise MeshError(f"{path}: triangles refer to points outside 0..{n_points - 1}; the file "
                        "is damaged: re-export it")
    mapped = nodes.positions(ids[triangles], path)
    _, first = np.unique(np.sort(mapped, axis=1), axis=0, return_index=True)
    return mapped[np.sort(first)]


_LOCAL_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def check_on_boundary(tets: np.ndarray, faces: Mapping[str, np.ndarray], paths: Mapping[str, str],
                      nodes: VolumeNodes) -> None:
    """Raise :class:`MeshError` unless every triangle of ``faces`` (name -> triangles of
    volume positions) is a face of exactly one of ``tets``: on the volume's boundary.

    The message names the file of the first face that fails, how many of its triangles
    are faces of no tetrahedron and how many are interior faces (of two or more)."""
    tets = np.asarray(tets)
    names = [n for n in faces if len(faces[n])]
    if not names or tets.size == 0:
        return
    element_faces = np.sort(tets[:, _LOCAL_FACES].reshape(-1, 3), axis=1)
    wanted = [np.sort(faces[n], axis=1) for n in names]
    keys, inverse = np.unique(np.concatenate([element_faces, *wanted]), axis=0, return_inverse=True)
    inverse = inverse.ravel()
    owners = np.bincount(inverse[:len(element_faces)], minlength=len(keys))
    at = len(element_faces)
    for name, tri in zip(names, wanted):
        count = owners[inverse[at:at + len(tri)]]
        at += len(tri)
        bad = np.flatnonzero(count != 1)
        if bad.size:
            none, inner = int((count == 0).sum()), int((count > 1).sum())
            first = nodes.numbers(faces[name][bad[0]]).tolist()
            raise MeshError(
                f"{paths[name]}: {bad.size} of its {len(tri)} triangles are not on the boundary of "
                f"the volume {nodes.path} ({none} are faces of no tetrahedron, {inner} are interior "
                f"faces of two or more); first: the triangle of {NODE_IDS} {first}. {_EXPORT_FIX}")


# ---------------------------------------------------------------------------------------
# writing


def write_folder(mesh, folder: str | os.PathLike) -> str:
    """Write ``mesh`` as a SimVascular mesh folder: ``mesh-complete.mesh.vtu`` (point data
    ``GlobalNodeID`` = node + 1, cell data ``GlobalElementID`` = element + 1) and one
    ``mesh-surfaces/<name>.vtp`` per facet set (ASCII VTK XML PolyData; point data
    ``GlobalNodeID``, cell data ``GlobalElementID`` of the element each triangle bounds and
    ``ModelFaceID``, the face's number from 1).

    The folder is created and must not exist yet, or be empty. Returns its path.

    Raises:
        OutputError: the folder exists and holds files.
        MeshError: a facet set with triangles that are not on the mesh's boundary.
    """
    import meshio

    from ..errors import OutputError

    folder = os.fspath(folder)
    if os.path.exists(folder) and (not os.path.isdir(folder) or os.listdir(folder)):
        raise OutputError(f"cannot write a SimVascular mesh folder at {folder}: it exists and is not "
                          "an empty folder; choose another name")
    owners = _owning_elements(mesh)
    os.makedirs(os.path.join(folder, SURFACES_FOLDER), exist_ok=True)
    numbers = np.arange(1, mesh.n_nodes + 1, dtype=np.int32)
    meshio.write(os.path.join(folder, VOLUME_FILE), meshio.Mesh(
        mesh.points, [("tetra", mesh.tets)], point_data={NODE_IDS: numbers},
        cell_data={"GlobalElementID": [np.arange(1, mesh.n_elements + 1, dtype=np.int32)]}),
        file_format="vtu")
    for number, (name, triangles) in enumerate(mesh.facet_sets.items(), start=1):
        triangles = np.asarray(triangles, dtype=np.int64)
        used, local = np.unique(triangles, return_inverse=True)
        elements = owners(triangles, name)
        _write_ascii_vtp(os.path.join(folder, SURFACES_FOLDER, f"{name}.vtp"), mesh.points[used],
                         local.reshape(-1, 3), {NODE_IDS: numbers[used]},
                         {"GlobalElementID": (elements + 1).astype(np.int32),
                          "ModelFaceID": np.full(len(triangles), number, dtype=np.int32)})
    return folder


def _owning_elements(mesh):
    """A function (triangles, name) -> the element each triangle is a face of."""
    faces = np.sort(mesh.tets[:, _LOCAL_FACES].reshape(-1, 3), axis=1)
    order = np.lexsort(faces.T[::-1])
    ordered = faces[order]

    def owners(triangles, name):
        if len(triangles) == 0:
            return np.zeros(0, dtype=np.int64)
        wanted = np.sort(triangles, axis=1)
        view = lambda a: np.ascontiguousarray(a).view([("", a.dtype)] * 3).ravel()  # noqa: E731
        keys, probe = view(ordered), view(wanted)
        first = np.searchsorted(keys, probe, side="left")
        last = np.searchsorted(keys, probe, side="right")
        if not np.all(last - first == 1):
            raise MeshError(f"facet set {name!r} holds {int(np.sum(last - first != 1))} triangles "
                            "that are not on the mesh's boundary; SimVascular's faces are boundary faces")
        return order[first] // 4

    return owners


def _write_ascii_vtp(path: str, points, triangles, point_data: dict, cell_data: dict) -> None:
    def array(name, values, kind, components=1):
        text = " ".join(repr(v) for v in np.asarray(values).ravel().tolist())
        extra = f' NumberOfComponents="{components}"' if components > 1 else ""
        return f'<DataArray type="{kind}" Name="{name}"{extra} format="ascii">{text}</DataArray>'

    lines = ['<?xml version="1.0"?>',
             '<VTKFile type="PolyData" version="0.1" byte_order="LittleEndian">', "<PolyData>",
             f'<Piece NumberOfPoints="{len(points)}" NumberOfVerts="0" NumberOfLines="0" '
             f'NumberOfStrips="0" NumberOfPolys="{len(triangles)}">',
             "<PointData>", *(array(k, v, "Int32") for k, v in point_data.items()), "</PointData>",
             "<CellData>", *(array(k, v, "Int32") for k, v in cell_data.items()), "</CellData>",
             "<Points>", array("Points", np.asarray(points, dtype=np.float64), "Float64", 3), "</Points>",
             "<Polys>", array("connectivity", triangles, "Int64"),
             array("offsets", 3 * np.arange(1, len(triangles) + 1), "Int64"), "</Polys>",
             "</Piece>", "</PolyData>", "</VTKFile>", ""]
    with open(path, "w") as f:
        f.write("\n".join(lines))
