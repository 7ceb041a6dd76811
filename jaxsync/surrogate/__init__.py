"""LSTM encoder-decoder surrogates of the partition-shared displacements (paper section 3),
and the linear autoregressive baseline beside them.

The names a user needs are here; everything else stays importable from its module:

=========================  =================================================================
:mod:`.model`              :class:`Surrogate`: the trained replicas of a partition as one
                           pytree, with ``predict`` (one refill) and ``rollout`` (refill
                           cycles); what the solver runs
:mod:`.fit`                :func:`train_surrogates`: trajectories in, trained surrogates and
                           files out (``jaxsync train`` and the demo call it)
:mod:`.lstm`               the network, written by hand (:class:`LSTMArchitecture`)
:mod:`.linear`             the linear autoregressive baseline, fitted by least squares
                           (:class:`LinearArchitecture`, :func:`fit_linear`)
:mod:`.architecture`       dispatch on the architecture: one code path for both models
:mod:`.refill`             Algorithm 3's refill index sets and ``refill_predict``
:mod:`.inference`          reduced-precision (bfloat16) inference: the check that it keeps
                           accuracy (:func:`check_inference_precision`,
                           :func:`reduced_precision`)
:mod:`.data`               sample-refill windows, normalization, padded replica datasets,
                           reading shared histories from trajectories
:mod:`.replicas`           padding and stacking one network per part
:mod:`.train`              optax training of all replicas in one program
                           (:func:`train_replicas`, :class:`TrainConfig`, :class:`TrainResult`)
:mod:`.training_state`     the resumable state of a training run
:mod:`.checkpoint`         checkpoint files of trained replicas (:class:`SurrogateCheckpoint`)
:mod:`.evaluate`           the offline rollout check, E_mse and the grid search
=========================  =================================================================
"""

from jaxsync.surrogate.checkpoint import SurrogateCheckpoint, load_checkpoint, save_checkpoint
from jaxsync.surrogate.data import build_dataset, stack_replicas
from jaxsync.surrogate.evaluate import GridSearchResult, RolloutWarning, e_mse, grid_search, rollout_errors
from jaxsync.surrogate.fit import TrainedSurrogates, train_surrogates
from jaxsync.surrogate.inference import ReducedPrecisionWarning, check_inference_precision, reduced_precision
from jaxsync.surrogate.linear import LinearArchitecture, LinearFitConfig, fit_linear
from jaxsync.surrogate.lstm import LSTMArchitecture
from jaxsync.surrogate.model import Surrogate
from jaxsync.surrogate.train import TrainConfig, TrainResult, train_replicas

__all__ = [
    "Surrogate", "LSTMArchitecture", "LinearArchitecture", "LinearFitConfig", "fit_linear",
    "train_surrogates", "TrainedSurrogates",
    "TrainConfig", "TrainResult", "train_replicas", "build_dataset", "stack_replicas",
    "SurrogateCheckpoint", "save_checkpoint", "load_checkpoint",
    "e_mse", "rollout_errors", "RolloutWarning", "grid_search", "GridSearchResult",
    "check_inference_precision", "reduced_precision", "ReducedPrecisionWarning",
]
