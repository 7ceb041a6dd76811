"""The constitutive laws. The modules are private; these names are the package's interface
(the main ones are re-exported by :mod:`jaxsync.fem` and :mod:`jaxsync`):

- the protocol every law implements: :class:`MaterialLaw` (:class:`MaterialParameters`,
  :class:`LawCost`; :func:`check_material_law` checks a law against it), and
  :class:`FiniteStrainLaw`, the base of a finite-strain law given by its stress;
- the small-strain linear elastic law: :class:`LinearElastic` (:func:`shear_modulus`,
  :func:`first_lame`);
- the finite-strain hyperelastic laws: :class:`NeoHookean`,
  :class:`NearlyIncompressibleNeoHookean`, :class:`HolzapfelGasserOgden` with its fibres
  (:func:`helical_fibres`); :func:`is_hyperelastic`;
- the viscoelastic laws, with their internal variables: Prony series of Maxwell branches
  (:class:`PronySeries`, :func:`check_branches`, :data:`STATE_NAMES`) on the neo-Hookean
  and HGO laws (:class:`ViscoelasticNeoHookean`, :class:`ViscoelasticHGO`,
  :class:`StandardLinearSolid`);
- a law with a prestrain per quadrature point: :class:`Prestressed`.

A law of your own implements :class:`MaterialLaw` (the guide Material laws of your own).
"""

from typing import TYPE_CHECKING

from ...lazy import export_lazily

__all__ = ["MaterialLaw", "FiniteStrainLaw", "MaterialParameters", "LawCost", "check_material_law", "LinearElastic",
           "shear_modulus", "first_lame", "NeoHookean", "NearlyIncompressibleNeoHookean", "HolzapfelGasserOgden",
           "helical_fibres", "is_hyperelastic", "PronySeries", "ViscoelasticNeoHookean", "ViscoelasticHGO",
           "StandardLinearSolid", "STATE_NAMES", "check_branches", "Prestressed"]

# where each name of __all__ is imported from on first use (jaxsync.lazy): the imports of TYPE_CHECKING below
__getattr__, __dir__ = export_lazily(__name__, {
    "._law": ("FiniteStrainLaw", "LawCost", "MaterialLaw", "MaterialParameters", "check_material_law"),
    "._linear_elastic": ("LinearElastic", "first_lame", "shear_modulus"),
    "._hyperelastic": ("HolzapfelGasserOgden", "NearlyIncompressibleNeoHookean", "NeoHookean", "helical_fibres",
                       "is_hyperelastic"),
    "._viscoelastic": ("PronySeries", "STATE_NAMES", "StandardLinearSolid", "ViscoelasticHGO", "ViscoelasticNeoHookean",
                       "check_branches"),
    "._prestress": ("Prestressed",),
})

if TYPE_CHECKING:
    from ._hyperelastic import (
        HolzapfelGasserOgden,
        NearlyIncompressibleNeoHookean,
        NeoHookean,
        helical_fibres,
        is_hyperelastic,
    )
    from ._law import FiniteStrainLaw, LawCost, MaterialLaw, MaterialParameters, check_material_law
    from ._linear_elastic import LinearElastic, first_lame, shear_modulus
    from ._prestress import Prestressed
    from ._viscoelastic import (
        STATE_NAMES,
        PronySeries,
        StandardLinearSolid,
        ViscoelasticHGO,
        ViscoelasticNeoHookean,
        check_branches,
    )
