import numpy as np
import pytest

from jaxsync import ProblemError
from jaxsync.metrics import l2_error, shared_node_errors


def test_l2_error_equals_formula():
    ref = np.zeros((2, 2, 3))
    pred = np.array([[[3.0, 0, 0], [0, 4.0, 0]], [[1.0, 1.0, 1.0], [1.0, 0, 0]]])
    np.testing.assert_allclose(l2_error(ref, pred), [5.0, 2.0])


def test_shared_node_errors_by_hand():
    # one time step, two shared nodes, three parts: node 0 held by parts 0 and 1,
    # node 1 held by parts 0, 1 and 2
    truth = np.zeros((1, 2, 3))
    predictions = np.zeros((3, 1, 2, 3))
    predictions[0, 0, 0] = [3.0, 0, 0]     # |err| mean over components = 1
    predictions[1, 0, 0] = [0.0, 0, 0]     # 0
    predictions[0, 0, 1] = [0.0, 3.0, 3.0]  # 2
    predictions[1, 0, 1] = [0.0, 0, 0]     # 0
    predictions[2, 0, 1] = [6.0, 0, 0]     # 2
    predictions[2, 0, 0] = [99.0, 99, 99]  # not held: ignored
    holds = np.array([[True, True], [True, True], [False, True]])
    out = shared_node_errors(truth, predictions, holds)
    # node 0: (1 + 0) / 2 = 0.5; node 1: (2 + 0 + 2) / 3 = 4/3
    np.testing.assert_allclose(out.et, [0.5, 4 / 3])
    np.testing.assert_allclose(out.es, [(0.5 + 4 / 3) / 2])
    # es_hat: node 0 pair (0,1): |[3,0,0]| mean = 1; node 1 pairs (0,1): 2, (0,2): (6+3+3)/3=4,
    # (1,2): 2 -> mean 8/3
    np.testing.assert_allclose(out.et_hat, [1.0, 8 / 3])
    np.testing.assert_allclose(out.es_hat, [(1.0 + 8 / 3) / 2])


def test_time_average():
    truth = np.zeros((4, 1, 3))
    predictions = np.zeros((2, 4, 1, 3))
    predictions[0, :, 0, 0] = [0.0, 3.0, 6.0, 3.0]  # errors 0, 1, 2, 1
    holds = np.ones((2, 1), bool)
    out = shared_node_errors(truth, predictions, holds)
    np.testing.assert_allclose(out.es, [0.0, 0.5, 1.0, 0.5])
    np.testing.assert_allclose(out.et, [0.5])
    np.testing.assert_allclose(out.es_hat, [0.0, 1.0, 2.0, 1.0])


def test_bad_inputs():
    with pytest.raises(ProblemError, match="at least two parts"):
        shared_node_errors(np.zeros((1, 1, 3)), np.zeros((2, 1, 1, 3)), np.array([[True], [False]]))
    with pytest.raises(ProblemError, match="equal shapes"):
        l2_error(np.zeros((2, 3)), np.zeros((3, 3)))


def test_estimate_quality_against_numpy_by_hand():
    from jaxsync.metrics import estimate_quality

    es = np.array([1.0, 2.0, 4.0, 8.0, 0.0])
    es_hat = np.array([1.0, 1.0, 1.0, 16.0, 3.0])  # ratios 1, 2, 4, 0.5; the last has es = 0
    q = estimate_quality(es, es_hat)
    assert q.n_snapshots == 4
    assert q.ratio_median == pytest.approx(1.5)
    assert q.ratio_max == pytest.approx(4.0)
    assert q.ratio_p95 == pytest.approx(np.percentile([1, 2, 4, 0.5], 95))
    assert q.within_factor_2 == pytest.approx(0.75)
    assert q.underestimated == pytest.approx(0.25)
    expected = np.corrcoef(np.log10(es[:4]), np.log10(es_hat[:4]))[0, 1]
    assert q.log_correlation == pytest.approx(expected)
    assert "underestimated" in q.summary()
    # an estimate proportional to the error correlates perfectly, with the right ratio
    q = estimate_quality(np.geomspace(1e-6, 1e-3, 50), 0.25 * np.geomspace(1e-6, 1e-3, 50))
    assert q.log_correlation == pytest.approx(1.0) and q.ratio_median == pytest.approx(4.0)
    assert q.underestimated == 1.0
    with pytest.raises(ProblemError):
        estimate_quality(np.ones(3), np.ones(4))


