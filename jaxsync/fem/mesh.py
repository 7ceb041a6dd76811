"""The earlier home of :mod:`jaxsync.mesh` (meshes, reading files, the box beam): every name
it had is re-exported from there, so that ``from jaxsync.fem.mesh import Mesh`` still
works. New code imports :mod:`jaxsync.mesh`."""

from ..mesh._generate import box_beam
from ..mesh._mesh import (
                          COINCIDENT_TOLERANCE,
                          Mesh,
                          MeshWarning,
                          coincident_nodes,
                          connected_components,
                          merge_coincident_nodes,
                          tet_volumes,
                          to_skfem,
                          validated_mesh,
                          warn_about_topology,
)
from ..mesh._read import read_mesh

__all__ = ["Mesh", "MeshWarning", "read_mesh", "box_beam", "tet_volumes", "to_skfem",
           "coincident_nodes", "connected_components", "merge_coincident_nodes"]

# names the module had beside __all__ (imported from here by earlier code)
_ALSO = (COINCIDENT_TOLERANCE, validated_mesh, warn_about_topology)
