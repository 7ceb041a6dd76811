"""VTK XML PolyData (``.vtp``) files, read without VTK: meshio (5.3) reads the volume of a
SimVascular folder but no ``.vtp`` file. ASCII, inline binary and appended (raw or base64)
data, uncompressed or compressed (zlib, LZMA; LZ4 with the ``lz4`` package), 32- or
64-bit headers, either byte order, several pieces.
"""

from __future__ import annotations

import base64
import dataclasses
import os
import re
from typing import NamedTuple

import numpy as np

from ..errors import MeshError

__all__ = ["PolyData", "CellBlock", "read_vtp"]

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
