"""The surrogate models, one interface: every call goes through the model's own methods.

A surrogate model is a :class:`~jaxsync.surrogate.models.SurrogateArchitecture` (the
protocol: ``init``, ``forward``, ``fit``, ``online_update``, ``prediction_cost``,
``to_dict``/``from_dict``) registered under its ``kind``
(:func:`~jaxsync.surrogate.models.register_surrogate`). ``forward(params, xs, load_parameter,
dof_mask, compute_dtype=None, loads=None)`` maps a normalized window (n_p, n_dof) to
(n_f, n_dof) (``compute_dtype="bfloat16"``: reduced-precision inference; ``loads``
(n_p + n_f, n_load): the known load signals of a model with load input, ``arch.n_load > 0``,
:class:`~jaxsync.fem.LoadSignals`). Two are built in:

=========  =====================================================
kind       architecture
=========  =====================================================
"lstm"     :class:`~jaxsync.surrogate.models.LSTMArchitecture`
"linear"   :class:`~jaxsync.surrogate.models.LinearArchitecture`
=========  =====================================================

The refill (:func:`~jaxsync.surrogate.refill_predict`) and the surrogate files
(:mod:`jaxsync.io.surrogate_file`) go through :func:`forward`, :func:`init_params`,
:func:`architecture_to_dict` and :func:`architecture_from_dict` (thin functions over the
model's methods and the registry), so :class:`~jaxsync.surrogate.Surrogate` and the solver
hold any model alike.

:class:`ArchitectureChoice` is what a user chooses before any data are read: the model (a
registered kind) and its sizes (:func:`jaxsync.surrogate.train_surrogates` makes the model
from it with the model's ``from_choice`` once the padded width n_dof is known).
"""

from __future__ import annotations

import dataclasses
import numbers
import sys
from types import ModuleType
from typing import Any

import jax

from jaxsync.errors import ConfigError
from jaxsync.surrogate.models._linear import DEFAULT_REGULARIZATION, LinearFitConfig
from jaxsync.surrogate.models._lstm import LSTMArchitecture
from jaxsync.surrogate.models._protocol import SurrogateArchitecture
from jaxsync.surrogate.models._registry import surrogate_class

__all__ = ["Architecture", "ArchitectureChoice", "model_module", "architecture_to_dict",
           "architecture_from_dict", "init_params", "forward"]

#: Any surrogate model (the protocol's base class)
Architecture = SurrogateArchitecture


@dataclasses.dataclass(frozen=True)
class ArchitectureChoice:
    """The surrogate to train and its size, chosen before the data are read: the
    ``architecture`` of :func:`jaxsync.surrogate.train_surrogates` and
    :func:`jaxsync.surrogate.grid_search`.

    The window lengths n_p, n_f are the :class:`~jaxsync.surrogate.training.Sampling`'s; the
    padded width n_dof (and the linear model's rank) come from the data. The defaults are
    those of :class:`~jaxsync.surrogate.models.LSTMArchitecture` and
    :class:`~jaxsync.surrogate.models.LinearFitConfig`, as ``jaxsync train`` uses them.

    Attributes:
        model: ``"lstm"`` (default), the encoder-decoder trained with optax, or
            ``"linear"``, the affine autoregressive baseline fitted by least squares on
            the same windows (:mod:`jaxsync.surrogate.models`; unconditional), or the kind
            of a model registered with :func:`~jaxsync.surrogate.register_surrogate`
            (which takes the fields below of the names of its own fields).
        n_hidden: n_H, hidden size of each encoder direction (default 50; the paper's
            text uses 100). LSTM only.
        n_layers: k, stacked bidirectional encoder layers (default 2). LSTM only.
        n_cond_repeat: q, copies of the load parameter fed to the decoder; > 0 trains the
            conditional network (paper: 12), which needs a load parameter per trajectory.
            Default 0; must be 0 for the linear model.
        dtype: ``"float32"`` (default) or ``"float64"``: parameters and computation, both
            models.
        regularization: relative ridge parameter r >= 0 of the linear fit (default 1e-8,
            :class:`~jaxsync.surrogate.models.LinearFitConfig`). Linear only.
        load_input: feed the networks the known load signals (the time functions of the
            problem's loads and prescribed motions, past and future window,
            :mod:`jaxsync.fem`): the LSTM reads them in its encoder and
            decoder, the linear model becomes ARX. None (default): on when the trajectories
            record load signals (every run of ``jaxsync simulate`` / ``jaxsync.simulate``
            does), off for trajectory files written before they were recorded. True
            requires them (a :class:`~jaxsync.errors.ConfigError` otherwise), False trains
            the load-blind model of the paper. Both models.
        highway: give the LSTM a linear autoregressive highway: it predicts the
            least-squares affine map of the window (the linear model, ARX with the load
            input) plus what its decoder learns on top, trained from that fit
            (:class:`~jaxsync.surrogate.models.LSTMArchitecture`). None (default): on for
            the unconditional LSTM (out of sample it predicts as well as the linear
            model where the plain network misses; ``docs/guides/surrogates.md``), off
            for the conditional one (the map does not read the load parameter), not
            applicable to the other models. False trains the paper's network; True for a model
            without a highway is refused.
    """

    model: str = "lstm"
    n_hidden: int = LSTMArchitecture.n_hidden
    n_layers: int = LSTMArchitecture.n_layers
    n_cond_repeat: int = LSTMArchitecture.n_cond_repeat
    dtype: str = LSTMArchitecture.dtype
    regularization: float = DEFAULT_REGULARIZATION
    load_input: bool | None = None
    highway: bool | None = None

    def __post_init__(self):
        if self.load_input is not None and not isinstance(self.load_input, bool):
            raise ConfigError(f"ArchitectureChoice.load_input must be True, False or None (on when the trajectories "
                              f"record load signals), got {self.load_input!r}")
        if self.highway is not None and not isinstance(self.highway, bool):
            raise ConfigError(f"ArchitectureChoice.highway must be True, False or None (the model's default), "
                              f"got {self.highway!r}")
        model = surrogate_class(self.model)  # refuses an unknown kind, naming the registered ones
        for name, low, what in (("n_hidden", 1, "encoder hidden size n_H"), ("n_layers", 1, "encoder layers k"),
                                ("n_cond_repeat", 0, "copies q of the load parameter; 0: unconditional")):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < low:
                raise ConfigError(f"ArchitectureChoice.{name} must be an integer >= {low} ({what}), got {value!r}")
        if self.dtype not in ("float32", "float64"):
            raise ConfigError(f"ArchitectureChoice.dtype must be 'float32' or 'float64', got {self.dtype!r}")
        model.check_choice(self)
        LinearFitConfig(self.regularization)  # refuses a bad regularization, naming it

    @property
    def fit_config(self) -> LinearFitConfig:
        """The least-squares settings of the linear model (its ``regularization``)."""
        return LinearFitConfig(self.regularization)

    def lstm(self, n_dof: int, n_past: int, n_future: int, n_load: int = 0) -> LSTMArchitecture:
        """The LSTM of this choice for windows of ``n_past`` -> ``n_future`` snapshots of
        ``n_dof`` (padded) dofs, reading ``n_load`` load signals."""
        return LSTMArchitecture(n_dof=n_dof, n_hidden=self.n_hidden, n_layers=self.n_layers, n_past=n_past,
                                n_future=n_future, n_cond_repeat=self.n_cond_repeat, dtype=self.dtype, n_load=n_load,
                                highway=self.n_cond_repeat == 0 if self.highway is None else self.highway)


    @property
    def model_class(self) -> type:
        """The registered class of :attr:`model` (:func:`~jaxsync.surrogate.models.surrogate_class`)."""
        return surrogate_class(self.model)


