"""LSTM encoder-decoder surrogates of the partition-shared displacements (paper section 3),
and the linear autoregressive baseline beside them.

The names a user needs are here; everything else stays importable from its module. The
models are in :mod:`.models`, their training in :mod:`.training`; what the solver and the
files use of a trained set is beside them:

===================================  ==========================================================
:mod:`.model`                        :class:`Surrogate`: the trained replicas of a partition as
                                     one pytree, with ``predict`` (one refill) and ``rollout``
                                     (refill cycles); what the solver runs
:mod:`.refill`                       Algorithm 3's refill index sets and ``refill_predict``
:mod:`.inference`                    reduced-precision (bfloat16) inference: the check that it
                                     keeps accuracy (:func:`check_inference_precision`,
                                     :func:`reduced_precision`)
:mod:`jaxsync.io.surrogate_file`      surrogate files of trained replicas (:class:`SavedSurrogate`)
:mod:`.models.lstm`                  the network, written by hand (:class:`LSTMArchitecture`)
:mod:`.models.linear`                the linear autoregressive baseline, fitted by least squares
                                     (:class:`LinearArchitecture`, :func:`fit_linear`)
:mod:`.models.protocol`              the surrogate-model protocol every model implements
                                     (:class:`SurrogateArchitecture`, :class:`GradientFitted`,
                                     :class:`LeastSquaresFitted`): init, forward, fit, cost, files
:mod:`.models.registry`              model kinds by name (:func:`register_surrogate`): what
                                     surrogate files and ``jaxsync train --model`` name
:mod:`.models.architecture`          one code path for every model through its methods;
                                     :class:`ArchitectureChoice`, the model and size to train
:mod:`.models.replicas`              padding and stacking one network per part
:mod:`.training.fit`                 :func:`train_surrogates`: trajectories in, trained
                                     surrogates out (``jaxsync train`` and the demo call it);
                                     :meth:`TrainedSurrogates.write` writes their files
:mod:`.training.data`                sample-refill windows (:class:`Sampling`, their settings),
                                     normalization, padded replica datasets
:mod:`.training.histories`           the shared histories read from distributed trajectories
:mod:`.training.train`               optax training of all replicas in one program
                                     (:func:`train_replicas`, :class:`TrainConfig`,
                                     :class:`TrainResult`)
:mod:`.training.loss`                the training loss of every gradient-fitted model
:mod:`.training.least_squares`       the linear model's and the highway's least squares
:mod:`.training.training_state`      the resumable state of a training run
                                     (:class:`TrainingState`: where and how often it is written)
:mod:`.training.evaluate`            the offline rollout check, E_mse (:class:`TrainingChecks`)
                                     and the grid search
:mod:`.training.online`              learning while synchronized (:class:`OnlineLearning`):
                                     updates from the steps error control recomputes
===================================  ==========================================================
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
    "jaxsync.surrogate.inference": ("ReducedPrecisionWarning", "check_inference_precision", "reduced_precision"),
    "jaxsync.surrogate.model": ("Surrogate",),
    "jaxsync.surrogate.models.architecture": ("ArchitectureChoice",),
    "jaxsync.surrogate.models.linear": ("LinearArchitecture", "LinearFitConfig", "fit_linear"),
    "jaxsync.surrogate.models.lstm": ("LSTMArchitecture",),
    "jaxsync.surrogate.models.protocol": ("FitSettings", "GradientFitted", "LeastSquaresFitted", "PredictionCost",
                                          "SurrogateArchitecture"),
    "jaxsync.surrogate.models.registry": ("register_surrogate", "surrogate_class", "surrogate_kinds",
                                          "unregister_surrogate"),
    "jaxsync.io.surrogate_file": ("SavedSurrogate", "load_surrogate", "save_surrogate"),
    "jaxsync.surrogate.training.data": ("Sampling", "build_dataset", "stack_replicas"),
    "jaxsync.surrogate.training.evaluate": ("GridSearchResult", "RolloutWarning", "TrainingChecks", "e_mse",
                                            "grid_search", "rollout_errors"),
    "jaxsync.surrogate.training.fit": ("TrainedSurrogates", "train_surrogates"),
    "jaxsync.surrogate.training.online": ("OnlineLearning",),
    "jaxsync.surrogate.training.train": ("TrainConfig", "TrainResult", "train_replicas"),
    "jaxsync.surrogate.training.training_state": ("TrainingState",),
})

if TYPE_CHECKING:
    from jaxsync.io.surrogate_file import SavedSurrogate, load_surrogate, save_surrogate
    from jaxsync.surrogate.inference import ReducedPrecisionWarning, check_inference_precision, reduced_precision
    from jaxsync.surrogate.model import Surrogate
    from jaxsync.surrogate.models.architecture import ArchitectureChoice
    from jaxsync.surrogate.models.linear import LinearArchitecture, LinearFitConfig, fit_linear
    from jaxsync.surrogate.models.lstm import LSTMArchitecture
    from jaxsync.surrogate.models.protocol import (
        FitSettings,
        GradientFitted,
        LeastSquaresFitted,
        PredictionCost,
        SurrogateArchitecture,
    )
    from jaxsync.surrogate.models.registry import (
        register_surrogate,
        surrogate_class,
        surrogate_kinds,
        unregister_surrogate,
    )
    from jaxsync.surrogate.training.data import Sampling, build_dataset, stack_replicas
    from jaxsync.surrogate.training.evaluate import (
        GridSearchResult,
        RolloutWarning,
        TrainingChecks,
        e_mse,
        grid_search,
        rollout_errors,
    )
    from jaxsync.surrogate.training.fit import TrainedSurrogates, train_surrogates
    from jaxsync.surrogate.training.online import OnlineLearning
    from jaxsync.surrogate.training.train import TrainConfig, TrainResult, train_replicas
    from jaxsync.surrogate.training.training_state import TrainingState
