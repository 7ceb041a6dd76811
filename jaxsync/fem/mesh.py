"""The earlier home of :mod:`jaxsync.mesh` (meshes, reading files, the box beam): every name
it had is re-exported from there, so that ``from jaxsync.fem.mesh import Mesh`` still
works. New code imports :mod:`jaxsync.mesh`."""

from ..mesh import (  # noqa: F401 - re-exported, the last three beside __all__ as before
    COINCIDENT_TOLERANCE,
    Mesh,
    MeshWarning,
    box_beam,
    coincident_nodes,
    connected_components,
    merge_coincident_nodes,
    read_mesh,
    tet_volumes,
    to_skfem,
    validated_mesh,
    warn_about_topology,
)

__all__ = ["Mesh", "MeshWarning", "read_mesh", "box_beam", "tet_volumes", "to_skfem",
           "coincident_nodes", "connected_components", "merge_coincident_nodes"]
