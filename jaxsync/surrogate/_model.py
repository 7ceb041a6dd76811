"""The trained surrogates of a partition as one pytree: :class:`Surrogate`.

One network per part -- an LSTM encoder-decoder (:class:`~jaxsync.surrogate.models.LSTMArchitecture`) or
the linear autoregressive baseline (:class:`~jaxsync.surrogate.models.LinearArchitecture`), the same code
for both (:func:`~jaxsync.surrogate.models.forward`) -- padded to the largest part and stacked on a
leading part axis (:func:`~jaxsync.surrogate.models.stack_params`), with each part's normalization, padding
mask and load parameter.  The solver places it on the devices like any other stacked
pytree (each part's replica on the device of its part) and calls, for one part,

* :meth:`Surrogate.predict` -- one refill: the next n_s n_f steps from the last
  n_s n_p (paper Algorithm 3);
* :meth:`Surrogate.rollout` -- refill cycles, each consuming the previous predictions:
  the one rollout of a surrogate, used by the offline evaluation
  (:func:`jaxsync.surrogate.training.e_mse`) and by full-system modeling.

Load input: replicas trained with the known load signals (``arch.n_load > 0``,
:mod:`jaxsync.fem`) read them at the refill's steps from the problem's own
time functions: bind them to the problem first, :meth:`Surrogate.for_problem` (the
solver does it: :func:`jaxsync.solve.coupling._predictors.predictor_for`), which refuses a problem
with other loads (another count, kind or time-function form) and accepts other
parameters of the same form (another waveform, another step-off time).

Files: :meth:`Surrogate.save` / :meth:`Surrogate.load` go through
:mod:`jaxsync.io.surrogate_file` (a :class:`~jaxsync.io.surrogate_file.SavedSurrogate`
also keeps the shared node ids and training metadata).
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxsync.errors import CheckpointError, ConfigError
from jaxsync.fem._load_signals import LoadSignals, check_load_inputs
from jaxsync.io.surrogate_file import SavedSurrogate, load_surrogate, save_surrogate
from jaxsync.pytree import pytree_dataclass, static_field
from jaxsync.surrogate._refill import (
    DEFAULT_REFILL_SAMPLES,
    refill_applications,
    refill_block_means,
    refill_predict,
    refill_rollout,
    smooth_curve,
)
from jaxsync.surrogate.models._architecture import Architecture
from jaxsync.surrogate.models._protocol import check_compute_dtype
from jaxsync.surrogate.training._data import padding_mask
from jaxsync.surrogate.training._histories import shared_dof_layout

__all__ = ["Surrogate"]


@pytree_dataclass
class Surrogate:
    """Trained replicas (LSTM or linear), one per part, stacked on a leading part axis.

    Attributes:
        params: stacked, padded network parameters (leading part axis).
        mean, std: (n_parts, n_dof) normalization [solver units, cm]; 0 and 1 on padding.
        dof_mask: (n_parts, n_dof) 1 on real dofs, 0 on padding (dtype of ``mean``).
        load_parameter: (n_parts,) float32 load parameter alpha_f fed to conditional
            networks (ignored by unconditional ones).
        arch: the architecture (static): :class:`~jaxsync.surrogate.models.LSTMArchitecture`
            or :class:`~jaxsync.surrogate.models.LinearArchitecture`; ``arch.n_dof`` is the
            padded width.
        n_s: the sampling stride the replicas were trained with (static).
        smooth: :meth:`predict` returns the refill as one smooth curve from the last
            known value (:func:`~jaxsync.surrogate.smooth_refill`; static). True by
            default: the raw refill interleaves n_s independent applications, and the
            step-to-step jitter it writes into the solver excites high-frequency noise
            (on the 11-part vessel demo, the worst interior error fell from 12 % to 7 %
            of the node's amplitude with it). False gives the paper's raw refill.
        refill_samples: the network applications a smooth refill evaluates (static;
            :func:`~jaxsync.surrogate.refill_block_means`): the curve goes through the
            block means of the n_s applications, estimated from this many evenly spaced
            ones (default 16; None: all n_s). A refill then costs ``refill_samples``
            network calls instead of n_s (the vessel demo's n_s = 1 000). Unused by the
            raw refill, which writes every application. A runtime option: surrogate files
            do not record it; set it with :meth:`with_refill_samples`.
        inference_dtype: None (default: the networks compute in ``arch.dtype``) or
            ``"bfloat16"``: reduced-precision inference, bfloat16 weights and activations
            with float32 accumulation (:mod:`jaxsync.surrogate.models`; static). Set it with
            :meth:`with_inference_dtype`, and check what it costs in accuracy with
            :func:`jaxsync.surrogate.check_inference_precision`. A runtime option:
            surrogate files keep the parameters as trained and do not record it.
        signal_scale: (n_parts, n_load) float64 scale of each load signal (the model reads
            u / scale); None without load input.
        load_inputs: (n_load,) :class:`~jaxsync.fem.LoadInput`: the load
            signals the replicas were trained with (static; empty without load input).
        load_signals: where :meth:`predict` reads the signals (static): a
            :class:`~jaxsync.fem.LoadSignals` (a problem's time functions at
            its dt, :meth:`for_problem`) or a
            :class:`~jaxsync.fem.RecordedLoadSignals` (a trajectory's record);
            None until bound.

    ``surrogate.part(p)`` (or ``jax.tree_util.tree_map(lambda x: x[p], surrogate)``, as
    vmap and shard_map do) is part p alone: the same type without the leading axis,
    whose :meth:`predict` and :meth:`rollout` work on that part's buffer.
    """

    params: Any
    mean: Any
    std: Any
    dof_mask: Any
    load_parameter: Any
    arch: Architecture = static_field()
    n_s: int = static_field()
    smooth: bool = static_field(default=True)
    refill_samples: int | None = static_field(default=DEFAULT_REFILL_SAMPLES)
    inference_dtype: str | None = static_field(default=None)
    signal_scale: Any = None
    load_inputs: tuple = static_field(default=())
    load_signals: Any = static_field(default=None)

    # ------------------------------------------------------------------ sizes

    @property
    def n_past(self) -> int:
        return self.arch.n_past

    @property
    def n_future(self) -> int:
        return self.arch.n_future

    @property
    def n_dof(self) -> int:
        """Padded width of a part's shared dofs."""
        return self.arch.n_dof

    @property
    def n_load(self) -> int:
        """Known load signals the replicas read (0: no load input)."""
        return getattr(self.arch, "n_load", 0)

    @property
    def n_parts(self) -> int:
        """Number of replicas (1 for a one-part view from :meth:`part`)."""
        return int(np.shape(self.dof_mask)[0]) if np.ndim(self.dof_mask) == 2 else 1

    @property
    def dof_counts(self) -> tuple[int, ...]:
        """Real shared dofs of each part (concrete arrays only)."""
        return tuple(int(c) for c in np.asarray(self.dof_mask).reshape(-1, self.n_dof).sum(axis=1))

    @property
    def history_steps(self) -> int:
        """n_s n_p: the steps a refill reads (the rows of ``buffer``)."""
        return self.n_s * self.arch.n_past

    @property
    def cycle_steps(self) -> int:
        """n_s n_f: the steps one refill predicts."""
        return self.n_s * self.arch.n_future

    def part(self, index: int) -> "Surrogate":
        """Part ``index`` alone (arrays without the part axis)."""
        return jax.tree_util.tree_map(lambda x: jnp.asarray(x)[index], self)

    # ------------------------------------------------------------------ prediction

    def predict(self, buffer, step):
        """One refill of ONE part: the (n_s n_f, n_dof) predictions of steps step + 1 ..
        step + n_s n_f from ``buffer`` (n_s n_p, n_dof), the displacements of steps
        step + 1 - n_s n_p .. step [cm].  The network reads only ``buffer``; ``step`` is
        the predictor interface of the solver.  With ``smooth``, one smooth curve from
        ``buffer[-1]`` through the block means of ``refill_samples`` applications
        (:func:`~jaxsync.surrogate.refill_block_means`,
        :func:`~jaxsync.surrogate.smooth_curve`); without, the paper's raw refill.
        Padded dofs are 0.  A surrogate with load input also reads the load signals at
        steps step + 1 - n_s n_p .. step + n_s n_f from ``load_signals`` (bind it with
        :meth:`for_problem`)."""
        load = self.load_parameter if self.arch.conditional else None
        args = (self.params, self.arch, self.mean, self.std, buffer, self.n_s, load, self.dof_mask,
                self.inference_dtype, self._signal_window(step))
        if self.smooth:
            out = smooth_curve(refill_block_means(*args, samples=self.refill_samples), buffer[-1], self.n_s)
        else:
            out = refill_predict(*args)
        return out * self.dof_mask[None]

    @property
    def refill_calls(self) -> int:
        """Network applications per refill: ``refill_samples`` (at most n_s) for the
        smooth refill, n_s for the raw one."""
        return len(refill_applications(self.n_s, self.refill_samples)) if self.smooth else self.n_s

    def with_refill_samples(self, samples: int | None) -> "Surrogate":
        """These replicas with a smooth refill of ``samples`` network applications per
        refill (None: all n_s).

        Raises:
            ConfigError: ``samples`` is not None or an integer >= 1."""
        refill_applications(self.n_s, samples)  # refuses a bad value, naming it
        return dataclasses.replace(self, refill_samples=samples)

    def rollout(self, buffer, step0, n_cycles: int):
        """``n_cycles`` refill cycles of ONE part, each consuming the predictions of the
        ones before (:func:`~jaxsync.surrogate.refill_rollout`).

        Args:
            buffer: (n_s n_p, n_dof) displacements of steps step0 + 1 - n_s n_p .. step0.
            step0: the last known step.
            n_cycles: refill cycles (static).

        Returns:
            (n_cycles n_s n_f, n_dof) predictions of steps step0 + 1 .. step0 +
            n_cycles n_s n_f, in the dtype of ``buffer``.
        """
        return refill_rollout(self, buffer, step0, n_cycles)

    def _signal_window(self, step):
        """(n_s (n_p + n_f), n_load) normalized load signals of the refill at ``step``; None
        without load input."""
        if not self.n_load:
            return None
        if self.load_signals is None:
            raise ConfigError(f"these surrogates read {self.n_load} known load signal(s) "
                              f"({'; '.join(map(str, self.load_inputs))}): bind them to the problem they run on, "
                              "surrogate.for_problem(problem) (the solver does it when given the surrogates)")
        rows = self.n_s * (self.arch.n_past + self.arch.n_future)
        values = self.load_signals.at_steps(step + 1 - self.history_steps, rows)
        return (values / jnp.asarray(self.signal_scale)[None]).astype(self.arch.dtype)

    def for_problem(self, problem, dt=None) -> "Surrogate":
        """These replicas reading the load signals of ``problem`` at time step ``dt``
        (default ``problem.dt``); replicas without load input are returned unchanged.

        Raises:
            CheckpointError: the problem's loads differ from those the replicas were
                trained with in count, kind or time-function form (the message names the
                difference; other parameters of the same form are accepted).
            ConfigError: traced time functions or dt."""
        if not self.n_load:
            return self
        check_load_inputs(self.load_inputs, problem)
        return dataclasses.replace(self, load_signals=LoadSignals.of(problem, problem.dt if dt is None else dt))

    def with_load_signals(self, signals) -> "Surrogate":
        """These replicas reading their load signals from ``signals`` (a
        :class:`~jaxsync.fem.RecordedLoadSignals`, e.g. a trajectory's
        record, or :class:`~jaxsync.fem.LoadSignals`), checked to be the
        signals they were trained with (count, kinds, forms)."""
        if not self.n_load:
            return self
        trained = [i.signature for i in self.load_inputs]
        given = [i.signature for i in signals.inputs]
        if trained != given:
            raise CheckpointError(f"these surrogates were trained with the load signals {trained} but were given "
                                  f"{given}; give them the signals of a run of the same loads")
        return dataclasses.replace(self, load_signals=signals)

    # ------------------------------------------------------------------ construction

    @classmethod
    def _build(cls, arch, params, mean, std, dof_mask, n_s, load_parameter, signal_scale=None,
               load_inputs=()) -> "Surrogate":
        if arch.conditional and load_parameter is None:
            raise CheckpointError("the surrogates are conditional on a load parameter: pass load_parameter=")
        if not arch.conditional and load_parameter is not None:
            raise CheckpointError(f"load_parameter={load_parameter} was given but the surrogates are unconditional "
                                  "(trained with n_cond_repeat=0) and would ignore it; train with --cond-repeat > 0 "
                                  "or leave the load parameter out")
        mean = np.asarray(mean)
        n = mean.shape[0]
        n_load = getattr(arch, "n_load", 0)
        if n_load and (signal_scale is None or np.shape(signal_scale) != (n, n_load) or len(load_inputs) != n_load):
            raise CheckpointError(f"the replicas read {n_load} load signals but come with a signal scale of shape "
                                  f"{np.shape(signal_scale)} and {len(load_inputs)} load input descriptions; expected "
                                  f"({n}, {n_load}) and {n_load}")
        return cls(params=params, mean=mean, std=np.asarray(std), dof_mask=np.asarray(dof_mask).astype(mean.dtype),
                   load_parameter=np.full(n, 0.0 if load_parameter is None else float(load_parameter),
                                          dtype=np.float32),
                   arch=arch, n_s=int(n_s),
                   signal_scale=np.asarray(signal_scale, np.float64) if n_load else None,
                   load_inputs=tuple(load_inputs) if n_load else ())

    def with_load_parameter(self, load_parameter: float | None) -> "Surrogate":
        """These replicas conditioned on ``load_parameter`` (a value seen in training or
        not); None returns them unchanged.

        Raises:
            CheckpointError: a value given to unconditional replicas, which would ignore it."""
        if load_parameter is None:
            return self
        conditioned = self._build(self.arch, self.params, self.mean, self.std, self.dof_mask, self.n_s, load_parameter,
                                  self.signal_scale, self.load_inputs)
        return dataclasses.replace(self, load_parameter=conditioned.load_parameter)

    def with_inference_dtype(self, dtype: str | None) -> "Surrogate":
        """These replicas computing in ``dtype``: ``"bfloat16"`` (bfloat16 weights and
        activations, float32 accumulation) or None (the architecture's own dtype). The
        parameters are not changed; :meth:`predict`, :meth:`rollout` and the online
        solver use the reduced precision. Unchecked: measure the deviation with
        :func:`jaxsync.surrogate.check_inference_precision` (or
        :func:`~jaxsync.surrogate.reduced_precision`, which does both).

        Raises:
            ConfigError: an unknown dtype."""
        check_compute_dtype(dtype)
        return dataclasses.replace(self, inference_dtype=dtype)

    @classmethod
    def initialized(cls, partition, n_s: int, *, n_hidden: int = 100, n_layers: int = 2, n_past: int = 20,
                    n_future: int = 20, dtype: str = "float32", seed: int = 0, model: str = "lstm",
                    rank: int | None = None, highway_rank: int = 0) -> "Surrogate":
        """Untrained replicas for ``partition``, unit normalization.

        For timing studies: an untrained network costs exactly what a trained one of the
        same architecture costs, and needs no training run.  Its predictions are
        meaningless.  The defaults are the paper's architecture (n_H = 100, 2 layers,
        n_p = n_f = 20). ``model="linear"``: the linear autoregressive map instead
        (:mod:`jaxsync.surrogate.models`, zero weights) of inner width ``rank`` (default
        n_p n_dof, the widest a fit can give); ``n_hidden`` and ``n_layers`` are unused.
        ``highway_rank`` > 0: the LSTM with a linear highway of that inner width (zero
        weights; :class:`~jaxsync.surrogate.models.LSTMArchitecture`)."""
        from jaxsync.surrogate.models._architecture import ArchitectureChoice

        choice = ArchitectureChoice(model=model, n_hidden=n_hidden, n_layers=n_layers, dtype=dtype)
        n_dof, counts = shared_dof_layout(partition)
        n = partition.n_parts
        arch = choice.model_class.from_choice(choice, n_dof, n_past, n_future, 0)
        if rank is not None:  # the linear map's inner width (default: the widest a fit can give)
            if "rank" not in {f.name for f in dataclasses.fields(arch)}:
                raise ConfigError(f"rank={rank} is the linear model's inner width; the {model} model has none: "
                                  "leave rank out")
            arch = dataclasses.replace(arch, rank=rank)
        if highway_rank:
            if "highway_rank" not in {f.name for f in dataclasses.fields(arch)}:
                raise ConfigError(f"highway_rank={highway_rank} is the LSTM's highway width; the {model} model has "
                                  "none: leave highway_rank out")
            arch = dataclasses.replace(arch, highway=True, highway_rank=int(highway_rank))
        params = arch.init_replicas(jax.random.PRNGKey(seed), tuple(int(c) for c in counts))
        # normalization and mask in float64, as a surrogate file stores them
        return cls._build(arch, params, np.zeros((n, n_dof)), np.ones((n, n_dof)), padding_mask(counts, n_dof),
                          n_s, None)

    @classmethod
    def from_saved(cls, saved, load_parameter: float | None = None) -> "Surrogate":
        """The surrogate of a :class:`~jaxsync.io.surrogate_file.SavedSurrogate`
        or of its file; ``load_parameter`` is required by conditional networks."""
        if not isinstance(saved, SavedSurrogate):
            saved = load_surrogate(saved)
        return cls._build(saved.arch, saved.params, saved.mean, saved.std, saved.dof_mask, saved.n_s, load_parameter,
                          saved.signal_scale, saved.load_inputs)

    @classmethod
    def from_result(cls, result, n_s: int, load_parameter: float | None = None) -> "Surrogate":
        """The surrogate of a :class:`~jaxsync.surrogate.training.TrainResult` trained at
        sampling stride ``n_s``."""
        return cls._build(result.arch, result.params, result.mean, result.std, result.dof_mask, n_s,
                          load_parameter, result.signal_scale, result.load_inputs)

    # ------------------------------------------------------------------ files

    def to_saved(self, shared_nodes=None, metadata: dict | None = None) -> SavedSurrogate:
        """A :class:`~jaxsync.io.surrogate_file.SavedSurrogate` of these replicas,
        with the partition's shared node ids (per part; needed to check a partition
        against it) and JSON-serializable ``metadata``."""
        return SavedSurrogate(
            arch=self.arch, params=jax.tree_util.tree_map(np.asarray, self.params),
            mean=np.asarray(self.mean, np.float64), std=np.asarray(self.std, np.float64),
            dof_counts=self.dof_counts, n_s=self.n_s,
            shared_nodes=None if shared_nodes is None else tuple(np.asarray(n, np.int64) for n in shared_nodes),
            metadata=dict(metadata or {}),
            signal_scale=None if self.signal_scale is None else np.asarray(self.signal_scale, np.float64),
            load_inputs=tuple(self.load_inputs),
        )

    def save(self, path: str | os.PathLike, *, shared_nodes=None, metadata: dict | None = None) -> None:
        """Write a surrogate file atomically (:func:`~jaxsync.io.surrogate_file.save_surrogate`)."""
        save_surrogate(path, self.to_saved(shared_nodes, metadata))

    @classmethod
    def load(cls, path: str | os.PathLike, load_parameter: float | None = None) -> "Surrogate":
        """Read a surrogate file (:func:`~jaxsync.io.surrogate_file.load_surrogate`)."""
        return cls.from_saved(load_surrogate(path), load_parameter)
