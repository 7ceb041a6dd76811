"""The host loop (jaxsync.solve.executors.run_chunks) with a toy runner whose values name
their step: chunks, the recorded shared histories (all of them, or a bounded tail), and
the segment kept before a divergence."""

import numpy as np
import pytest

from jaxsync.solve.executors import Chunk, Diverged, run_chunks


class StepRunner:
    """A runner whose state is the step and whose values are the step number: the full
    field (1 node) every ``save_every`` steps, two parts' shared values every step
    (part p: step * (p + 1)); the step ``bad`` and later are NaN."""

    def __init__(self, save_every=2, bad=None):
        self.save_every, self.n_nodes, self.bad = save_every, 1, bad

    def chunk_steps(self, steps_left, preferred):
        return min(steps_left, preferred)

    def compile(self, state, steps):
        return 0.0

    def advance(self, state, steps):
        steps_done = np.arange(state + 1, state + steps + 1, dtype=float)
        values = np.where(steps_done >= (self.bad or np.inf), np.nan, steps_done)
        saved = values[self.save_every - 1::self.save_every]
        disp = np.repeat(saved[:, None, None], 3, axis=2)
        shared = [values[:, None] * (p + 1) * np.ones((1, 2)) for p in range(2)]
        return state + steps, Chunk(disp, shared)


def test_all_shared_rows_or_a_bounded_tail_with_the_largest_value_counted():
    full = run_chunks(StepRunner(), 0, 0, 60, kind="synchronized", limit=1e9, chunk_steps=10)
    assert [len(r) for r in full.shared] == [60, 60]
    np.testing.assert_array_equal(full.shared[1][:, 0], 2 * np.arange(1, 61))
    tail = run_chunks(StepRunner(), 0, 0, 60, kind="synchronized", limit=1e9, chunk_steps=10, keep_shared=15)
    for got, every in zip(tail.shared, full.shared):
        assert 15 <= len(got) < 15 + 10  # whole chunks
        np.testing.assert_array_equal(got, every[-len(got):])
    assert tail.shared_abs_max == full.shared_abs_max == 120.0
    np.testing.assert_array_equal(tail.displacement, full.displacement)


@pytest.mark.parametrize("keep", [None, 15])
def test_divergence_keeps_the_steps_before_the_bad_snapshot(keep):
    with pytest.raises(Diverged) as caught:
        run_chunks(StepRunner(bad=37), 0, 0, 60, kind="synchronized", limit=1e9, chunk_steps=10,
                   keep_shared=keep)
    seg = caught.value
    assert seg.step == 38  # the first saved snapshot at or after step 37
    assert seg.segment.last == 36 and seg.segment.displacement[-1, 0, 0] == 36
    for part, rows in enumerate(seg.segment.shared):
        assert rows[-1, 0] == 36 * (part + 1) and np.isfinite(rows).all()
        if keep is None:
            assert len(rows) == 36


def test_the_progress_bar_never_moves_backwards_and_counts_the_recomputed_steps():
    from jaxsync.solve.executors import Progress

    with Progress(100, show=True) as bar:
        shown = []
        bar.update(40)
        shown.append(bar.bar.n)
        bar.set(20)  # a rejected cycle: back to the synchronized state of step 20
        shown.append(bar.bar.n)
        bar.update(15)  # recomputing steps 21 .. 35
        shown.append(bar.bar.n)
        bar.update(15)  # 36 .. 50: 36 .. 40 recomputed, 41 .. 50 new
        shown.append(bar.bar.n)
        assert shown == [40, 40, 40, 50] and bar.recomputed == 20
        assert "recomputed 20 steps" in str(bar.bar)
        bar.set(70)  # a resumed checkpoint moves forward
        assert bar.bar.n == 70
