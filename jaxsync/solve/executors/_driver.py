"""The one host loop: compiled chunks of a runner, timed, checked and shown.

Every run of jaxsync -- single device, distributed, the predicted phase of a
synchronization-avoiding run and its re-synchronized stretches -- advances through
:func:`run_chunks`. A *runner* owns the compiled programs and the device state; the loop
owns what happens between chunks: chunk sizes, compilation ahead of the timed call,
timing, the divergence check, progress and the per-chunk hook (checkpoints).

The runner protocol (:class:`Runner`): attributes ``save_every`` and ``n_nodes`` (of the
mesh), and methods ``chunk_steps(steps_left, preferred)`` (how many steps the next call
advances), ``compile(state, steps) -> seconds`` (ahead, untimed) and
``advance(state, steps) -> (state, Chunk)``. Runners of synchronized runs also offer
``to_global`` / ``from_global`` (a :class:`~jaxsync.fem.SolverState` of the whole
mesh, for checkpoints and restarts).
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any, Callable, NamedTuple, Protocol

import numpy as np

__all__ = ["Runner", "Chunk", "Segment", "Progress", "Diverged", "Stopped", "run_chunks", "divergence_limit",
           "chunk_of_saves"]


class Chunk(NamedTuple):
    """What one compiled call returns to the host.

    Attributes:
        displacement: (n_saved, n_nodes, 3) global field at the saved steps [cm] (at
            shared nodes of a predicted chunk: the mean over the parts that hold it).
        shared: per part, (steps, 3 n_shared_p) shared-node displacement after every
            step [cm], or None when the runner does not record it.
        predictions: (n_parts, n_saved, n_dof) each part's own predictions at the saved
            steps [cm] (predicted chunks), or None.
    """

    displacement: np.ndarray
    shared: list | None = None
    predictions: np.ndarray | None = None


class Runner(Protocol):
    """What :func:`run_chunks` drives (see the module docstring)."""

    save_every: int
    n_nodes: int

    def chunk_steps(self, steps_left: int, preferred: int) -> int: ...

    def compile(self, state, steps: int) -> float: ...

    def advance(self, state, steps: int) -> tuple[Any, Chunk]: ...


@dataclasses.dataclass
class Segment:
    """Steps ``first`` + 1 .. ``last`` of a run as one runner advanced them.

    Attributes:
        kind: a label (``"synchronized"``, ``"predicted"``).
        first, last: step before the first and last step advanced.
        displacement: (n_saved, n_nodes, 3) [cm] at steps first + save_every, ..., last.
        shared: per part, (last - first, 3 n_shared_p) every step, or None; with
            ``run_chunks(keep_shared=k)`` only the last rows, at least min(k, last -
            first) of them.
        shared_abs_max: the largest |shared| over all the segment's steps (0 without).
        predictions: (n_parts, n_saved, n_dof) or None.
        seconds: wall time of the compiled calls (compilation excluded) [s].
        compile_seconds: time spent compiling [s].
        state: the runner's state at ``last``.
    """

    kind: str
    first: int
    last: int
    displacement: np.ndarray
    shared: list | None
    predictions: np.ndarray | None
    seconds: float
    compile_seconds: float
    state: Any
    shared_abs_max: float = 0.0

    @property
    def n_steps(self) -> int:
        return self.last - self.first


class Diverged(Exception):
    """Raised by :func:`run_chunks` when a chunk holds NaN/Inf or a blow-up: ``segment``
    holds the steps before the bad snapshot, ``step`` the step of the first bad one,
    ``part`` the part whose prediction went bad (None: the solution itself)."""

    def __init__(self, segment: Segment, step: int, part: int | None):
        super().__init__(f"diverged by step {step}")
        self.segment, self.step, self.part = segment, step, part


class Stopped(Exception):
    """Raised by a runner's ``advance`` to end :func:`run_chunks` early (a rejected
    predicted cycle, say); the loop sets ``segment`` to the steps advanced before."""

    segment: Segment | None = None


class Progress:
    """One progress bar over a whole run (tqdm), shared by the loop's calls; ``show``
    None shows it for runs of 20 000 steps or more. Use as a context manager: an error
    clears the bar instead of leaving a blank line before the traceback.

    The bar shows the furthest step the run has reached, so it never moves backwards:
    when a synchronization-avoiding run goes back to a synchronized state (:meth:`set` to
    an earlier step), the steps it recomputes are counted beside the bar ("recomputed")
    until the run passes the furthest step again."""

    def __init__(self, total: int, *, show: bool | None = None, label: str = "", initial: int = 0):
        from tqdm import tqdm

        show = show if show is not None else total >= 20000
        self.bar = tqdm(total=total, initial=initial, disable=not show, unit="step", desc=label,
                        dynamic_ncols=True)
        self.step = self.furthest = int(initial)  # where the run is, and the furthest it has been
        self.recomputed = 0

    def label(self, text: str) -> None:
        self.bar.set_description_str(text, refresh=False)

    def update(self, steps: int) -> None:
        """The run advanced ``steps`` steps."""
        redone = max(0, min(self.step + steps, self.furthest) - self.step)
        self.step += steps
        if redone:
            self.recomputed += redone
            self.bar.set_postfix_str(f"recomputed {self.recomputed} steps", refresh=False)
        if self.step > self.furthest:
            self.bar.update(self.step - self.furthest)
            self.furthest = self.step
        elif redone:
            self.bar.refresh()

    def set(self, done: int) -> None:
        """The run is at step ``done`` (earlier than the furthest: it goes back to recompute)."""
        self.step = int(done)
        if self.step > self.furthest:
            self.bar.update(self.step - self.furthest)
            self.furthest = self.step

    def __enter__(self):
        return self

    def __exit__(self, kind, *_):
        if kind is not None:
            self.bar.leave = False
        self.bar.close()
        return False


def chunk_of_saves(steps_left: int, preferred: int, save_every: int) -> int:
    """Steps of the next chunk of a synchronized runner: whole saves, about ``preferred``
    steps, at most ``steps_left``."""
    return min(max(1, preferred // save_every), steps_left // save_every) * save_every


def divergence_limit(mesh, blowup_factor: float) -> float:
    """The |displacement| [cm] above which a run counts as diverged: ``blowup_factor``
    times the diagonal of the mesh's bounding box."""
    return blowup_factor * float(np.linalg.norm(np.ptp(mesh.points, axis=0)))


