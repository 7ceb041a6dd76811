"""Learning while synchronized (jaxsync.surrogate.training.OnlineLearning): the windows cut from recomputed
steps, the least-squares refit of the linear model, the gradient update of the LSTM, and
the synchronization-avoiding run that learns after every rejected cycle."""

import warnings

import jax
import numpy as np
import pytest

import jaxsync
from jaxsync import ProblemError
from jaxsync.errors import ConfigError
from jaxsync.solve import ResyncTolerance, simulate_sync_avoiding
from jaxsync.solve.coupling import OraclePredictor
from jaxsync.surrogate import (
    ArchitectureChoice,
    Sampling,
    TrainConfig,
    TrainingChecks,
    refill_input_steps,
    refill_target_steps,
    train_surrogates,
)
from jaxsync.surrogate.models import fit_linear
from jaxsync.surrogate.training import (
    OnlineLearner,
    OnlineLearning,
    sample_refill_windows,
    solve_least_squares,
    window_starts,
)

N_STEPS = 4000
N_S, N_P, N_F = 20, 10, 10


@pytest.fixture(scope="module")
def problem():
    return jaxsync.cantilever()


@pytest.fixture(scope="module")
def partition(problem):
    return jaxsync.partition(problem.mesh, 2)


@pytest.fixture(scope="module")
def reference(problem, partition):
    return jaxsync.simulate(problem, N_STEPS, partitions=partition)


def _trained(reference, model):
    """A brief training, one candidate per part, without the offline checks (E_mse, the
    rollout): these tests check the updates, not the first training."""
    return train_surrogates(reference, architecture=ArchitectureChoice(model=model, n_hidden=16, n_layers=1),
                            sampling=Sampling(n_s=N_S, n_past=N_P, n_future=N_F),
                            optimizer=TrainConfig(n_epochs=20, eta0=3e-3, gamma=0.98, n_candidates=1),
                            checks=TrainingChecks(emse_applications=0, rollout_tolerance=None),
                            progress=False).surrogate


@pytest.fixture(scope="module")
def linear(reference, problem):
    return _trained(reference, "linear").for_problem(problem)


@pytest.fixture(scope="module")
def lstm(reference, problem):
    return _trained(reference, "lstm").for_problem(problem)


def shared_rows(reference, first, last):
    """Per part, the shared values of steps first .. last - 1."""
    return [p.shared_displacement[first:last] for p in reference.parts]


def test_windows_are_the_refill_index_sets():
    """Window c's inputs and targets are the rows of refill application i at step n with
    c = n + 1 + i - n_s (paper Algorithm 3's N_p^i and N_f^i)."""
    rows = np.random.default_rng(0).normal(size=(300, 4))
    n_s, n_p, n_f = 5, 4, 3
    starts = window_starts(len(rows), n_s, n_p, n_f, per_stride=5)
    assert starts.min() == n_s * (n_p - 1) and starts.max() == len(rows) - n_s * n_f - 1
    assert np.all(np.diff(starts) == 1)
    x, y = sample_refill_windows(rows, n_s, n_p, n_f, starts)
    checked = 0
    for w, c in enumerate(starts):
        for i in range(n_s):
            n = c - 1 - i + n_s  # the refill step whose application i ends its inputs at row c
            if n + 1 < n_s * n_p or n + n_s * n_f >= len(rows):
                continue
            assert refill_input_steps(n, n_s, n_p, i)[-1] == c
            np.testing.assert_array_equal(x[w], rows[refill_input_steps(n, n_s, n_p, i)])
            np.testing.assert_array_equal(y[w], rows[refill_target_steps(n, n_s, n_f, i)])
            checked += 1
    assert checked >= len(starts)
    with pytest.raises(ConfigError, match="window starts"):
        sample_refill_windows(rows, n_s, n_p, n_f, np.array([len(rows) - 1]))
    thinned = window_starts(len(rows), n_s, n_p, n_f, per_stride=1, count=7)
    assert len(thinned) == 7 and thinned[-1] == starts[-1]  # the newest window kept


