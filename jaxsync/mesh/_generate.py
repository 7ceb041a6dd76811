"""Generated meshes: the structured box beam of the paper's cantilever."""

from __future__ import annotations

import numpy as np

from ..errors import MeshError
from ._mesh import Mesh, tet_volumes


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

    try:
        counts = [float(n) for n in divisions]
    except (TypeError, ValueError):
        counts = []
    if len(counts) != 3 or any(isinstance(n, (bool, np.bool_)) for n in divisions) or not all(
            np.isfinite(n) and n == int(n) and n >= 1 for n in counts):
        raise MeshError(f"box_beam divisions must be three whole numbers >= 1 (cells along x, y, z), got {divisions!r}")
    nx, ny, nz = (int(n) for n in counts)
    try:
        sizes = [float(v) for v in (length, width, height)]
    except (TypeError, ValueError):
        sizes = [float("nan")]
    if not all(np.isfinite(v) and v > 0 for v in sizes):
        raise MeshError(f"box_beam dimensions must be positive finite lengths [cm], got {(length, width, height)}")
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
