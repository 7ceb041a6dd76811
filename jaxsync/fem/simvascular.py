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

import base64
import dataclasses
import os
import pathlib
import re
from typing import Any, Mapping, NamedTuple

import numpy as np

from ..errors import MeshError

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


# ---------------------------------------------------------------------------------------
# reading VTK XML PolyData


class CellBlock(NamedTuple):
    """Cells of one kind, as meshio has them: ``type`` and ``data`` (n_cells, n_nodes)."""

    type: str
    data: np.ndarray


@dataclasses.dataclass(frozen=True, eq=False)
class PolyData:
    """The content of a ``.vtp`` file, laid out like a ``meshio.Mesh``.

    Attributes:
        points: (n_points, 3) coordinates.
        cells: :class:`CellBlock` runs in the file's cell order (VTK's: vertices, lines,
            polygons, strips): ``"vertex"``, ``"polyvertex"``, ``"line"``, ``"polyline"``,
            ``"triangle"``, ``"quad"``, ``"polygon"`` (5 or more nodes) and
            ``"triangle_strip"``.
        point_data: name -> (n_points, ...) array.
        cell_data: name -> list of arrays, one per block of ``cells``.
    """

    points: np.ndarray
    cells: list
    point_data: dict
    cell_data: dict


_VTK_TYPES = {"Int8": "i1", "UInt8": "u1", "Int16": "i2", "UInt16": "u2", "Int32": "i4",
              "UInt32": "u4", "Int64": "i8", "UInt64": "u8", "Float32": "f4", "Float64": "f8"}
_SECTIONS = ("Verts", "Lines", "Polys", "Strips")  # VTK's cell order in PolyData
_NAMED_SIZES = {("Verts", 1): "vertex", ("Lines", 2): "line", ("Polys", 3): "triangle",
                ("Polys", 4): "quad"}
_GENERAL = {"Verts": "polyvertex", "Lines": "polyline", "Polys": "polygon",
            "Strips": "triangle_strip"}


def read_vtp(path: str | os.PathLike) -> PolyData:
    """Read a VTK XML PolyData file (``.vtp``).

    Raises:
        MeshError: the file is not VTK XML PolyData, or is damaged or truncated (the
            message names the file).
    """
    path = os.fspath(path)
    try:
        with open(path, "rb") as f:
            content = f.read()
    except OSError as exc:
        raise MeshError(f"could not read face file {path!r}: {exc.strerror or exc}") from exc
    try:
        return _XmlPolyData(content, path).read()
    except MeshError:
        raise
    except Exception as exc:  # a damaged file fails in many ways: XML, base64, zlib, shapes
        raise MeshError(f"could not read face file {path!r} ({type(exc).__name__}: {exc}); it is "
                        "not a complete VTK XML PolyData (.vtp) file: re-export it") from exc


