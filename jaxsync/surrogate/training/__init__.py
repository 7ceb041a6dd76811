"""Training the surrogate models: from trajectories to trained surrogates (:mod:`.fit`), the
shared histories and sample-refill windows they learn from (:mod:`.histories`,
:mod:`.data`), gradient training of every part's replica in one program (:mod:`.train`,
:mod:`.loss`, :mod:`.training_state`), the least squares of the linear models
(:mod:`.least_squares`), the offline checks (:mod:`.evaluate`) and learning while a run is
synchronized (:mod:`.online`). Their names are exported by :mod:`jaxsync.surrogate`."""
