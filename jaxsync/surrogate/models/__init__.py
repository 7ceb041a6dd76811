"""The surrogate models: the protocol every model implements (:mod:`.protocol`), the
registry of model kinds by name (:mod:`.registry`), the one code path through a model's
methods (:mod:`.architecture`), the hand-written LSTM encoder-decoder (:mod:`.lstm`), the
linear autoregressive model (:mod:`.linear`), and one replica per part, padded and stacked
(:mod:`.replicas`). Their names are exported by :mod:`jaxsync.surrogate`."""
