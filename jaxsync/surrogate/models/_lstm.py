"""LSTM encoder-decoder written by hand in JAX (Tong & Schiavazzi 2022, section 3).

The network maps a window of ``n_past`` snapshots of a part's shared degrees of freedom
to the next ``n_future`` snapshots.  Everything here is unbatched (one window); callers
``jax.vmap`` over windows and over replicas.

Cell (Hochreiter & Schmidhuber), for input ``d`` and previous state ``(h, c)``::

    f = sigmoid(W_fd d + W_fh h + b_f)         forget gate
    i = sigmoid(W_id d + W_ih h + b_i)         input gate
    g = tanh   (W_gd d + W_gh h + b_g)         candidate cell update
    o = sigmoid(W_od d + W_oh h + b_o)         output gate
    c' = f * c + i * g
    h' = o * tanh(c')

The four gate blocks are stacked in the order (f, i, g, o) along the first axis of
``w_d`` (4 n_H, n_in), ``w_h`` (4 n_H, n_H) and ``b`` (4 n_H,).

Parameters are a plain pytree of arrays::

    {"encoder": [{"forward": cell, "backward": cell}, ...],   # n_layers entries
     "decoder": cell,                                          # hidden size 2 n_H
     "dense": {"w": (n_dof, 2 n_H), "b": (n_dof,)},
     "highway": {...}}                                         # with a linear highway only

Initialization (the defaults of PyTorch's ``nn.LSTM`` and ``nn.Linear``): every LSTM
weight and bias ~ U(-1/sqrt(H), 1/sqrt(H)) with H the hidden size of that cell (n_H in
the encoder, 2 n_H in the decoder); the dense layer's weight and bias
~ U(-1/sqrt(2 n_H), 1/sqrt(2 n_H)).  Forget-gate biases get no special offset.

Conditional variant: the decoder input is ``[y_prev, alpha_f repeated q times]``.

Load input (``n_load > 0``): the known load signals u (:mod:`jaxsync.fem`,
normalized by the surrogate's per-signal scale) at the window's n_p + n_f sample times,
``loads`` (n_p + n_f, n_load). Their past values u(1 .. n_p) are appended to the inputs
of the first encoder layer, step by step, and the future values u(n_p + 1 .. n_p + n_f)
to the decoder's input of the step that predicts that snapshot. Their weights are kept
apart, ``"w_u"`` (4 H, n_load) in the first layer's forward and backward cells and in the
decoder cell, and added as a separate term ``W_u u`` to the input projection
``W_d d + b``: a network whose ``w_u`` are zero computes bit for bit what the same
network without load input computes, and with ``n_load = 0`` the parameters and the
computation are those of a network without it (surrogate files written before the load
input load unchanged).

Linear highway (``highway=True``, after LSTNet, Lai et al. 2018): the prediction is
the least-squares affine map of the window -- the linear model of
:mod:`jaxsync.surrogate.models`, ARX with the load signals -- plus the decoder's
output. Each decoder step adds the highway's prediction of its snapshot to its dense
output and feeds the sum back. The map is fitted first, in closed form, on the training
windows; the dense layer starts at zero, so training starts from the linear model's
predictions and the recurrent part learns what they miss. No gradient reaches the map
(training it with the decoder moves it off the least-squares fit and worsens the
out-of-sample rollout); online learning refits it by least squares on the run's windows,
as the linear model learns, and trains the recurrent part by gradient. Its parameters
are ``"highway": {"w_in", "w_out", "b"[, "w_load"]}`` of
:func:`jaxsync.surrogate.models.param_shapes`, of rank ``highway_rank``.

Reduced-precision inference (``compute_dtype="bfloat16"`` in :func:`forward`):
every matrix product takes bfloat16 operands -- the weights, the layer inputs, the hidden
states and the fed-back predictions, rounded to bfloat16 -- and accumulates in float32
(``preferred_element_type``); biases are rounded to bfloat16 and added in float32, and the
gate nonlinearities, the cell state and the outputs stay float32.  The parameters are
stored as trained; the rounding happens inside the compiled program.  Whether a trained
network keeps its accuracy this way is measured, not assumed:
:func:`jaxsync.surrogate.check_inference_precision`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from jaxsync.errors import ConfigError
from jaxsync.surrogate.models._protocol import (  # noqa: F401 - the input checks, importable from here as before
    COMPUTE_DTYPES,
    GradientFitted,
    PredictionCost,
    check_compute_dtype,
    check_loads,
)
from jaxsync.surrogate.models._replicas import (
    count_parameters,  # noqa: F401 - importable from here as before
    pad_params,
    stack_params,
)

Params = dict[str, Any]

_DTYPES = ("float32", "float64")

@jax.tree_util.register_static
@dataclasses.dataclass(frozen=True)
class LSTMArchitecture(GradientFitted):
    """Shape of one encoder-decoder (static: it never carries arrays): a surrogate model
    trained by gradient (:mod:`jaxsync.surrogate.models`).

    Attributes:
        n_dof: degrees of freedom per snapshot (input and output width). For a set of
            replicas trained together this is the padded width (largest part).
        n_hidden: n_H, hidden size of each encoder direction; the decoder has 2 n_H.
            Default 50, as ``jaxsync train`` and the cantilever demo (the paper's
            published code; within 2 % on the cantilever's fixed-load cases, see
            ``benchmarks/paper_experiments.py``); the paper's text uses 100.
        n_layers: k, number of stacked bidirectional encoder layers.
        n_past: n_p, snapshots in an input window.
        n_future: n_f, snapshots the decoder predicts (fed its own output).
        n_cond_repeat: q, copies of the load parameter appended to every decoder input;
            0 gives the unconditional network.
        dtype: "float32" (default) or "float64" for the parameters and computation.
        n_load: number of known load signals fed in (module docstring); 0 (default):
            none, the network of the paper.
        highway: add a linear autoregressive highway (module docstring): the
            prediction is the least-squares affine map of the window (ARX with the load
            signals) plus the decoder's output, trained together from the map's
            least-squares fit (:meth:`fit`). False (default): the paper's network.
        highway_rank: the highway's inner width (its least-squares rank, set by
            :meth:`fit`; 0 without a highway).
        kind: "lstm" (class attribute, not a field): the model a surrogate file holds
            (:mod:`jaxsync.surrogate.models`).
    """

    kind: ClassVar[str] = "lstm"
    display_name: ClassVar[str] = "LSTM"

    n_dof: int
    n_hidden: int = 50
    n_layers: int = 2
    n_past: int = 20
    n_future: int = 20
    n_cond_repeat: int = 0
    dtype: str = "float32"
    n_load: int = 0
    highway: bool = False
    highway_rank: int = 0

    def __post_init__(self):
        if isinstance(self.n_load, bool) or not isinstance(self.n_load, (int, np.integer)) or self.n_load < 0:
            raise ConfigError(f"LSTMArchitecture.n_load must be an integer >= 0 (load signals), got {self.n_load!r}")
        if not isinstance(self.highway, (bool, np.bool_)):
            raise ConfigError(f"LSTMArchitecture.highway must be True or False, got {self.highway!r}")
        rank = self.highway_rank
        if isinstance(rank, bool) or not isinstance(rank, (int, np.integer)) or rank < 0 or (rank and not self.highway):
            raise ConfigError(f"LSTMArchitecture.highway_rank must be an integer >= 0, and 0 without a highway; got "
                              f"{rank!r} (highway={self.highway})")
        for name in ("n_dof", "n_hidden", "n_layers", "n_past", "n_future"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value < 1:
                raise ConfigError(f"LSTMArchitecture.{name} must be a positive integer, got {value!r}")
        if not isinstance(self.n_cond_repeat, (int, np.integer)) or self.n_cond_repeat < 0:
            raise ConfigError(
                f"LSTMArchitecture.n_cond_repeat must be an integer >= 0, got {self.n_cond_repeat!r}"
            )
        if self.dtype not in _DTYPES:
            raise ConfigError(f"LSTMArchitecture.dtype must be one of {_DTYPES}, got {self.dtype!r}")

    @property
    def conditional(self) -> bool:
        """True when the decoder input carries the load parameter."""
        return self.n_cond_repeat > 0

    @property
    def decoder_hidden(self) -> int:
        """Hidden size of the decoder, 2 n_H (forward and backward states concatenated)."""
        return 2 * self.n_hidden

    @classmethod
    def from_choice(cls, choice, n_dof: int, n_past: int, n_future: int, n_load: int) -> "LSTMArchitecture":
        """The network of an :class:`~jaxsync.surrogate.ArchitectureChoice` for the data's
        windows (:meth:`~jaxsync.surrogate.ArchitectureChoice.lstm`)."""
        return choice.lstm(n_dof, n_past, n_future, n_load)

    @property
    def highway_arch(self):
        """The highway's :class:`~jaxsync.surrogate.models.LinearArchitecture` (None
        without a highway, or before :meth:`fit` set its rank)."""
        if not self.highway_rank:
            return None
        from jaxsync.surrogate.models._linear import LinearArchitecture

        return LinearArchitecture(n_dof=self.n_dof, rank=self.highway_rank, n_past=self.n_past,
                                  n_future=self.n_future, dtype=self.dtype, n_load=self.n_load)

    def to_dict(self) -> dict[str, Any]:
        """The hyperparameters; ``highway`` and ``highway_rank`` only with a highway (a
        network without one is stored as before the highway existed)."""
        values = super().to_dict()
        if not self.highway:
            values.pop("highway")
            values.pop("highway_rank")
        return values

    def init(self, key: jax.Array) -> Params:
        """:func:`init_params` of this network."""
        return init_params(key, self)

    def online_update(self, learner, params, x, y, signals, weight, load_parameter, dof_mask, started: float):
        """With a highway, its least-squares refit first, on every window the run has
        synchronized (``learner.every_window()``, as the linear model learns online; no
        gradient reaches it), then the recurrent part's full-batch Adam steps on the
        weighted sample ``x`` ... ``weight``."""
        if self.highway_rank:
            from jaxsync.surrogate.models._linear import refit

            hx, hy, hu, hw = learner.every_window()
            highway = refit(params["highway"], self.highway_arch, hx, hy, hu, hw, dof_mask)
            params = {**params, "highway": jax.tree_util.tree_map(jnp.asarray, highway)}
        return learner.gradient_steps(params, x, y, signals, weight, load_parameter, dof_mask, started)

    def fit(self, data, settings):
        """Gradient training (:func:`~jaxsync.surrogate.training.train_replicas`); with a
        highway, from the least-squares affine map of the training windows
        (:func:`~jaxsync.surrogate.models._linear.fit_affine`, the choice's ``regularization``) and
        a zero output layer, so that training starts from the linear model's predictions
        and the decoder learns what they miss."""
        if not self.highway:
            return super().fit(data, settings)
        from jaxsync.surrogate.models._linear import fit_affine
        from jaxsync.surrogate.training._train import train_replicas

        linear, highway = fit_affine(data, settings.architecture.regularization, self.dtype)
        arch = dataclasses.replace(self, highway_rank=linear.rank)
        init_key, _ = jax.random.split(settings.key)  # the key train_replicas initializes with
        params = arch.init_replicas(init_key, data.dof_counts)
        params = {**params, "highway": jax.tree_util.tree_map(jnp.asarray, highway),
                  "dense": jax.tree_util.tree_map(jnp.zeros_like, params["dense"])}
        return train_replicas(data, arch, settings.optimizer, settings.key, init=params, progress=settings.progress,
                              devices=settings.devices, state=settings.state, callback=settings.callback)

    def init_replicas(self, key: jax.Array, dof_counts) -> Params:
        """Replica r is ``init_params(fold_in(key, r))`` at its own dof count (so it equals a
        network initialized alone), zero-padded to ``n_dof``
        (:func:`~jaxsync.surrogate.models.pad_params`)."""
        replicas = []
        for r, count in enumerate(dof_counts):
            own = dataclasses.replace(self, n_dof=int(count))
            replicas.append(pad_params(init_params(jax.random.fold_in(key, r), own), own, self.n_dof))
        return stack_params(replicas)

    def forward(self, params: Params, xs: jax.Array, load_parameter=None, dof_mask=None,
                compute_dtype: str | None = None, loads=None) -> jax.Array:
        """:func:`forward` of this network."""
        return forward(params, self, xs, load_parameter, dof_mask, compute_dtype=compute_dtype, loads=loads)

    def prediction_cost(self, n_s: int, masked: bool = True, io_bytes_per_value: int = 8) -> PredictionCost:
        """Bytes and flops of one refill prediction (:func:`count_prediction_cost`)."""
        return count_prediction_cost(self, n_s, masked, io_bytes_per_value)


# ----------------------------------------------------------------------------- init


def _param_shapes(arch: LSTMArchitecture) -> Params:
    """Pytree of ``(shape, init_bound)`` with the structure of the parameters."""
    def cell(n_in, n_h, n_load=0):
        bound = 1.0 / math.sqrt(n_h)
        out = {"w_d": ((4 * n_h, n_in), bound), "w_h": ((4 * n_h, n_h), bound), "b": ((4 * n_h,), bound)}
        if n_load:
            out["w_u"] = ((4 * n_h, n_load), bound)
        return out

    encoder = [
        {"forward": cell(n_in, arch.n_hidden, n_load), "backward": cell(n_in, arch.n_hidden, n_load)}
        for n_in, n_load in [(arch.n_dof, arch.n_load)] + [(2 * arch.n_hidden, 0)] * (arch.n_layers - 1)
    ]
    n_dec = arch.decoder_hidden
    dense_bound = 1.0 / math.sqrt(n_dec)
    shapes = {
        "encoder": encoder,
        "decoder": cell(arch.n_dof + arch.n_cond_repeat, n_dec, arch.n_load),
        "dense": {"w": ((arch.n_dof, n_dec), dense_bound), "b": ((arch.n_dof,), dense_bound)},
    }
    if arch.highway_rank:  # zero: set by the least-squares fit (LSTMArchitecture.fit)
        from jaxsync.surrogate.models._linear import param_shapes

        shapes["highway"] = {name: (shape, 0.0) for name, shape in param_shapes(arch.highway_arch).items()}
    return shapes


@functools.partial(jax.jit, static_argnames="arch")
def init_params(key: jax.Array, arch: LSTMArchitecture) -> Params:
    """Random parameters for one encoder-decoder (initialization in the module docstring).

    Args:
        key: PRNG key.
        arch: the architecture; ``arch.n_dof`` sets the input and output widths.

    Returns:
        The parameter pytree, arrays of dtype ``arch.dtype``.
    """
    spec = _param_shapes(arch)
    is_spec = lambda x: isinstance(x, tuple) and len(x) == 2 and isinstance(x[0], tuple)  # noqa: E731
    leaves, treedef = jax.tree_util.tree_flatten(spec, is_leaf=is_spec)
    sizes = [math.prod(shape) for shape, _ in leaves]
    # One draw for all leaves, cut into pieces: a single PRNG call compiles much faster
    # than one per array.
    unit = jax.random.uniform(key, (sum(sizes),), dtype=jnp.dtype(arch.dtype), minval=-1.0, maxval=1.0)
    pieces = jnp.split(unit, np.cumsum(sizes)[:-1])
    arrays = [piece.reshape(shape) * bound for piece, (shape, bound) in zip(pieces, leaves)]
    return jax.tree_util.tree_unflatten(treedef, arrays)


# ----------------------------------------------------------------------------- cell


def _reduced(params: Params, compute_dtype: str | None) -> Params:
    """``params`` rounded to ``compute_dtype`` (unchanged for None)."""
    if compute_dtype is None:
        return params
    return jax.tree_util.tree_map(lambda w: w.astype(compute_dtype), params)


def _matmul(a: jax.Array, b: jax.Array) -> jax.Array:
    """``a @ b``; when either operand (the weights) is bfloat16, both are rounded to
    bfloat16 and the product accumulates in float32 (the float32 result)."""
    if jnp.bfloat16 in (a.dtype, b.dtype):
        return jnp.matmul(a.astype(jnp.bfloat16), b.astype(jnp.bfloat16), preferred_element_type=jnp.float32)
    return a @ b


def _bias(b: jax.Array) -> jax.Array:
    """A bias as added: float32 when rounded to bfloat16 (the accumulation type)."""
    return b.astype(jnp.float32) if b.dtype == jnp.bfloat16 else b


def _cell_update(w_h: jax.Array, carry: tuple[jax.Array, jax.Array], z_in: jax.Array):
    """Cell step given the input projection ``z_in = W_d d + b`` (4 n_H,)."""
    h, c = carry
    z = z_in + _matmul(w_h, h)
    f, i, g, o = jnp.split(z, 4, axis=-1)
    c = jax.nn.sigmoid(f) * c + jax.nn.sigmoid(i) * jnp.tanh(g)
    h = jax.nn.sigmoid(o) * jnp.tanh(c)
    return h, c


def lstm_cell(cell: Params, carry: tuple[jax.Array, jax.Array], d: jax.Array, u: jax.Array | None = None):
    """One LSTM step (unbatched).

    Args:
        cell: ``{"w_d": (4H, n_in), "w_h": (4H, H), "b": (4H,)}``, gates ordered (f, i, g, o),
            and ``"w_u": (4H, n_load)`` for a cell that reads load signals.
        carry: ``(h, c)``, each (H,).
        d: input (n_in,).
        u: the load signals (n_load,) of a cell with ``"w_u"``, added as ``W_u u``.

    Returns:
        The new ``(h, c)``.
    """
    z_in = _matmul(cell["w_d"], d) + _bias(cell["b"])
    if u is not None:
        z_in = z_in + _matmul(cell["w_u"], u)
    return _cell_update(cell["w_h"], carry, z_in)


def run_lstm(cell: Params, xs: jax.Array, carry: tuple[jax.Array, jax.Array], us: jax.Array | None = None):
    """Run one direction over a sequence with ``lax.scan``.

    Args:
        cell: cell parameters.
        xs: inputs (T, n_in), processed in the given order.
        carry: initial ``(h, c)``, each (H,).
        us: the load signals (T, n_load) of a cell with ``"w_u"`` (in the order of ``xs``),
            or None.

    Returns:
        ``(hs, (h_T, c_T))``: the hidden states (T, H) and the final state.
    """
    # The input projection does not depend on the recursion: one matmul for all steps.
    z_in = _matmul(xs, cell["w_d"].T) + _bias(cell["b"])[None]
    if us is not None:
        z_in = z_in + _matmul(us, cell["w_u"].T)

    def step(carry, z_t):
        carry = _cell_update(cell["w_h"], carry, z_t)
        return carry, carry[0]

    final, hs = jax.lax.scan(step, carry, z_in)
    return hs, final


def _bidirectional_layer(layer: Params, xs: jax.Array, n_hidden: int, us: jax.Array | None = None):
    """One encoder layer: the forward cell reads ``xs``, the backward cell ``xs[::-1]``
    (and the load signals ``us`` (T, n_load) alike, for the first layer of a network with
    load input).

    Returns:
        ``(outputs (T, 2H) in time order [forward | backward], ((h_f, c_f), (h_b, c_b)))``
        where the backward final state summarizes the window read from its last snapshot
        back to its first.
    """
    # Derived from the input, not a constant, so that it has the input's type (varying
    # over the mesh axis) when called under shard_map.
    zeros = jnp.zeros_like(xs[0, :1], shape=(n_hidden,))
    hs_f, final_f = run_lstm(layer["forward"], xs, (zeros, zeros), us)
    hs_b, final_b = run_lstm(layer["backward"], xs[::-1], (zeros, zeros), None if us is None else us[::-1])
    return jnp.concatenate([hs_f, hs_b[::-1]], axis=-1), (final_f, final_b)


@functools.partial(jax.jit, static_argnames="arch")
def encode(params: Params, arch: LSTMArchitecture, xs: jax.Array, us: jax.Array | None = None):
    """Stacked bidirectional encoder.

    Args:
        params: network parameters.
        arch: architecture.
        xs: normalized input window (n_p, n_dof).
        us: normalized past load signals (n_p, n_load) of a network with load input
            (read by the first layer), else None.

    Returns:
        The decoder's initial state ``(h0, c0)``, each (2 n_H,): the last layer's final
        forward and backward states concatenated ``[forward, backward]``.
    """
    layer_in = xs
    final = None
    for k, layer in enumerate(params["encoder"]):
        layer_in, final = _bidirectional_layer(layer, layer_in, arch.n_hidden, us if k == 0 else None)
    (h_f, c_f), (h_b, c_b) = final
    return jnp.concatenate([h_f, h_b]), jnp.concatenate([c_f, c_b])


@functools.partial(jax.jit, static_argnames="arch")
def decode(
    params: Params,
    arch: LSTMArchitecture,
    state: tuple[jax.Array, jax.Array],
    first_input: jax.Array,
    load_parameter: jax.Array | None = None,
    dof_mask: jax.Array | None = None,
    us: jax.Array | None = None,
    offsets: jax.Array | None = None,
) -> jax.Array:
    """Decoder fed its own predictions for ``n_future`` steps.

    Args:
        params: network parameters.
        arch: architecture.
        state: initial ``(h, c)``, each (2 n_H,).
        first_input: the last input snapshot d(n_p) (n_dof,).
        load_parameter: scalar load parameter (conditional networks only).
        dof_mask: (n_dof,) 1 for real dofs, 0 for padding; padded outputs are zeroed
            before being fed back so that padding never influences real dofs.
        us: normalized future load signals (n_f, n_load) of a network with load input:
            row j enters the step that predicts snapshot j; else None.
        offsets: (n_f, n_dof) the highway's predictions, added to the output of the
            step that predicts each snapshot (and fed back with it); None: none.

    Returns:
        Predictions (n_f, n_dof).
    """
    if arch.conditional:
        if load_parameter is None:
            raise ConfigError("this network is conditional (n_cond_repeat > 0): pass the load parameter")
        repeated_load = jnp.full((arch.n_cond_repeat,), load_parameter, dtype=first_input.dtype)
    dense = params["dense"]

    def step(carry, inputs):
        hc, y_prev = carry
        u, offset = inputs
        d = jnp.concatenate([y_prev, repeated_load]) if arch.conditional else y_prev
        hc = lstm_cell(params["decoder"], hc, d, u)
        y = _matmul(dense["w"], hc[0]) + _bias(dense["b"])
        if offset is not None:
            y = y + offset.astype(y.dtype)
        if dof_mask is not None:
            y = y * dof_mask.astype(y.dtype)
        return (hc, y), y

    _, ys = jax.lax.scan(step, (state, first_input), (us, offsets), length=arch.n_future)
    return ys


@functools.partial(jax.jit, static_argnames=("arch", "compute_dtype"))
def forward(
    params: Params,
    arch: LSTMArchitecture,
    xs: jax.Array,
    load_parameter: jax.Array | None = None,
    dof_mask: jax.Array | None = None,
    compute_dtype: str | None = None,
    loads: jax.Array | None = None,
) -> jax.Array:
    """Predict the next ``n_future`` snapshots from ``n_past`` snapshots (unbatched).

    Args:
        params: network parameters.
        arch: architecture.
        xs: normalized window (n_p, n_dof).
        load_parameter: scalar load parameter (conditional networks only).
        dof_mask: optional (n_dof,) padding mask, see :func:`decode`.
        compute_dtype: None (``arch.dtype`` throughout) or ``"bfloat16"``: bfloat16
            operands, float32 accumulation (module docstring).
        loads: (n_p + n_f, n_load) normalized load signals at the window's sample times
            (rows 0 .. n_p - 1 those of the inputs, then those of the predictions), required
            when ``arch.n_load > 0``, and None otherwise.

    Returns:
        Normalized predictions (n_f, n_dof), dtype ``arch.dtype``.
    """
    if xs.ndim != 2 or xs.shape[1] != arch.n_dof:
        raise ConfigError(f"input window must have shape (n_past, {arch.n_dof}), got {xs.shape}")
    check_compute_dtype(compute_dtype)
    loads = check_loads(arch, loads)
    xs = xs.astype(arch.dtype)
    offsets = None
    if arch.highway_rank:
        from jaxsync.surrogate.models._linear import forward as affine

        # the highway stays the least-squares fit: no gradient reaches it (measured: trained with
        # the decoder, it drifts from that fit and predicts worse out of sample)
        highway = jax.lax.stop_gradient(params["highway"])
        offsets = affine(highway, arch.highway_arch, xs, compute_dtype=compute_dtype, loads=loads)
    if compute_dtype is not None:
        params = _reduced(params, compute_dtype)
        # the states and outputs in the accumulation type, float32
        xs = xs.astype(jnp.float32)
        loads = None if loads is None else loads.astype(jnp.float32)
        if dof_mask is not None:
            dof_mask = dof_mask.astype(jnp.float32)
    past, future = (None, None) if loads is None else (loads[:arch.n_past], loads[arch.n_past:])
    state = encode(params, arch, xs, past)
    return decode(params, arch, state, xs[-1], load_parameter, dof_mask, future, offsets).astype(arch.dtype)


# ----------------------------------------------------------------------------- cost


def count_flops(arch: LSTMArchitecture, n_s: int, masked: bool = True) -> dict[str, float]:
    """Flops of one refill prediction (n_s windows), by kind (the formulas of
    :mod:`jaxsync.perf.roofline`'s module docstring).

    Returns:
        ``{"matmul": ..., "bias": ..., "cell": ..., "normalize": ..., "mask": ...}``:
        ``"matmul"`` the matrix products (2 flops per weight entry per use), ``"bias"``
        the bias additions, ``"cell"`` the gate arithmetic (13 per hidden unit per
        step), ``"normalize"`` the input and output scaling, ``"mask"`` the padding mask.
    """
    h, hd, d, q = arch.n_hidden, arch.decoder_hidden, arch.n_dof, arch.n_cond_repeat
    t, f = arch.n_past, arch.n_future
    matmul = bias = cell = 0
    for layer in range(arch.n_layers):
        n_in = d if layer == 0 else 2 * h
        # two directions, each: projection of all T inputs, then T recursive steps
        matmul += 2 * (2 * 4 * h * n_in * t + t * 2 * 4 * h * h)
        bias += 2 * 4 * h * t
        cell += 2 * t * 13 * h
    matmul += f * (2 * 4 * hd * (d + q) + 2 * 4 * hd * hd + 2 * d * hd)
    bias += f * (4 * hd + d)
    cell += f * 13 * hd
    if arch.highway_rank:  # the affine map (LinearArchitecture.prediction_cost) and its addition
        r, u = arch.highway_rank, arch.n_load
        matmul += 2 * t * d * r + 2 * (t + f) * u * r + 2 * r * f * d
        bias += 2 * f * d
    per_window = {"matmul": matmul, "bias": bias, "cell": cell, "normalize": 2 * d * (t + f),
                  "mask": f * d if masked else 0}
    return {k: float(n_s * v) for k, v in per_window.items()}


def count_prediction_cost(arch: LSTMArchitecture, n_s: int, masked: bool = True,
                          io_bytes_per_value: int = 8) -> PredictionCost:
    """Bytes and flops of one refill prediction (n_s windows of one part): the parameters
    (itemsize of ``arch.dtype``) read once per sequential matrix product, plus the input
    buffer, mean, std, mask and output at ``io_bytes_per_value`` (the formulas of
    :mod:`jaxsync.perf.roofline`'s module docstring)."""
    p_item = np.dtype(arch.dtype).itemsize
    h, hd, d, q = arch.n_hidden, arch.decoder_hidden, arch.n_dof, arch.n_cond_repeat
    t, f = arch.n_past, arch.n_future
    params = 0
    for layer in range(arch.n_layers):
        n_in = d if layer == 0 else 2 * h
        params += 2 * ((4 * h * n_in + 4 * h) + t * 4 * h * h)  # w_d, b once; w_h per step
    params += f * (4 * hd * (d + q) + 4 * hd * hd + 4 * hd)  # decoder cell per step
    params += f * (d * hd + d)  # dense per step
    if arch.highway_rank:  # read once
        r, u = arch.highway_rank, arch.n_load
        params += t * d * r + (t + f) * u * r + r * f * d + f * d
    io = n_s * t * d + 2 * d + n_s * f * d + (d if masked else 0)
    flops = sum(count_flops(arch, n_s, masked).values())
    return PredictionCost(float(p_item * params + io_bytes_per_value * io), float(flops))
