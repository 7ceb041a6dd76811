"""Reading tetrahedral meshes: any meshio-readable file, or a SimVascular mesh folder."""

from __future__ import annotations

import contextlib
import io
import os
import pathlib

import numpy as np

from ..errors import MeshError
from . import simvascular
from ._mesh import Mesh, validated_mesh

_TETRA_TYPES = ("tetra", "tetra10")
_UNSUPPORTED_3D = ("hexahedron", "hexahedron20", "hexahedron27", "wedge", "pyramid")


def read_mesh(path: str | os.PathLike, *, faces=None) -> Mesh:
    """Read a tetrahedral mesh from any meshio-readable file (gmsh .msh, VTK, VTU, XDMF...),
    or from a SimVascular mesh folder.

    Tetrahedra of all ``tetra`` blocks are kept, or of all ``tetra10`` blocks (quadratic
    tetrahedra: the mesh keeps their edge nodes as :attr:`Mesh.mid_nodes`, and problems on
    it use P2 elements by default); other cell blocks (vertices, lines) are ignored, except
    triangles (``triangle`` or ``triangle6``: their vertices), which become boundary facet
    sets: one per physical tag
    (``gmsh:physical`` cell data, named through ``field_data`` when the file has names),
    plus named ``cell_sets`` of triangles. Untagged triangles are kept as ``"boundary"``.

    A folder is read in SimVascular's layout (:mod:`jaxsync.mesh.simvascular`): the volume
    ``mesh-complete.mesh.vtu`` and one facet set per ``mesh-surfaces/<name>.vtp``, named
    after the file's stem, its triangles mapped onto the volume's nodes through the point
    data ``GlobalNodeID`` (1-based; through the volume's own ``GlobalNodeID`` when it has
    one, whose values - 1 then become :attr:`Mesh.source_node_ids`).

    Args:
        path: a mesh file, or a SimVascular mesh folder.
        faces: face files for a volume file, in the same form as SimVascular's
            (``.vtp`` PolyData of triangles with point data ``GlobalNodeID``): a list of
            paths (each a facet set named after its stem) or a mapping name -> path.

    Every face must lie on the volume's boundary (each triangle a face of exactly one
    tetrahedron). The result goes through the same checks and repairs as any mesh.

    Raises:
        MeshError: missing, empty, unreadable or unsupported file, no tetrahedra, bad
            coordinates or connectivity; a folder without ``mesh-complete.mesh.vtu`` or
            without face files; a face file without ``GlobalNodeID``, with ids that are not
            nodes of the volume, with cells other than triangles, or off the boundary.
    """
    path = os.fspath(path)
    if os.path.isdir(path):
        if faces is not None:
            raise MeshError(f"{path!r} is a folder, read in SimVascular's layout with the faces of "
                            "its mesh-surfaces/; pass faces=... only with a volume file")
        path, faces = simvascular.folder_layout(path)
    elif faces is not None:
        faces = simvascular.named_faces(faces)
    raw = _read_raw(path)
    tet_blocks, tri_blocks = {"tetra": [], "tetra10": []}, []
    for i, block in enumerate(raw.cells):
        if block.type in _TETRA_TYPES:
            tet_blocks[block.type].append(block.data)
        elif block.type in ("triangle", "triangle6"):
            tri_blocks.append((i, block.data[:, :3]))
    if not tet_blocks["tetra"] and not tet_blocks["tetra10"]:
        kinds = ", ".join(sorted({b.type for b in raw.cells})) or "none"
        hint = (" (non-tetrahedral volume cells are not supported: export tetrahedra)"
                if any(b.type in _UNSUPPORTED_3D for b in raw.cells) else "")
        raise MeshError(f"{path}: the file has no tetrahedra (cell blocks: {kinds}){hint}")
    if tet_blocks["tetra"] and tet_blocks["tetra10"]:
        raise MeshError(f"{path}: the file mixes linear (tetra) and quadratic (tetra10) tetrahedra; export "
                        "one order")
    others = sorted({b.type for b in raw.cells if b.type in _UNSUPPORTED_3D})
    if others:  # dropping them would silently cut the body
        count = sum(len(b.data) for b in raw.cells if b.type in _UNSUPPORTED_3D)
        raise MeshError(f"{path}: the file holds {count} volume cells that are not tetrahedra ({', '.join(others)}) "
                        "beside its tetrahedra; jaxsync solves on tetrahedra only: split them into tetrahedra "
                        "(in gmsh: Mesh.SubdivisionAlgorithm = 0 and tetrahedral meshing) and export again")
    mid_nodes = mid_node_ids = None
    if tet_blocks["tetra10"]:
        cells = np.concatenate(tet_blocks["tetra10"], axis=0)
        tets, mid_node_ids = cells[:, :4], np.unique(cells[:, 4:])
        if np.any((cells < 0) | (cells >= len(raw.points))):
            raise MeshError(f"{path}: a tetra10 cell refers to nodes outside 0..{len(raw.points) - 1}")
        mid_nodes = np.asarray(raw.points, dtype=float)[cells[:, 4:10]]
    else:
        tets = np.concatenate(tet_blocks["tetra"], axis=0)
    facet_sets = _triangle_sets(raw, tri_blocks)
    points = raw.points
    if points.shape[1] == 2:
        raise MeshError(f"{path}: points are 2-D; jaxsync needs a 3-D tetrahedral mesh")
    source_node_ids = None
    if faces:
        facet_sets, source_node_ids = _with_face_files(raw, path, tets, facet_sets, faces)
    return validated_mesh(points, tets, facet_sets, source_node_ids, origin=path, mid_nodes=mid_nodes,
                          mid_node_ids=mid_node_ids)


