"""Tetrahedral meshes: the :class:`Mesh` container, reading files, generating the box beam.

Layout follows meshio (``points`` is (n_nodes, 3), ``tets`` is (n_elements, 4)), the
transpose of scikit-fem's ``p``/``t``. Boundary facet sets are named triangle lists.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import os
import pathlib
import warnings
from typing import Mapping

import numpy as np

from ..errors import MeshError

__all__ = ["Mesh", "MeshWarning", "read_mesh", "box_beam", "tet_volumes", "to_skfem"]


class MeshWarning(UserWarning):
    """Something in a mesh was repaired at load (inverted elements, unused nodes)."""


@dataclasses.dataclass(frozen=True, eq=False)
class Mesh:
    """A mesh of linear (4-node) tetrahedra.

    Attributes:
        points: (n_nodes, 3) float64 node coordinates [cm].
        tets: (n_elements, 4) int64 node indices, positively oriented.
        facet_sets: name -> (n_facets, 3) int64 node triples of boundary triangles.
        source_node_ids: (n_nodes,) int64 index of each node in the file it was read
            from (differs from ``arange`` when unused nodes were dropped).
    """

    points: np.ndarray
    tets: np.ndarray
    facet_sets: Mapping[str, np.ndarray] = dataclasses.field(default_factory=dict)
    source_node_ids: np.ndarray | None = None

    def __post_init__(self):
        points = np.ascontiguousarray(self.points, dtype=np.float64)
        tets = np.ascontiguousarray(self.tets, dtype=np.int64)
        facets = {str(k): np.ascontiguousarray(v, dtype=np.int64).reshape(-1, 3)
                  for k, v in dict(self.facet_sets).items()}
        src = (np.arange(len(points), dtype=np.int64) if self.source_node_ids is None
               else np.asarray(self.source_node_ids, dtype=np.int64))
        for arr in (points, tets, src, *facets.values()):
            arr.setflags(write=False)
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "tets", tets)
        object.__setattr__(self, "facet_sets", facets)
        object.__setattr__(self, "source_node_ids", src)

    @property
    def n_nodes(self) -> int:
        return self.points.shape[0]

    @property
    def n_elements(self) -> int:
        return self.tets.shape[0]

    @property
    def n_dofs(self) -> int:
        return 3 * self.n_nodes

    @property
    def bounding_box(self) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) corners, each (3,)."""
        return self.points.min(axis=0), self.points.max(axis=0)

    def volumes(self) -> np.ndarray:
        """(n_elements,) element volumes [cm^3]."""
        return tet_volumes(self.points, self.tets)

    def boundary_facets(self) -> np.ndarray:
        """(n_boundary_facets, 3) node triples of faces that belong to one element only,
        ordered so that their right-hand normal points out of the mesh."""
        local = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
        faces = self.tets[:, local].reshape(-1, 3)
        key = np.sort(faces, axis=1)
        _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        return faces[counts[inverse.ravel()] == 1]

    def nodes_where(self, predicate) -> np.ndarray:
        """Indices of nodes whose coordinates satisfy ``predicate(points) -> (n,) bool``."""
        mask = np.asarray(predicate(self.points), dtype=bool).reshape(-1)
        if mask.shape != (self.n_nodes,):
            raise MeshError(
                f"node predicate returned shape {mask.shape}, expected ({self.n_nodes},): "
                "write it to take the (n_nodes, 3) coordinate array and return one bool per node"
            )
        return np.flatnonzero(mask)

    def facet_nodes(self, name: str) -> np.ndarray:
        """Sorted unique node indices of the facet set ``name``."""
        return np.unique(self.facet_set(name))

    def facet_set(self, name: str) -> np.ndarray:
        """(n_facets, 3) triangles of the facet set ``name``; clear error if unknown."""
        if name not in self.facet_sets:
            known = ", ".join(sorted(self.facet_sets)) or "none"
            raise MeshError(
                f"the mesh has no facet set named {name!r} (known: {known}); tag the surface "
                "as a physical group in gmsh or pick one of the known names"
            )
        return self.facet_sets[name]

    def __repr__(self) -> str:
        names = ", ".join(f"{k}: {len(v)}" for k, v in self.facet_sets.items())
        return f"Mesh(n_nodes={self.n_nodes}, n_elements={self.n_elements}, facet_sets={{{names}}})"


