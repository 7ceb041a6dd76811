"""LSTM encoder-decoder surrogates of the partition-shared displacements (paper section 3).

Modules: :mod:`~jaxsync.surrogate.lstm` (network), :mod:`~jaxsync.surrogate.data`
(sample-refill windows, normalization, refill index sets), :mod:`~jaxsync.surrogate.train`
(optax training of all replicas together), :mod:`~jaxsync.surrogate.evaluate` (refill
prediction, E_mse, grid search), :mod:`~jaxsync.surrogate.checkpoint` (HDF5 files),
:mod:`~jaxsync.app.train` (``jaxsync train``).
"""

from jaxsync.surrogate.checkpoint import (
    FORMAT_VERSION,
    SurrogateCheckpoint,
    check_compatible,
    load_checkpoint,
    save_checkpoint,
)
from jaxsync.surrogate.data import (
    Normalization,
    ReplicaData,
    SharedHistories,
    WindowDataset,
    build_dataset,
    make_windows,
    padding_mask,
    read_shared_histories,
    refill_index_sets,
    refill_input_steps,
    refill_scatter,
    refill_target_steps,
    refill_windows,
    split_indices,
    stack_replicas,
    subsample,
)
from jaxsync.surrogate.evaluate import (
    GridPoint,
    GridSearchResult,
    e_mse,
    evaluate_result,
    grid_search,
    max_applications,
    refill_predict,
    rollout,
    rollout_replicas,
)
from jaxsync.surrogate.lstm import (
    LSTMArchitecture,
    count_parameters,
    decode,
    encode,
    forward,
    init_params,
    lstm_cell,
    run_lstm,
)
from jaxsync.surrogate.train import (
    TrainConfig,
    TrainResult,
    init_replicas,
    learning_rate_schedule,
    n_epoch_rule,
    pad_params,
    replica_params,
    stack_params,
    train_replicas,
    unpad_params,
)

__all__ = [
    "FORMAT_VERSION", "SurrogateCheckpoint", "check_compatible", "load_checkpoint", "save_checkpoint",
    "Normalization", "ReplicaData", "SharedHistories", "WindowDataset", "build_dataset", "make_windows", "padding_mask",
    "read_shared_histories", "refill_index_sets", "refill_input_steps", "refill_scatter", "refill_target_steps", "refill_windows",
    "split_indices", "stack_replicas", "subsample",
    "GridPoint", "GridSearchResult", "e_mse", "evaluate_result", "grid_search", "max_applications",
    "refill_predict", "rollout", "rollout_replicas",
    "LSTMArchitecture", "count_parameters", "decode", "encode", "forward", "init_params", "lstm_cell",
    "run_lstm",
    "TrainConfig", "TrainResult", "init_replicas", "learning_rate_schedule", "n_epoch_rule", "pad_params", "replica_params",
    "stack_params", "train_replicas", "unpad_params",
]