def _with_face_files(raw, path: str, tets: np.ndarray, facet_sets: dict,
                     faces: dict[str, str]) -> tuple[dict, np.ndarray | None]:
    """The facet sets of the volume file plus one per face file (name -> path), and the
    volume's own node numbers (its ``GlobalNodeID`` - 1; None without)."""
    nodes = simvascular.VolumeNodes(raw.point_data.get(simvascular.NODE_IDS), len(raw.points), path)
    sets = dict(facet_sets)
    for name, face_path in faces.items():
        if name in sets:
            raise MeshError(f"{face_path}: the facet set {name!r} is also a set of triangles of "
                            f"{path}; give the face another name (faces={{name: path}})")
        sets[name] = simvascular.face_triangles(_read_face(face_path), face_path, nodes)
    tets = np.asarray(tets)
    if (tets.ndim == 2 and tets.shape[1] == 4 and np.issubdtype(tets.dtype, np.integer)
            and tets.size and tets.min() >= 0 and tets.max() < len(raw.points)):
        # otherwise validated_mesh says what is wrong with the elements
        simvascular.check_on_boundary(tets, {n: sets[n] for n in faces}, faces, nodes)
    return sets, nodes.source_node_ids


def _read_face(path: str):
    """A face file: ``.vtp`` (VTK XML PolyData) through :func:`simvascular.read_vtp`,
    any other surface format through meshio."""
    if pathlib.Path(path).suffix.lower() == ".vtp":
        _check_exists(path, "face file")
        _check_not_blank(path, "face file")
        return simvascular.read_vtp(path)
    return _read_raw(path, "face file")


def _known_mesh_extensions(path: str) -> list[str]:
    """meshio formats that the file name's extension(s) stand for (``[]``: unknown)."""
    import meshio

    ext, formats = "", []
    for suffix in reversed(pathlib.Path(path).suffixes):
        ext = (suffix + ext).lower()
        formats += meshio.extension_to_filetypes.get(ext, [])
    return formats


def _is_blank(path: str, limit: int = 1 << 16) -> bool:
    """True for a file of at most ``limit`` bytes that holds nothing but white space."""
    if os.path.getsize(path) > limit:
        return False
    with open(path, "rb") as f:
        return not f.read().strip()


def _check_exists(path: str, what: str = "mesh file") -> None:
    """:class:`MeshError` for a file that does not exist or is a folder."""
    if not os.path.exists(path):
        raise MeshError(f"{what} {path!r} does not exist; check the path (relative paths "
                        f"are taken from {os.getcwd()!r})")
    if os.path.isdir(path):
        raise MeshError(f"{what} {path!r} is a folder; give the path of a mesh file")


