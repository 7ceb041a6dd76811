"""Training the surrogate models. The modules are private; these names are the package's
interface (the main ones are re-exported by :mod:`jaxsync.surrogate`):

- from trajectories to trained surrogates: :func:`train_surrogates`
  (:class:`TrainedSurrogates`, :func:`choose_candidates`);
- the shared histories they learn from (:class:`SharedHistories`,
  :func:`read_shared_histories`, :func:`shared_dof_layout`) and the sample-refill windows
  (:class:`Sampling`, :func:`build_dataset`, :func:`stack_replicas`, :class:`ReplicaData`,
  :class:`Normalization`, :func:`normalize`, :func:`subsample`, :func:`make_windows`,
  :func:`split_indices`, :func:`padding_mask`, :func:`last_trained_step`);
- gradient training of every part's replica in one program: :func:`train_replicas`
  (:class:`TrainConfig`, :class:`TrainResult`, :func:`n_epoch_rule`,
  :func:`learning_rate_schedule`), its loss (:func:`masked_mse`) and its resumable state
  (:class:`TrainingState`, :func:`load_training_state`);
- the least squares of the linear models and of the LSTM's highway:
  :func:`solve_least_squares`, and :func:`select_regularization` by
  :func:`rollout_error` (:data:`DEFAULT_REGULARIZATION`, :data:`REGULARIZATION_CHOICES`,
  :data:`ROLLOUT_SLACK`, :data:`FREE_REGULARIZATION`, :data:`FILTER_CUT`);
- the offline checks: :class:`TrainingChecks`, :func:`e_mse`, :func:`rollout_errors`
  (:func:`max_applications`), :class:`RolloutWarning`, and the grid search
  (:func:`grid_search`, :class:`GridSearchResult`);
- learning while a run is synchronized: :class:`OnlineLearning` (:class:`OnlineLearner`,
  :class:`UpdateReport`, :func:`sample_refill_windows`, :func:`window_starts`).
"""

from typing import TYPE_CHECKING

from ...lazy import export_lazily

__all__ = ["train_surrogates", "TrainedSurrogates", "choose_candidates", "SharedHistories", "shared_dof_layout",
           "read_shared_histories", "Sampling", "Normalization", "ReplicaData", "build_dataset", "stack_replicas",
           "subsample", "make_windows", "split_indices", "normalize", "padding_mask", "last_trained_step",
           "TrainConfig", "TrainResult", "train_replicas", "n_epoch_rule", "learning_rate_schedule", "masked_mse",
           "TrainingState", "load_training_state", "DEFAULT_REGULARIZATION", "REGULARIZATION_CHOICES", "ROLLOUT_SLACK",
           "FREE_REGULARIZATION", "FILTER_CUT", "solve_least_squares", "rollout_error", "select_regularization",
           "TrainingChecks", "e_mse", "rollout_errors", "RolloutWarning", "GridSearchResult", "grid_search",
           "max_applications", "OnlineLearning", "OnlineLearner", "UpdateReport", "sample_refill_windows",
           "window_starts"]

# where each name of __all__ is imported from on first use (jaxsync.lazy): the imports of TYPE_CHECKING below
__getattr__, __dir__ = export_lazily(__name__, {
    "._fit": ("TrainedSurrogates", "choose_candidates", "train_surrogates"),
    "._histories": ("SharedHistories", "read_shared_histories", "shared_dof_layout"),
    "._data": ("Normalization", "ReplicaData", "Sampling", "build_dataset", "last_trained_step", "make_windows",
               "normalize", "padding_mask", "split_indices", "stack_replicas", "subsample"),
    "._train": ("TrainConfig", "TrainResult", "learning_rate_schedule", "n_epoch_rule", "train_replicas"),
    "._loss": ("masked_mse",),
    "._training_state": ("TrainingState", "load_training_state"),
    "._least_squares": ("DEFAULT_REGULARIZATION", "FILTER_CUT", "FREE_REGULARIZATION", "REGULARIZATION_CHOICES",
                        "ROLLOUT_SLACK", "rollout_error", "select_regularization", "solve_least_squares"),
    "._evaluate": ("GridSearchResult", "RolloutWarning", "TrainingChecks", "e_mse", "grid_search", "max_applications",
                   "rollout_errors"),
    "._online": ("OnlineLearner", "OnlineLearning", "UpdateReport", "sample_refill_windows", "window_starts"),
})

if TYPE_CHECKING:
    from ._data import (
        Normalization,
        ReplicaData,
        Sampling,
        build_dataset,
        last_trained_step,
        make_windows,
        normalize,
        padding_mask,
        split_indices,
        stack_replicas,
        subsample,
    )
    from ._evaluate import (
        GridSearchResult,
        RolloutWarning,
        TrainingChecks,
        e_mse,
        grid_search,
        max_applications,
        rollout_errors,
    )
    from ._fit import TrainedSurrogates, choose_candidates, train_surrogates
    from ._histories import SharedHistories, read_shared_histories, shared_dof_layout
    from ._least_squares import (
        DEFAULT_REGULARIZATION,
        FILTER_CUT,
        FREE_REGULARIZATION,
        REGULARIZATION_CHOICES,
        ROLLOUT_SLACK,
        rollout_error,
        select_regularization,
        solve_least_squares,
    )
    from ._loss import masked_mse
    from ._online import OnlineLearner, OnlineLearning, UpdateReport, sample_refill_windows, window_starts
    from ._train import TrainConfig, TrainResult, learning_rate_schedule, n_epoch_rule, train_replicas
    from ._training_state import TrainingState, load_training_state
