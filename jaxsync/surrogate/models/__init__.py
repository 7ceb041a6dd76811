"""The surrogate models. The modules are private; these names are the package's interface
(the main ones are re-exported by :mod:`jaxsync.surrogate`):

- the protocol every model implements: :class:`SurrogateArchitecture` (init, forward, fit,
  cost, files), :class:`GradientFitted`, :class:`LeastSquaresFitted`,
  :class:`FitSettings`, :class:`PredictionCost`; :data:`COMPUTE_DTYPES`,
  :func:`check_compute_dtype` and :func:`check_loads` check what a model is given;
- the registry of model kinds by name, what surrogate files and ``jaxsync train --model``
  name: :func:`register_surrogate`, :func:`unregister_surrogate`, :func:`surrogate_class`,
  :func:`surrogate_kinds`;
- one code path for every model through its methods: :func:`init_params`,
  :func:`forward`, :func:`architecture_to_dict`, :func:`architecture_from_dict`,
  :func:`model_module`; and :class:`ArchitectureChoice`, the model and size to train;
- the hand-written LSTM encoder-decoder: :class:`LSTMArchitecture` (its pieces
  :func:`lstm_cell`, :func:`run_lstm`, :func:`encode`; its cost :func:`count_flops`);
- the linear autoregressive model, fitted by least squares: :class:`LinearArchitecture`,
  :class:`LinearFitConfig`, :func:`fit_linear`, :func:`param_shapes`;
- one replica per part, padded and stacked: :func:`init_replicas`, :func:`pad_params`,
  :func:`unpad_params`, :func:`stack_params`, :func:`replica_params`,
  :func:`count_parameters`.
"""

from typing import TYPE_CHECKING

from ...lazy import export_lazily

__all__ = ["SurrogateArchitecture", "GradientFitted", "LeastSquaresFitted", "FitSettings", "PredictionCost",
           "COMPUTE_DTYPES", "check_compute_dtype", "check_loads", "register_surrogate", "unregister_surrogate",
           "surrogate_class", "surrogate_kinds", "ArchitectureChoice", "model_module", "architecture_to_dict",
           "architecture_from_dict", "init_params", "forward", "LSTMArchitecture", "lstm_cell", "run_lstm", "encode",
           "count_flops", "LinearArchitecture", "LinearFitConfig", "fit_linear", "pad_params", "unpad_params",
           "stack_params", "replica_params", "init_replicas", "count_parameters", "param_shapes"]

# where each name of __all__ is imported from on first use (jaxsync.lazy): the imports of TYPE_CHECKING below
__getattr__, __dir__ = export_lazily(__name__, {
    "._protocol": ("COMPUTE_DTYPES", "FitSettings", "GradientFitted", "LeastSquaresFitted", "PredictionCost",
                   "SurrogateArchitecture", "check_compute_dtype", "check_loads"),
    "._registry": ("register_surrogate", "surrogate_class", "surrogate_kinds", "unregister_surrogate"),
    "._architecture": ("ArchitectureChoice", "architecture_from_dict", "architecture_to_dict", "forward", "init_params",
                       "model_module"),
    "._lstm": ("LSTMArchitecture", "count_flops", "encode", "lstm_cell", "run_lstm"),
    "._linear": ("LinearArchitecture", "LinearFitConfig", "fit_linear", "param_shapes"),
    "._replicas": ("count_parameters", "init_replicas", "pad_params", "replica_params", "stack_params", "unpad_params"),
})

if TYPE_CHECKING:
    from ._architecture import (
        ArchitectureChoice,
        architecture_from_dict,
        architecture_to_dict,
        forward,
        init_params,
        model_module,
    )
    from ._linear import LinearArchitecture, LinearFitConfig, fit_linear, param_shapes
    from ._lstm import LSTMArchitecture, count_flops, encode, lstm_cell, run_lstm
    from ._protocol import (
        COMPUTE_DTYPES,
        FitSettings,
        GradientFitted,
        LeastSquaresFitted,
        PredictionCost,
        SurrogateArchitecture,
        check_compute_dtype,
        check_loads,
    )
    from ._registry import register_surrogate, surrogate_class, surrogate_kinds, unregister_surrogate
    from ._replicas import count_parameters, init_replicas, pad_params, replica_params, stack_params, unpad_params
