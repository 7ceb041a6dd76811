"""LSTM encoder-decoder surrogates of the partition-shared displacements (paper section 3),
and the linear autoregressive baseline beside them.

The names a user needs are here; the modules are private. The models are
:mod:`jaxsync.surrogate.models`, their training :mod:`jaxsync.surrogate.training` (each
exports its names; the main ones are re-exported here); what the solver and the files use
of a trained set is beside them:

- :class:`Surrogate`: the trained replicas of a partition as one pytree, with ``predict``
  (one refill) and ``rollout`` (refill cycles); what the solver runs;
- Algorithm 3's refill: its index sets (:func:`refill_input_steps`,
  :func:`refill_target_steps`, :func:`refill_index_sets`), its windows
  (:func:`refill_windows`, :func:`refill_scatter`) and its predictions
  (:func:`refill_predict`, :func:`smooth_refill`, :func:`refill_cycle`,
  :func:`refill_rollout`), and the smooth refill from a few applications
  (:func:`refill_applications`, :func:`refill_block_means`, :func:`smooth_curve`,
  :data:`DEFAULT_REFILL_SAMPLES`);
- reduced-precision (bfloat16) inference and the check that it keeps accuracy
  (:func:`check_inference_precision`, :func:`reduced_precision`,
  :class:`ReducedPrecisionWarning`, :data:`DEFAULT_BOUND`, :func:`inference_deviation`,
  on the windows that :func:`surrogate_windows` and :func:`surrogate_signal_windows`
  make);
- surrogate files of trained replicas (:class:`SavedSurrogate`, :func:`save_surrogate`,
  :func:`load_surrogate`, of :mod:`jaxsync.io.surrogate_file`).

From :mod:`jaxsync.surrogate.models`: the models (:class:`LSTMArchitecture`,
:class:`LinearArchitecture` with :class:`LinearFitConfig` and :func:`fit_linear`), the
protocol every model implements (:class:`SurrogateArchitecture`, :class:`GradientFitted`,
:class:`LeastSquaresFitted`, :class:`FitSettings`, :class:`PredictionCost`), the registry
of model kinds (:func:`register_surrogate`, :func:`unregister_surrogate`,
:func:`surrogate_class`, :func:`surrogate_kinds`) and :class:`ArchitectureChoice`, the
model and size to train. From :mod:`jaxsync.surrogate.training`: :func:`train_surrogates`
(:class:`TrainedSurrogates`), the windows (:class:`Sampling`, :func:`build_dataset`,
:func:`stack_replicas`), gradient training (:func:`train_replicas`, :class:`TrainConfig`,
:class:`TrainResult`, :class:`TrainingState`), the offline checks (:class:`TrainingChecks`,
:func:`e_mse`, :func:`rollout_errors`, :class:`RolloutWarning`, :func:`grid_search`,
:class:`GridSearchResult`) and learning while synchronized (:class:`OnlineLearning`).
"""

from typing import TYPE_CHECKING

from ..lazy import export_lazily

__all__ = ["Surrogate", "LSTMArchitecture", "LinearArchitecture", "LinearFitConfig", "fit_linear", "train_surrogates",
           "TrainedSurrogates", "ArchitectureChoice", "Sampling", "TrainingChecks", "TrainingState", "TrainConfig",
           "TrainResult", "train_replicas", "build_dataset", "stack_replicas", "SavedSurrogate", "save_surrogate",
           "load_surrogate", "e_mse", "rollout_errors", "RolloutWarning", "grid_search", "GridSearchResult",
           "check_inference_precision", "reduced_precision", "ReducedPrecisionWarning", "OnlineLearning",
           "SurrogateArchitecture", "GradientFitted", "LeastSquaresFitted", "FitSettings", "PredictionCost",
           "register_surrogate", "unregister_surrogate", "surrogate_class", "surrogate_kinds", "DEFAULT_BOUND",
           "inference_deviation", "surrogate_windows", "surrogate_signal_windows", "refill_input_steps",
           "refill_target_steps", "refill_index_sets", "refill_windows", "refill_scatter", "refill_predict",
           "refill_applications", "refill_block_means", "smooth_refill", "smooth_curve", "refill_cycle",
           "refill_rollout", "DEFAULT_REFILL_SAMPLES"]

# where each name of __all__ is imported from on first use (jaxsync.lazy): the imports of TYPE_CHECKING below
__getattr__, __dir__ = export_lazily(__name__, {
    "._inference": ("DEFAULT_BOUND", "ReducedPrecisionWarning", "check_inference_precision", "inference_deviation",
                    "reduced_precision", "surrogate_signal_windows", "surrogate_windows"),
    "._model": ("Surrogate",),
    ".models._architecture": ("ArchitectureChoice",),
    ".models._linear": ("LinearArchitecture", "LinearFitConfig", "fit_linear"),
    ".models._lstm": ("LSTMArchitecture",),
    ".models._protocol": ("FitSettings", "GradientFitted", "LeastSquaresFitted", "PredictionCost",
                          "SurrogateArchitecture"),
    ".models._registry": ("register_surrogate", "surrogate_class", "surrogate_kinds", "unregister_surrogate"),
    "..io.surrogate_file": ("SavedSurrogate", "load_surrogate", "save_surrogate"),
    ".training._data": ("Sampling", "build_dataset", "stack_replicas"),
    ".training._evaluate": ("GridSearchResult", "RolloutWarning", "TrainingChecks", "e_mse", "grid_search",
                            "rollout_errors"),
    ".training._fit": ("TrainedSurrogates", "train_surrogates"),
    ".training._online": ("OnlineLearning",),
    ".training._train": ("TrainConfig", "TrainResult", "train_replicas"),
    ".training._training_state": ("TrainingState",),
    "._refill": ("DEFAULT_REFILL_SAMPLES", "refill_applications", "refill_block_means", "refill_cycle",
                 "refill_index_sets", "refill_input_steps", "refill_predict", "refill_rollout", "refill_scatter",
                 "refill_target_steps", "refill_windows", "smooth_curve", "smooth_refill"),
})

if TYPE_CHECKING:
    from ..io.surrogate_file import SavedSurrogate, load_surrogate, save_surrogate
    from ._inference import (
        DEFAULT_BOUND,
        ReducedPrecisionWarning,
        check_inference_precision,
        inference_deviation,
        reduced_precision,
        surrogate_signal_windows,
        surrogate_windows,
    )
    from ._model import Surrogate
    from ._refill import (
        DEFAULT_REFILL_SAMPLES,
        refill_applications,
        refill_block_means,
        refill_cycle,
        refill_index_sets,
        refill_input_steps,
        refill_predict,
        refill_rollout,
        refill_scatter,
        refill_target_steps,
        refill_windows,
        smooth_curve,
        smooth_refill,
    )
    from .models._architecture import ArchitectureChoice
    from .models._linear import LinearArchitecture, LinearFitConfig, fit_linear
    from .models._lstm import LSTMArchitecture
    from .models._protocol import FitSettings, GradientFitted, LeastSquaresFitted, PredictionCost, SurrogateArchitecture
    from .models._registry import register_surrogate, surrogate_class, surrogate_kinds, unregister_surrogate
    from .training._data import Sampling, build_dataset, stack_replicas
    from .training._evaluate import GridSearchResult, RolloutWarning, TrainingChecks, e_mse, grid_search, rollout_errors
    from .training._fit import TrainedSurrogates, train_surrogates
    from .training._online import OnlineLearning
    from .training._train import TrainConfig, TrainResult, train_replicas
    from .training._training_state import TrainingState