def _first_bad(chunk: Chunk, limit: float) -> tuple[int, int | None] | None:
    """(index of the first bad saved snapshot, part or None) or None when all are good."""
    if chunk.predictions is not None:
        bad = ~np.isfinite(chunk.predictions).all(axis=-1)  # (n_parts, n_saved)
        if bad.any():
            parts, saves = np.nonzero(bad)
            j = int(saves.min())
            return j, int(parts[saves == j][0])
    disp = chunk.displacement
    ok = np.isfinite(disp).all(axis=(1, 2)) & (np.abs(disp).max(axis=(1, 2), initial=0) <= limit)
    return None if ok.all() else (int(np.argmin(ok)), None)


def run_chunks(runner: Runner, state, first: int, last: int, *, kind: str, limit: float,
               progress: Progress | None = None, chunk_steps: int = 5000,
               after_chunk: Callable[[int, Callable[[], Segment]], None] | None = None,
               keep_shared: int | None = None) -> Segment:
    """Advance ``state`` from step ``first`` to ``last`` in compiled chunks of ``runner``.

    Each chunk's program is compiled ahead of its timed call (so ``seconds`` excludes
    compilation), its snapshots are checked (NaN/Inf, or |d| above ``limit`` [cm]; NaN
    predictions of a predicted chunk are named by part), the progress bar moves, and
    ``after_chunk(step, segment)`` runs (checkpoints; ``segment()`` builds the segment so
    far, only when the hook needs it).

    Returns the :class:`Segment`. Raises :class:`Diverged` (with the good part of the
    segment) on divergence; a :class:`Stopped` from the runner propagates with the
    segment so far in its ``segment`` attribute.

    ``keep_shared``: keep only about the last ``keep_shared`` steps of the shared
    histories a recording runner returns (whole chunks; the memory of a long
    re-synchronized stretch stays bounded), their largest |value| still counted.
    """
    save_every = runner.save_every
    pieces, shared, preds = [], None, []
    shared_max = 0.0
    seconds = compile_seconds = 0.0
    step = first

    def segment(upto: int | None = None) -> Segment:
        disp = np.concatenate(pieces) if pieces else np.zeros((0, runner.n_nodes, 3))
        pred = np.concatenate(preds, axis=1) if preds else None
        rec = None if shared is None else [np.concatenate(s) for s in shared]
        if upto is not None:  # keep the snapshots before index `upto` of the last chunk
            n_keep = len(disp) - len(pieces[-1]) + upto
            disp = disp[:n_keep]
            pred = None if pred is None else pred[:, :n_keep]
            drop = (len(pieces[-1]) - upto) * save_every  # the last chunk's steps from the bad one on
            rec = None if rec is None else [r[:len(r) - drop] for r in rec]
        n_steps = len(disp) * save_every
        return Segment(kind, first, first + n_steps, disp, rec, pred, seconds, compile_seconds, state, shared_max)

    while step < last:
        steps = runner.chunk_steps(last - step, chunk_steps)
        compile_seconds += runner.compile(state, steps)
        start = time.perf_counter()
        try:
            new_state, chunk = runner.advance(state, steps)
        except Stopped as stop:
            seconds += time.perf_counter() - start
            stop.segment = segment()
            raise
        seconds += time.perf_counter() - start
        pieces.append(chunk.displacement)
        if chunk.predictions is not None:
            preds.append(chunk.predictions)
        if chunk.shared is not None:
            shared = shared or [[] for _ in chunk.shared]
            for rec, values in zip(shared, chunk.shared):
                rec.append(values)
                finite = np.abs(values[np.isfinite(values)])
                shared_max = max(shared_max, float(finite.max(initial=0.0)))
                while keep_shared is not None and len(rec) > 1 and sum(map(len, rec[1:])) >= keep_shared:
                    del rec[0]  # the later chunks hold the last keep_shared steps
        bad = _first_bad(chunk, limit)
        if bad is not None:
            index, part = bad
            raise Diverged(segment(upto=index), step + (index + 1) * save_every, part)
        state = new_state
        step += steps
        if progress is not None:
            progress.update(steps)
        if after_chunk is not None:
            after_chunk(step, segment)
    return segment()
