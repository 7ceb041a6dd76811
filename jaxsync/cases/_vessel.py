"""Generated geometries: a thick-walled vessel, straight or bifurcating, meshed with gmsh.

:func:`vessel_mesh` builds a coronary-like artery segment with gmsh's OpenCASCADE kernel
(cylinders for the lumen and for the outer wall, fused, then the lumen cut out of the
wall), meshes it with linear tetrahedra, tags the boundary surfaces as physical groups,
and reads the result back through :func:`jaxsync.read_mesh`, so that the generated mesh
goes through the same path as a user's own ``.msh`` file. It is the stand-in for the
paper's patient-specific coronary mesh (DESIGN.md, reference problem "Coronary").

Coordinates are in cm. The main vessel runs along +z from its inlet at z = 0; branches
lie in the x-z plane.
"""

from __future__ import annotations

import contextlib
import io
import math
import os
import shutil
import tempfile

import numpy as np

from ..errors import MeshError
from ..mesh import Mesh, read_mesh

__all__ = ["vessel_mesh", "estimated_elements", "vessel_centerline"]

#: Tetrahedra per unit of volume / (size**2 min(size, wall)) that gmsh's Delaunay mesher
#: produces for this geometry (measured 4.4-7.1 for sizes 0.03-0.08 cm, wall 0.05 cm): the
#: estimate errs on the high side.
_TETS_PER_SIZE_CUBED = 8.5

MAX_ELEMENTS = 2_000_000
"""The largest mesh the generators make (tetrahedra): beyond it gmsh needs more memory than
a workstation has; ask for fewer elements or a larger size."""

# gmsh options set for every run (recorded and restored when the caller already holds
# an initialized gmsh session).
_OPTIONS = {
    "General.NumThreads": 1,               # deterministic: no threaded meshing
    "Mesh.MaxNumThreads1D": 1,
    "Mesh.MaxNumThreads2D": 1,
    "Mesh.MaxNumThreads3D": 1,
    "Mesh.RandomSeed": 1,
    "Mesh.Algorithm": 6,                   # Frontal-Delaunay surfaces
    "Mesh.Algorithm3D": 1,                 # Delaunay volumes
    "Mesh.ElementOrder": 1,                # linear tetrahedra
    "Mesh.MeshSizeFromPoints": 0,
    "Mesh.MeshSizeFromCurvature": 0,
    "Mesh.MeshSizeExtendFromBoundary": 0,
    "Mesh.Optimize": 1,
    "Mesh.MshFileVersion": 4.1,
    "Mesh.Binary": 0,
    "Mesh.SaveAll": 0,                     # only elements of physical groups
}


