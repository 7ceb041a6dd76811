"""Solver-in-the-loop fine-tuning of the surrogates (beyond the paper).

The surrogates are trained offline, one part at a time, on windows of the synchronized
run's shared-node history: each network learns to predict its boundary from the true past.
Online, each refill reads the network's own earlier predictions, and the solver's response
to them; small errors then compound cycle after cycle. Fine-tuning in the loop trains every
part's network on what the online run actually does: the loss is the error of the coupled
synchronization-avoiding run (the traced executor, :func:`jaxsync.solve.executors.run_traced`, all
parts, their networks and the unsynchronized solver together) over a window of refill
cycles, against the synchronized run from the same state, and its gradient flows through
the solver steps into the weights of every network.

A window starts at a synchronized state of the training run (any step after the first n_s
n_p), runs n_s n_p synchronized steps (the networks' input history), then
``window_cycles`` refill cycles predicted; its loss is the mean squared difference from the
synchronized run over the predicted steps' saves, relative to the training run's largest
displacement squared. Windows are drawn at random from a grid of start steps inside the
steps given (the span the surrogates were trained on), with Adam on the weights (gradient
clipped), and the weights with the lowest loss on a fixed set of validation windows are
kept (the start's, when no step improved on it).

Any surrogate model is tuned alike (:mod:`jaxsync.surrogate.models`): the gradient flows
through the model's own ``forward``, whatever the model and however it was first fitted
(by gradient, or in closed form like the linear one).
"""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError
from ..fem._stepper import SolverState, advance, build_system, initial_state
from ._strategies import Recompute
from .coupling._predictors import predictor_for
from .executors._distributed import DistributedParts
from .executors._phases import PredictedSteps, SynchronizedSteps
from .executors._traced import run_traced

__all__ = ["FineTuneConfig", "FineTuneResult", "fine_tune_in_the_loop"]


