"""The constitutive laws: the protocol every law implements (:mod:`.law`), the small-strain
linear elastic law (:mod:`.linear_elastic`), the finite-strain hyperelastic laws
(:mod:`.hyperelastic`), the viscoelastic laws with their internal variables
(:mod:`.viscoelastic`) and a law with a prestrain per quadrature point (:mod:`.prestress`).
Their names are exported by :mod:`jaxsync.fem` and :mod:`jaxsync`; a law of your own is one
module implementing :class:`~jaxsync.fem.materials.law.MaterialLaw` (the guide Material laws
of your own)."""
