"""The measurement harness (jaxsync.perf.measure): round-robin order, untimed warm-up and
the best round, checked with a fake clock passed through its ``clock`` argument; the
machine's rates computed from hand-set times. No test asserts a speed."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxsync import ProblemError
from jaxsync.perf.measure import (
    best_time,
    best_times,
    copy_bandwidth,
    describe_devices,
    matmul_flop_rate,
    per_step_times,
    sample_times,
)


class FakeClock:
    """A clock whose k-th timed call lasts ``durations[k]`` seconds (two readings per call)."""

    def __init__(self, durations):
        self.readings = []
        t = 0.0
        for d in durations:
            self.readings += [t, t + d]
            t += d + 1.0
        self.readings.reverse()

    def __call__(self):
        return self.readings.pop()


def test_round_robin_after_an_untimed_warm_up():
    log = []
    calls = {"a": (lambda x: log.append(("a", x)), (1,)), "b": (lambda: log.append(("b", None)), ())}
    # rounds: a 3 s, b 5 s; a 1 s, b 4 s; a 2 s, b 6 s
    samples = sample_times(calls, 3, clock=FakeClock([3, 5, 1, 4, 2, 6]))
    assert log == [("a", 1), ("b", None)] * 4  # warm-up of each, then three rounds in turn
    np.testing.assert_array_equal(samples["a"], [3, 1, 2])
    np.testing.assert_array_equal(samples["b"], [5, 4, 6])
    assert list(samples) == ["a", "b"]
    assert best_times(calls, 3, clock=FakeClock([3, 5, 1, 4, 2, 6])) == {"a": 1.0, "b": 4.0}
    assert best_time(lambda x, y: log.append(x + y), 2, 2, 3, clock=FakeClock([0.5, 0.25])) == 0.25
    assert log[-1] == 5


def test_jax_results_are_waited_for():
    f = jax.jit(lambda x: x @ x)
    x = jnp.ones((8, 8))
    times = sample_times({"matmul": (f, (x,))}, 2)
    assert times["matmul"].shape == (2,) and np.all(times["matmul"] >= 0)


def test_per_step_times_remove_the_call():
    best = {"x": 0.5, "y": 0.1, "call": 0.2}
    assert per_step_times(best, 10) == pytest.approx({"x": 0.03, "y": 0.0})  # y clipped at 0
    assert best == {"x": 0.5, "y": 0.1, "call": 0.2}  # not consumed
    with pytest.raises(ProblemError, match="call"):
        per_step_times({"x": 0.5}, 10)
    with pytest.raises(ProblemError, match="n_steps"):
        per_step_times(best, 0)


def test_copy_bandwidth_counts_read_and_write():
    # 1000 float64 = 8000 bytes read and 8000 written per copy; best copy 0.5 s
    assert copy_bandwidth(8000, 3, clock=FakeClock([1.0, 0.5, 2.0])) == pytest.approx(16000 / 0.5)
    rate = copy_bandwidth(8e5, 2)
    assert math.isfinite(rate) and rate > 0


def test_matmul_flop_rate_counts_2n3():
    assert matmul_flop_rate(16, repeats=3, clock=FakeClock([1.0, 0.25, 0.5])) == pytest.approx(2 * 16 ** 3 / 0.25)
    rate = matmul_flop_rate(64, repeats=2)
    assert math.isfinite(rate) and rate > 0


def test_bad_arguments_are_refused():
    with pytest.raises(ProblemError, match="repeats"):
        sample_times({"a": (lambda: None, ())}, 0)
    with pytest.raises(ProblemError, match="at least one"):
        best_times({}, 3)
    with pytest.raises(ProblemError, match="n_bytes"):
        copy_bandwidth(4)
    with pytest.raises(ProblemError, match="repeats"):
        copy_bandwidth(8e3, repeats=0)
    with pytest.raises(ProblemError, match="dtype"):
        matmul_flop_rate(8, dtype="int8")
    with pytest.raises(ProblemError, match="repeats"):
        matmul_flop_rate(8, repeats=0)


def test_describe_devices():
    assert len(jax.devices()) == 2  # tests/conftest.py
    text = describe_devices(jax.devices())
    assert text.startswith("2 x cpu") and "emulated" in text
    assert "every part on this one device" in describe_devices(jax.devices()[:1])
