"""Tetrahedral meshes: the :class:`Mesh` container and its checks, reading any
meshio-readable file or a SimVascular mesh folder, the generated box beam, and writing a
SimVascular folder (:mod:`jaxsync.mesh.simvascular`).

Layout follows meshio (``points`` is (n_nodes, 3), ``tets`` is (n_elements, 4)), the
transpose of scikit-fem's ``p``/``t``. Boundary facet sets are named triangle lists.
Generated vessels (:func:`jaxsync.vessel_mesh`, :func:`jaxsync.coronary_mesh`) build on
these.
"""

from typing import TYPE_CHECKING

from ..lazy import export_lazily

__all__ = ["Mesh", "MeshWarning", "read_mesh", "box_beam", "tet_volumes", "to_skfem", "validated_mesh",
           "coincident_nodes", "connected_components", "merge_coincident_nodes", "warn_about_topology",
           "COINCIDENT_TOLERANCE", "read_vtp", "PolyData", "CellBlock", "write_mesh", "MESH_FORMATS"]

# where each name of __all__ is imported from on first use (jaxsync.lazy): the imports of TYPE_CHECKING below
__getattr__, __dir__ = export_lazily(__name__, {
    "._generate": ("box_beam",),
    "._mesh": ("COINCIDENT_TOLERANCE", "Mesh", "MeshWarning", "coincident_nodes", "connected_components",
               "merge_coincident_nodes", "tet_volumes", "to_skfem", "validated_mesh", "warn_about_topology"),
    "._read": ("read_mesh",),
    "._vtp": ("CellBlock", "PolyData", "read_vtp"),
    "._write": ("MESH_FORMATS", "write_mesh"),
})

if TYPE_CHECKING:
    from ._generate import box_beam
    from ._mesh import (
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
    from ._read import read_mesh
    from ._vtp import CellBlock, PolyData, read_vtp
    from ._write import MESH_FORMATS, write_mesh