def tet_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volumes (n_elements,) of tetrahedra; positive for right-handed ordering."""
    p = points[tets]
    a, b, c = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
    return np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0


def validated_mesh(points, tets, facet_sets=None, source_node_ids=None, *, origin="mesh") -> Mesh:
    """Check and repair raw arrays into a :class:`Mesh`.

    Errors (:class:`MeshError`) for: no tetrahedra, wrong shapes, non-finite coordinates,
    out-of-range indices, repeated nodes within an element, zero-volume elements.
    Repairs (with a :class:`MeshWarning`): inverted elements are re-oriented; nodes used
    by no element are dropped and the remaining nodes renumbered (``source_node_ids``
    keeps the original numbering; facet sets are renumbered too).
    """
    points = np.asarray(points, dtype=np.float64)
    tets = np.asarray(tets)
    if points.ndim != 2 or points.shape[1] not in (2, 3):
        raise MeshError(f"{origin}: points must have shape (n_nodes, 3), got {points.shape}")
    if points.shape[1] == 2:
        raise MeshError(f"{origin}: points are 2-D; jaxsync needs a 3-D tetrahedral mesh")
    if tets.size == 0:
        raise MeshError(
            f"{origin}: the mesh has no tetrahedra; export a 3-D volume mesh "
            "(in gmsh: Mesh > 3D, and include the volume in a physical group)"
        )
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise MeshError(f"{origin}: tets must have shape (n_elements, 4), got {tets.shape}")
    if not np.issubdtype(tets.dtype, np.integer):
        raise MeshError(f"{origin}: element connectivity must be integers, got {tets.dtype}")
    tets = tets.astype(np.int64)
    bad_points = np.flatnonzero(~np.isfinite(points).all(axis=1))
    if bad_points.size:
        raise MeshError(
            f"{origin}: node {bad_points[0]} has non-finite coordinates {points[bad_points[0]]} "
            f"({bad_points.size} such nodes); fix the mesh file"
        )
    out_of_range = np.flatnonzero(((tets < 0) | (tets >= len(points))).any(axis=1))
    if out_of_range.size:
        e = out_of_range[0]
        raise MeshError(
            f"{origin}: element {e} refers to node indices {tets[e].tolist()} outside "
            f"0..{len(points) - 1} ({out_of_range.size} such elements); the connectivity "
            "does not match the node list"
        )
    sorted_tets = np.sort(tets, axis=1)
    repeated = np.flatnonzero((sorted_tets[:, 1:] == sorted_tets[:, :-1]).any(axis=1))
    if repeated.size:
        e = repeated[0]
        raise MeshError(
            f"{origin}: element {e} repeats a node ({tets[e].tolist()}), so it has zero volume; "
            "remove degenerate elements from the mesh"
        )
    vol = tet_volumes(points, tets)
    # Degenerate: volume at round-off level relative to the element's own longest edge.
    p = points[tets]
    longest = np.max([np.linalg.norm(p[:, i] - p[:, j], axis=1)
                      for i in range(4) for j in range(i + 1, 4)], axis=0)
    tiny = np.abs(vol) <= 1e-10 * longest**3
    if tiny.any():
        e = np.flatnonzero(tiny)[0]
        raise MeshError(
            f"{origin}: element {e} (nodes {tets[e].tolist()}) has zero volume "
            f"({vol[e]:.3e}); {int(tiny.sum())} degenerate elements in all: remesh or remove them"
        )
    inverted = vol < 0
    if inverted.any():
        tets = tets.copy()
        tets[inverted] = tets[inverted][:, [0, 2, 1, 3]]
        warnings.warn(
            f"{origin}: {int(inverted.sum())} inverted elements (negative volume) were "
            f"re-oriented, first: element {int(np.flatnonzero(inverted)[0])}",
            MeshWarning, stacklevel=3,
        )
    facet_sets = {k: np.asarray(v, dtype=np.int64).reshape(-1, 3) for k, v in (facet_sets or {}).items()}
    src = np.arange(len(points)) if source_node_ids is None else np.asarray(source_node_ids)
    used = np.zeros(len(points), dtype=bool)
    used[tets.ravel()] = True
    if not used.all():
        new_index = np.full(len(points), -1, dtype=np.int64)
        new_index[used] = np.arange(used.sum())
        warnings.warn(
            f"{origin}: {int((~used).sum())} nodes are used by no element and were dropped "
            "(Mesh.source_node_ids maps the new numbering to the file's)",
            MeshWarning, stacklevel=3,
        )
        tets = new_index[tets]
        kept = {}
        for name, tri in facet_sets.items():
            ok = used[tri].all(axis=1)
            kept[name] = new_index[tri[ok]]
        facet_sets = kept
        points, src = points[used], src[used]
    return Mesh(points=points, tets=tets, facet_sets=facet_sets, source_node_ids=src)


_TETRA_TYPES = ("tetra",)
_UNSUPPORTED_3D = ("tetra10", "hexahedron", "hexahedron20", "hexahedron27", "wedge", "pyramid")


def read_mesh(path: str | os.PathLike) -> Mesh:
    """Read a tetrahedral mesh from any meshio-readable file (gmsh .msh, VTK, VTU, XDMF...).

    Tetrahedra of all ``tetra`` blocks are kept; other cell blocks (vertices, lines) are
    ignored, except triangles, which become boundary facet sets: one per physical tag
    (``gmsh:physical`` cell data, named through ``field_data`` when the file has names),
    plus named ``cell_sets`` of triangles. Untagged triangles are kept as ``"boundary"``.

    Raises:
        MeshError: missing, empty, unreadable or unsupported file, no tetrahedra, bad
            coordinates or connectivity.
    """
    path = os.fspath(path)
    raw = _read_raw(path)
    tet_blocks, tri_blocks = [], []
    for i, block in enumerate(raw.cells):
        if block.type in _TETRA_TYPES:
            tet_blocks.append(block.data)
        elif block.type == "triangle":
            tri_blocks.append((i, block.data))
    if not tet_blocks:
        kinds = ", ".join(sorted({b.type for b in raw.cells})) or "none"
        hint = (" (quadratic or non-tetrahedral volume cells are not supported: export "
                "linear tetrahedra)" if any(b.type in _UNSUPPORTED_3D for b in raw.cells) else "")
        raise MeshError(f"{path}: the file has no tetrahedra (cell blocks: {kinds}){hint}")
    tets = np.concatenate(tet_blocks, axis=0)
    facet_sets = _triangle_sets(raw, tri_blocks)
    points = raw.points
    if points.shape[1] == 2:
        raise MeshError(f"{path}: points are 2-D; jaxsync needs a 3-D tetrahedral mesh")
    return validated_mesh(points, tets, facet_sets, origin=path)


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


def _read_raw(path: str):
    """``meshio.read(path)`` with every failure turned into a :class:`MeshError` that names
    the file. meshio ends the interpreter (``SystemExit``) when no reader accepts a file
    and prints its readers' complaints; those are caught and put into the message."""
    import meshio

    if not os.path.exists(path):
        raise MeshError(f"mesh file {path!r} does not exist; check the path (relative paths "
                        f"are taken from {os.getcwd()!r})")
    if os.path.isdir(path):
        raise MeshError(f"mesh file {path!r} is a folder; give the path of a mesh file")
    if not _known_mesh_extensions(path):
        common = ".msh (gmsh), .vtk, .vtu, .xdmf, .med, .inp (Abaqus)"
        raise MeshError(
            f"mesh file {path!r}: unknown extension {os.path.splitext(path)[1] or '(none)'!r}; "
            f"jaxsync reads meshes through meshio, which picks the format from the "
            f"extension: rename the file or convert it to one of {common}")
    if _is_blank(path):
        raise MeshError(f"mesh file {path!r} is empty; re-export the mesh "
                        "(in gmsh: File > Export, or gmsh -3 file.geo -o file.msh)")
    chatter = io.StringIO()
    try:
        with contextlib.redirect_stdout(chatter), contextlib.redirect_stderr(chatter):
            return meshio.read(path)
    except SystemExit as exc:  # meshio's "no reader accepted the file"; not KeyboardInterrupt
        said = " ".join(chatter.getvalue().split())
        raise MeshError(f"could not read mesh file {path!r}: it is not a valid "
                        f"{'/'.join(_known_mesh_extensions(path))} file"
                        + (f" (meshio: {said})" if said else "")
                        + "; check that it is a complete mesh file, or re-export it") from exc
    except Exception as exc:  # meshio raises many types; re-raise as ours with the cause
        raise MeshError(f"could not read mesh file {path!r} "
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


def box_beam(length: float = 25.0, width: float = 1.0, height: float = 1.0,
             divisions: tuple[int, int, int] = (25, 1, 1)) -> Mesh:
    """Structured tetrahedral mesh of the box [0, length] x [0, width] x [0, height].

    Each hexahedral cell is split into 6 tetrahedra (scikit-fem ``MeshTet.init_tensor``).
    Facet sets ``x0, x1, y0, y1, z0, z1`` name the six faces (``x0`` is the clamped end of
    the cantilever). Default: the coarse cantilever, 104 nodes, 150 elements.

    Args:
        length, width, height: box dimensions [cm] along x, y, z.
        divisions: number of cells along x, y, z (each >= 1).
    """
    from skfem import MeshTet

    nx, ny, nz = (int(n) for n in divisions)
    if min(nx, ny, nz) < 1:
        raise MeshError(f"box_beam divisions must be >= 1 along each axis, got {divisions}")
    if min(length, width, height) <= 0:
        raise MeshError(f"box_beam dimensions must be positive, got {(length, width, height)}")
    m = MeshTet.init_tensor(np.linspace(0, length, nx + 1), np.linspace(0, width, ny + 1),
                            np.linspace(0, height, nz + 1))
    points, tets = m.p.T.copy(), m.t.T.copy()
    vol = tet_volumes(points, tets)
    tets[vol < 0] = tets[vol < 0][:, [0, 2, 1, 3]]
    mesh = Mesh(points=points, tets=tets)
    faces = mesh.boundary_facets()
    centers = points[faces].mean(axis=1)
    tol = 1e-9 * max(length, width, height)
    sets = {}
    for axis, (name, upper) in enumerate((("x", length), ("y", width), ("z", height))):
        sets[f"{name}0"] = faces[np.abs(centers[:, axis]) < tol]
        sets[f"{name}1"] = faces[np.abs(centers[:, axis] - upper) < tol]
    return Mesh(points=points, tets=tets, facet_sets=sets)


def to_skfem(mesh: Mesh):
    """The scikit-fem ``MeshTet`` of ``mesh`` (same node and element numbering)."""
    from skfem import MeshTet

    return MeshTet(np.ascontiguousarray(mesh.points.T), np.ascontiguousarray(mesh.tets.T),
                   sort_t=False)