@dataclasses.dataclass(frozen=True)
class FineTuneConfig:
    """Settings of :func:`fine_tune_in_the_loop`.

    Attributes:
        n_iterations: Adam steps, one window each.
        window_cycles: refill cycles predicted in a window (its horizon: window_cycles n_s
            n_f steps after the n_s n_p synchronized ones).
        learning_rate: Adam's step size.
        clip_norm: the gradients' global norm is clipped to this.
        n_starts: start steps on the grid the windows are drawn from (evenly spread).
        n_validation: windows (of the grid, evenly spread) whose mean loss decides which
            weights are kept.
        validate_every: iterations between two validations.
        seed: draws of the windows.
    """

    n_iterations: int = 60
    window_cycles: int = 2
    learning_rate: float = 1e-4
    clip_norm: float = 1.0
    n_starts: int = 24
    n_validation: int = 4
    validate_every: int = 10
    seed: int = 0

    def __post_init__(self):
        for name in ("n_iterations", "window_cycles", "n_starts", "n_validation", "validate_every"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ConfigError(f"FineTuneConfig.{name} must be an integer >= 1, got {value!r}")
        for name in ("learning_rate", "clip_norm"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
                    or not value > 0:
                raise ConfigError(f"FineTuneConfig.{name} must be > 0, got {value!r}")
        if self.n_validation > self.n_starts:
            raise ConfigError(f"FineTuneConfig.n_validation={self.n_validation} exceeds n_starts={self.n_starts}")


@dataclasses.dataclass(frozen=True)
class FineTuneResult:
    """What :func:`fine_tune_in_the_loop` returns.

    Attributes:
        surrogate: the fine-tuned :class:`jaxsync.surrogate.Surrogate` (the weights with the
            lowest validation loss; the given ones when none was lower).
        loss_history: (n_iterations,) the loss of each iteration's window before its update
            (relative mean squared error, see the module docstring).
        validation: (n_validations, 2) rows (iteration, mean validation loss), iteration 0
            the given weights.
        best_iteration: the iteration whose weights were kept (0: the given ones).
        window_starts: (n_starts,) the grid of start steps.
        amplitude: the training run's largest |displacement| [cm] the losses are relative to.
        seconds: wall time, compilation included; compile_seconds: of that, compiling.
    """

    surrogate: object
    loss_history: np.ndarray
    validation: np.ndarray
    best_iteration: int
    window_starts: np.ndarray
    amplitude: float
    seconds: float
    compile_seconds: float

    @property
    def improvement(self) -> float:
        """Validation loss of the kept weights over the given ones' (< 1: better)."""
        kept = self.validation[self.validation[:, 0] == self.best_iteration, 1][0]
        return float(kept / self.validation[0, 1])

    def summary(self) -> dict:
        return {"n_iterations": len(self.loss_history), "best_iteration": self.best_iteration,
                "validation": self.validation.tolist(), "improvement": self.improvement,
                "window_starts": self.window_starts.tolist(), "amplitude_cm": self.amplitude,
                "seconds": self.seconds, "compile_seconds": self.compile_seconds}


def fine_tune_in_the_loop(problem, surrogate, partitions, *, n_steps: int, config: FineTuneConfig | None = None,
                          dt=None, mode: str = "preassembled", sync=None, progress: bool = False) -> FineTuneResult:
    """Fine-tune every part's network on the error of the coupled online run.

    Args:
        problem: the problem the surrogates were trained on.
        surrogate: a :class:`jaxsync.surrogate.Surrogate` for ``partitions`` (e.g.
            ``Surrogate.from_saved(trained.saved)``); its ``params`` are tuned, the
            normalization and the rest are kept.
        partitions: n_parts or the :class:`jaxsync.Partition` the surrogates were trained on.
        n_steps: the end of the span windows are drawn from [steps] (the steps of the
            training data that the networks were fitted on: no window reads beyond it).
        config: :class:`FineTuneConfig`.
        dt, mode, sync: as for :func:`jaxsync.simulate` (``sync``: ``"psum"``, ``"ppermute"``
            or ``"halo"`` strategies, which carry the devices).
        progress: a tqdm bar over the iterations.

    Returns:
        :class:`FineTuneResult`.

    Raises:
        ConfigError: a span too short for the windows.
    """
    from ..surrogate._model import Surrogate

    if not isinstance(surrogate, Surrogate):
        raise ConfigError(f"fine_tune_in_the_loop tunes a jaxsync.surrogate.Surrogate, got {type(surrogate).__name__}")
    config = FineTuneConfig() if config is None else config
    wall = time.perf_counter()
    dt = float(problem.dt if dt is None else dt)
    history, cycle = surrogate.history_steps, surrogate.cycle_steps
    window = history + config.window_cycles * cycle
    save_every = surrogate.n_s  # divides both the history and a cycle
    first, last = 0, int(n_steps) - window  # window starts: the history begins at the start
    if last < first:
        raise ConfigError(f"a window needs {window} steps (n_s n_p = {history} synchronized, then "
                          f"{config.window_cycles} cycles of {cycle}); n_steps={n_steps} is too short: "
                          "use fewer window_cycles or a longer span")
    starts = np.unique(np.linspace(first, last, config.n_starts).round().astype(int) // save_every * save_every)
    distributed = DistributedParts(problem, partitions, sync, mode=mode)
    surrogate = predictor_for(surrogate, distributed.partition, problem, dt)  # made for this partition and its loads
    schedule = (SynchronizedSteps(history), PredictedSteps(window - history))
    system = build_system(problem, dt, mode)
    states, amplitude = _start_states(system, initial_state(problem, system), starts, int(n_steps), save_every)
    n_saves, n_history_saves = window // save_every, history // save_every

    def window_loss(params, start: SolverState):
        tuned = dataclasses.replace(surrogate, params=params)
        online = run_traced(problem, system, start, schedule, save_every=save_every, adjoint=Recompute(),
                            distributed=distributed, predictor=tuned).saved
        _, reference = advance(system, start, n_saves, save_every)
        error = (online - jax.lax.stop_gradient(reference))[n_history_saves:]
        return jnp.mean(error ** 2) / amplitude ** 2

    import optax

    optimizer = optax.chain(optax.clip_by_global_norm(config.clip_norm), optax.adam(config.learning_rate))
    params = surrogate.params
    opt_state = optimizer.init(params)

    @jax.jit
    def update(params, opt_state, start):
        loss, grads = jax.value_and_grad(window_loss)(params, start)
        with jax.numpy_dtype_promotion("standard"):  # optax's bias correction mixes float and int
            updates, opt_state = optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss

    loss_only = jax.jit(window_loss)
    pick = lambda k: jax.tree_util.tree_map(lambda x: x[k], states)  # noqa: E731
    validation_windows = np.unique(np.linspace(0, len(starts) - 1, config.n_validation).round().astype(int))

    def validate(params) -> float:
        return float(np.mean([float(loss_only(params, pick(k))) for k in validation_windows]))

    compile_start = time.perf_counter()
    update_compiled = update.lower(params, opt_state, pick(0)).compile()
    loss_only = loss_only.lower(params, pick(0)).compile()
    compile_seconds = time.perf_counter() - compile_start

    rng = np.random.default_rng(config.seed)
    best, best_loss, best_iteration = params, validate(params), 0
    validation = [(0, best_loss)]
    losses = []
    iterations = range(1, config.n_iterations + 1)
    if progress:
        from tqdm.auto import tqdm

        iterations = tqdm(iterations, desc="fine-tuning in the loop", unit="window")
    for it in iterations:
        params, opt_state, loss = update_compiled(params, opt_state, pick(int(rng.integers(len(starts)))))
        losses.append(float(loss))
        if it % config.validate_every == 0 or it == config.n_iterations:
            value = validate(params)
            validation.append((it, value))
            if value < best_loss:
                best, best_loss, best_iteration = params, value, it
    return FineTuneResult(surrogate=dataclasses.replace(surrogate, params=best), loss_history=np.asarray(losses),
                          validation=np.asarray(validation, dtype=float), best_iteration=best_iteration,
                          window_starts=starts, amplitude=amplitude, seconds=time.perf_counter() - wall,
                          compile_seconds=compile_seconds)


def _start_states(system, state: SolverState, starts: np.ndarray, n_steps: int, save_every: int):
    """The synchronized (single-device) run's states at ``starts`` (increasing, multiples of
    ``save_every``), stacked, and its largest |displacement| [cm] over ``n_steps`` steps
    (at the saves every ``save_every`` steps)."""
    gaps = np.diff(np.concatenate([[0], starts]))
    kept, amplitude, step = [], 0.0, 0
    run = jax.jit(advance, static_argnums=(2, 3))
    for gap in gaps:
        if gap:
            state, saved = run(system, state, int(gap) // save_every, save_every)
            amplitude = max(amplitude, float(jnp.max(jnp.abs(saved))))
            step += int(gap)
        kept.append(state)
    if n_steps > step:
        left = (n_steps - step) // save_every
        if left:
            _, saved = run(system, state, left, save_every)
            amplitude = max(amplitude, float(jnp.max(jnp.abs(saved))))
    stacked = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *kept)
    if not amplitude > 0:
        raise ConfigError("the synchronized run does not move over the span given: nothing to fine-tune on")
    return stacked, amplitude
