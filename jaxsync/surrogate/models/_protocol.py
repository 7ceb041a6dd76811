"""The surrogate-model protocol: what a model provides so that training, the solver, online
learning, fine-tuning and the surrogate files run it.

A surrogate model is a frozen dataclass of its hyperparameters, registered as a static
pytree (``@jax.tree_util.register_static``: it never carries arrays), subclassing
:class:`GradientFitted` (trained by optax on a loss) or :class:`LeastSquaresFitted`
(fitted in closed form), with a class attribute ``kind`` (its name in surrogate files and
on the command line, :func:`jaxsync.surrogate.register_surrogate`). Its parameters are a
pytree of arrays; one set per part (a *replica*), stacked on a leading part axis.

Fields every model has (the window geometry, set from the data by :meth:`SurrogateArchitecture.from_choice`):

* ``n_dof``: D, values per snapshot: the shared-node displacements of a part (3 per
  shared node), padded to the widest part;
* ``n_past``, ``n_future``: n_p snapshots in, n_f out (spaced n_s steps apart);
* ``dtype``: ``"float32"`` or ``"float64"``, parameters and computation;
* ``n_load``: L, known load signals read (0: none).

Shapes, one replica, one window (callers ``jax.vmap`` over windows and replicas), all
normalized (displacements by the part's per-dof mean and std, load signals by their
scale; :mod:`jaxsync.surrogate.training`):

==================  =========================  =========================================
``xs``              (n_p, D)                   the past shared displacements
``loads``           (n_p + n_f, L) or None     the load signals at the n_p past then the
                                               n_f predicted snapshots (None when L = 0)
``load_parameter``  scalar or None             conditional models only
``dof_mask``        (D,) or None               1 on a part's real dofs, 0 on padding:
                                               predictions there must be 0
result              (n_f, D)                   the predicted snapshots, ``dtype``
==================  =========================  =========================================

The methods (defaults in :class:`SurrogateArchitecture` where one exists):

==============================  ==========================================================
``init(key)``                   initial parameters of one replica (required)
``forward(params, xs, ...)``    the prediction above (required)
``loss(params, x, y, ...)``     weighted masked MSE over windows (default
                                :func:`~jaxsync.surrogate.training.masked_mse`); what gradient
                                training and online learning minimise
``fit(data, settings)``         train all replicas on windows (:class:`FitSettings`): by
                                gradient (:class:`GradientFitted`, through
                                :func:`~jaxsync.surrogate.training.train_replicas`) or in
                                closed form (:class:`LeastSquaresFitted`, the model's own
                                solve)
``online_update(...)``          one update from the windows a run recomputes (gradient
                                steps, or the model's ``refit``)
``prediction_cost(n_s)``        bytes and flops of one refill prediction (n_s windows)
``to_dict``, ``from_dict``      the hyperparameters, JSON-ready, as a surrogate file stores
                                them (default: the dataclass fields)
``from_choice(choice, ...)``    the model for the data's windows from an
                                :class:`~jaxsync.surrogate.ArchitectureChoice` (default:
                                the choice's fields of the same names)
==============================  ==========================================================

A worked example: the guide "Extending the surrogates" (``docs/guides/extending-surrogates.md``).
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxsync.errors import ConfigError
from jaxsync.surrogate.training._loss import masked_mse

__all__ = ["SurrogateArchitecture", "GradientFitted", "LeastSquaresFitted", "FitSettings", "PredictionCost",
           "COMPUTE_DTYPES", "check_compute_dtype", "check_loads"]

Params = Any


class PredictionCost(NamedTuple):
    """Counted cost of one refill prediction (n_s windows of one part): ``bytes``, the
    memory traffic [bytes] (the parameters as read, the solver-side buffer, normalization,
    mask and output), and ``flops``, the floating-point operations [flop]."""

    bytes: float
    flops: float


@dataclasses.dataclass(frozen=True)
class FitSettings:
    """What :meth:`SurrogateArchitecture.fit` is given besides the windows: the settings of
    :func:`jaxsync.surrogate.train_surrogates`.

    Attributes:
        architecture: the :class:`~jaxsync.surrogate.ArchitectureChoice` (e.g. the linear
            model's ``regularization``).
        optimizer: the :class:`~jaxsync.surrogate.TrainConfig` (gradient-fitted models).
        key: PRNG key of initialization and shuffling.
        progress: show a progress bar.
        devices: local devices to spread the parts over (None: as many as divide them).
        state: the resumable :class:`~jaxsync.surrogate.TrainingState`, or None.
        callback: called with a :class:`~jaxsync.surrogate.training._train.TrainProgress` after every
            compiled chunk of epochs, or None.
    """

    architecture: Any
    optimizer: Any
    key: Any
    progress: bool = False
    devices: int | None = None
    state: Any = None
    callback: Any = None


# the ArchitectureChoice fields a model may take by name (from_choice's default)
_CHOICE_FIELDS = ("n_hidden", "n_layers", "n_cond_repeat", "dtype")


class SurrogateArchitecture:
    """Base of every surrogate model (module docstring: fields, shapes, methods).

    Its class attributes: ``kind``, the model's name in surrogate files and on the command
    line; ``display_name``, how messages and plots name it (default: ``kind``);
    ``load_jump_windows``, whether training keeps the windows across a recorded load jump
    by default (``"keep"``, or ``"exclude"``: :class:`~jaxsync.surrogate.Sampling`);
    ``resumes_training``, its training writes a resumable state
    (:class:`~jaxsync.surrogate.TrainingState`); ``accuracy_advice``, what a failed offline
    check advises first.
    """

    kind: ClassVar[str]
    display_name: ClassVar[str | None] = None
    load_jump_windows: ClassVar[str] = "keep"
    resumes_training: ClassVar[bool] = False
    accuracy_advice: ClassVar[str] = "Train on more data"

    # ------------------------------------------------------------ the model

    @property
    def n_cond_repeat(self) -> int:
        """Copies of the load parameter the model reads (0: unconditional)."""
        return 0

    @property
    def conditional(self) -> bool:
        """The model reads a load parameter."""
        return self.n_cond_repeat > 0

    def init(self, key: jax.Array) -> Params:
        """Initial parameters of one replica of width ``n_dof``."""
        raise NotImplementedError(f"{type(self).__name__} must define init(key)")

    def forward(self, params: Params, xs: jax.Array, load_parameter=None, dof_mask=None,
                compute_dtype: str | None = None, loads=None) -> jax.Array:
        """Normalized window (n_p, D) -> predictions (n_f, D) (shapes: module docstring);
        ``compute_dtype``: None, or ``"bfloat16"`` for reduced-precision inference where
        the model supports it."""
        raise NotImplementedError(f"{type(self).__name__} must define forward(params, xs, ...)")

    def init_replicas(self, key: jax.Array, dof_counts) -> Params:
        """Stacked initial parameters of one replica per part (``dof_counts`` real dofs
        each): replica r is ``init(fold_in(key, r))`` at the padded width. Padded inputs
        are 0 and padded outputs are masked, so the weights that touch padding never
        change what a replica predicts on its real dofs."""
        replicas = [self.init(jax.random.fold_in(key, r)) for r in range(len(dof_counts))]
        return jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *replicas)

    def loss(self, params, x, y, load_parameter, weight, dof_mask, signals=None):
        """The training loss of one replica (default
        :func:`~jaxsync.surrogate.training.masked_mse`)."""
        return masked_mse(params, self, x, y, load_parameter, weight, dof_mask, signals)

    def prediction_cost(self, n_s: int, masked: bool = True, io_bytes_per_value: int = 8) -> PredictionCost:
        """Bytes and flops of one refill prediction: n_s windows of one part
        (:func:`jaxsync.perf.roofline.surrogate_costs` reads it)."""
        raise NotImplementedError(f"{type(self).__name__} does not count its cost (prediction_cost)")

    # ------------------------------------------------------------ hyperparameters

    def to_dict(self) -> dict[str, Any]:
        """The hyperparameters, JSON-ready (what a surrogate file stores beside ``kind``):
        the dataclass fields, ``n_load`` only when > 0 (a model without load input is
        stored as before the load input existed)."""
        return {f.name: _plain(getattr(self, f.name)) for f in dataclasses.fields(self)
                if f.name != "n_load" or self.n_load}

    @classmethod
    def from_dict(cls, values: dict[str, Any]):
        """Inverse of :meth:`to_dict`; a ``kind`` entry, if present, must be this model's."""
        values = dict(values)
        kind = values.pop("kind", cls.kind)
        if kind != cls.kind:
            raise ConfigError(f"architecture of kind {kind!r} given to {cls.__name__}.from_dict; read it with "
                              "jaxsync.surrogate.models.architecture_from_dict")
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(values) - names
        if unknown:
            raise ConfigError(f"unknown {cls.__name__} fields {sorted(unknown)}; expected {sorted(names)}")
        return cls(**values)

    @classmethod
    def check_choice(cls, choice) -> None:
        """Refuse an :class:`~jaxsync.surrogate.ArchitectureChoice` this model cannot
        train, before any data are read (default: a conditional choice for a model without
        an ``n_cond_repeat`` field)."""
        names = {f.name for f in dataclasses.fields(cls)}
        if getattr(choice, "highway", None) is True and "highway" not in names:
            raise ConfigError(f"the {cls._name()} surrogate has no linear highway: highway (--highway) goes with "
                              "model='lstm' (--model lstm)")
        if choice.n_cond_repeat > 0 and "n_cond_repeat" not in names:
            raise ConfigError(f"the {cls._name()} surrogate is unconditional: n_cond_repeat (--cond-repeat) must be "
                              "0; train model='lstm' (--model lstm) for a conditional surrogate")

    @classmethod
    def from_choice(cls, choice, n_dof: int, n_past: int, n_future: int, n_load: int):
        """The model for windows of ``n_past`` -> ``n_future`` snapshots of ``n_dof``
        (padded) values reading ``n_load`` load signals, its other hyperparameters the
        fields of ``choice`` (:class:`~jaxsync.surrogate.ArchitectureChoice`) of the same
        names (``n_hidden``, ``n_layers``, ``n_cond_repeat``, ``dtype``); the rest keep
        the model's defaults."""
        names = {f.name for f in dataclasses.fields(cls)}
        if n_load and "n_load" not in names:
            raise ConfigError(f"the {cls._name()} surrogate takes no load signals: train it with "
                              "load_input=False (--no-load-input)")
        values = {name: getattr(choice, name) for name in _CHOICE_FIELDS if name in names}
        values.update(n_dof=n_dof, n_past=n_past, n_future=n_future)
        if "n_load" in names:
            values["n_load"] = n_load
        return cls(**values)

    @classmethod
    def _name(cls) -> str:
        return cls.display_name or cls.kind

    # ------------------------------------------------------------ fitting

    @classmethod
    def candidates_per_part(cls, optimizer) -> int:
        """Replicas trained per part from different initial weights (the best kept)."""
        return 1

    def fit(self, data, settings: FitSettings):
        """Fit one replica per part on ``data`` (a
        :class:`~jaxsync.surrogate.training.ReplicaData`); returns a
        :class:`~jaxsync.surrogate.TrainResult` (its ``arch`` the fitted model)."""
        raise NotImplementedError(f"{type(self).__name__} must define fit(data, settings)")

    def online_update(self, learner, params, x, y, signals, weight, load_parameter, dof_mask, started: float):
        """Update the stacked replicas ``params`` on weighted windows of a run
        (:class:`~jaxsync.surrogate.training.OnlineLearner`); returns ``(params, iterations)``."""
        raise NotImplementedError(f"{type(self).__name__} must define online_update")

    def summary_fields(self, result, state_every: int) -> dict[str, Any]:
        """The training entries of ``train_summary.json`` (``training``, ``n_epochs_run``,
        ``seconds_per_epoch``, ``gradient_steps_per_second``)."""
        raise NotImplementedError(f"{type(self).__name__} must define summary_fields")

    def fit_description(self, result) -> str:
        """One phrase on how ``result`` was fitted (``jaxsync train`` prints it)."""
        raise NotImplementedError(f"{type(self).__name__} must define fit_description")


class GradientFitted(SurrogateArchitecture):
    """A model trained by gradient: optax Adam on :meth:`~SurrogateArchitecture.loss`
    (:func:`~jaxsync.surrogate.training.train_replicas`: mini-batches, a decaying learning
    rate, early stopping, resumable state, several candidates per part), learning online
    by full-batch Adam steps. Subclasses define ``init`` and ``forward``."""

    resumes_training: ClassVar[bool] = True
    accuracy_advice: ClassVar[str] = "Train longer (more epochs or patience), on more data"

    @classmethod
    def candidates_per_part(cls, optimizer) -> int:
        """``optimizer.n_candidates``."""
        return int(optimizer.n_candidates)

    def fit(self, data, settings: FitSettings):
        """:func:`~jaxsync.surrogate.training.train_replicas` with ``settings``."""
        from jaxsync.surrogate.training._train import train_replicas

        return train_replicas(data, self, settings.optimizer, settings.key, progress=settings.progress,
                              devices=settings.devices, state=settings.state, callback=settings.callback)

    def online_update(self, learner, params, x, y, signals, weight, load_parameter, dof_mask, started: float):
        """Full-batch Adam steps within the learner's budget (``learner.gradient_steps``)."""
        return learner.gradient_steps(params, x, y, signals, weight, load_parameter, dof_mask, started)

    def summary_fields(self, result, state_every: int) -> dict[str, Any]:
        training = {**result.config.to_dict(), "n_epochs_run": result.n_epochs_run,
                    "stopped_early": result.stopped_epoch is not None, "stopped_at_epoch": result.stopped_epoch,
                    "best_epoch": [int(e) for e in result.best_epoch],
                    "resumed_from_epoch": result.resumed_from, "state_every": state_every}
        return {"training": training, "n_epochs_run": result.n_epochs_run,
                "seconds_per_epoch": result.seconds_per_epoch,
                "gradient_steps_per_second": (result.steps_per_epoch / result.seconds_per_epoch
                                              if result.seconds_per_epoch > 0 else None)}

    def fit_description(self, result) -> str:
        return (f"stopped early at epoch {result.stopped_epoch}" if result.stopped_epoch is not None
                else f"{result.n_epochs_run} epochs")


class LeastSquaresFitted(SurrogateArchitecture):
    """A model fitted in closed form: subclasses define ``init``, ``forward``, ``fit`` (the
    solve on the training windows, returning a :class:`~jaxsync.surrogate.TrainResult` of
    one row of losses, ``steps_per_epoch`` 0) and ``refit`` (the same solve on weighted
    windows, what online learning runs)."""

    accuracy_advice: ClassVar[str] = "Fit with another regularization, on more data"

    def refit(self, params, x, y, signals, weight, dof_mask) -> Params:
        """The stacked replicas fitted again on weighted windows.

        Args:
            params: the current stacked replicas (their shapes are kept).
            x: (n_parts, n_w, n_p, D); y: (n_parts, n_w, n_f, D); signals:
                (n_parts, n_w, n_p + n_f, L) or None (normalized windows).
            weight: (n_w,) window weights >= 0.
            dof_mask: (n_parts, D) 1 on real dofs.
        """
        raise NotImplementedError(f"{type(self).__name__} must define refit")

    def online_update(self, learner, params, x, y, signals, weight, load_parameter, dof_mask, started: float):
        """One :meth:`refit` (an exact solve in place of gradient steps) on every window the
        run has synchronized (``learner.every_window()``: the first fit corrected, not
        replaced by a fit of the few new windows; ``x`` ... ``weight`` are the gradient
        update's sample and are not used)."""
        x, y, signals, weight = learner.every_window()
        refitted = self.refit(params, x, y, signals, weight, dof_mask)
        return jax.tree_util.tree_map(jnp.asarray, refitted), 1

    def summary_fields(self, result, state_every: int) -> dict[str, Any]:
        training = {**result.config.to_dict(), "fit_seconds": result.seconds_per_epoch, "n_epochs_run": None,
                    "candidates": "not applicable: least squares has one solution (n_candidates ignored)"}
        return {"training": training, "n_epochs_run": None, "seconds_per_epoch": None,
                "gradient_steps_per_second": None}

    def fit_description(self, result) -> str:
        return f"{self._name()}, least-squares fit in {result.seconds_per_epoch:.2f} s"


#: Reduced-precision compute dtypes :func:`forward` accepts (``compute_dtype``); None is
#: the architecture's own dtype.
COMPUTE_DTYPES = ("bfloat16",)


def check_compute_dtype(compute_dtype: str | None) -> None:
    """Raise :class:`ConfigError` unless ``compute_dtype`` is None or in :data:`COMPUTE_DTYPES`."""
    if compute_dtype is not None and compute_dtype not in COMPUTE_DTYPES:
        raise ConfigError(f"reduced-precision compute dtype must be one of {COMPUTE_DTYPES} (or None for the "
                          f"architecture's dtype), got {compute_dtype!r}")


def check_loads(arch, loads: jax.Array | None) -> jax.Array | None:
    """``loads`` in ``arch.dtype``, checked: (n_p + n_f, n_load) for a model with load input
    (``arch.n_load > 0``), None for one without.

    Raises:
        ConfigError: load signals missing, given to a model without load input, or of
            the wrong shape."""
    n_load = getattr(arch, "n_load", 0)
    if n_load == 0:
        if loads is not None:
            raise ConfigError("load signals were given to a surrogate trained without load input (n_load=0), which "
                              "would ignore them; train with the load input (load_input=True) or leave them out")
        return None
    if loads is None:
        raise ConfigError(f"this surrogate takes {n_load} known load signal(s) (n_load={n_load}); pass loads of "
                          f"shape (n_past + n_future, {n_load}), or bind the surrogate to its problem "
                          "(Surrogate.for_problem)")
    expected = (arch.n_past + arch.n_future, n_load)
    if tuple(loads.shape) != expected:
        raise ConfigError(f"load signals must have shape (n_past + n_future, n_load) = {expected}, got {loads.shape}")
    return loads.astype(arch.dtype)


def _plain(value):
    """A JSON-ready copy of a hyperparameter (NumPy scalars to Python numbers)."""
    return value.item() if isinstance(value, np.generic) else value