def test_weighted_least_squares_against_numpy():
    """The weighted fit equals NumPy's lstsq on the rows scaled by sqrt(w) (intercept as a
    column of ones); zero-weight rows drop out; max_rank keeps the leading directions."""
    rng = np.random.default_rng(1)
    x, y = rng.normal(size=(40, 6)), rng.normal(size=(40, 3))
    w = rng.uniform(0.2, 2.0, 40)
    w[:5] = 0.0
    w_in, w_out, b = solve_least_squares(x, y, regularization=0.0, weight=w)
    design = np.sqrt(w)[:, None] * np.concatenate([x, np.ones((40, 1))], axis=1)
    coef = np.linalg.lstsq(design, np.sqrt(w)[:, None] * y, rcond=None)[0]
    np.testing.assert_allclose(w_in @ w_out, coef[:6], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(b, coef[6], rtol=1e-10, atol=1e-12)
    # truncated to 2 directions: the rank-2 truncated SVD solution of the weighted, centred problem
    w_in2, w_out2, b2 = solve_least_squares(x, y, regularization=0.0, weight=w, max_rank=2)
    assert w_in2.shape == (6, 2)
    p = w / w.sum()
    xc, yc = x - p @ x, y - p @ y
    u, s, vt = np.linalg.svd(np.sqrt(p)[:, None] * xc, full_matrices=False)
    expected = vt[:2].T @ np.diag(1 / s[:2]) @ u[:, :2].T @ (np.sqrt(p)[:, None] * yc)
    np.testing.assert_allclose(w_in2 @ w_out2, expected, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(b2, p @ y - (p @ x) @ expected, rtol=1e-10, atol=1e-12)


def test_settings_are_checked():
    for bad in ({"iterations": 0}, {"learning_rate": -1.0}, {"budget_seconds": 0}, {"windows": 2.5},
                {"new_weight": 1.5}, {"replay": -1}, {"starts_per_stride": True}, {"save_to": 3},
                {"save_to": "/no/such/folder/learned.h5"}):
        with pytest.raises(ConfigError, match=next(iter(bad))):
            OnlineLearning(**bad)
    with pytest.raises(ConfigError, match="create it first"):
        OnlineLearning(save_to="/no/such/folder/learned.h5")
    assert OnlineLearning.parse(True) == OnlineLearning() and OnlineLearning.parse(False) is None
    with pytest.raises(ConfigError, match="learning"):
        OnlineLearning.parse("yes")


def _future_error(predictor, reference, first, n_steps):
    """RMS error [cm] of one refill per window over steps first .. first + n_steps against
    the synchronized run (the truth), every part."""
    out = []
    for c in range(first, first + n_steps - N_S * N_F, N_S * N_F):
        for p in range(predictor.n_parts):
            part = predictor.part(p)
            hist = reference.parts[p].shared_displacement
            width = hist.shape[1]
            buffer = np.zeros((N_S * N_P, part.n_dof))
            buffer[:, :width] = hist[c - N_S * N_P + 1:c + 1]
            pred = np.asarray(part.predict(buffer, c))[:, :width]
            out.append(pred - hist[c + 1:c + 1 + N_S * N_F])
    return float(np.sqrt(np.mean(np.square(out))))


def test_the_linear_refit_is_the_least_squares_fit_of_every_window_seen(linear, reference):
    """A closed-form model's update corrects its first fit: it replays every chained window
    of the first synchronized stretch (one per stride, not the gradient models' sample),
    weighs them like the new windows, and the refit IS the least-squares fit of their
    union -- the same map as fit_linear on the same windows -- with a lower error on the
    new windows and no higher error on the steps after them than before (the truth: the
    synchronized run)."""
    replay = shared_rows(reference, 0, 981)  # a union within the surrogate's rank: no direction truncated
    learner = OnlineLearner(OnlineLearning(windows=1000, starts_per_stride=1), linear, replay)
    n_replay = len(window_starts(981, N_S, N_P, N_F, 1))
    first, last = 2000, 3000
    rows = shared_rows(reference, first, last)
    added = learner.add_stretch(rows, first)
    assert added == ((last - first - N_S * N_F - 1) - N_S * (N_P - 1)) // N_S + 1  # one per stride
    updated = learner.update(last - 1)
    report = learner.reports[-1]
    assert report.n_new == added and report.iterations == 1
    assert np.all(report.loss_after < report.loss_before)
    before = _future_error(linear, reference, last, 800)
    after = _future_error(updated, reference, last, 800)
    assert after < 1.05 * before, (before, after)
    # fit_linear on the union, normalized like the surrogate's windows, gives the same predictions
    x, y, u, _ = learner.every_window()
    assert x.shape[1] == added + n_replay
    from jaxsync.surrogate.training import ReplicaData

    stacked = ReplicaData(x_train=x, y_train=y, load_parameter_train=np.zeros(x.shape[:2]),
                          x_val=x[:, :0], y_val=y[:, :0], load_parameter_val=np.zeros((x.shape[0], 0)),
                          dof_mask=np.asarray(linear.dof_mask), dof_counts=linear.dof_counts,
                          mean=np.asarray(linear.mean), std=np.asarray(linear.std),
                          signal_train=u, signal_val=None if u is None else u[:, :0],
                          signal_scale=None if u is None else np.asarray(linear.signal_scale),
                          load_inputs=linear.load_inputs)
    direct = fit_linear(stacked, dtype=linear.arch.dtype)
    assert direct.arch.rank <= linear.arch.rank  # no direction truncated: the same map
    from jaxsync.surrogate.models import forward

    for p in range(linear.n_parts):
        one = jax.tree_util.tree_map(lambda a: a[p], updated.params)
        ref = jax.tree_util.tree_map(lambda a: a[p], direct.params)
        for w in (0, added // 2, added - 1, x.shape[1] - 1):
            ua = None if u is None else u[p, w]
            mine = np.asarray(forward(one, linear.arch, x[p, w], None, linear.dof_mask[p], None, ua))
            theirs = np.asarray(forward(ref, direct.arch, x[p, w], None, linear.dof_mask[p], None, ua))
            np.testing.assert_allclose(mine, theirs, rtol=1e-3, atol=1e-3 * np.abs(theirs).max())


def test_the_lstm_update_lowers_the_error_on_the_steps_after(lstm, reference):
    """Adam steps on a recomputed stretch (with replayed windows of the first half) lower
    the refill error on the steps that follow it, against the synchronized run; a part
    whose loss would rise keeps its weights."""
    replay = shared_rows(reference, 0, 2001)
    # every iteration, however loaded the machine (the budget is test_the_budget_bounds_the_update_time's)
    learner = OnlineLearner(OnlineLearning(iterations=60, learning_rate=3e-3, budget_seconds=3600.0), lstm, replay)
    first, last = 2400, 3200
    learner.add_stretch(shared_rows(reference, first, last), first)
    updated = learner.update(last - 1)
    report = learner.reports[-1]
    assert report.n_replay > 0 and report.iterations == 60
    assert np.all(report.loss_after <= report.loss_before) and np.any(report.loss_after < 0.8 * report.loss_before)
    before = _future_error(lstm, reference, last, 800)
    after = _future_error(updated, reference, last, 800)
    assert after < before, (before, after)


def test_the_budget_bounds_the_update_time(lstm, reference):
    learner = OnlineLearner(OnlineLearning(iterations=10_000, iterations_per_call=5, budget_seconds=1e-3), lstm)
    learner.add_stretch(shared_rows(reference, 2400, 3200), 2400)
    learner.update(3199)
    assert learner.reports[-1].iterations == 5 and learner.exhausted
    assert learner.update(3300) is learner.predictor and len(learner.reports) == 1  # no update after it


def test_a_run_learns_after_every_rejected_cycle_and_stays_within_the_tolerance(problem, partition, reference,
                                                                                   linear):
    """Every re-synchronized stretch is followed by an update (at its last step); the run
    is still held to its tolerance against the synchronized run, and its statistics say
    what was learned, also through a saved file."""
    tol = 2e-4
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        traj = simulate_sync_avoiding(problem, N_STEPS, partitions=partition, surrogates=linear, n_cri=2000,
                                      resync_tolerance=ResyncTolerance(absolute=tol, learning=True))
    st = traj.stats
    assert st.n_resynchronizations >= 1
    ends = [min(at + N_S * N_F, N_STEPS) for at in st.resynchronized_at]  # the first try after each anchor
    assert len(st.surrogate_updated_at) == st.n_resynchronizations
    assert set(st.surrogate_updated_at) <= set(range(2000, N_STEPS + 1))
    assert st.surrogate_updated_at[0] >= ends[0] and st.seconds_updating > 0
    error = np.linalg.norm(traj.displacement - reference.displacement, axis=2).max()
    assert error <= 1.2 * tol
    assert "surrogate update" in jaxsync.solve.coupling.describe_run(traj)


def test_learning_needs_weights_and_is_said_in_the_tolerance(problem, partition, linear):
    oracle = OraclePredictor(np.zeros((2, 10, linear.n_dof)), 0, N_S, N_P, N_F)
    with pytest.raises(ProblemError, match="no weights"):
        simulate_sync_avoiding(problem, 2400, partitions=partition, surrogates=oracle, n_cri=2000,
                               resync_tolerance=ResyncTolerance(absolute=1e-4, learning=True))
    with pytest.raises(ProblemError, match="learning"):
        ResyncTolerance(absolute=1e-4, learning="yes")
    assert str(ResyncTolerance(relative=0.01, learning=OnlineLearning(budget_seconds=5))) == "1 % + learning"
    assert str(ResyncTolerance(relative=0.01, learning=False)) == "1 %"


# slow (66 s of the default run's worker time): the default run keeps the same path -- a
# synchronization-avoiding run with the linear surrogate that learns after every rejected
# cycle -- on the cantilever (test_a_run_learns_after_every_rejected_cycle_and_stays_within_the_tolerance)
# and from the command line (test_cli_pipeline.py::test_predict_learns_after_every_rejected_cycle)
@pytest.mark.slow
def test_on_a_reduced_vessel_the_updates_turn_rejected_cycles_into_predicted_ones():
    """The generated coronary tree (3300 tets, three parts, the paper's pulsatile pressure
    ramping up), the load-aware linear surrogate fitted on the first quarter, error control
    at 3 % of the run's shared amplitude: without learning the run predicts nothing of the
    3000 steps after n_cri (every cycle it tries beyond the pressure it was fitted under
    is rejected); learning from the recomputed steps (its first fit corrected by them), it
    predicts most of them after one rejection and one update, and the error against the
    synchronized run stays within the tolerance."""
    from jaxsync.app.demo import vessel_problem

    problem = vessel_problem(3300)[1]
    partition = jaxsync.partition(problem.mesh, 3, seed=0)
    n_steps, n_cri = 4000, 1000
    reference = jaxsync.simulate(problem, n_steps, partitions=partition, save=jaxsync.SaveAt(10, 1))
    # the fit without the offline checks (E_mse, the rollout): they measure it, they do not change it
    net = train_surrogates(reference, architecture=ArchitectureChoice(model="linear"),
                           sampling=Sampling(n_s=10, n_past=10, n_future=10, train_fraction=n_cri / n_steps),
                           checks=TrainingChecks(emse_applications=0, rollout_tolerance=None),
                           progress=False).surrogate
    amplitude = max(float(np.abs(p.shared_displacement).max()) for p in reference.parts)
    runs = {}
    for learn in (False, True):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "mostly synchronized"
            tolerance = ResyncTolerance(relative=0.03, amplitude=amplitude, learning=learn)
            runs[learn] = simulate_sync_avoiding(problem, n_steps, partitions=partition, surrogates=net,
                                                 n_cri=n_cri, save=10, resync_tolerance=tolerance)
    blind, learning = runs[False].stats, runs[True].stats
    assert blind.n_resynchronizations >= 2 and blind.n_predicted_steps <= 500, blind.n_predicted_steps
    assert 1 <= learning.n_resynchronizations < blind.n_resynchronizations
    assert len(learning.surrogate_updated_at) == learning.n_resynchronizations
    assert learning.n_predicted_steps >= blind.n_predicted_steps + 1500, (blind.n_predicted_steps,
                                                                          learning.n_predicted_steps)
    # the predicted steps follow the last update, and are held to the tolerance
    assert learning.n_predicted_steps <= n_steps - learning.surrogate_updated_at[-1]
    error = np.linalg.norm(runs[True].displacement - reference.displacement, axis=2).max()
    assert error <= 0.03 * amplitude, (error, 0.03 * amplitude)
