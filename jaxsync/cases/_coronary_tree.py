"""A generated coronary-like vessel tree: a main vessel branching into six outlets.

:func:`coronary_tree` describes the centerline of a left coronary artery in the form of
straight segments (start, end, lumen radius, all in cm): the left main (LM) splits into
the left anterior descending (LAD) and the circumflex (LCx); each gives off two side
branches (diagonals D1, D2 and obtuse marginals OM1, OM2), so six ends are open.
:func:`coronary_mesh` turns it into a thick-walled tube of linear tetrahedra with gmsh
(OpenCASCADE: per segment an outer and a lumen cylinder, a sphere at every junction,
all fused, the lumen cut out of the wall) and reads it back through
:func:`jaxsync.read_mesh`, the path a user's own ``.msh`` with the same tags takes.

The root (inlet) is at the origin and the left main runs along +z; the LAD side goes
towards +x, the LCx side towards -x, diagonals towards +y, marginals towards -y.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from ..errors import MeshError
from ..mesh import Mesh
from ._vessel import (
    MAX_ELEMENTS,
    add_physical_groups,
    generated_mesh,
    occ_cylinder,
    occ_wall,
    positive_length,
    tag_surfaces,
)

__all__ = ["VesselSegment", "CoronaryTree", "coronary_tree", "coronary_mesh",
           "estimated_tree_elements"]

#: Tetrahedra per wall volume / (size**2 min(size, wall)) = _TETS_COEFF (size / wall)**_TETS_EXP:
#: fitted to gmsh's counts for the default tree, wall 0.05 cm, sizes 0.02-0.12 cm (4.3-8.0).
_TETS_COEFF = 5.9
_TETS_EXP = 0.35

#: Default element count of :func:`coronary_mesh` when neither size nor target is given.
_DEFAULT_TARGET = 8_000


@dataclass(frozen=True)
class VesselSegment:
    """One straight piece of a vessel tree's centerline.

    Attributes:
        name: a label (``"LAD"``...).
        start, end: (3,) end points [cm].
        radius: lumen radius [cm].
        parent: index of the segment whose ``end`` is this one's ``start`` (None: the root).
    """

    name: str
    start: tuple[float, float, float]
    end: tuple[float, float, float]
    radius: float
    parent: int | None = None

    @property
    def length(self) -> float:
        """[cm]"""
        return float(np.linalg.norm(np.subtract(self.end, self.start)))

    @property
    def axis(self) -> np.ndarray:
        """(3,) unit vector from start to end."""
        d = np.subtract(self.end, self.start)
        return d / np.linalg.norm(d)


@dataclass(frozen=True)
class CoronaryTree:
    """A vessel tree: segments in order, the root (inlet) first, every parent before its
    children. Segments without children are the outlets, numbered in this order."""

    segments: tuple[VesselSegment, ...]

    @property
    def outlets(self) -> list[int]:
        """Indices of the segments whose ``end`` is an open outlet (outlet_1, outlet_2...)."""
        parents = {s.parent for s in self.segments}
        return [k for k in range(len(self.segments)) if k not in parents]

    @property
    def junctions(self) -> list[int]:
        """Indices of the segments whose ``end`` is a branching point."""
        parents = {s.parent for s in self.segments if s.parent is not None}
        return sorted(parents)

    def wall_volume_estimate(self, wall: float) -> float:
        """Sum of the segments' annular wall volumes pi ((r + wall)^2 - r^2) L [cm^3]
        (junctions neither added nor subtracted)."""
        return sum(math.pi * ((s.radius + wall) ** 2 - s.radius**2) * s.length for s in self.segments)

    def surface_gap(self, points: np.ndarray, offset: float = 0.0) -> np.ndarray:
        """(n,) min over segments of (distance to the segment - radius - offset) [cm] for
        (n, 3) points: 0 on the lumen surface (offset 0) or on the outer surface
        (offset = wall), negative inside. Segment ends are rounded (spheres), as are the
        generated junctions."""
        best = np.full(len(points), np.inf)
        for s in self.segments:
            a, b = np.asarray(s.start), np.asarray(s.end)
            ab = b - a
            t = np.clip((points - a) @ ab / (ab @ ab), 0.0, 1.0)
            d = np.linalg.norm(points - (a + t[:, None] * ab), axis=1)
            best = np.minimum(best, d - s.radius - offset)
        return best


def _direction(polar: float, azimuth: float) -> np.ndarray:
    """Unit vector at ``polar`` degrees from +z and ``azimuth`` degrees from +x."""
    p, a = math.radians(polar), math.radians(azimuth)
    return np.array([math.sin(p) * math.cos(a), math.sin(p) * math.sin(a), math.cos(p)])


# name, parent name, length [cm], lumen radius [cm], polar / azimuth angle [degrees]
_LEFT_CORONARY = (
    ("LM", None, 1.0, 0.20, 0.0, 0.0),
    ("LAD1", "LM", 0.8, 0.17, 35.0, 0.0),
    ("LAD2", "LAD1", 0.8, 0.14, 25.0, 0.0),
    ("LAD3", "LAD2", 0.9, 0.12, 15.0, 0.0),       # outlet_1
    ("D1", "LAD1", 0.7, 0.11, 55.0, 70.0),        # outlet_2
    ("D2", "LAD2", 0.6, 0.10, 60.0, 60.0),        # outlet_3
    ("LCx1", "LM", 0.8, 0.15, 50.0, 180.0),
    ("LCx2", "LCx1", 0.8, 0.13, 60.0, 190.0),
    ("LCx3", "LCx2", 0.8, 0.11, 70.0, 200.0),     # outlet_4
    ("OM1", "LCx1", 0.7, 0.11, 70.0, 240.0),      # outlet_5
    ("OM2", "LCx2", 0.6, 0.10, 90.0, 250.0),      # outlet_6
)


def coronary_tree() -> CoronaryTree:
    """The default left-coronary-like tree (cm): left main 1.0 long, lumen radius 0.20,
    splitting into LAD (radius 0.17 -> 0.14 -> 0.12, 2.5 long) and LCx (0.15 -> 0.13 ->
    0.11, 2.4 long); side branches D1 (0.11), D2 (0.10), OM1 (0.11), OM2 (0.10), 0.6-0.7
    long. 11 segments, 8.5 cm of centerline, 5 junctions, 6 outlets: LAD3, D1, D2, LCx3,
    OM1, OM2 (outlet_1 ... outlet_6)."""
    index, segments = {}, []
    for name, parent, length, radius, polar, azimuth in _LEFT_CORONARY:
        start = np.zeros(3) if parent is None else np.asarray(segments[index[parent]].end)
        end = start + length * _direction(polar, azimuth)
        index[name] = len(segments)
        segments.append(VesselSegment(name, tuple(start.tolist()), tuple(end.tolist()), radius,
                                      None if parent is None else index[parent]))
    return CoronaryTree(tuple(segments))


def estimated_tree_elements(tree: CoronaryTree, *, size: float, wall: float = 0.05) -> int:
    """About how many tetrahedra :func:`coronary_mesh` makes at element size ``size`` [cm]:
    a fit to gmsh's counts (within ~20 % for sizes 0.02-0.12 cm), growing like the wall
    volume / (size**2 min(size, wall))."""
    volume = tree.wall_volume_estimate(wall)
    coeff = _TETS_COEFF * (size / wall) ** _TETS_EXP
    return int(coeff * volume / (size**2 * min(size, wall))) + 1


def _size_for(tree: CoronaryTree, target: float, wall: float) -> float:
    """The element size [cm] whose estimated count is ``target`` (the inverse of
    :func:`estimated_tree_elements`: a power of the size on each side of ``wall``)."""
    work = _TETS_COEFF * tree.wall_volume_estimate(wall) / (target * wall**_TETS_EXP)
    size = work ** (1 / (3 - _TETS_EXP))
    return size if size <= wall else (work / wall) ** (1 / (2 - _TETS_EXP))


def coronary_mesh(path: str | os.PathLike | None = None, *, size: float | None = None,
                  target_elements: int | None = None, wall: float = 0.05,
                  tree: CoronaryTree | None = None, verbose: bool = False) -> Mesh:
    """Mesh a thick-walled coronary-like vessel tree with linear tetrahedra.

    Boundary facet sets (gmsh physical surfaces): ``inlet`` (the annulus at the root),
    ``outlet_1`` ... ``outlet_6`` (the end annuli of the tree's outlet segments, in
    :attr:`CoronaryTree.outlets` order), ``outlet`` (all of them), ``lumen`` (the inner
    wall; ``jaxsync.Pressure(p, surface="lumen")`` with p > 0 inflates the tree) and
    ``outer``. The volume is the physical group ``wall``. Same arguments, same mesh.

    Args:
        path: where to write the gmsh ``.msh`` (4.1, ASCII); None writes nothing. The
            file appears only once the mesh was made and read back.
        size: element edge length [cm]; or
        target_elements: roughly how many tetrahedra (5 000 to 400 000 are practical;
            the size is chosen from :func:`estimated_tree_elements`).
            Give one of the two; neither: about ``8 000``, a second or two of gmsh.
        wall: wall thickness [cm], below the smallest lumen radius.
        tree: the centerline (default :func:`coronary_tree`).
        verbose: let gmsh print its progress.

    Raises:
        MeshError: both size and target_elements, non-positive
            values, a wall as thick as a lumen radius, a mesh that would be too large
            (over 2 000 000 tetrahedra) or too coarse for the thinnest branch, a gmsh
            failure.
    """
    tree = coronary_tree() if tree is None else tree
    wall = _positive("wall", wall)
    r_min = min(s.radius for s in tree.segments)
    if wall >= r_min:
        raise MeshError(f"coronary_mesh: wall={wall:g} cm is not thinner than the smallest lumen "
                        f"radius {r_min:g} cm; use a wall below {r_min:g} cm (coronary: ~0.05)")
    size = _chosen_size(tree, size, target_elements, wall)
    return generated_mesh(
        path, "coronary_mesh", lambda gmsh: _build_and_tag(gmsh, tree, wall),
        size=size, verbose=verbose,
        what=f"the coronary tree (wall={wall:g}, size={size:.4g})",
        required=["inlet", "outlet", "lumen", "outer"],
        outlets=[f"outlet_{k + 1}" for k in range(len(tree.outlets))])


def _positive(name: str, value) -> float:
    return positive_length("coronary_mesh", name, value)


def _chosen_size(tree: CoronaryTree, size, target_elements, wall: float) -> float:
    """The element size [cm] from exactly one of ``size`` / ``target_elements``, within
    (the estimate at the largest size, 2 000 000 tetrahedra)."""
    if size is not None and target_elements is not None:
        raise MeshError("coronary_mesh: give either size (element size in cm) or "
                        "target_elements (about how many tetrahedra), not both")
    coarsest = min(s.radius for s in tree.segments) + wall     # the thinnest outer radius
    n_min = estimated_tree_elements(tree, size=coarsest, wall=wall)
    if size is None:
        target = _DEFAULT_TARGET if target_elements is None else _positive("target_elements", target_elements)
        if target > MAX_ELEMENTS:
            raise MeshError(f"coronary_mesh: target_elements={target:,.0f} is above the limit of "
                            f"{MAX_ELEMENTS:,} tetrahedra; ask for fewer")
        if target < n_min:
            raise MeshError(f"coronary_mesh: target_elements={target:,.0f} is too coarse for the "
                            f"thinnest branch; ask for at least {n_min:,}")
        return _size_for(tree, target, wall)
    size = _positive("size", size)
    if size > coarsest:
        raise MeshError(f"coronary_mesh: size={size:g} cm is larger than the thinnest branch's "
                        f"outer radius {coarsest:g} cm; choose a size of at most {coarsest:g} cm")
    n_est = estimated_tree_elements(tree, size=size, wall=wall)
    if n_est > MAX_ELEMENTS:
        raise MeshError(f"coronary_mesh: size={size:g} cm would give about {n_est:,} tetrahedra, "
                        f"more than {MAX_ELEMENTS:,}; choose a larger size (at least "
                        f"{_size_for(tree, MAX_ELEMENTS, wall):.3g} cm) or use target_elements")
    return size


def _build_and_tag(gmsh, tree: CoronaryTree, wall: float) -> None:
    """Make, mesh and tag the tree's wall in the current gmsh model."""
    _build(gmsh, tree, wall)
    gmsh.model.mesh.generate(3)
    _tag(gmsh, tree, wall)