def test_estimate_quality_when_es_hat_is_zero_is_said_and_written_as_null():
    """es_hat = 0 everywhere (the parts' predictions agree exactly): no numpy warning, one
    line that says the tracking cannot be measured, null (never NaN/Infinity) in JSON."""
    import json
    import warnings

    from jaxsync.io import json_value
    from jaxsync.metrics import EstimateQuality, estimate_quality

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        q = estimate_quality(np.geomspace(1e-6, 1e-3, 39), np.zeros(39))
        partial = estimate_quality(np.ones(10), np.r_[np.ones(5), np.zeros(5)])  # half the snapshots at 0
    assert q.es_hat_zero and q.n_snapshots == 39 and q.underestimated == 1.0 and q.within_factor_2 == 0.0
    assert q.summary() == ("es_hat is 0 at every one of the 39 compared snapshots (the parts' predictions agree "
                           "exactly): its tracking of es cannot be measured")
    text = json.dumps(json_value(q.to_dict()), allow_nan=False)
    assert json.loads(text)["ratio_median"] is None and json.loads(text)["log_correlation"] is None
    assert EstimateQuality(**json.loads(text)).summary() == q.summary()  # read back from summary.json
    assert not partial.es_hat_zero and partial.ratio_p95 == np.inf and partial.ratio_median == np.inf
    assert json_value(partial.to_dict())["ratio_p95"] is None
    none = estimate_quality(np.zeros(3), np.zeros(3))
    assert none.summary() == "es_hat tracks es: no snapshot with es > 0 to compare"
    assert json_value({"a": np.array([1.0, np.nan, -np.inf]), "b": np.float64("inf"), "c": (float("nan"), 2)}) == {
        "a": [1.0, None, None], "b": None, "c": [None, 2]}


def test_node_error_against_numpy():
    rng = np.random.default_rng(3)
    ref = rng.normal(size=(7, 4, 3))
    pred = ref + 0.1 * rng.normal(size=(7, 4, 3))
    from jaxsync.metrics import node_error

    for component in (0, 1, 2):
        out = node_error(ref, pred, 2, component)
        err = np.abs(pred[:, 2, component] - ref[:, 2, component])
        amplitude = np.abs(ref[:, 2, component]).max()
        assert (out.node, out.component) == (2, component)
        assert out.amplitude == pytest.approx(amplitude, rel=1e-15)
        assert out.max_error == pytest.approx(err.max(), rel=1e-15)
        assert out.relative == pytest.approx(err.max() / amplitude, rel=1e-15)
        assert out.final_error == pytest.approx(err[-1], rel=1e-15)
        assert out.rms_error == pytest.approx(np.sqrt((err ** 2).sum() / 7), rel=1e-14)
    # the vector: norms in place of absolute values
    out = node_error(ref, pred, 1)
    err = np.sqrt(((pred[:, 1] - ref[:, 1]) ** 2).sum(axis=1))
    amplitude = np.sqrt((ref[:, 1] ** 2).sum(axis=1)).max()
    assert out.component is None
    assert out.relative == pytest.approx(err.max() / amplitude, rel=1e-14)
    assert out.final_error == pytest.approx(err[-1], rel=1e-14)
    # a node that never moves has no relative error
    ref[:, 0] = 0.0
    assert node_error(ref, pred, 0, 2).relative is None
    with pytest.raises(ProblemError, match="equal shapes"):
        node_error(ref, pred[:-1], 0)
    with pytest.raises(ProblemError, match="not one of the 4 nodes"):
        node_error(ref, pred, 4)
    with pytest.raises(ProblemError, match="component"):
        node_error(ref, pred, 0, 3)