class _XmlPolyData:
    """One parse of a ``.vtp`` file's bytes."""

    def __init__(self, content: bytes, path: str):
        from xml.etree import ElementTree

        self.path = path
        self.appended, self.appended_raw = b"", True
        start = re.search(rb"<AppendedData\b[^>]*>", content)
        if start is None:
            root = ElementTree.fromstring(content)
        else:
            # raw appended data is not XML: parse the head, keep the bytes after the "_"
            tag = ElementTree.fromstring(start.group(0)[:-1] + b"/>")
            self.appended_raw = tag.get("encoding", "raw") == "raw"
            begin = content.index(b"_", start.end()) + 1
            end = content.rfind(b"</AppendedData>")
            self.appended = content[begin:end if end > begin else len(content)]
            if not self.appended_raw:
                self.appended = b"".join(self.appended.split())
            root = ElementTree.fromstring(content[:start.start()] + b"</VTKFile>")
        if root.tag != "VTKFile":
            raise MeshError(f"face file {path!r} is not a VTK XML file (its root is <{root.tag}>); "
                            "faces are VTK XML PolyData (.vtp) surfaces")
        kind = root.get("type")
        if kind != "PolyData":
            raise MeshError(f"face file {path!r} holds VTK XML {kind}, not PolyData; faces are "
                            "surfaces of triangles in .vtp files (SimVascular's mesh-surfaces/)")
        self.root = root
        self.order = ">" if root.get("byte_order") == "BigEndian" else "<"
        self.header = np.dtype(self.order + {"UInt32": "u4", "UInt64": "u8"}[
            root.get("header_type", "UInt32")])
        self.decompress = _decompressor(root.get("compressor"), path)

    def read(self) -> PolyData:
        grid = self.root.find("PolyData")
        pieces = [] if grid is None else grid.findall("Piece")
        if not pieces:
            raise MeshError(f"face file {self.path!r} has no <PolyData><Piece>: it holds no surface")
        points, blocks, point_data, cell_data, offset = [], [], {}, {}, 0
        for piece in pieces:
            n_points = int(piece.get("NumberOfPoints", 0))
            coords = piece.find("Points/DataArray")
            xyz = (np.zeros((0, 3)) if coords is None or n_points == 0
                   else self.array(coords).reshape(n_points, -1))
            points.append(xyz)
            runs = []  # (section, type, data) in VTK's cell order
            for section in _SECTIONS:
                runs += self.cells(piece, section, offset)
            blocks += [CellBlock(kind, data) for kind, data in runs]
            n_cells = sum(len(data) for _, data in runs)
            for name, value in self.data(piece.find("PointData"), n_points).items():
                point_data.setdefault(name, []).append(value)
            bounds = np.cumsum([0] + [len(data) for _, data in runs])
            for name, value in self.data(piece.find("CellData"), n_cells).items():
                cell_data.setdefault(name, []).extend(
                    value[a:b] for a, b in zip(bounds[:-1], bounds[1:]))
            offset += n_points
        n_pieces = len(pieces)
        point_data = {k: np.concatenate(v) for k, v in point_data.items() if len(v) == n_pieces}
        cell_data = {k: v for k, v in cell_data.items() if len(v) == len(blocks)}
        return PolyData(points=np.concatenate(points).astype(np.float64), cells=blocks,
                        point_data=point_data, cell_data=cell_data)

    def cells(self, piece, section: str, offset: int) -> list[tuple[str, np.ndarray]]:
        count = int(piece.get(f"NumberOf{section}", 0))
        element = piece.find(section)
        if count == 0 or element is None:
            return []
        arrays = {a.get("Name"): a for a in element.findall("DataArray")}
        if "connectivity" not in arrays or "offsets" not in arrays:
            raise MeshError(f"face file {self.path!r}: <{section}> lacks its connectivity or offsets "
                            "array (a VTK legacy layout?); re-export it with a current VTK or SimVascular")
        connectivity = self.array(arrays["connectivity"]).astype(np.int64).ravel()
        ends = self.array(arrays["offsets"]).astype(np.int64).ravel()
        if len(ends) == count + 1 and ends[0] == 0:
            ends = ends[1:]  # offsets with the leading 0
        if len(ends) != count or (count and ends[-1] > len(connectivity)):
            raise MeshError(f"face file {self.path!r}: <{section}> has {len(ends)} offsets for "
                            f"{count} cells; the file is damaged: re-export it")
        sizes = np.diff(ends, prepend=0)
        starts = ends - sizes
        cut = np.concatenate([[0], np.flatnonzero(np.diff(sizes)) + 1, [count]])
        runs = []
        for a, b in zip(cut[:-1], cut[1:]):
            k = int(sizes[a])
            data = connectivity[starts[a]:ends[b - 1]].reshape(b - a, k) + offset
            runs.append((_NAMED_SIZES.get((section, k), _GENERAL[section]), data))
        return runs

    def data(self, element, n: int) -> dict[str, np.ndarray]:
        out = {}
        for array in ([] if element is None else element.findall("DataArray")):
            name = array.get("Name")
            values = self.array(array)
            if name and len(values) == n:
                out[name] = values
        return out

    def array(self, element) -> np.ndarray:
        kind = element.get("type")
        if kind not in _VTK_TYPES:
            raise MeshError(f"face file {self.path!r}: data array {element.get('Name')!r} has the "
                            f"unknown type {kind!r}")
        dtype = np.dtype(self.order + _VTK_TYPES[kind])
        form = element.get("format", "ascii")
        if form == "ascii":
            values = np.array((element.text or "").split(), dtype=dtype.newbyteorder("="))
        elif form == "binary":
            values = np.frombuffer(self.base64_block(b"".join((element.text or "").encode().split())),
                                   dtype=dtype)
        elif form == "appended":
            start = int(element.get("offset", 0))
            block = (self.raw_block(start) if self.appended_raw
                     else self.base64_block(self.appended[start:]))
            values = np.frombuffer(block, dtype=dtype)
        else:
            raise MeshError(f"face file {self.path!r}: unknown data format {form!r}")
        components = int(element.get("NumberOfComponents") or 1)
        values = values.astype(dtype.newbyteorder("="))
        return values.reshape(-1, components) if components > 1 else values

    def raw_block(self, start: int) -> bytes:
        """An array's bytes in raw appended data: its header, then its (compressed) blocks."""
        data, size = self.appended, self.header.itemsize
        if self.decompress is None:
            n = int(np.frombuffer(data[start:start + size], self.header)[0])
            return data[start + size:start + size + n]
        n_blocks = int(np.frombuffer(data[start:start + size], self.header)[0])
        header = np.frombuffer(data[start:start + (3 + n_blocks) * size], self.header)
        return self.inflate(header, data[start + (3 + n_blocks) * size:])

    def base64_block(self, text: bytes) -> bytes:
        """An array's bytes from base64 text: VTK encodes the header and the data apart
        (the header then ends with '=' padding); a single stream is read too."""
        size = self.header.itemsize
        n_items = 1
        if self.decompress is not None:
            first = base64.b64decode(text[:_b64_length(size)])[:size]
            n_items = 3 + int(np.frombuffer(first, self.header)[0])
        head_chars = _b64_length(n_items * size)
        head_text = text[:head_chars]
        header = np.frombuffer(base64.b64decode(head_text)[:n_items * size], self.header)
        if head_text.endswith(b"="):
            body = base64.b64decode(text[head_chars:])
        else:
            body = base64.b64decode(text)[n_items * size:]
        if self.decompress is None:
            return body[:int(header[0])]
        return self.inflate(header, body)

    def inflate(self, header: np.ndarray, body: bytes) -> bytes:
        n_blocks, full, last = (int(v) for v in header[:3])
        out, at = [], 0
        for k, compressed in enumerate(header[3:3 + n_blocks]):
            compressed = int(compressed)
            expected = last if (k == n_blocks - 1 and last) else full
            out.append(self.decompress(body[at:at + compressed], expected))
            at += compressed
        return b"".join(out)


def _b64_length(n_bytes: int) -> int:
    return 4 * ((n_bytes + 2) // 3)


def _decompressor(name: str | None, path: str):
    """(compressed bytes, uncompressed size) -> bytes for a VTK compressor, None: none."""
    if name is None:
        return None
    if name == "vtkZLibDataCompressor":
        import zlib

        return lambda data, size: zlib.decompress(data)
    if name == "vtkLZMADataCompressor":
        import lzma

        return lambda data, size: lzma.decompress(data)
    if name == "vtkLZ4DataCompressor":
        try:
            import lz4.block
        except ImportError:
            raise MeshError(f"face file {path!r} is LZ4-compressed: install the lz4 package "
                            "(pip install lz4), or re-export it with zlib compression") from None
        return lambda data, size: lz4.block.decompress(data, uncompressed_size=size)
    raise MeshError(f"face file {path!r}: unknown compressor {name!r}; re-export it with zlib "
                    "compression or none")


# ---------------------------------------------------------------------------------------
# the folder and the face files


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
