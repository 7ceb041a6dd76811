"""Training of one LSTM replica per part, all parts in one compiled program.

Optimizer: optax Adam with a learning rate that decays once per epoch,
``eta(epoch) = eta0 * gamma**epoch`` (``optax.exponential_decay`` with staircase steps of
one epoch).  Mini-batches are reshuffled every epoch.

Defaults (:class:`TrainConfig`, the same as ``jaxsync train``'s): n_B = 5, eta0 = 2e-3,
gamma = 0.995, 300 epochs, early stopping after 100 epochs without a better validation
loss.  These fit a laptop (the coarse cantilever trains in about a minute and reaches
about 2 % error online).  The paper's schedule (n_B = 5, eta0 = 5e-4, gamma = 0.9995 run
for ``n_epoch = floor(log_gamma(eta_min / eta0))`` = 13 812 epochs, about 40 minutes) is
``TrainConfig(eta0=5e-4, gamma=0.9995, eta_min=5e-7, n_epochs=None)``
(``jaxsync train --epochs paper --eta0 5e-4 --gamma 0.9995``).

Best parameters and early stopping: after every epoch each replica's validation loss is
compared with its best so far; the returned parameters of a replica are those of its
epoch with the lowest validation loss.  With ``patience`` set, training stops once no
replica has improved for ``patience`` epochs (checked after every epoch inside the
compiled loop, so the stop epoch does not depend on ``epochs_per_call``).

Resumable training: with ``checkpoint=path``, :func:`train_replicas` writes its whole
state (parameters, Adam state, best parameters, loss history) atomically every
``checkpoint_every`` epochs and at the end; called again with the same data, settings and
key it continues from that state and ends with the same parameters as an uninterrupted
run (the compiled chunks end at the same epochs).  A state written with other data or
settings is refused with :class:`~jaxsync.errors.CheckpointError`.

Replicas: parts have different shared-dof counts, so inputs, outputs and parameters are
zero-padded to the largest count and a dof mask (1 real, 0 padding) is applied to the
decoder's output and to the loss.  Padded inputs are zero, padded outputs are forced to
zero, so the parameters that touch padding get exactly zero gradients and Adam leaves
them at their (zero) initial value: each replica trains as it would alone (equal up to
float32 round-off, since XLA may order the sums of batched products differently).  The
per-epoch function is ``jax.vmap``-ed over the part axis (and, with several local devices,
``jax.shard_map``-ed so each device trains its own parts), and ``epochs_per_call`` epochs
run in one ``jax.lax.scan`` inside ``jax.jit``; Python only updates the progress bar and
writes checkpoints.

Reproducibility: the PRNG key is split into an initialization key (replica ``r`` uses
``fold_in(init_key, r)``) and a shuffling key (epoch ``e`` uses ``fold_in(shuffle_key, e)``,
shared by all replicas since their windows are aligned in time).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P
from tqdm.auto import tqdm

from jaxsync.errors import CheckpointError, ConfigError
from jaxsync.trajectory import array_checksum
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

    The defaults are the laptop schedule that ``jaxsync train`` and ``jaxsync demo`` use;
    the paper's is ``TrainConfig(eta0=5e-4, gamma=0.9995, eta_min=5e-7, n_epochs=None)``.

    Attributes:
        batch_size: n_B, windows per mini-batch.
        eta0: initial learning rate.
        gamma: per-epoch decay factor of the learning rate.
        eta_min: final learning rate of the paper's epoch rule (used when n_epochs is None).
        n_epochs: largest number of epochs; None applies the paper's
            :func:`n_epoch_rule` floor(log_gamma(eta_min / eta0)).
        epochs_per_call: epochs run inside one compiled call (between progress updates).
        patience: stop when no replica's validation loss has improved for this many
            epochs; None never stops early.  The best parameters are returned either way.
    """

    batch_size: int = 5
    eta0: float = 2e-3
    gamma: float = 0.995
    eta_min: float = 5e-7
    n_epochs: int | None = 300
    epochs_per_call: int = 10
    patience: int | None = 100

    def __post_init__(self):
        if self.batch_size < 1:
            raise ConfigError(f"batch_size must be >= 1, got {self.batch_size}")
        if self.eta0 <= 0:
            raise ConfigError(f"eta0 must be > 0, got {self.eta0}")
        if self.n_epochs is not None and self.n_epochs < 1:
            raise ConfigError(f"n_epochs must be >= 1 or None (paper rule), got {self.n_epochs}")
        if self.epochs_per_call < 1:
            raise ConfigError(f"epochs_per_call must be >= 1, got {self.epochs_per_call}")
        if self.patience is not None and (isinstance(self.patience, bool) or self.patience < 1):
            raise ConfigError(f"patience must be >= 1 epoch or None (no early stopping), got {self.patience}")
        if self.n_epochs is None:
            n_epoch_rule(self.eta0, self.gamma, self.eta_min)  # validates gamma, eta_min
        elif not 0.0 < self.gamma <= 1.0:
            raise ConfigError(f"decay rate gamma must be in (0, 1], got {self.gamma}")

    @property
    def resolved_epochs(self) -> int:
        """Largest epoch count (early stopping may end sooner)."""
        if self.n_epochs is not None:
            return int(self.n_epochs)
        return n_epoch_rule(self.eta0, self.gamma, self.eta_min)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclasses.dataclass(frozen=True)
