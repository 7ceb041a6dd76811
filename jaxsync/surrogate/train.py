"""Training of one LSTM replica per part, all parts in one compiled program.

Optimizer: optax Adam with a learning rate that decays once per epoch,
``eta(epoch) = eta0 * gamma**epoch`` (``optax.exponential_decay`` with staircase steps of
one epoch), run for the paper's ``n_epoch = floor(log_gamma(eta_min / eta0))`` epochs
unless a count is given.  Mini-batches are reshuffled every epoch.

Replicas: parts have different shared-dof counts, so inputs, outputs and parameters are
zero-padded to the largest count and a dof mask (1 real, 0 padding) is applied to the
decoder's output and to the loss.  Padded inputs are zero, padded outputs are forced to
zero, so the parameters that touch padding get exactly zero gradients and Adam leaves
them at their (zero) initial value: each replica trains as it would alone (equal up to
float32 round-off, since XLA may order the sums of batched products differently).  The
per-epoch function is ``jax.vmap``-ed over the part axis (and, with several local devices,
``jax.shard_map``-ed so each device trains its own parts), and ``epochs_per_call`` epochs
run in one ``jax.lax.scan`` inside ``jax.jit``; Python only updates the progress bar.

Reproducibility: the PRNG key is split into an initialization key (replica ``r`` uses
``fold_in(init_key, r)``) and a shuffling key (epoch ``e`` uses ``fold_in(shuffle_key, e)``,
shared by all replicas since their windows are aligned in time).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P
from tqdm.auto import tqdm

from jaxsync.errors import ConfigError
from jaxsync.surrogate.data import ReplicaData, padding_mask
from jaxsync.surrogate.lstm import LSTMArchitecture, Params, forward, init_params


def n_epoch_rule(eta0: float, gamma: float, eta_min: float) -> int:
    """The paper's epoch count ``floor(log_gamma(eta_min / eta0))``: the number of
    per-epoch decays that bring eta0 down to eta_min (13 812 for the paper's defaults)."""
    if not (0.0 < gamma < 1.0):
        raise ConfigError(f"decay rate gamma must be in (0, 1), got {gamma}")
    if not (0.0 < eta_min < eta0):
        raise ConfigError(f"need 0 < eta_min < eta0, got eta_min={eta_min}, eta0={eta0}")
    return int(math.floor(math.log(eta_min / eta0) / math.log(gamma)))


@jax.tree_util.register_static
@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Optimization settings (static under jit).

    Attributes:
        batch_size: n_B, windows per mini-batch.
        eta0: initial learning rate.
        gamma: per-epoch decay factor of the learning rate.
        eta_min: final learning rate of the n_epoch rule.
        n_epochs: number of epochs; None applies :func:`n_epoch_rule`.
        epochs_per_call: epochs run inside one compiled call (between progress updates).
    """

    batch_size: int = 5
    eta0: float = 5e-4
    gamma: float = 0.9995
    eta_min: float = 5e-7
    n_epochs: int | None = None
    epochs_per_call: int = 10

    def __post_init__(self):
        if self.batch_size < 1:
            raise ConfigError(f"batch_size must be >= 1, got {self.batch_size}")
        if self.eta0 <= 0:
            raise ConfigError(f"eta0 must be > 0, got {self.eta0}")
        if self.n_epochs is not None and self.n_epochs < 1:
            raise ConfigError(f"n_epochs must be >= 1 or None (paper rule), got {self.n_epochs}")
        if self.epochs_per_call < 1:
            raise ConfigError(f"epochs_per_call must be >= 1, got {self.epochs_per_call}")
        if self.n_epochs is None:
            n_epoch_rule(self.eta0, self.gamma, self.eta_min)  # validates gamma, eta_min
        elif not 0.0 < self.gamma <= 1.0:
            raise ConfigError(f"decay rate gamma must be in (0, 1], got {self.gamma}")

    @property
    def resolved_epochs(self) -> int:
        """Epoch count actually run."""
        if self.n_epochs is not None:
            return int(self.n_epochs)
        return n_epoch_rule(self.eta0, self.gamma, self.eta_min)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclasses.dataclass(frozen=True)
class TrainResult:
    """Trained replicas and their loss history.

    Attributes:
        params: stacked, padded parameters (leading part axis), numpy arrays.
        arch: architecture (n_dof is the padded width).
        config: the training configuration.
        dof_counts: real dofs per part.
        mean, std: (n_parts, n_dof) normalization of each part.
        train_loss: (n_epochs, n_parts) mean training MSE of each epoch (normalized units).
        val_loss: (n_epochs, n_parts) validation MSE after each epoch.
        initial_val_loss: (n_parts,) validation MSE of the initial parameters.
        seconds_per_epoch: wall time per epoch, compilation excluded.
        compile_seconds: wall time spent compiling the epoch loop in this call (0 when
            an earlier call with the same settings compiled it).
        steps_per_epoch: gradient steps per epoch.
    """

    params: Params
    arch: LSTMArchitecture
    config: TrainConfig
    dof_counts: tuple[int, ...]
    mean: np.ndarray
    std: np.ndarray
    train_loss: np.ndarray
    val_loss: np.ndarray
    initial_val_loss: np.ndarray
    seconds_per_epoch: float
    compile_seconds: float
    steps_per_epoch: int

    @property
    def dof_mask(self) -> np.ndarray:
        return padding_mask(self.dof_counts, self.arch.n_dof)


# ----------------------------------------------------------------------------- params


def pad_params(params: Params, arch: LSTMArchitecture, n_dof: int) -> Params:
    """Zero-pad one replica's parameters from ``arch.n_dof`` to ``n_dof`` dofs.

    Pads the first encoder layer's input columns, the decoder's input columns (the dof
    block, before the q load-parameter columns) and the dense layer's output rows.
    """
    extra = n_dof - arch.n_dof
    if extra < 0:
        raise ConfigError(f"cannot pad {arch.n_dof} dofs down to {n_dof}")

    def pad_cols(w, start):
        return jnp.concatenate([w[:, :start], jnp.zeros((w.shape[0], extra), w.dtype), w[:, start:]], axis=1)

    encoder = [dict(layer) for layer in params["encoder"]]
    encoder[0] = {
        direction: {**cell, "w_d": pad_cols(cell["w_d"], arch.n_dof)} for direction, cell in encoder[0].items()
    }
    decoder = {**params["decoder"], "w_d": pad_cols(params["decoder"]["w_d"], arch.n_dof)}
    dense = {
        "w": jnp.pad(params["dense"]["w"], ((0, extra), (0, 0))),
        "b": jnp.pad(params["dense"]["b"], (0, extra)),
    }
    return {"encoder": encoder, "decoder": decoder, "dense": dense}


def unpad_params(params: Params, arch: LSTMArchitecture, n_dof: int) -> Params:
    """Inverse of :func:`pad_params`: keep the first ``n_dof`` dofs of a padded replica."""
    q = arch.n_cond_repeat

    def cut_cols(w):
        return jnp.concatenate([w[:, :n_dof], w[:, arch.n_dof:arch.n_dof + q]], axis=1)

    encoder = [dict(layer) for layer in params["encoder"]]
    encoder[0] = {d: {**cell, "w_d": cell["w_d"][:, :n_dof]} for d, cell in encoder[0].items()}
    decoder = {**params["decoder"], "w_d": cut_cols(params["decoder"]["w_d"])}
    dense = {"w": params["dense"]["w"][:n_dof], "b": params["dense"]["b"][:n_dof]}
    return {"encoder": encoder, "decoder": decoder, "dense": dense}


def stack_params(replicas: list[Params]) -> Params:
    """Stack equally shaped replicas on a new leading axis."""
    return jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *replicas)


def replica_params(stacked: Params, index: int) -> Params:
    """The ``index``-th replica of stacked parameters (still padded)."""
    return jax.tree_util.tree_map(lambda leaf: leaf[index], stacked)


def init_replicas(key: jax.Array, arch: LSTMArchitecture, dof_counts: tuple[int, ...]) -> Params:
    """Initial stacked parameters: replica r is ``init_params(fold_in(key, r))`` at its own
    dof count (so it equals a replica initialized alone), zero-padded to ``arch.n_dof``."""
    replicas = []
    for r, count in enumerate(dof_counts):
        own = dataclasses.replace(arch, n_dof=int(count))
        replicas.append(pad_params(init_params(jax.random.fold_in(key, r), own), own, arch.n_dof))
    return stack_params(replicas)


# ----------------------------------------------------------------------------- loss


def masked_mse(params, arch, x, y, cond, weight, dof_mask):
    """Weighted mean squared error over windows, steps and real dofs (one replica).

    Args:
        x: (B, n_p, n_dof) inputs; y: (B, n_f, n_dof) targets; cond: (B,) load parameters;
        weight: (B,) window weights (0 for the filler of a short last batch);
        dof_mask: (n_dof,) 1 on real dofs.
    """
    cond_arg = cond if arch.conditional else None
    in_axes = (None, None, 0, 0 if arch.conditional else None, None)
    pred = jax.vmap(forward, in_axes=in_axes)(params, arch, x, cond_arg, dof_mask)
    sq = jnp.square(pred - y) * dof_mask
    per_window = jnp.sum(sq, axis=(1, 2)) / (arch.n_future * jnp.sum(dof_mask))
    return jnp.sum(weight * per_window) / jnp.sum(weight)


def learning_rate_schedule(config: TrainConfig, steps_per_epoch: int) -> optax.Schedule:
    """Gradient step -> learning rate ``eta0 * gamma**floor(step / steps_per_epoch)``."""
    return optax.exponential_decay(
        init_value=config.eta0, transition_steps=steps_per_epoch, decay_rate=config.gamma, staircase=True
    )


def make_optimizer(config: TrainConfig, steps_per_epoch: int) -> optax.GradientTransformation:
    """Adam whose learning rate is eta0 gamma**epoch (decays once per epoch)."""
    return optax.adam(learning_rate_schedule(config, steps_per_epoch))


def _parts_mesh(n_parts: int, devices: int | None) -> Mesh | None:
    """Mesh over the part axis: as many local devices as divide ``n_parts`` evenly (None: one)."""
    available = len(jax.local_devices())
    n = available if devices is None else int(devices)
    if n < 1 or n > available:
        raise ConfigError(f"devices must be between 1 and the {available} local devices, got {devices}")
    while n_parts % n:
        n -= 1
    return None if n == 1 else Mesh(np.array(jax.local_devices()[:n]), ("parts",))


@functools.lru_cache(maxsize=16)
def _epoch_runner(arch: LSTMArchitecture, config: TrainConfig, n_train: int, mesh: Mesh | None):
    """Compiled function running a chunk of epochs for all replicas (split over ``mesh``)."""
    batch = config.batch_size
    steps = -(-n_train // batch)
    optimizer = make_optimizer(config, steps)
    fill = steps * batch - n_train

    def replica_epoch(params, opt_state, x, y, c, xv, yv, cv, mask, key):
        # A short last batch is filled with window 0 at weight 0 so every step has one shape.
        order = jnp.concatenate([jax.random.permutation(key, n_train), jnp.zeros(fill, jnp.int32)])
        weights = jnp.concatenate([jnp.ones(n_train, jnp.float32), jnp.zeros(fill, jnp.float32)])

        def step(carry, batch_ids):
            params, opt_state = carry
            ids, w = batch_ids
            loss, grads = jax.value_and_grad(masked_mse)(params, arch, x[ids], y[ids], c[ids], w, mask)
            updates, opt_state = optimizer.update(grads, opt_state, params)
            return (optax.apply_updates(params, updates), opt_state), loss * jnp.sum(w)

        (params, opt_state), losses = jax.lax.scan(
            step, (params, opt_state), (order.reshape(steps, batch), weights.reshape(steps, batch))
        )
        val = masked_mse(params, arch, xv, yv, cv, jnp.ones(xv.shape[0], jnp.float32), mask)
        return params, opt_state, jnp.sum(losses) / n_train, val

    all_replicas = jax.vmap(replica_epoch, in_axes=(0,) * 9 + (None,))
    if mesh is not None:
        # Replicas are independent: each device trains its block of parts, no communication.
        all_replicas = jax.shard_map(all_replicas, mesh=mesh, in_specs=(P("parts"),) * 9 + (P(),),
                                     out_specs=P("parts"))

    def run_chunk(params, opt_state, data, shuffle_key, epochs):
        def body(carry, epoch):
            params, opt_state = carry
            params, opt_state, train, val = all_replicas(
                params, opt_state, *data, jax.random.fold_in(shuffle_key, epoch)
            )
            return (params, opt_state), (train, val)

        (params, opt_state), (train, val) = jax.lax.scan(body, (params, opt_state), epochs)
        return params, opt_state, train, val

    val_loss = jax.jit(jax.vmap(
        lambda p, xv, yv, cv, m: masked_mse(p, arch, xv, yv, cv, jnp.ones(xv.shape[0], jnp.float32), m)
    ))
    return optimizer, steps, jax.jit(run_chunk), val_loss, {}


def train_replicas(
    data: ReplicaData,
    arch: LSTMArchitecture,
    config: TrainConfig,
    key: jax.Array,
    init: Params | None = None,
    progress: bool = True,
    description: str = "training",
    devices: int | None = None,
) -> TrainResult:
    """Train one replica per part, all together.

    Args:
        data: stacked, padded windows (:func:`jaxsync.surrogate.data.stack_replicas`).
        arch: architecture; ``arch.n_dof`` must equal ``data.n_dof_max``.
        config: optimization settings.
        key: PRNG key (initialization and shuffling).
        init: optional initial stacked parameters (default :func:`init_replicas`).
        progress: show a tqdm bar with the epoch and the largest train/val loss over parts.
        description: label of the progress bar.
        devices: local devices to spread the parts over (default: as many as divide the
            number of parts); 1 keeps everything on one device.  The result does not
            depend on it beyond float32 round-off.

    Returns:
        A :class:`TrainResult`.
    """
    if arch.n_dof != data.n_dof_max:
        raise ConfigError(f"architecture has n_dof={arch.n_dof} but the data are padded to {data.n_dof_max}")
    if data.x_train.shape[2] != arch.n_past or data.y_train.shape[2] != arch.n_future:
        raise ConfigError(
            f"windows are {data.x_train.shape[2]} -> {data.y_train.shape[2]} snapshots but the architecture "
            f"expects n_past={arch.n_past}, n_future={arch.n_future}"
        )
    init_key, shuffle_key = jax.random.split(key)
    dtype = jnp.dtype(arch.dtype)
    if init is None:
        params = init_replicas(init_key, arch, data.dof_counts)
    else:
        params = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), init)
        expected = jax.eval_shape(lambda k: init_replicas(k, arch, data.dof_counts), init_key)
        if jax.tree_util.tree_structure(params) != jax.tree_util.tree_structure(expected) or any(
            a.shape != b.shape for a, b in zip(jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(expected))
        ):
            raise ConfigError(
                "init parameters do not match the architecture and part count; build them with init_replicas"
            )
    n_train = data.x_train.shape[1]
    mesh = _parts_mesh(data.n_parts, devices)
    optimizer, steps, run_chunk, val_loss_fn, executables = _epoch_runner(arch, config, n_train, mesh)
    opt_state = jax.vmap(optimizer.init)(params)
    arrays = tuple(jnp.asarray(a, dtype) for a in (
        data.x_train, data.y_train, data.cond_train, data.x_val, data.y_val, data.cond_val, data.dof_mask
    ))
    if mesh is not None:
        params, opt_state, arrays = jax.device_put((params, opt_state, arrays), NamedSharding(mesh, P("parts")))
    initial_val = np.asarray(val_loss_fn(params, *arrays[3:7]))

    def executable(chunk):
        # Compiled ahead of time (and kept with the cached runner) so that compilation is
        # timed apart from training; one executable per chunk length and data shape.
        signature = (chunk,) + tuple(a.shape for a in arrays)
        if signature not in executables:
            epochs = jax.ShapeDtypeStruct((chunk,), jnp.int32)
            executables[signature] = run_chunk.lower(params, opt_state, arrays, shuffle_key, epochs).compile()
        return executables[signature]

    n_epochs = config.resolved_epochs
    train_hist, val_hist = [], []
    train_seconds, compile_seconds = 0.0, 0.0
    with tqdm(total=n_epochs, desc=description, disable=not progress, unit="epoch") as bar:
        done = 0
        while done < n_epochs:
            chunk = min(config.epochs_per_call, n_epochs - done)
            start = time.perf_counter()
            run = executable(chunk)
            compiled = time.perf_counter()
            params, opt_state, train, val = run(
                params, opt_state, arrays, shuffle_key, jnp.arange(done, done + chunk, dtype=jnp.int32)
            )
            train, val = np.asarray(train), np.asarray(val)  # waits for the chunk
            compile_seconds += compiled - start
            train_seconds += time.perf_counter() - compiled
            if not np.all(np.isfinite(train)):
                raise ConfigError(
                    f"training diverged (non-finite loss) by epoch {done + chunk}; lower eta0 (now {config.eta0})"
                )
            train_hist.append(train)
            val_hist.append(val)
            done += chunk
            bar.update(chunk)
            bar.set_postfix(train=f"{train[-1].max():.3e}", val=f"{val[-1].max():.3e}")

    return TrainResult(
        params=jax.tree_util.tree_map(np.asarray, params),
        arch=arch,
        config=config,
        dof_counts=tuple(data.dof_counts),
        mean=np.asarray(data.mean),
        std=np.asarray(data.std),
        train_loss=np.concatenate(train_hist),
        val_loss=np.concatenate(val_hist),
        initial_val_loss=initial_val,
        seconds_per_epoch=train_seconds / n_epochs,
        compile_seconds=compile_seconds,
        steps_per_epoch=int(steps),
    )
