"""LSTM encoder-decoder surrogates of the partition-shared displacements (paper section 3),
and the linear autoregressive baseline beside them.

The names a user needs are here; everything else stays importable from its module:

=========================  =================================================================
:mod:`.model`              :class:`Surrogate`: the trained replicas of a partition as one
                           pytree, with ``predict`` (one refill) and ``rollout`` (refill
                           cycles); what the solver runs
:mod:`.fit`                :func:`train_surrogates`: trajectories in, trained surrogates out
                           (``jaxsync train`` and the demo call it);
                           :meth:`TrainedSurrogates.write` writes their files
:mod:`.lstm`               the network, written by hand (:class:`LSTMArchitecture`)
:mod:`.linear`             the linear autoregressive baseline, fitted by least squares
                           (:class:`LinearArchitecture`, :func:`fit_linear`)
:mod:`.protocol`           the surrogate-model protocol every model implements
                           (:class:`SurrogateArchitecture`, :class:`GradientFitted`,
                           :class:`LeastSquaresFitted`): init, forward, fit, cost, files
:mod:`.registry`           model kinds by name (:func:`register_surrogate`): what
                           surrogate files and ``jaxsync train --model`` name
:mod:`.architecture`       one code path for every model through its methods;
                           :class:`ArchitectureChoice`, the model and size to train
:mod:`.refill`             Algorithm 3's refill index sets and ``refill_predict``
:mod:`.inference`          reduced-precision (bfloat16) inference: the check that it keeps
                           accuracy (:func:`check_inference_precision`,
                           :func:`reduced_precision`)
:mod:`.data`               sample-refill windows (:class:`Sampling`, their settings),
                           normalization, padded replica datasets, reading shared
                           histories from trajectories
:mod:`.replicas`           padding and stacking one network per part
:mod:`.train`              optax training of all replicas in one program
                           (:func:`train_replicas`, :class:`TrainConfig`, :class:`TrainResult`)
:mod:`.training_state`     the resumable state of a training run (:class:`TrainingState`:
                           where and how often it is written)
:mod:`.saved`              surrogate files of trained replicas (:class:`SavedSurrogate`)
:mod:`.evaluate`           the offline rollout check, E_mse (:class:`TrainingChecks`) and
                           the grid search
:mod:`.online`             learning while synchronized (:class:`OnlineLearning`): updates
                           from the steps error control recomputes
=========================  =================================================================
"""


from typing import TYPE_CHECKING

from jaxsync.lazy import export_lazily

__all__ = [
    "Surrogate", "LSTMArchitecture", "LinearArchitecture", "LinearFitConfig", "fit_linear",
    "train_surrogates", "TrainedSurrogates", "ArchitectureChoice", "Sampling", "TrainingChecks", "TrainingState",
    "TrainConfig", "TrainResult", "train_replicas", "build_dataset", "stack_replicas",
    "SavedSurrogate", "save_surrogate", "load_surrogate",
    "e_mse", "rollout_errors", "RolloutWarning", "grid_search", "GridSearchResult",
    "check_inference_precision", "reduced_precision", "ReducedPrecisionWarning", "OnlineLearning",
    "SurrogateArchitecture", "GradientFitted", "LeastSquaresFitted", "FitSettings", "PredictionCost",
    "register_surrogate", "unregister_surrogate", "surrogate_class", "surrogate_kinds",
]

# where each name of __all__ is imported from on first use (jaxsync.lazy): the imports of TYPE_CHECKING below
__getattr__, __dir__ = export_lazily(__name__, {
    "jaxsync.surrogate.architecture": ("ArchitectureChoice",),
    "jaxsync.surrogate.data": ("Sampling", "build_dataset", "stack_replicas"),
    "jaxsync.surrogate.evaluate": ("GridSearchResult", "RolloutWarning", "TrainingChecks", "e_mse", "grid_search",
                                   "rollout_errors"),
    "jaxsync.surrogate.fit": ("TrainedSurrogates", "train_surrogates"),
    "jaxsync.surrogate.inference": ("ReducedPrecisionWarning", "check_inference_precision", "reduced_precision"),
    "jaxsync.surrogate.linear": ("LinearArchitecture", "LinearFitConfig", "fit_linear"),
    "jaxsync.surrogate.lstm": ("LSTMArchitecture",),
    "jaxsync.surrogate.model": ("Surrogate",),
    "jaxsync.surrogate.online": ("OnlineLearning",),
    "jaxsync.surrogate.protocol": ("FitSettings", "GradientFitted", "LeastSquaresFitted", "PredictionCost",
                                   "SurrogateArchitecture"),
    "jaxsync.surrogate.registry": ("register_surrogate", "surrogate_class", "surrogate_kinds",
                                   "unregister_surrogate"),
    "jaxsync.surrogate.saved": ("SavedSurrogate", "load_surrogate", "save_surrogate"),
    "jaxsync.surrogate.train": ("TrainConfig", "TrainResult", "train_replicas"),
    "jaxsync.surrogate.training_state": ("TrainingState",),
})

if TYPE_CHECKING:
    from jaxsync.surrogate.architecture import ArchitectureChoice
    from jaxsync.surrogate.data import Sampling, build_dataset, stack_replicas
    from jaxsync.surrogate.evaluate import (
        GridSearchResult,
        RolloutWarning,
        TrainingChecks,
        e_mse,
        grid_search,
        rollout_errors,
    )
    from jaxsync.surrogate.fit import TrainedSurrogates, train_surrogates
    from jaxsync.surrogate.inference import ReducedPrecisionWarning, check_inference_precision, reduced_precision
    from jaxsync.surrogate.linear import LinearArchitecture, LinearFitConfig, fit_linear
    from jaxsync.surrogate.lstm import LSTMArchitecture
    from jaxsync.surrogate.model import Surrogate
    from jaxsync.surrogate.online import OnlineLearning
    from jaxsync.surrogate.protocol import (
        FitSettings,
        GradientFitted,
        LeastSquaresFitted,
        PredictionCost,
        SurrogateArchitecture,
    )
    from jaxsync.surrogate.registry import (
        register_surrogate,
        surrogate_class,
        surrogate_kinds,
        unregister_surrogate,
    )
    from jaxsync.surrogate.saved import SavedSurrogate, load_surrogate, save_surrogate
    from jaxsync.surrogate.train import TrainConfig, TrainResult, train_replicas
    from jaxsync.surrogate.training_state import TrainingState
