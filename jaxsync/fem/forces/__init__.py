"""The forces the explicit step asks of the physics: the seam (:mod:`.internal_force`: the
force model a run compiles, preassembled or formed every step), element forces of small-strain
laws (:mod:`.element_force`), the total-Lagrangian internal force of finite-strain laws
(:mod:`.total_lagrangian`), follower pressure (:mod:`.follower`), elastic supports
(:mod:`.support`), and the forces of the zero-pressure problem's unknown reference
(:mod:`.inverse`, :mod:`.inverse_loads`)."""