class TrainResult:
    """Trained replicas and their loss history.

    Attributes:
        params: stacked, padded parameters (leading part axis), numpy arrays: each
            replica's parameters of its best epoch (lowest validation loss).
        arch: architecture (n_dof is the padded width).
        config: the training configuration.
        dof_counts: real dofs per part.
        mean, std: (n_parts, n_dof) normalization of each part.
        train_loss: (n_epochs_run, n_parts) mean training MSE of each epoch (normalized units).
        val_loss: (n_epochs_run, n_parts) validation MSE after each epoch.
        initial_val_loss: (n_parts,) validation MSE of the initial parameters.
        seconds_per_epoch: wall time per epoch, compilation excluded (over every session
            of a resumed run).
        compile_seconds: wall time spent compiling the epoch loop in this call (0 when
            an earlier call with the same settings compiled it).
        steps_per_epoch: gradient steps per epoch.
        best_epoch: (n_parts,) epoch (1-based) whose parameters each replica returns.
        stopped_epoch: epochs run when early stopping ended the training, None when it
            ran all ``config.resolved_epochs``.
        resumed_from: epochs restored from a training checkpoint (0: a fresh start).
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
    best_epoch: np.ndarray | None = None
    stopped_epoch: int | None = None
    resumed_from: int = 0

    @property
    def dof_mask(self) -> np.ndarray:
        return padding_mask(self.dof_counts, self.arch.n_dof)

    @property
    def n_epochs_run(self) -> int:
        return int(self.train_loss.shape[0])

    @property
    def best_val_loss(self) -> np.ndarray:
        """(n_parts,) validation MSE of the returned parameters."""
        if self.best_epoch is None:
            return self.val_loss[-1]
        return self.val_loss[np.asarray(self.best_epoch) - 1, np.arange(self.val_loss.shape[1])]


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


def _runner_config(config: TrainConfig) -> TrainConfig:
    """The part of ``config`` the compiled program depends on (the cache key of the runner)."""
    return TrainConfig(batch_size=config.batch_size, eta0=config.eta0, gamma=config.gamma,
                       n_epochs=1, patience=None)


@functools.lru_cache(maxsize=16)
def _epoch_runner(arch: LSTMArchitecture, config: TrainConfig, n_train: int, mesh: Mesh | None):
    """Compiled function running a chunk of epochs for all replicas (split over ``mesh``).

    The chunk carries ``(params, opt_state, best_params, best_val, best_epoch)``; an epoch
    whose index ``e`` (epochs done before it) has ``e - best_epoch >= patience`` for every
    replica is skipped (early stop, ``patience > 0``) and reported as not run.
    """
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

    def run_chunk(state, data, shuffle_key, epochs, patience):
        def run_epoch(carry, epoch):
            params, opt_state, best_params, best_val, best_epoch = carry
            params, opt_state, train, val = all_replicas(
                params, opt_state, *data, jax.random.fold_in(shuffle_key, epoch)
            )
            better = val < best_val

            def keep(new, old):
                return jnp.where(better.reshape(better.shape + (1,) * (new.ndim - 1)), new, old)

            best_params = jax.tree_util.tree_map(keep, params, best_params)
            best_val = jnp.where(better, val, best_val)
            best_epoch = jnp.where(better, epoch + 1, best_epoch)
            return (params, opt_state, best_params, best_val, best_epoch), (train, val, jnp.bool_(True))

        def skip_epoch(carry, epoch):
            nan = jnp.full_like(carry[3], jnp.nan)
            return carry, (nan, nan, jnp.bool_(False))

        def body(carry, epoch):
            stop = (patience > 0) & jnp.all(epoch - carry[4] >= patience)
            return jax.lax.cond(stop, skip_epoch, run_epoch, carry, epoch)

        state, (train, val, ran) = jax.lax.scan(body, state, epochs)
        return state, train, val, ran

    val_loss = jax.jit(jax.vmap(
        lambda p, xv, yv, cv, m: masked_mse(p, arch, xv, yv, cv, jnp.ones(xv.shape[0], jnp.float32), m)
    ))
    return optimizer, steps, jax.jit(run_chunk), val_loss, {}


# ----------------------------------------------------------------------------- training state

_STATE_KIND = "jaxsync-training-state"
_STATE_VERSION = 1


def _digest(arrays) -> str:
    """sha256 over a sequence of arrays (dtype, shape and bytes of each)."""
    return array_checksum({f"{i:04d}": np.asarray(a) for i, a in enumerate(arrays)}, {})


def training_fingerprint(data: ReplicaData, arch: LSTMArchitecture, config: TrainConfig, key: jax.Array,
                         init: Params | None = None, checkpoint_every: int | None = None) -> dict[str, Any]:
    """Everything that determines a training run, as a JSON-serializable dict.

    A training checkpoint is resumed only by a run with the same fingerprint: same
    windows and normalization (hashed), architecture, configuration, key, initial
    parameters and checkpoint interval (which sets where the compiled chunks end).
    """
    return {
        "data_sha256": _digest([data.x_train, data.y_train, data.cond_train, data.x_val, data.y_val,
                                data.cond_val, data.dof_mask, data.mean, data.std]),
        "architecture": arch.to_dict(),
        "config": config.to_dict(),
        "key": np.asarray(jax.random.key_data(key)).ravel().tolist(),
        "init_sha256": None if init is None else _digest(jax.tree_util.tree_leaves(init)),
        "checkpoint_every": checkpoint_every,
    }


def _fingerprint_differences(stored: dict, current: dict) -> list[str]:
    out = []
    for name in sorted(set(stored) | set(current)):
        a, b = stored.get(name), current.get(name)
        if a == b:
            continue
        if isinstance(a, dict) and isinstance(b, dict):
            out += [f"{name}.{k}: {a.get(k)!r} there, {b.get(k)!r} here"
                    for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]
        elif name.endswith("sha256"):
            out.append(f"{name[:-len('_sha256')]} differ")
        else:
            out.append(f"{name}: {a!r} there, {b!r} here")
    return out


def _state_checksum(arrays: dict[str, np.ndarray], attrs: dict[str, Any]) -> str:
    return array_checksum(arrays, attrs)


def _save_training_state(path, fingerprint: dict, state, history: dict[str, np.ndarray],
                         info: dict[str, Any]) -> None:
    """Write the training state atomically (HDF5): the chunk carry as flat leaves, the
    loss history and the bookkeeping in ``info`` (epochs done, stopped, timings)."""
    from jaxsync.trajectory import atomic_h5

    arrays = {f"state/{i:04d}": np.asarray(leaf) for i, leaf in enumerate(jax.tree_util.tree_leaves(state))}
    arrays.update({f"history/{k}": np.asarray(v) for k, v in history.items()})
    attrs = {"kind": _STATE_KIND, "version": _STATE_VERSION, "fingerprint": json.dumps(fingerprint, sort_keys=True),
             "info": json.dumps(info, sort_keys=True)}
    with atomic_h5(path) as f:
        for name, value in attrs.items():
            f.attrs[name] = value
        f.attrs["checksum"] = _state_checksum(arrays, attrs)
        for name, array in arrays.items():
            f[name] = array


def _load_training_state(path, fingerprint: dict, template):
    """Read a state written by :func:`_save_training_state` for a run with ``fingerprint``;
    ``template`` is the chunk carry of this run (tree structure, shapes and dtypes)."""
    import h5py

    fix = "delete it to start over, or write to another output folder"
    try:
        with h5py.File(path, "r") as f:
            attrs = {k: (v.item() if hasattr(v, "item") else v) for k, v in f.attrs.items() if k != "checksum"}
            attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in attrs.items()}
            stored_sum = f.attrs.get("checksum")
            arrays = {}
            f.visititems(lambda name, obj: arrays.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    except Exception as exc:
        raise CheckpointError(f"cannot read training checkpoint {path} ({exc}); {fix}") from exc
    if attrs.get("kind") != _STATE_KIND:
        raise CheckpointError(f"{path} is not a jaxsync training checkpoint; {fix}")
    if int(attrs.get("version", -1)) != _STATE_VERSION:
        raise CheckpointError(f"training checkpoint {path} has version {attrs.get('version')}, this jaxsync "
                              f"reads {_STATE_VERSION}; {fix}")
    if stored_sum is None or str(stored_sum.decode() if isinstance(stored_sum, bytes) else stored_sum) != \
            _state_checksum(arrays, attrs):
        raise CheckpointError(f"training checkpoint {path} fails its checksum (damaged or altered); {fix}")
    stored = json.loads(attrs["fingerprint"])
    if stored != fingerprint:
        diffs = "; ".join(_fingerprint_differences(stored, fingerprint))
        raise CheckpointError(
            f"training checkpoint {path} was written by a run with other data or settings ({diffs}); "
            f"rerun with the same arguments to resume, or {fix}"
        )
    leaves, treedef = jax.tree_util.tree_flatten(template)
    loaded = [arrays.get(f"state/{i:04d}") for i in range(len(leaves))]
    for i, (a, b) in enumerate(zip(loaded, leaves)):
        if a is None or a.shape != b.shape or a.dtype != b.dtype:
            raise CheckpointError(f"training checkpoint {path}: state array {i} does not fit this run; {fix}")
    history = {k[len("history/"):]: v for k, v in arrays.items() if k.startswith("history/")}
    return jax.tree_util.tree_unflatten(treedef, loaded), history, json.loads(attrs["info"])


# ----------------------------------------------------------------------------- training


def train_replicas(
    data: ReplicaData,
    arch: LSTMArchitecture,
    config: TrainConfig,
    key: jax.Array,
    init: Params | None = None,
    progress: bool = True,
    description: str = "training",
    devices: int | None = None,
    checkpoint: str | os.PathLike | None = None,
    checkpoint_every: int | None = 50,
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
        checkpoint: HDF5 path of a resumable training state (None: none).  If the file
            exists it must come from a run with the same data, architecture, config, key,
            init and ``checkpoint_every`` (else :class:`CheckpointError`), and training
            continues from it.  It is rewritten atomically every ``checkpoint_every``
            epochs and at the end; delete it once the results are saved.
        checkpoint_every: epochs between training checkpoints (None or 0: only at the
            end).  Compiled chunks also end at its multiples, so a multiple of
            ``config.epochs_per_call`` avoids compiling a second chunk length.

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
    if checkpoint_every is not None and (isinstance(checkpoint_every, bool) or checkpoint_every < 0):
        raise ConfigError(f"checkpoint_every must be >= 0 epochs (0 or None: only at the end), got {checkpoint_every}")
    every = int(checkpoint_every or 0)
    fingerprint = training_fingerprint(data, arch, config, key, init, every) if checkpoint is not None else None
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
    optimizer, steps, run_chunk, val_loss_fn, executables = _epoch_runner(
        arch, _runner_config(config), n_train, mesh)
    opt_state = jax.vmap(optimizer.init)(params)
    state = (params, opt_state, params, jnp.full(data.n_parts, jnp.inf, dtype),
             jnp.zeros(data.n_parts, jnp.int32))
    arrays = tuple(jnp.asarray(a, dtype) for a in (
        data.x_train, data.y_train, data.cond_train, data.x_val, data.y_val, data.cond_val, data.dof_mask
    ))

    n_epochs = config.resolved_epochs
    train_hist = np.zeros((0, data.n_parts), dtype)
    val_hist = np.zeros((0, data.n_parts), dtype)
    initial_val = None
    info = {"epochs_done": 0, "stopped": False, "train_seconds": 0.0, "epochs_timed": 0}
    if checkpoint is not None and os.path.exists(checkpoint):
        state, history, info = _load_training_state(checkpoint, fingerprint, jax.tree_util.tree_map(np.asarray, state))
        train_hist, val_hist, initial_val = history["train_loss"], history["val_loss"], history["initial_val_loss"]
        if train_hist.shape != (info["epochs_done"], data.n_parts):
            raise CheckpointError(f"training checkpoint {checkpoint} holds an inconsistent loss history; "
                                  "delete it to start over")
    resumed_from = int(info["epochs_done"])
    if mesh is not None:
        state, arrays = jax.device_put((state, arrays), NamedSharding(mesh, P("parts")))
    else:
        state = jax.tree_util.tree_map(jnp.asarray, state)
    if initial_val is None:
        initial_val = np.asarray(val_loss_fn(state[0], *arrays[3:7]))
    patience = jnp.int32(config.patience or 0)

    def executable(chunk):
        # Compiled ahead of time (and kept with the cached runner) so that compilation is
        # timed apart from training; one executable per chunk length and data shape.
        signature = (chunk,) + tuple(a.shape for a in arrays)
        if signature not in executables:
            epochs = jax.ShapeDtypeStruct((chunk,), jnp.int32)
            executables[signature] = run_chunk.lower(state, arrays, shuffle_key, epochs, patience).compile()
        return executables[signature]

    def save():
        _save_training_state(checkpoint, fingerprint, jax.tree_util.tree_map(np.asarray, state),
                             {"train_loss": train_hist, "val_loss": val_hist, "initial_val_loss": initial_val},
                             info)

    def next_boundary(done, step):
        return (done // step + 1) * step

    compile_seconds = 0.0
    done = int(info["epochs_done"])
    with tqdm(total=n_epochs, initial=done, desc=description, disable=not progress, unit="epoch") as bar:
        while done < n_epochs and not info["stopped"]:
            # Chunks end at multiples of epochs_per_call and checkpoint_every: fixed epochs,
            # so a resumed run compiles and runs the same chunks as an uninterrupted one.
            end = min(next_boundary(done, config.epochs_per_call), n_epochs)
            if every:
                end = min(end, next_boundary(done, every))
            chunk = end - done
            start = time.perf_counter()
            run = executable(chunk)
            compiled = time.perf_counter()
            state, train, val, ran = run(state, arrays, shuffle_key, jnp.arange(done, end, dtype=jnp.int32), patience)
            train, val, ran = np.asarray(train), np.asarray(val), np.asarray(ran)  # waits for the chunk
            compile_seconds += compiled - start
            n_ran = int(ran.sum())
            info["train_seconds"] += time.perf_counter() - compiled
            info["epochs_timed"] += n_ran
            if not np.all(np.isfinite(train[:n_ran])):
                raise ConfigError(
                    f"training diverged (non-finite loss) by epoch {done + chunk}; lower eta0 (now {config.eta0})"
                )
            train_hist = np.concatenate([train_hist, train[:n_ran]])
            val_hist = np.concatenate([val_hist, val[:n_ran]])
            done += n_ran
            info["epochs_done"] = done
            info["stopped"] = n_ran < chunk
            bar.update(n_ran)
            if n_ran:
                bar.set_postfix(train=f"{train[n_ran - 1].max():.3e}", val=f"{val[n_ran - 1].max():.3e}")
            if checkpoint is not None and (info["stopped"] or done == n_epochs or (every and done % every == 0)):
                save()

    best_epoch = np.asarray(state[4])
    return TrainResult(
        params=jax.tree_util.tree_map(np.asarray, state[2]),
        arch=arch,
        config=config,
        dof_counts=tuple(data.dof_counts),
        mean=np.asarray(data.mean),
        std=np.asarray(data.std),
        train_loss=train_hist,
        val_loss=val_hist,
        initial_val_loss=np.asarray(initial_val),
        seconds_per_epoch=info["train_seconds"] / max(info["epochs_timed"], 1),
        compile_seconds=compile_seconds,
        steps_per_epoch=int(steps),
        best_epoch=best_epoch,
        stopped_epoch=done if info["stopped"] else None,
        resumed_from=resumed_from,
    )