def _check_model(arch) -> SurrogateArchitecture:
    if not isinstance(arch, SurrogateArchitecture):
        raise ConfigError(f"{arch!r} is not a surrogate model; expected a jaxsync.surrogate.SurrogateArchitecture "
                          "(LSTMArchitecture, LinearArchitecture or a registered model)")
    return arch


def model_module(arch: Architecture) -> ModuleType:
    """The module that defines ``arch``'s class (the private module of a built-in model
    in :mod:`jaxsync.surrogate.models`, or a user's)."""
    return sys.modules[type(_check_model(arch)).__module__]


def architecture_to_dict(arch: Architecture) -> dict[str, Any]:
    """``{"kind": ..., **arch.to_dict()}`` (JSON-ready): what surrogate files and summaries store.

    Raises:
        ConfigError: ``arch`` is not a surrogate model, or its kind is not registered to
            its class (a file of it could not be loaded)."""
    if surrogate_class(_check_model(arch).kind) is not type(arch):
        raise ConfigError(f"the surrogate kind {arch.kind!r} is registered to another class than "
                          f"{type(arch).__name__}; register it (jaxsync.surrogate.register_surrogate) so that its "
                          "files load")
    return {"kind": arch.kind, **arch.to_dict()}


def architecture_from_dict(values: dict[str, Any]) -> Architecture:
    """Inverse of :func:`architecture_to_dict`.  A dict without ``kind`` is an LSTM's
    (surrogate files written before the linear surrogate existed).

    Raises:
        ConfigError: an unknown kind or fields of another architecture.
    """
    return surrogate_class(values.get("kind", LSTMArchitecture.kind), "architecture kind").from_dict(values)


def init_params(key: jax.Array, arch: Architecture):
    """Initial parameters of one replica (the model's own ``init``)."""
    return _check_model(arch).init(key)


def forward(params, arch: Architecture, xs: jax.Array, load_parameter: jax.Array | None = None,
            dof_mask: jax.Array | None = None, compute_dtype: str | None = None,
            loads: jax.Array | None = None) -> jax.Array:
    """Normalized window (n_p, n_dof) -> predictions (n_f, n_dof) of one replica (the
    model's own ``forward``); ``compute_dtype="bfloat16"``: reduced-precision inference
    (bfloat16 operands, float32 accumulation; None: the architecture's dtype); ``loads``
    (n_p + n_f, n_load): the normalized load signals of a model with load input."""
    return _check_model(arch).forward(params, xs, load_parameter, dof_mask, compute_dtype=compute_dtype, loads=loads)