def _build(gmsh, tree: CoronaryTree, wall: float) -> None:
    """Outer and lumen cylinders per segment and spheres at the junctions (of the parent's
    radii), fused; the lumen cut out. Lumen cylinders overhang the open ends by wall/2 so
    that the cut leaves clean end annuli."""
    occ = gmsh.model.occ
    overhang = 0.5 * wall
    outlets = set(tree.outlets)
    outers, lumens = [], []
    for k, s in enumerate(tree.segments):
        a, b = np.asarray(s.start), np.asarray(s.end)
        outers.append(occ_cylinder(occ, a, b, s.radius + wall))
        lumens.append(occ_cylinder(occ, a, b, s.radius, overhang if s.parent is None else 0.0,
                                   overhang if k in outlets else 0.0))
    for k in tree.junctions:
        s = tree.segments[k]
        outers.append((3, occ.addSphere(*s.end, s.radius + wall)))
        lumens.append((3, occ.addSphere(*s.end, s.radius)))
    occ_wall(occ, outers, lumens, "the coronary tree's wall")


def _tag(gmsh, tree: CoronaryTree, wall: float) -> None:
    """Inlet and outlets: the planar annuli at the root's start and the outlets' ends;
    other surfaces are lumen or outer by their nodes' gap to the lumen surface."""
    root = tree.segments[0]
    ends = [(np.asarray(root.start), root.axis, root.radius + wall)]
    ends += [(np.asarray(tree.segments[k].end), tree.segments[k].axis, tree.segments[k].radius + wall)
             for k in tree.outlets]

    def is_lumen(pts):
        return abs(np.median(tree.surface_gap(pts))) < 0.5 * wall

    at_end, lumen, outer = tag_surfaces(gmsh, ends, is_lumen, tol=1e-6)
    add_physical_groups(gmsh, at_end[0], at_end[1:], lumen, outer, split_outlets=True)
