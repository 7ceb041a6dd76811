"""The reference problems and generated geometries: the paper's cantilever and coronary
artery, the generated left coronary tree and the generated vessel.

They are built from the public finite-element layer (:mod:`jaxsync.fem`, :mod:`jaxsync.mesh`)
as a user's own problem would be: :func:`cantilever` (the paper's beam, Table 1),
:func:`coronary` (the paper's artery: material, pulsatile lumen pressure
:func:`coronary_waveform`, inlet and outlet clamps), :func:`coronary_mesh` (a left coronary
tree of linear tetrahedra generated with gmsh, from the centerline :func:`coronary_tree`)
and :func:`vessel_mesh` (a thick-walled, possibly curved tube along
:func:`vessel_centerline`). Each is also exported at the top level (``jaxsync.cantilever``).
"""

from typing import TYPE_CHECKING

from ..lazy import export_lazily

__all__ = ["cantilever", "coronary", "coronary_waveform", "coronary_material", "DEFAULT_WAVEFORM", "MMHG",
           "CORONARY_PERIOD", "coronary_mesh", "coronary_tree", "CoronaryTree", "VesselSegment",
           "estimated_tree_elements", "vessel_mesh", "vessel_centerline", "estimated_elements"]

# where each name of __all__ is imported from on first use (jaxsync.lazy): the imports of TYPE_CHECKING below
__getattr__, __dir__ = export_lazily(__name__, {
    "._cantilever": ("cantilever",),
    "._coronary": ("CORONARY_PERIOD", "DEFAULT_WAVEFORM", "MMHG", "coronary", "coronary_material",
                   "coronary_waveform"),
    "._coronary_tree": ("CoronaryTree", "VesselSegment", "coronary_mesh", "coronary_tree", "estimated_tree_elements"),
    "._vessel": ("estimated_elements", "vessel_centerline", "vessel_mesh"),
})

if TYPE_CHECKING:
    from ._cantilever import cantilever
    from ._coronary import CORONARY_PERIOD, DEFAULT_WAVEFORM, MMHG, coronary, coronary_material, coronary_waveform
    from ._coronary_tree import CoronaryTree, VesselSegment, coronary_mesh, coronary_tree, estimated_tree_elements
    from ._vessel import estimated_elements, vessel_centerline, vessel_mesh
