"""Training of one replica per part by gradient, all parts in one compiled program: the
fit of every :class:`~jaxsync.surrogate.models.GradientFitted` model (the LSTM, or a
user's), which minimises the model's own ``loss`` (default: the masked MSE of its
``forward``, :func:`masked_mse`).

Optimizer: optax Adam with a learning rate that decays once per epoch,
``eta(epoch) = eta0 * gamma**epoch`` (``optax.exponential_decay`` with staircase steps of
one epoch).  Mini-batches are reshuffled every epoch.

Defaults (:class:`TrainConfig`, the same as ``jaxsync train``'s): n_B = 10, eta0 = 2e-3,
gamma = 0.995, 800 epochs, early stopping after 200 epochs without a better validation
loss (n_B and the epochs of the paper's published code).  These fit a laptop (the coarse
cantilever trains in 2-4 minutes on 2 cores and stays within 2 % of the free end's
amplitude on its fixed-load cases: ``benchmarks/paper_experiments.py``; the 300 epochs
of n_B = 5 of earlier versions reached 4 % on the skewed load).  The paper's schedule
(n_B = 5, eta0 = 5e-4, gamma = 0.9995 run for ``n_epoch = floor(log_gamma(eta_min /
eta0))`` = 13 812 epochs, about 40 minutes) is ``TrainConfig(batch_size=5, eta0=5e-4,
gamma=0.9995, eta_min=5e-7, n_epochs=None)`` (``jaxsync train --epochs paper
--batch-size 5 --eta0 5e-4 --gamma 0.9995``).

Best parameters and early stopping: after every epoch each replica's validation loss is
compared with its best so far; the returned parameters of a replica are those of its
epoch with the lowest validation loss.  With ``patience`` set, training stops once no
replica has improved for ``patience`` epochs (checked after every epoch inside the
compiled loop, so the stop epoch does not depend on ``epochs_per_call``).

Resumable training: with ``state=TrainingState(folder, every)``, :func:`train_replicas`
writes its state (:mod:`jaxsync.surrogate.training`) into ``folder`` every ``every``
epochs and at the end; called again with the same data, settings and key it continues
from it and ends with the same parameters as an uninterrupted run (the compiled chunks
end at the same epochs).

Replicas: parts have different shared-dof counts, so inputs, outputs and parameters are
zero-padded to the largest count and a dof mask (1 real, 0 padding) is applied to the
decoder's output and to the loss.  Padded inputs are zero, padded outputs are forced to
zero, so the parameters that touch padding get exactly zero gradients and Adam leaves
them at their (zero) initial value: each replica trains as it would alone (equal up to
float32 round-off, since XLA may order the sums of batched products differently).  The
per-epoch function of one replica becomes a program over all parts through
:func:`jaxsync.parallel.spmd_program` (vmapped over the parts of a device, each
device training its own block of parts, no communication), and ``epochs_per_call``
epochs run in one ``jax.lax.scan`` inside ``jax.jit``; Python only updates the progress
bar, writes the training state and calls the optional ``callback``.  Padding and
stacking replicas: :mod:`jaxsync.surrogate.models`.

Reproducibility: the PRNG key is split into an initialization key (replica ``r`` uses
``fold_in(init_key, r)``) and a shuffling key (epoch ``e`` uses ``fold_in(shuffle_key, e)``,
shared by all replicas since their windows are aligned in time).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import time
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding
from tqdm.auto import tqdm

from jaxsync.errors import CheckpointError, ConfigError
from jaxsync.parallel._spmd import AXIS, part_spec, spmd_program
from jaxsync.surrogate.models._replicas import Params, init_replicas
from jaxsync.surrogate.training._data import ReplicaData, padding_mask
from jaxsync.surrogate.training._loss import masked_mse
from jaxsync.surrogate.training._training_state import (
    TrainingState,
    load_training_state,
    save_training_state,
    training_fingerprint,
)

__all__ = ["n_epoch_rule", "TrainConfig", "TrainResult", "TrainProgress", "masked_mse",
           "learning_rate_schedule", "make_optimizer", "train_replicas"]


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
    the paper's is ``TrainConfig(batch_size=5, eta0=5e-4, gamma=0.9995, eta_min=5e-7, n_epochs=None)``.
    It is the ``optimizer`` of :func:`jaxsync.surrogate.train_surrogates` and
    :func:`jaxsync.surrogate.grid_search`.

    Attributes:
        batch_size: n_B, windows per mini-batch.
        eta0: initial learning rate.
        gamma: per-epoch decay factor of the learning rate.
        eta_min: final learning rate of the paper's epoch rule (used when n_epochs is None).
        n_epochs: largest number of epochs; None applies the paper's
            :func:`n_epoch_rule` floor(log_gamma(eta_min / eta0)).
        epochs_per_call: epochs run inside one compiled call (between progress updates);
            one program of this many epochs is compiled per data shape, and runs the
            shorter chunks too (the last one, those that end at a training state's save).
        patience: stop when no replica's validation loss has improved for this many
            epochs; None never stops early.  The best parameters are returned either way.
        n_candidates: networks :func:`jaxsync.surrogate.train_surrogates` trains per part
            from different initial weights (all in one compiled program, on the same
            windows); each part keeps the one of lowest validation loss.  Default 2:
            training an LSTM lands in basins of different quality (on the demo's
            cantilever one seed's pair reached a 5x higher validation loss and a 4.5 %
            free-end error where another's reached 1.3 %), and choosing between two costs
            less than twice the time, since the per-part work is small.
            :func:`train_replicas` trains the replicas it is given and does not read it.
    """

    batch_size: int = 10
    eta0: float = 2e-3
    gamma: float = 0.995
    eta_min: float = 5e-7
    n_epochs: int | None = 800
    epochs_per_call: int = 10
    patience: int | None = 200
    n_candidates: int = 2

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
        if (isinstance(self.n_candidates, bool) or not isinstance(self.n_candidates, (int, np.integer))
                or self.n_candidates < 1):
            raise ConfigError(f"n_candidates must be an integer >= 1 (networks trained per part), "
                              f"got {self.n_candidates!r}")
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

    The least-squares fit of the linear surrogate
    (:func:`jaxsync.surrogate.models.fit_linear`) returns one too: ``arch`` a
    :class:`~jaxsync.surrogate.models.LinearArchitecture`, ``config`` a
    :class:`~jaxsync.surrogate.models.LinearFitConfig`, one row of losses (the solve),
    ``seconds_per_epoch`` the solve's wall time and ``steps_per_epoch`` 0.

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
        resumed_from: epochs restored from a training state (0: a fresh start).
        signal_scale: (n_parts, n_load) scale of the load signals (load input), or None.
        load_inputs: (n_load,) :class:`~jaxsync.fem.LoadInput` descriptions
            of the load signals (empty without load input).
    """

    params: Params
    arch: Any  # LSTMArchitecture, or LinearArchitecture (jaxsync.surrogate.models)
    config: Any  # TrainConfig, or LinearFitConfig
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
    signal_scale: np.ndarray | None = None
    load_inputs: tuple = ()

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


# ----------------------------------------------------------------------------- loss


def learning_rate_schedule(config: TrainConfig, steps_per_epoch: int) -> optax.Schedule:
    """Gradient step -> learning rate ``eta0 * gamma**floor(step / steps_per_epoch)``."""
    return optax.exponential_decay(
        init_value=config.eta0, transition_steps=steps_per_epoch, decay_rate=config.gamma, staircase=True
    )


def make_optimizer(config: TrainConfig, steps_per_epoch: int) -> optax.GradientTransformation:
    """Adam whose learning rate is eta0 gamma**epoch (decays once per epoch)."""
    return optax.adam(learning_rate_schedule(config, steps_per_epoch))


def _parts_mesh(n_parts: int, devices: int | None) -> Mesh:
    """Device mesh over the part axis: as many local devices as divide ``n_parts`` evenly."""
    available = len(jax.local_devices())
    n = available if devices is None else int(devices)
    if n < 1 or n > available:
        raise ConfigError(f"devices must be between 1 and the {available} local devices, got {devices}")
    while n_parts % n:
        n -= 1
    return Mesh(np.array(jax.local_devices()[:n]), (AXIS,))


def _runner_config(config: TrainConfig) -> TrainConfig:
    """The part of ``config`` the compiled program depends on (the cache key of the runner)."""
    return TrainConfig(batch_size=config.batch_size, eta0=config.eta0, gamma=config.gamma,
                       n_epochs=1, patience=None)


@functools.lru_cache(maxsize=16)
def _epoch_runner(arch, config: TrainConfig, n_train: int, mesh: Mesh):
    """Compiled function running a chunk of epochs for all replicas (split over ``mesh``).

    The chunk carries ``(params, opt_state, best_params, best_val, best_epoch)``; an epoch
    whose index ``e`` (epochs done before it) is at or past the chunk's ``end``, or has
    ``e - best_epoch >= patience`` for every replica (early stop, ``patience > 0``), is
    skipped and reported as not run.
    """
    batch = config.batch_size
    steps = -(-n_train // batch)
    optimizer = make_optimizer(config, steps)
    fill = steps * batch - n_train

    def replica_epoch(params, opt_state, x, y, load, x_val, y_val, load_val, mask, u, u_val, key):
        # A short last batch is filled with window 0 at weight 0 so every step has one shape.
        order = jax.random.permutation(key, n_train)
        order = jnp.concatenate([order, jnp.zeros(fill, order.dtype)])
        weights = jnp.concatenate([jnp.ones(n_train, x.dtype), jnp.zeros(fill, x.dtype)])

        def step(carry, batch_ids):
            params, opt_state = carry
            ids, w = batch_ids
            loss, grads = jax.value_and_grad(arch.loss)(params, x[ids], y[ids], load[ids], w, mask, u[ids])
            # optax mixes Python floats with int32 step counts (Adam's bias correction, the
            # decay schedule): standard dtype promotion, whatever the caller's setting
            with jax.numpy_dtype_promotion("standard"):
                updates, opt_state = optimizer.update(grads, opt_state, params)
                params = optax.apply_updates(params, updates)
            return (params, opt_state), loss * jnp.sum(w)

        (params, opt_state), losses = jax.lax.scan(
            step, (params, opt_state), (order.reshape(steps, batch), weights.reshape(steps, batch))
        )
        val = arch.loss(params, x_val, y_val, load_val, jnp.ones(x_val.shape[0], x_val.dtype), mask, u_val)
        return params, opt_state, jnp.sum(losses) / n_train, val

    # Replicas are independent: each device trains its block of parts, no communication;
    # the shuffling key (argument 11) is the same for all parts.
    all_replicas = spmd_program(replica_epoch, mesh, n_in=12, n_out=4, replicated_in=(11,), jit=False)

    def run_chunk(state, data, shuffle_key, epochs, end, patience):
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
            # epochs from ``end`` on belong to the next chunk: one program runs chunks of
            # any length up to its own
            stop = (epoch >= end) | ((patience > 0) & jnp.all(epoch - carry[4] >= patience))
            return jax.lax.cond(stop, skip_epoch, run_epoch, carry, epoch)

        state, (train, val, ran) = jax.lax.scan(body, state, epochs)
        return state, train, val, ran

    def replica_val_loss(params, x_val, y_val, load_val, mask, u_val):
        return arch.loss(params, x_val, y_val, load_val, jnp.ones(x_val.shape[0], x_val.dtype), mask, u_val)

    val_loss = spmd_program(replica_val_loss, mesh, n_in=6, n_out=1)
    return optimizer, steps, jax.jit(run_chunk), val_loss, {}


# ----------------------------------------------------------------------------- training


@dataclasses.dataclass(frozen=True)
class TrainProgress:
    """What the ``callback`` of :func:`train_replicas` is given after each compiled chunk
    of epochs (after the training state, if any, is written).

    Attributes:
        epochs_done: epochs run so far (a resumed run counts the restored ones).
        n_epochs: largest number of epochs (``config.resolved_epochs``).
        train_loss, val_loss: (n_parts,) losses of the last epoch run (NaN before any).
        state_written: the training state file was rewritten after this chunk.
        stopped: early stopping ended the training.
    """

    epochs_done: int
    n_epochs: int
    train_loss: np.ndarray
    val_loss: np.ndarray
    state_written: bool
    stopped: bool


def _initial_params(arch, data, init_key, init):
    """Default :func:`init_replicas`, or ``init`` checked against them."""
    if init is None:
        return init_replicas(init_key, arch, data.dof_counts)
    params = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.dtype(arch.dtype)), init)
    expected = jax.eval_shape(lambda k: init_replicas(k, arch, data.dof_counts), init_key)
    if jax.tree_util.tree_structure(params) != jax.tree_util.tree_structure(expected) or any(
        a.shape != b.shape for a, b in zip(jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(expected))
    ):
        raise ConfigError("init parameters do not match the architecture and part count; build them with init_replicas")
    return params


def train_replicas(
    data: ReplicaData,
    arch,
    config: TrainConfig,
    key: jax.Array,
    init: Params | None = None,
    progress: bool = True,
    description: str = "training",
    devices: int | None = None,
    state: TrainingState | None = None,
    callback: Callable[[TrainProgress], None] | None = None,
) -> TrainResult:
    """Train one replica per part, all together, by gradient on the model's ``loss``.

    Args:
        data: stacked, padded windows (:func:`jaxsync.surrogate.training.stack_replicas`).
        arch: the model (a :class:`~jaxsync.surrogate.models.GradientFitted`: the
            :class:`~jaxsync.surrogate.models.LSTMArchitecture` or a user's);
            ``arch.n_dof`` must equal ``data.n_dof_max``.
        config: optimization settings.
        key: PRNG key (initialization and shuffling).
        init: optional initial stacked parameters (default
            :func:`~jaxsync.surrogate.models.init_replicas`).
        progress: show a tqdm bar with the epoch and the largest train/val loss over parts.
        description: label of the progress bar.
        devices: local devices to spread the parts over (default: as many as divide the
            number of parts); 1 keeps everything on one device.  The result does not
            depend on it beyond float32 round-off.
        state: where and how often to write the resumable training state
            (:class:`~jaxsync.surrogate.training.TrainingState`; None: none).  If
            its file exists it must come from a run with the same data, architecture,
            config, key, init and ``state.every`` (else :class:`CheckpointError`), and
            training continues from it.  It is rewritten atomically every ``state.every``
            epochs and at the end; delete it once the results are saved.  Chunks
            also end at the multiples of ``state.every`` (the same compiled program
            runs chunks of every length).
        callback: called with a :class:`TrainProgress` after every compiled chunk (for
            logging; an exception raised there ends the training, and a state written
            before it can be resumed).

    Returns:
        A :class:`TrainResult`.
    """
    if arch.n_dof != data.n_dof_max:
        raise ConfigError(f"architecture has n_dof={arch.n_dof} but the data are padded to {data.n_dof_max}")
    if data.n_load != arch.n_load:
        raise ConfigError(f"the windows carry {data.n_load} load signals but the architecture reads n_load="
                          f"{arch.n_load}; make the architecture with n_load=data.n_load")
    if data.x_train.shape[2] != arch.n_past or data.y_train.shape[2] != arch.n_future:
        raise ConfigError(
            f"windows are {data.x_train.shape[2]} -> {data.y_train.shape[2]} snapshots but the architecture "
            f"expects n_past={arch.n_past}, n_future={arch.n_future}"
        )
    if state is not None and not isinstance(state, TrainingState):
        raise ConfigError(f"state must be a jaxsync.surrogate.TrainingState(folder, every) or None, got {state!r}")
    every = 0 if state is None else int(state.every)
    path = None if state is None else state.path
    fingerprint = training_fingerprint(data, arch, config, key, init, every) if state is not None else None
    init_key, shuffle_key = jax.random.split(key)
    dtype = jnp.dtype(arch.dtype)
    params = _initial_params(arch, data, init_key, init)
    n_train = data.x_train.shape[1]
    mesh = _parts_mesh(data.n_parts, devices)
    optimizer, steps, run_chunk, val_loss_fn, executables = _epoch_runner(
        arch, _runner_config(config), n_train, mesh)
    opt_state = jax.vmap(optimizer.init)(params)
    carry = (params, opt_state, params, jnp.full(data.n_parts, jnp.inf, dtype),
             jnp.zeros(data.n_parts, jnp.int32))
    def signals(u, x):  # windows without load signals carry an empty (n_parts, n, n_p + n_f, 0) array
        return np.zeros(x.shape[:2] + (arch.n_past + arch.n_future, 0)) if u is None else u

    arrays = tuple(jnp.asarray(a, dtype) for a in (
        data.x_train, data.y_train, data.load_parameter_train, data.x_val, data.y_val, data.load_parameter_val,
        data.dof_mask, signals(data.signal_train, data.x_train), signals(data.signal_val, data.x_val),
    ))

    n_epochs = config.resolved_epochs
    train_hist = np.zeros((0, data.n_parts), dtype)
    val_hist = np.zeros((0, data.n_parts), dtype)
    initial_val = None
    info = {"epochs_done": 0, "stopped": False, "train_seconds": 0.0, "epochs_timed": 0}
    if path is not None and os.path.exists(path):
        carry, history, info = load_training_state(path, fingerprint, jax.tree_util.tree_map(np.asarray, carry))
        train_hist, val_hist, initial_val = history["train_loss"], history["val_loss"], history["initial_val_loss"]
        if train_hist.shape != (info["epochs_done"], data.n_parts):
            raise CheckpointError(f"training state {path} holds an inconsistent loss history; "
                                  "delete it to start over")
    elif path is not None:
        os.makedirs(state.folder, exist_ok=True)
    resumed_from = int(info["epochs_done"])
    carry, arrays = jax.device_put((carry, arrays), NamedSharding(mesh, part_spec()))
    if initial_val is None:
        initial_val = np.asarray(val_loss_fn(carry[0], *arrays[3:7], arrays[8]))
    patience = jnp.int32(config.patience or 0)

    # Every chunk runs in one program of epochs_per_call epochs (a shorter chunk skips the
    # epochs after its end): one compilation per data shape, whatever the chunk lengths.
    length = config.epochs_per_call

    def executable():
        # Compiled ahead of time (and kept with the cached runner) so that compilation is
        # timed apart from training.
        signature = (length,) + tuple(a.shape for a in arrays)
        if signature not in executables:
            epochs = jax.ShapeDtypeStruct((length,), jnp.int32)
            executables[signature] = run_chunk.lower(carry, arrays, shuffle_key, epochs, jnp.int32(0),
                                                     patience).compile()
        return executables[signature]

    def next_boundary(done, step):
        return (done // step + 1) * step

    compile_seconds = 0.0
    done = int(info["epochs_done"])
    with tqdm(total=n_epochs, initial=done, desc=description, disable=not progress, unit="epoch") as bar:
        while done < n_epochs and not info["stopped"]:
            # Chunks end at multiples of epochs_per_call and state.every: fixed epochs,
            # so a resumed run compiles and runs the same chunks as an uninterrupted one.
            end = min(next_boundary(done, config.epochs_per_call), n_epochs)
            if every:
                end = min(end, next_boundary(done, every))
            chunk = end - done
            start = time.perf_counter()
            run = executable()
            compiled = time.perf_counter()
            carry, train, val, ran = run(carry, arrays, shuffle_key, jnp.arange(done, done + length, dtype=jnp.int32),
                                         jnp.int32(end), patience)
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
            write = path is not None and (info["stopped"] or done == n_epochs or (every and done % every == 0))
            if write:
                save_training_state(path, fingerprint, jax.tree_util.tree_map(np.asarray, carry),
                                    {"train_loss": train_hist, "val_loss": val_hist, "initial_val_loss": initial_val},
                                    info)
            if callback is not None:
                last = (train_hist[-1], val_hist[-1]) if done else (np.full(data.n_parts, np.nan),) * 2
                callback(TrainProgress(done, n_epochs, *last, state_written=bool(write), stopped=info["stopped"]))

    best_epoch = np.asarray(carry[4])
    return TrainResult(
        params=jax.tree_util.tree_map(np.asarray, carry[2]),
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
        signal_scale=data.signal_scale,
        load_inputs=tuple(data.load_inputs),
    )