def _check_not_blank(path: str, what: str = "mesh file") -> None:
    if _is_blank(path):
        raise MeshError(f"{what} {path!r} is empty; re-export the mesh "
                        "(in gmsh: File > Export, or gmsh -3 file.geo -o file.msh)")


def _read_raw(path: str, what: str = "mesh file"):
    """``meshio.read(path)`` with every failure turned into a :class:`MeshError` that names
    the file. meshio ends the interpreter (``SystemExit``) when no reader accepts a file
    and prints its readers' complaints; those are caught and put into the message."""
    import meshio

    _check_exists(path, what)
    if pathlib.Path(path).suffix.lower() == ".vtp":
        raise MeshError(
            f"{what} {path!r} is a .vtp surface (VTK PolyData), not a volume mesh; give the "
            "volume (.vtu) with the surfaces as faces: read_mesh(volume, faces=[...]), or the "
            "SimVascular mesh folder that holds both")
    if not _known_mesh_extensions(path):
        common = ".msh (gmsh), .vtk, .vtu, .xdmf, .med, .inp (Abaqus)"
        raise MeshError(
            f"{what} {path!r}: unknown extension {os.path.splitext(path)[1] or '(none)'!r}; "
            f"jaxsync reads meshes through meshio, which picks the format from the "
            f"extension: rename the file or convert it to one of {common}")
    _check_not_blank(path, what)
    chatter = io.StringIO()
    try:
        with contextlib.redirect_stdout(chatter), contextlib.redirect_stderr(chatter):
            return meshio.read(path)
    except SystemExit as exc:  # meshio's "no reader accepted the file"; not KeyboardInterrupt
        said = " ".join(chatter.getvalue().split())
        raise MeshError(f"could not read {what} {path!r}: it is not a valid "
                        f"{'/'.join(_known_mesh_extensions(path))} file"
                        + (f" (meshio: {said})" if said else "")
                        + "; check that it is a complete mesh file, or re-export it") from exc
    except Exception as exc:  # meshio raises many types; re-raise as ours with the cause
        raise MeshError(f"could not read {what} {path!r} "
                        f"({type(exc).__name__}: {exc}); the file is damaged, truncated or "
                        "not a mesh of that format: re-export it") from exc


def _triangle_sets(raw, tri_blocks) -> dict[str, np.ndarray]:
    """Group triangle blocks into named facet sets from physical tags / cell sets."""
    if not tri_blocks:
        return {}
    names_by_tag = {}
    for name, value in (raw.field_data or {}).items():
        value = np.atleast_1d(value)
        if len(value) >= 2 and int(value[1]) == 2:
            names_by_tag[int(value[0])] = name
    sets: dict[str, list[np.ndarray]] = {}
    tagged_any = False
    # cell sets first: meshio lists every member of each physical group there, while
    # "gmsh:physical" keeps only an element's FIRST tag, so a surface in two groups
    # would be missing from the second one
    for name, per_block in (raw.cell_sets or {}).items():
        if name.startswith("gmsh:"):
            continue
        for i, tri in tri_blocks:
            idx = per_block[i] if i < len(per_block) else None
            if idx is not None and len(idx):
                tagged_any = True
                sets.setdefault(name, []).append(tri[np.asarray(idx)])
    for key, per_block in raw.cell_data.items():  # jaxsync.mesh.write_mesh's VTK facet sets
        if key.startswith("facet_set:"):
            for i, tri in tri_blocks:
                marked = np.asarray(per_block[i]).reshape(-1) == 1
                if marked.any():
                    tagged_any = True
                    sets.setdefault(key[len("facet_set:"):], []).append(tri[marked])
    physical = raw.cell_data.get("gmsh:physical")
    for i, tri in tri_blocks:
        if physical is not None and len(physical[i]) == len(tri):
            for tag in np.unique(physical[i]):
                name = names_by_tag.get(int(tag), f"tag{int(tag)}")
                if name in (raw.cell_sets or {}):
                    continue  # complete in the cell sets
                tagged_any = True
                sets.setdefault(name, []).append(tri[physical[i] == tag])
    if not tagged_any:
        sets["boundary"] = [tri for _, tri in tri_blocks]
    return {k: np.concatenate(v, axis=0) for k, v in sets.items()}