def vessel_centerline(*, length: float = 3.0, branch: bool = False,
                      angle: float = 30.0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Centerline segments ``[(start (3,), end (3,)), ...]`` [cm] of :func:`vessel_mesh`.

    Straight: one segment from the origin to (0, 0, length). Bifurcating: the main
    vessel from the origin to the junction (0, 0, length/2), then two branches of length
    length/2 at +-angle degrees from the z axis in the x-z plane (branch 1 towards +x).
    """
    origin = np.zeros(3)
    if not branch:
        return [(origin, np.array([0.0, 0.0, float(length)]))]
    junction = np.array([0.0, 0.0, 0.5 * length])
    a = math.radians(angle)
    ends = [junction + 0.5 * length * np.array([sign * math.sin(a), 0.0, math.cos(a)])
            for sign in (1.0, -1.0)]
    return [(origin, junction), (junction, ends[0]), (junction, ends[1])]


def estimated_elements(*, length: float = 3.0, radius: float = 0.175, wall: float = 0.05,
                       branch: bool = False, size: float = 0.05) -> int:
    """Rough number of tetrahedra :func:`vessel_mesh` makes for these arguments (an
    upper-side estimate from the wall volume and the target element size)."""
    ro = radius + wall
    segments = 3 if branch else 1
    seg_length = length / 2 if branch else length
    volume = segments * math.pi * (ro**2 - radius**2) * seg_length
    # At least one element across the wall, however coarse the size.
    return int(_TETS_PER_SIZE_CUBED * volume / (size**2 * min(size, wall))) + 1


def vessel_mesh(path: str | os.PathLike | None = None, *, length: float = 3.0,
                radius: float = 0.175, wall: float = 0.05, branch: bool = False,
                angle: float = 30.0, size: float = 0.05,
                max_elements: int = MAX_ELEMENTS, verbose: bool = False, order: int = 1) -> Mesh:
    """Mesh a thick-walled vessel (a coronary-like artery) with tetrahedra.

    A tube of lumen radius ``radius`` and wall thickness ``wall`` along the centerline of
    :func:`vessel_centerline`; with ``branch=True`` the main vessel splits into two
    branches of the same radii at its mid-length (a sphere at the junction rounds the
    outside of the bend). Boundary facet sets (gmsh physical surfaces):

    - ``inlet``: the annulus at z = 0;
    - ``outlet``: every outlet annulus; with branches also ``outlet_1`` (towards +x)
      and ``outlet_2`` (towards -x);
    - ``lumen``: the inner wall, where the blood pressure acts (the outward normal of
      the solid there points into the lumen, so ``jaxsync.Pressure(p, surface="lumen")``
      with p > 0 inflates the vessel);
    - ``outer``: the outer wall.

    The volume is the physical group ``wall``. The same arguments give the same mesh.

    Args:
        path: where to write the gmsh ``.msh`` (format 4.1, ASCII) file; None writes
            nothing. The file appears only when the mesh was made and read back.
        length: [cm] of the straight tube; with branches, main vessel and each branch
            are ``length / 2`` long.
        radius: lumen radius [cm] (coronary: 0.15-0.2).
        wall: wall thickness [cm] (coronary: ~0.05).
        branch: make a bifurcation.
        angle: angle of each branch to the main axis [degrees], in (5, 75).
        size: target element edge length [cm]; smaller is finer. The number of
            elements grows like 1 / size**3 (at the default 0.05: about 11 000 for
            the straight tube, 15 000 with branches; a second or two of gmsh).
        max_elements: refuse sizes whose estimated element count exceeds this.
        verbose: let gmsh print its progress to the terminal.
        order: 1 (linear tetrahedra) or 2 (quadratic ``tetra10``, gmsh's mid nodes on the
            curved walls: problems on it use isoparametric P2 elements by default).

    Returns:
        The :class:`jaxsync.Mesh`, read back from the written file.

    Raises:
        MeshError: bad dimensions or size, a mesh that would be too large, or a gmsh
            failure (geometry or meshing), with gmsh's message.
    """
    length, radius, wall, angle, size = _checked(length, radius, wall, angle, size, branch)
    if order not in (1, 2) or isinstance(order, bool):
        raise MeshError(f"vessel_mesh: order must be 1 (linear tetrahedra) or 2 (quadratic), got {order!r}")
    n_est = estimated_elements(length=length, radius=radius, wall=wall, branch=branch, size=size)
    if n_est > max_elements:
        raise MeshError(
            f"vessel_mesh: size={size:g} cm would give about {n_est:,} tetrahedra, more than "
            f"max_elements={max_elements:,}; choose a larger size (at least "
            f"{size * (n_est / max_elements) ** (1 / 3):.3g} cm) or raise max_elements")
    return generated_mesh(
        path, "vessel_mesh",
        lambda gmsh: _build_and_tag(gmsh, length=length, radius=radius, wall=wall,
                                    branch=branch, angle=angle, order=order),
        size=size, verbose=verbose,
        what=f"the vessel (length={length:g}, radius={radius:g}, wall={wall:g}, "
             f"branch={branch}, size={size:g})",
        required=["inlet", "outlet", "lumen", "outer"],
        outlets=["outlet_1", "outlet_2"] if branch else [])


def positive_length(generator: str, name: str, value) -> float:
    """``value`` as a positive finite float, or a :class:`MeshError` naming the
    ``generator``'s argument ``name``."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise MeshError(f"{generator}: {name} must be a number, got {value!r}") from None
    if not math.isfinite(number) or number <= 0:
        raise MeshError(f"{generator}: {name} must be positive and finite, got {value!r}")
    return number


def _checked(length, radius, wall, angle, size, branch):
    length, radius, wall, angle, size = (
        positive_length("vessel_mesh", name, value)
        for name, value in (("length", length), ("radius", radius), ("wall", wall), ("angle", angle),
                            ("size", size)))
    outer = radius + wall
    if size > 2 * outer:
        raise MeshError(f"vessel_mesh: size={size:g} cm is larger than the vessel's outer "
                        f"diameter {2 * outer:g} cm; choose a size of about the wall thickness "
                        f"({wall:g} cm) or below")
    if branch:
        if not 5.0 < angle < 75.0:
            raise MeshError(f"vessel_mesh: branch angle must lie in (5, 75) degrees, got {angle:g}")
        # The branches' outer walls separate at outer / sin(angle) from the junction;
        # they need some length beyond that.
        needed = 2 * (outer / math.sin(math.radians(angle)) + outer)
        if length / 2 < needed:
            raise MeshError(f"vessel_mesh: with branch angle {angle:g} degrees each branch must be "
                            f"longer than {needed:.3g} cm (length > {2 * needed:.3g} cm), got "
                            f"length={length:g}; lengthen the vessel or widen the angle")
    elif length < 2 * outer:
        raise MeshError(f"vessel_mesh: length={length:g} cm is shorter than the vessel's outer "
                        f"diameter {2 * outer:g} cm; make it longer")
    return length, radius, wall, angle, size


# ---------------------------------------------------------------------------------------
# gmsh machinery shared by the generators (also used by the coronary tree's, :func:`jaxsync.cases.coronary_mesh`)
# ---------------------------------------------------------------------------------------

def generated_mesh(path, who: str, build, *, size: float, verbose: bool, what: str,
                   required: list[str], outlets: list[str]) -> Mesh:
    """Run ``build(gmsh)`` (make the geometry, mesh it, add the physical groups) in a gmsh
    session set up by :func:`gmsh_model`, write the ``.msh`` to a temporary file, read it
    back with :func:`jaxsync.read_mesh`, check its facet sets (:func:`check_facet_sets`)
    and only then move it to ``path`` (None: keep no file). ``who`` names the caller in
    messages, ``what`` the geometry."""
    try:
        import gmsh
    except ImportError as exc:  # pragma: no cover - gmsh is a dependency
        raise MeshError(f"{who} needs the gmsh Python package: pip install gmsh") from exc
    target = _target_path(path, who)
    workdir = tempfile.mkdtemp(prefix=f".{who}-", dir=None if target is None else os.path.dirname(target))
    try:
        tmp_file = os.path.join(workdir, "mesh.msh")
        with gmsh_model(gmsh, size=size, verbose=verbose, what=what):
            build(gmsh)
            gmsh.write(tmp_file)
        with contextlib.redirect_stdout(io.StringIO()):   # meshio prints a blank line
            mesh = read_mesh(tmp_file)
        check_facet_sets(mesh, required, outlets, who)
        if target is not None:
            os.replace(tmp_file, target)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    return mesh


def _target_path(path, who: str) -> str | None:
    """The absolute ``.msh`` path to write (its folder created), or None."""
    if path is None:
        return None
    target = os.path.abspath(os.fspath(path))
    if os.path.isdir(target):
        raise MeshError(f"{who}: {target!r} is a directory; give a file name ending in .msh")
    if not target.endswith(".msh"):
        raise MeshError(f"{who} writes gmsh files: the path must end in .msh, got {target!r}")
    os.makedirs(os.path.dirname(target), exist_ok=True)
    return target


@contextlib.contextmanager
def gmsh_model(gmsh, *, size: float, verbose: bool, what: str):
    """A fresh gmsh model with the deterministic :data:`_OPTIONS` and element size
    ``size`` [cm]. A session this opens is finalized on exit; a caller's session gets its
    options and current model back. gmsh failures become :class:`MeshError` naming
    ``what`` with gmsh's last error lines."""
    owns_session = not gmsh.isInitialized()
    if owns_session:
        gmsh.initialize(readConfigFiles=False, interruptible=False)
    saved = {}
    previous_model = None
    model_name = "jaxsync_mesh"
    try:
        options = dict(_OPTIONS, **{"General.Terminal": 1 if verbose else 0,
                                    "General.Verbosity": 5 if verbose else 0,
                                    "Mesh.MeshSizeMin": 0.5 * size,
                                    "Mesh.MeshSizeMax": size})
        for name, value in options.items():
            if not owns_session:
                saved[name] = gmsh.option.getNumber(name)
            gmsh.option.setNumber(name, value)
        if not owns_session:
            previous_model = gmsh.model.getCurrent()
            model_name = f"jaxsync_mesh_{id(saved):x}"
        gmsh.logger.start()
        gmsh.model.add(model_name)
        yield
    except MeshError:
        raise
    except Exception as exc:  # gmsh raises plain Exception with its last error message
        raise MeshError(
            f"gmsh could not build {what}: {exc}{_gmsh_errors(gmsh)}; try a different "
            "size or geometry, or pass verbose=True to see gmsh's output") from exc
    finally:
        _close_model(gmsh, owns_session, model_name, saved, previous_model)


def _close_model(gmsh, owns_session, model_name, saved, previous_model) -> None:
    try:
        if owns_session:
            gmsh.finalize()
            return
        try:
            gmsh.logger.stop()
            gmsh.model.setCurrent(model_name)
            gmsh.model.remove()
        finally:
            for name, value in saved.items():
                gmsh.option.setNumber(name, value)
            if previous_model:
                gmsh.model.setCurrent(previous_model)
    except Exception:  # cleanup must never hide the original error
        pass


def _gmsh_errors(gmsh) -> str:
    try:
        lines = [m for m in gmsh.logger.get() if m.startswith("Error")]
    except Exception:
        return ""
    return (" [gmsh: " + " | ".join(lines[-3:]) + "]") if lines else ""


def occ_cylinder(occ, start: np.ndarray, end: np.ndarray, r: float,
                 extend_start: float = 0.0, extend_end: float = 0.0) -> tuple[int, int]:
    """OCC cylinder (dim, tag) of radius ``r`` [cm] on the segment start-end (3,) [cm],
    lengthened by ``extend_start`` / ``extend_end`` [cm] beyond its ends."""
    axis = (end - start) / np.linalg.norm(end - start)
    a = start - extend_start * axis
    b = end + extend_end * axis
    return (3, occ.addCylinder(*a, *(b - a), r))


def occ_wall(occ, outers: list, lumens: list, what: str) -> None:
    """The wall solid: union of the ``outers`` (dim, tag) minus union of the ``lumens``;
    synchronizes the model and checks that one volume came out."""
    wall = occ.fuse(outers[:1], outers[1:])[0] if len(outers) > 1 else outers
    lumen = occ.fuse(lumens[:1], lumens[1:])[0] if len(lumens) > 1 else lumens
    result, _ = occ.cut(wall, lumen)
    occ.synchronize()
    volumes = [tag for dim, tag in result if dim == 3]
    if len(volumes) != 1:
        raise MeshError(f"gmsh: {what} came out as {len(volumes)} volumes instead of one; "
                        "check the radii, wall thickness and angles")


def tag_surfaces(gmsh, ends: list[tuple[np.ndarray, np.ndarray, float]], is_lumen, tol: float):
    """Sort the meshed surfaces: a planar surface through ``ends[k]`` = (point (3,),
    axis (3,), outer radius) [cm] goes to ``ends[k]``; any other to ``lumen`` when
    ``is_lumen(nodes (n, 3))``, else to ``outer``. Returns (tags per end, lumen tags,
    outer tags)."""
    at_end = [[] for _ in ends]
    lumen, outer = [], []
    for _, tag in gmsh.model.getEntities(2):
        _, coords, _ = gmsh.model.mesh.getNodes(2, tag, includeBoundary=True,
                                                returnParametricCoord=False)
        pts = np.asarray(coords, dtype=float).reshape(-1, 3)
        if len(pts) == 0:
            raise MeshError(f"gmsh: surface {tag} has no mesh nodes")
        hit = [k for k, (p, axis, r_out) in enumerate(ends)
               if abs((pts - p) @ axis).max() <= tol and np.linalg.norm(pts - p, axis=1).max() <= r_out + tol]
        if hit:
            at_end[hit[0]].append(tag)
        else:
            (lumen if is_lumen(pts) else outer).append(tag)
    return at_end, lumen, outer


def add_physical_groups(gmsh, inlet: list[int], outlets: list[list[int]], lumen: list[int],
                        outer: list[int], split_outlets: bool) -> None:
    """Physical groups ``inlet``, ``outlet`` (all outlets), ``outlet_1``... (when
    ``split_outlets``), ``lumen``, ``outer`` and the volume ``wall``; raises
    :class:`MeshError` naming any surface that was not found."""
    missing = [name for name, tags in (("inlet", inlet), ("lumen", lumen), ("outer", outer)) if not tags]
    missing += [f"outlet_{k + 1}" for k, tags in enumerate(outlets) if not tags]
    if missing:
        raise MeshError(f"gmsh: could not find the vessel surfaces {', '.join(missing)}; "
                        "check the geometry arguments")
    # Split outlets first, so that their file tags (meshio's gmsh:physical keeps the
    # first tag of a surface) name them; "outlet" then comes from the cell sets.
    if split_outlets:
        for k, tags in enumerate(outlets):
            gmsh.model.addPhysicalGroup(2, tags, name=f"outlet_{k + 1}")
    gmsh.model.addPhysicalGroup(2, [t for tags in outlets for t in tags], name="outlet")
    for name, tags in (("inlet", inlet), ("lumen", lumen), ("outer", outer)):
        gmsh.model.addPhysicalGroup(2, tags, name=name)
    gmsh.model.addPhysicalGroup(3, [tag for _, tag in gmsh.model.getEntities(3)], name="wall")


def check_facet_sets(mesh: Mesh, required: list[str], outlets: list[str], who: str) -> None:
    """The read-back mesh must carry every ``required`` and ``outlets`` facet set,
    non-empty, and the ``outlets`` together must be the ``outlet`` set."""
    missing = [n for n in required + outlets if len(mesh.facet_sets.get(n, ())) == 0]
    if missing:
        raise MeshError(f"{who}: the mesh read back without facet sets {', '.join(missing)} "
                        f"(found: {', '.join(sorted(mesh.facet_sets)) or 'none'})")
    if outlets:
        n_out = len(mesh.facet_sets["outlet"])
        n_split = sum(len(mesh.facet_sets[n]) for n in outlets)
        if n_out != n_split:
            raise MeshError(f"{who}: the mesh read back with {n_out} outlet triangles but "
                            f"{n_split} in {', '.join(outlets)}; the .msh physical tags were "
                            "not read as expected")


# ---------------------------------------------------------------------------------------
# the vessel
# ---------------------------------------------------------------------------------------

def _build_and_tag(gmsh, *, length, radius, wall, branch, angle, order=1):
    """Make, mesh and tag the vessel in the current gmsh model (of ``order`` 1 or 2)."""
    _build(gmsh, length=length, radius=radius, wall=wall, branch=branch, angle=angle)
    gmsh.model.mesh.generate(3)
    _tag(gmsh, length=length, radius=radius, wall=wall, branch=branch, angle=angle)
    if order == 2:  # mid nodes on the geometry: the curved walls stay curved
        gmsh.model.mesh.setOrder(2)


def _build(gmsh, *, length, radius, wall, branch, angle):
    """The wall solid: union of the outer cylinders minus the union of the lumen ones."""
    occ = gmsh.model.occ
    outer = radius + wall
    segments = vessel_centerline(length=length, branch=branch, angle=angle)
    # The lumen cylinders stick out of the open ends so that the cut leaves clean
    # annuli there instead of faces that coincide with the wall's end caps.
    overhang = 0.5 * wall
    if not branch:
        (start, end), = segments
        outers = [occ_cylinder(occ, start, end, outer)]
        lumens = [occ_cylinder(occ, start, end, radius, overhang, overhang)]
    else:
        junction = segments[0][1]
        outers = [occ_cylinder(occ, s, e, outer) for s, e in segments]
        lumens = [occ_cylinder(occ, segments[0][0], segments[0][1], radius, overhang, 0.0)]
        lumens += [occ_cylinder(occ, s, e, radius, 0.0, overhang) for s, e in segments[1:]]
        outers.append((3, occ.addSphere(*junction, outer)))
        lumens.append((3, occ.addSphere(*junction, radius)))
    occ_wall(occ, outers, lumens, "the vessel wall")


def _distance_to_centerline(points: np.ndarray, segments) -> np.ndarray:
    best = np.full(len(points), np.inf)
    for a, b in segments:
        ab = b - a
        s = np.clip((points - a) @ ab / (ab @ ab), 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(points - (a + s[:, None] * ab), axis=1))
    return best


def _tag(gmsh, *, length, radius, wall, branch, angle):
    """Physical groups from the meshed surfaces: planar ends by their position, curved
    surfaces by the distance of their nodes from the centerline."""
    outer = radius + wall
    segments = vessel_centerline(length=length, branch=branch, angle=angle)
    outlet_segments = segments[1:] if branch else segments
    ends = [(segments[0][0], _unit(segments[0][1] - segments[0][0]), outer)]
    ends += [(b, _unit(b - a), outer) for a, b in outlet_segments]

    def is_lumen(pts):
        return np.median(_distance_to_centerline(pts, segments)) < radius + 0.5 * wall

    at_end, lumen, outer_tags = tag_surfaces(gmsh, ends, is_lumen, tol=1e-6 * max(length, 1.0))
    add_physical_groups(gmsh, at_end[0], at_end[1:], lumen, outer_tags, split_outlets=branch)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)
