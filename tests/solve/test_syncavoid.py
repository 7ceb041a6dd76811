import warnings
from typing import Any

import jax
import numpy as np
import pytest

import jaxsync
from jaxsync import CheckpointError, ProblemError, StabilityError
from jaxsync.pytree import pytree_dataclass, static_field
from jaxsync.solve.coupling import OraclePredictor, simulate_sync_avoiding
from jaxsync.solve.executors import PredictedPhase
from jaxsync.surrogate.training import shared_dof_layout

N_S, N_P, N_F = 5, 4, 4
N_CRI = N_S * N_P + 1 + 19  # 40
N_STEPS = N_CRI + 3 * N_S * N_F + 10  # three full refill cycles and a partial one


@pytest.fixture(scope="module")
def problem():
    return jaxsync.cantilever()


@pytest.fixture(scope="module")
def partition(problem):
    return jaxsync.partition(problem.mesh, 2)


@pytest.fixture(scope="module")
def reference(problem, partition):
    return jaxsync.simulate(problem, N_STEPS, partitions=partition)


def oracle(reference, partition, shift=0, poison_step=None, n_steps=N_STEPS):
    """Replays the synchronized run's shared displacements after N_CRI (optionally shifted
    by some steps, or with NaN from a step on)."""
    n_dof, counts = shared_dof_layout(partition)
    length = N_S * N_F
    n_cycles = -(-(n_steps - N_CRI) // length)
    future = np.zeros((partition.n_parts, n_cycles * length, n_dof))
    for p, part in enumerate(partition.parts):
        values = reference.displacement[N_CRI + 1:, part.shared_nodes].reshape(n_steps - N_CRI, -1)
        future[p, :len(values), :counts[p]] = values
    future = np.roll(future, shift, axis=1)
    if poison_step is not None:
        future[1, poison_step - N_CRI - 1:] = np.nan
    return OraclePredictor(future, first_step=N_CRI + 1, n_s=N_S, n_past=N_P, n_future=N_F)


def test_oracle_reproduces_the_synchronized_run(problem, partition, reference):
    traj = simulate_sync_avoiding(problem, N_STEPS, partitions=partition,
                                  surrogates=oracle(reference, partition), n_cri=N_CRI)
    assert traj.n_saved == N_STEPS + 1
    np.testing.assert_array_equal(traj.synchronized, np.arange(N_STEPS + 1) <= N_CRI)
    scale = np.abs(reference.displacement).max()
    assert np.abs(traj.displacement - reference.displacement).max() <= 1e-13 * scale
    # each part's own predictions are what the oracle said
    for p, part in enumerate(partition.parts):
        np.testing.assert_array_equal(
            traj.parts[p].predicted_shared_displacement,
            reference.displacement[N_CRI + 1:, part.shared_nodes].reshape(N_STEPS - N_CRI, -1))


def test_wrong_overwrite_timing_is_detected(problem, partition, reference):
    """The same oracle shifted by one step must not reproduce the run (the refill
    indexing matters)."""
    traj = simulate_sync_avoiding(problem, N_STEPS, partitions=partition,
                                  surrogates=oracle(reference, partition, shift=1), n_cri=N_CRI)
    assert np.abs(traj.displacement - reference.displacement).max() > 1e-3 * np.abs(reference.displacement).max()


def test_oracle_with_save_every_and_four_parts(problem, reference):
    part4 = jaxsync.partition(problem.mesh, 4)
    ref4 = jaxsync.simulate(problem, N_STEPS - 10, partitions=part4)
    traj = simulate_sync_avoiding(problem, N_STEPS - 10, partitions=part4, save=10,
                                  surrogates=oracle(ref4, part4, n_steps=N_STEPS - 10), n_cri=N_CRI)
    np.testing.assert_allclose(traj.displacement, ref4.displacement[::10], rtol=0,
                               atol=1e-13 * np.abs(ref4.displacement).max())
    assert traj.parts[0].predicted_shared_displacement.shape[0] == (N_STEPS - 10 - N_CRI) // 10


def test_predicted_phase_has_no_collective(problem, partition, reference):
    from jaxsync.fem import build_system, initial_state
    from jaxsync.solve.executors import DistributedRunner

    system = build_system(problem, problem.dt)
    runner = DistributedRunner(problem, system, partition, save_every=1)
    online = PredictedPhase(runner, oracle(reference, partition), save_every=1)
    n_dof, _ = shared_dof_layout(partition)
    state = runner.from_global(initial_state(problem, system))
    buffer = runner.put(np.zeros((2, N_S * N_P, n_dof)))
    text = online.lowered_text(state, buffer, 2, N_S * N_F).lower()
    for collective in ("all-reduce", "all-gather", "collective-permute", "all-to-all", "reduce-scatter"):
        assert collective not in text
    # while the synchronized program does contain one
    sync_text = runner._compiled(1).lower(runner.parts, state).compile().as_text().lower()
    assert "all-reduce" in sync_text


def test_n_cri_too_small(problem, partition, reference):
    with pytest.raises(ProblemError, match="n_cri=19 is too small"):
        simulate_sync_avoiding(problem, N_STEPS, partitions=partition,
                               surrogates=oracle(reference, partition), n_cri=N_S * N_P - 1)


def test_save_every_must_divide(problem, partition, reference):
    with pytest.raises(ProblemError, match="save_every"):
        simulate_sync_avoiding(problem, N_STEPS, partitions=partition, save=3,
                               surrogates=oracle(reference, partition), n_cri=N_CRI)


def test_nan_prediction_names_step_and_part(problem, partition, reference):
    poison = N_CRI + N_S * N_F + 7
    with pytest.raises(StabilityError, match=f"part 1 predicted NaN/Inf for step {poison}") as info:
        simulate_sync_avoiding(problem, N_STEPS, partitions=partition,
                               executor=jaxsync.HostExecutor(cycles_per_chunk=1),
                               surrogates=oracle(reference, partition, poison_step=poison), n_cri=N_CRI)
    partial = info.value.trajectory
    # every snapshot before the poisoned step is kept (steps 0 .. poison - 1), and the
    # oracle replays the synchronized run, so they are the reference's
    assert partial.n_saved == poison
    np.testing.assert_allclose(partial.displacement, reference.displacement[:poison], rtol=0,
                               atol=1e-12 * np.abs(reference.displacement).max())


def test_predicted_blow_up_stops_like_a_synchronized_divergence(problem, partition, reference):
    """Finite but absurd predictions (1e6 cm at the shared nodes from a step on) drive the
    displacement past the divergence limit: the run stops there, keeping the steps before."""
    net = oracle(reference, partition)
    jump = N_CRI + N_S * N_F + 3
    future = np.asarray(net.future).copy()
    future[:, jump - N_CRI - 1:] = 1e6
    net = OraclePredictor(future, first_step=N_CRI + 1, n_s=N_S, n_past=N_P, n_future=N_F)
    with pytest.raises(StabilityError, match=f"the predicted run diverged by step {jump}") as info:
        simulate_sync_avoiding(problem, N_STEPS, partitions=partition, surrogates=net, n_cri=N_CRI)
    partial = info.value.trajectory
    assert partial.n_saved == jump
    np.testing.assert_allclose(partial.displacement, reference.displacement[:jump], rtol=0,
                               atol=1e-12 * np.abs(reference.displacement).max())


def test_full_system_oracle_reproduces_the_reference(problem):
    from jaxsync.solve import simulate_full_system

    reference = jaxsync.simulate(problem, N_STEPS)
    n_dof = problem.mesh.n_dofs
    length = N_S * N_F
    n_cycles = -(-(N_STEPS - N_CRI) // length)
    future = np.zeros((1, n_cycles * length, n_dof))
    future[0, :N_STEPS - N_CRI] = reference.displacement[N_CRI + 1:].reshape(N_STEPS - N_CRI, -1)
    future[0, :, :3] += 1e-3  # node 0 is clamped: the network's values there are reported
    oracle_all = OraclePredictor(future, first_step=N_CRI + 1, n_s=N_S, n_past=N_P, n_future=N_F)
    traj = simulate_full_system(problem, reference, oracle_all, n_cri=N_CRI)
    assert traj.n_saved == N_STEPS + 1
    np.testing.assert_array_equal(traj.displacement[:, 1:], reference.displacement[:, 1:])
    assert traj.stats.dirichlet_max_abs_predicted == pytest.approx(1e-3)
    assert traj.synchronized.sum() == N_CRI + 1


def test_full_system_needs_one_replica_over_all_dofs(problem, partition, reference, tmp_path):
    import jax

    from jaxsync.solve import simulate_full_system
    from jaxsync.surrogate import LSTMArchitecture, SavedSurrogate
    from jaxsync.surrogate.models import init_replicas

    counts = (12, 12)
    arch = LSTMArchitecture(n_dof=12, n_hidden=4, n_layers=1, n_past=N_P, n_future=N_F)
    params = jax.tree_util.tree_map(np.asarray, init_replicas(jax.random.key(0), arch, counts))
    ckpt = SavedSurrogate(arch=arch, params=params, mean=np.zeros((2, 12), np.float32),
                          std=np.ones((2, 12), np.float32), dof_counts=counts, n_s=N_S)
    with pytest.raises(CheckpointError, match="one surrogate over all 312 dofs"):
        simulate_full_system(problem, jaxsync.simulate(problem, N_STEPS), ckpt, n_cri=N_CRI)


def test_surrogates_of_another_partition_are_refused(problem, reference):
    import jax

    from jaxsync.surrogate import LSTMArchitecture, SavedSurrogate
    from jaxsync.surrogate.models import init_replicas

    other = jaxsync.partition(problem.mesh, 4)
    counts = tuple(3 * p.n_shared for p in other.parts)
    arch = LSTMArchitecture(n_dof=max(counts), n_hidden=4, n_layers=1, n_past=N_P, n_future=N_F)
    params = jax.tree_util.tree_map(np.asarray, init_replicas(jax.random.key(0), arch, counts))
    ckpt = SavedSurrogate(arch=arch, params=params, mean=np.zeros((4, arch.n_dof), np.float32),
                          std=np.ones((4, arch.n_dof), np.float32), dof_counts=counts, n_s=N_S,
                          shared_nodes=tuple(p.shared_nodes for p in other.parts))
    with pytest.raises(CheckpointError, match="partition has 2 parts"):
        simulate_sync_avoiding(problem, N_STEPS, partitions=2, surrogates=ckpt, n_cri=N_CRI)


def test_trained_surrogates_run_online_and_metrics_are_consistent(problem, partition, long_reference):
    """Tiny replicas trained on the synchronized run drive the online solver; the error
    metrics computed from the run agree with their definitions."""
    import jax

    from jaxsync.metrics import l2_error, predictions_by_node, shared_node_errors
    from jaxsync.surrogate import (
        LSTMArchitecture,
        SavedSurrogate,
        TrainConfig,
        build_dataset,
        stack_replicas,
        train_replicas,
    )

    # the first 400 steps of the module's 1000-step synchronized run
    shared = [long_reference.parts[p].shared_displacement[:401] for p in range(2)]
    displacement = long_reference.displacement[:401]
    data = stack_replicas([build_dataset([shared[p]], N_S, N_P, N_F,
                                         train_fraction=1.0) for p in range(2)])
    arch = LSTMArchitecture(n_dof=data.n_dof_max, n_hidden=8, n_layers=1, n_past=N_P, n_future=N_F)
    result = train_replicas(data, arch, TrainConfig(n_epochs=3), jax.random.key(0), progress=False)
    ckpt = SavedSurrogate.from_result(result, N_S, [p.shared_nodes for p in partition.parts])
    online = simulate_sync_avoiding(problem, 400, partitions=partition, surrogates=ckpt, n_cri=N_CRI)
    assert np.all(np.isfinite(online.displacement))
    np.testing.assert_array_equal(online.displacement[:N_CRI + 1], displacement[:N_CRI + 1])
    predictions, holds, steps = predictions_by_node(online, partition)
    assert steps[0] == N_CRI + 1 and len(steps) == 400 - N_CRI
    errs = shared_node_errors(displacement[steps][:, partition.shared_nodes], predictions, holds)
    # the global displacement at a shared node is the mean of the parts' predictions
    node = partition.shared_nodes[0]
    np.testing.assert_allclose(online.displacement[steps, node],
                               predictions[holds[:, 0], :, 0].mean(axis=0), rtol=1e-12)
    assert np.all(errs.es >= 0) and errs.es.shape == (len(steps),)
    assert l2_error(displacement, online.displacement)[:N_CRI + 1].max() == 0.0


def untrained(partition):
    from jaxsync.surrogate import Surrogate

    return Surrogate.initialized(partition, N_S, n_hidden=4, n_layers=1, n_past=N_P,
                                          n_future=N_F, seed=3)


def test_resync_tolerance_never_reached_changes_nothing(problem, partition):
    """The monitored run (each cycle predicted, checked, then stepped) equals the fused
    unmonitored program when nothing triggers."""
    net = untrained(partition)
    plain = simulate_sync_avoiding(problem, N_STEPS, partitions=partition, surrogates=net, n_cri=N_CRI,
                                   executor=jaxsync.HostExecutor(cycles_per_chunk=1))
    watched = simulate_sync_avoiding(problem, N_STEPS, partitions=partition, surrogates=net,
                                     n_cri=N_CRI, resync_tolerance=np.inf)
    np.testing.assert_array_equal(watched.displacement, plain.displacement)
    np.testing.assert_array_equal(watched.synchronized, plain.synchronized)
    for a, b in zip(watched.parts, plain.parts):
        np.testing.assert_array_equal(a.predicted_shared_displacement, b.predicted_shared_displacement)
    assert watched.stats.resynchronized_at == ()
    assert watched.stats.n_predicted_steps == N_STEPS - N_CRI


@pytree_dataclass
class DriftingOracle:
    """The synchronized history plus a chosen perturbation path ``w`` (per part), as a
    network would err: each part continues its OWN last known value with the increments
    of reference + w, so from a synchronized history the error starts at zero, and left
    alone it follows w (a drift grows without bound; jitter is step-to-step noise like
    that of the interleaved refill sequences of a trained network)."""

    reference: Any  # (P, T, n_dof) shared dofs at steps 0 .. T - 1
    path: Any  # (P, T, n_dof) perturbation w, zero on padding
    n_s: int = static_field(default=N_S)
    n_past: int = static_field(default=N_P)
    n_future: int = static_field(default=N_F)

    def predict(self, buffer, step):
        length = self.n_s * self.n_future
        at = lambda a: jax.lax.dynamic_index_in_dim(a, step, keepdims=False)  # noqa: E731
        ahead = lambda a: jax.lax.dynamic_slice_in_dim(a, step + 1, length)  # noqa: E731
        own_error = buffer[-1] - at(self.reference) - at(self.path)
        return ahead(self.reference) + ahead(self.path) + own_error[None]


def drifting_oracle(reference, partition, drift, jitter=0.0, drift_until=None, seed=0):
    """w_p(step) = drift[p] * min(step, drift_until) on every dof + uniform jitter."""
    n_dof, counts = shared_dof_layout(partition)
    n = reference.n_saved + 2 * N_S * N_F
    values = np.zeros((partition.n_parts, n, n_dof))
    path = np.zeros_like(values)
    rng = np.random.default_rng(seed)
    steps = np.minimum(np.arange(n), n if drift_until is None else drift_until)
    for p, part in enumerate(partition.parts):
        shared = reference.parts[p].shared_displacement
        values[p, :len(shared), :counts[p]] = shared
        values[p, len(shared):, :counts[p]] = shared[-1]
        path[p, :, :counts[p]] = drift[p] * steps[:, None] + jitter * rng.uniform(-1, 1, (n, counts[p]))
    return DriftingOracle(values, path)


@pytest.fixture(scope="module")
def long_reference(problem, partition):
    return jaxsync.simulate(problem, 1000, partitions=partition)


def test_drift_beyond_the_tolerance_is_recomputed_synchronized(problem, partition, long_reference):
    """Parts drifting apart by 2e-6 cm per step, tolerance 1e-4 cm: after a synchronized
    point the first two cycles pass (es_hat up to 8e-5) and the third (1.2e-4) is rejected
    BEFORE it is used; the run goes back to the synchronized point and recomputes through
    the rejected cycle with the synchronized solver (the two accepted cycles are
    discarded: their state carries the drift). The synchronized stretches equal the
    synchronized reference to round-off, not merely a run from the same restart; the
    final stretch, never rejected, stays predicted."""
    cycle, rate, tol, n_steps = N_S * N_F, 1e-6, 1e-4, 980
    net = drifting_oracle(long_reference, partition, drift=(+rate, -rate))
    with pytest.warns(RuntimeWarning, match="only 40 of the 940 steps"):
        traj = simulate_sync_avoiding(problem, n_steps, partitions=partition, surrogates=net,
                                      n_cri=N_CRI, resync_tolerance=tol)
    st = traj.stats
    rejected = list(range(N_CRI + 2 * cycle, n_steps, 3 * cycle))  # 80, 140, ..., 920
    assert list(st.resynchronized_at) == rejected
    # es_hat of the rejected cycle: |drift_0 - drift_1| = 2e-6 cm per step, 3 cycles on
    np.testing.assert_allclose(st.es_hat_trigger, 2 * rate * 3 * cycle, rtol=1e-9)
    assert list(st.tolerance_cm) == [tol] * len(rejected)
    assert st.n_discarded_steps == 2 * cycle * len(rejected)
    steps = np.arange(n_steps + 1)
    expected = steps <= rejected[-1] + cycle
    np.testing.assert_array_equal(traj.synchronized, expected)
    assert st.n_synchronized_steps == rejected[-1] + cycle
    assert st.n_synchronized_steps + st.n_predicted_steps == n_steps
    scale = np.abs(long_reference.displacement).max()
    err = np.abs(traj.displacement - long_reference.displacement[:n_steps + 1]).max(axis=(1, 2))
    assert err[expected].max() <= 1e-12 * scale
    assert 0 < err.max() <= 2 * rate * 2 * cycle  # the accepted drift of the final stretch


def test_noisy_oracle_error_stays_bounded_by_the_tolerance(problem, partition, long_reference):
    """Jittering predictions that drift apart for 600 steps, then only jitter: without a
    tolerance the drift stays in the run (over 5x the bounded error); with one the error
    stays below a bound set by the tolerance (es_hat <= tol at every used prediction: the
    error at the shared nodes is about tol, and the parts' interiors follow them), over
    the many cycles after the last re-synchronization."""
    net = drifting_oracle(long_reference, partition, drift=(2e-6, -1e-6), jitter=2e-6, drift_until=600)

    def run(tol):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # "mostly synchronized"
            traj = simulate_sync_avoiding(problem, 1000, partitions=partition, surrogates=net,
                                          n_cri=N_CRI, resync_tolerance=tol)
        return np.abs(traj.displacement - long_reference.displacement).max(axis=(1, 2)), traj

    free, _ = run(None)
    errors = {}
    for tol in (1e-4, 3e-5):
        errors[tol], traj = run(tol)
        assert traj.stats.n_resynchronizations >= 3
        assert traj.stats.n_predicted_steps >= 300
        assert errors[tol].max() <= 2 * tol, (tol, errors[tol].max())
    assert free.max() > 5 * errors[1e-4].max()


def test_untrained_networks_fall_back_to_the_synchronized_run(problem, partition, long_reference):
    """Untrained networks disagree at once: every cycle right after a synchronized point is
    rejected, the synchronized stretch doubles each time (1, 2, 4 cycles...), the run is
    the synchronized one to round-off, and the user is warned."""
    with pytest.warns(RuntimeWarning, match="only 0 of the"):
        traj = simulate_sync_avoiding(problem, 400, partitions=partition, surrogates=untrained(partition),
                                      n_cri=N_CRI, resync_tolerance=1e-12)
    cycle = N_S * N_F
    assert list(traj.stats.resynchronized_at) == [N_CRI, N_CRI + 2 * cycle, N_CRI + 6 * cycle,
                                                    N_CRI + 14 * cycle]
    assert traj.synchronized.all() and traj.stats.n_predicted_steps == 0
    assert traj.stats.n_discarded_steps == 0
    scale = np.abs(long_reference.displacement).max()
    assert np.abs(traj.displacement - long_reference.displacement[:401]).max() <= 1e-12 * scale


def test_tolerance_relative_to_the_amplitude(problem, partition, long_reference):
    """'2%' is 2 % of the largest shared-node |displacement| seen in the synchronized steps
    so far (the load ramps up, so the tolerance grows as the run goes on)."""
    from jaxsync.solve import ResyncTolerance

    net = drifting_oracle(long_reference, partition, drift=(+1e-6, -1e-6))
    with pytest.warns(RuntimeWarning):
        traj = simulate_sync_avoiding(problem, 1000, partitions=partition, surrogates=net,
                                      n_cri=N_CRI, resync_tolerance="2%")
    st = traj.stats
    assert st.resync_tolerance == "2 %" and st.n_resynchronizations >= 3
    for step, tol in zip(st.resynchronized_at, st.tolerance_cm):
        # here every rejection comes right after a synchronized stretch ending at `step`
        seen = max(np.abs(part.shared_displacement[:step + 1]).max() for part in long_reference.parts)
        assert tol == pytest.approx(0.02 * seen, rel=1e-12)
    assert list(st.tolerance_cm) == sorted(st.tolerance_cm) and st.tolerance_cm[-1] > st.tolerance_cm[0]
    assert ResyncTolerance.parse("1e-4") == ResyncTolerance(absolute=1e-4)
    assert ResyncTolerance.parse(2e-4).cm(5.0) == 2e-4
    assert ResyncTolerance.parse("5%").cm(2.0) == pytest.approx(0.1)
    assert ResyncTolerance.parse("100%").cm(2.0) == pytest.approx(2.0)
    for bad, match in (("200%", "above 100%"), ("inf%", "above 100%"), ("nan%", "> 0"), ("-1%", "> 0")):
        with pytest.raises(ProblemError, match=match):
            ResyncTolerance.parse(bad)


def test_tolerance_relative_to_a_given_amplitude(problem, partition, long_reference):
    """ResyncTolerance(relative=, amplitude=A): the tolerance is that fraction of A at every
    check, whatever the run has seen (a ramped load's early amplitude is small)."""
    from jaxsync.solve import ResyncTolerance

    amplitude = max(np.abs(part.shared_displacement[:1001]).max() for part in long_reference.parts)
    tolerance = ResyncTolerance(relative=0.02, amplitude=float(amplitude))
    assert tolerance.cm(1e-9) == pytest.approx(0.02 * amplitude, rel=1e-12)
    net = drifting_oracle(long_reference, partition, drift=(+1e-6, -1e-6))
    with pytest.warns(RuntimeWarning):
        traj = simulate_sync_avoiding(problem, 1000, partitions=partition, surrogates=net,
                                      n_cri=N_CRI, resync_tolerance=tolerance)
    st = traj.stats
    assert st.resync_tolerance == f"2 % of {amplitude:.4g} cm" and st.n_resynchronizations >= 1
    assert all(tol == pytest.approx(0.02 * amplitude, rel=1e-12) for tol in st.tolerance_cm)
    for bad in (dict(absolute=1e-4, amplitude=1.0), dict(relative=0.01, amplitude=-1.0),
                dict(relative=0.01, amplitude=float("nan"))):
        with pytest.raises(ProblemError, match="amplitude"):
            ResyncTolerance(**bad)


def test_resync_tolerance_is_checked(problem, partition, reference):
    for bad in (0.0, -1.0, float("nan"), "small", "-2%", True):
        with pytest.raises(ProblemError, match="resync_tolerance"):
            simulate_sync_avoiding(problem, N_STEPS, partitions=partition, surrogates=untrained(partition),
                                   n_cri=N_CRI, resync_tolerance=bad)
    from jaxsync.solve import ResyncTolerance

    with pytest.raises(ProblemError, match="OraclePredictor"):  # es_hat of an oracle is zero
        simulate_sync_avoiding(problem, N_STEPS, partitions=partition, surrogates=oracle(reference, partition),
                               n_cri=N_CRI, resync_tolerance=ResyncTolerance(absolute=1e-3, indicator="es_hat"))


def test_float32_mode_is_refused(problem, partition, reference):
    import jax

    jax.config.update("jax_enable_x64", False)
    try:
        with pytest.raises(jaxsync.PrecisionError, match="jax_enable_x64"):
            simulate_sync_avoiding(problem, N_STEPS, partitions=partition,
                                   surrogates=oracle(reference, partition), n_cri=N_CRI)
        with pytest.raises(jaxsync.PrecisionError, match="jax_enable_x64"):
            jaxsync.simulate(problem, 10)
    finally:
        jax.config.update("jax_enable_x64", True)


@pytest.fixture(scope="module")
def briefly_trained(problem, partition):
    """Replicas trained for a few seconds on a 4000-step synchronized run (n_s 20,
    n_p = n_f = 10): a surrogate that errs by a few % of the amplitude, as a user's
    under-trained network would."""
    from jaxsync.surrogate import (
        LSTMArchitecture,
        SavedSurrogate,
        TrainConfig,
        build_dataset,
        stack_replicas,
        train_replicas,
    )

    reference = jaxsync.simulate(problem, 4000, partitions=partition)
    data = stack_replicas([build_dataset([reference.parts[p].shared_displacement], 20, 10, 10)
                           for p in range(2)])
    arch = LSTMArchitecture(n_dof=data.n_dof_max, n_hidden=16, n_layers=1, n_past=10, n_future=10)
    result = train_replicas(data, arch, TrainConfig(n_epochs=30, eta0=3e-3, gamma=0.98),
                            jax.random.key(0), progress=False)
    return reference, SavedSurrogate.from_result(result, 20, [p.shared_nodes for p in partition.parts])


def test_a_tolerance_never_makes_a_trained_run_worse(problem, partition, briefly_trained):
    """Against the synchronized reference: every tolerance gives an error no larger than
    the run without one, and a tight one gives the synchronized run (round-off)."""
    reference, ckpt = briefly_trained

    def max_error(tol):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            traj = simulate_sync_avoiding(problem, 4000, partitions=partition, surrogates=ckpt,
                                          n_cri=200, resync_tolerance=tol)
        return np.abs(traj.displacement - reference.displacement).max(), traj.stats

    free, _ = max_error(None)
    assert free > 1e-4  # the network is far from perfect
    for tol in (1e-3, 1e-4):
        error, _ = max_error(tol)
        assert error <= free * (1 + 1e-9), (tol, error, free)
    tight, stats = max_error(1e-8)
    assert tight <= 1e-12 * np.abs(reference.displacement).max()
    assert stats.n_predicted_steps == 0 and stats.n_synchronized_steps == 4000


@pytest.mark.slow
def test_demo_surrogate_error_control(problem, partition):
    """The demo's case and training (n_s 80, n_p = n_f = 20, n_H 32, 300 epochs, 1e5 steps):
    against the synchronized reference, no tolerance makes the run worse than none, and a
    tight one gives the synchronized run. (The issue's report: 1e-4 cm gave 3.0 cm, 1700x
    worse.)"""
    from jaxsync.surrogate import (
        LSTMArchitecture,
        SavedSurrogate,
        TrainConfig,
        build_dataset,
        stack_replicas,
        train_replicas,
    )

    reference = jaxsync.simulate(problem, 100_000, partitions=partition, save=jaxsync.SaveAt(80, 1))
    data = stack_replicas([build_dataset([p.shared_displacement], 80, 20, 20) for p in reference.parts])
    arch = LSTMArchitecture(n_dof=data.n_dof_max, n_hidden=32, n_past=20, n_future=20)
    result = train_replicas(data, arch, TrainConfig(), jax.random.key(0), progress=False)
    ckpt = SavedSurrogate.from_result(result, 80, [p.shared_nodes for p in partition.parts])

    def max_error(tol):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            traj = simulate_sync_avoiding(problem, 100_000, partitions=partition, surrogates=ckpt,
                                          n_cri=1600, save=80, resync_tolerance=tol)
        return np.abs(traj.displacement - reference.displacement).max()

    free = max_error(None)
    scale = np.abs(reference.displacement).max()
    assert free < 0.05 * scale
    for tol in (1e-2, 1e-3, 1e-4, "1%", "0.1%"):
        assert max_error(tol) <= free * (1 + 1e-9), tol
    assert max_error(1e-7) <= 1e-12 * scale


def test_a_conditional_surrogate_takes_the_load_parameter_given_to_the_run(problem, partition, reference):
    """A Surrogate object (not only a checkpoint) is conditioned on the run's load
    parameter: the run equals the checkpoint's at that value and differs from the run at
    the value it was built with; unconditional replicas refuse a value."""
    import dataclasses

    import jax

    from jaxsync.surrogate import LSTMArchitecture, SavedSurrogate, Surrogate
    from jaxsync.surrogate.models import init_replicas

    n_dof, counts = shared_dof_layout(partition)
    arch = LSTMArchitecture(n_dof=n_dof, n_hidden=4, n_layers=1, n_past=N_P, n_future=N_F, n_cond_repeat=2)
    params = jax.tree_util.tree_map(np.asarray, init_replicas(jax.random.key(1), arch, tuple(counts)))
    scale = np.full((2, n_dof), 1e-3)
    ckpt = SavedSurrogate(params=params, arch=arch, mean=np.zeros((2, n_dof)), std=scale, n_s=N_S,
                          dof_counts=tuple(int(c) for c in counts),
                          shared_nodes=tuple(p.shared_nodes for p in partition.parts))
    built_at_one = Surrogate.from_saved(ckpt, 1.0)
    at_03 = {"object": built_at_one.with_load_parameter(0.3), "checkpoint": Surrogate.from_saved(ckpt, 0.3),
             "own": built_at_one}
    runs = {name: simulate_sync_avoiding(problem, N_STEPS, partitions=partition, surrogates=s, n_cri=N_CRI)
            for name, s in at_03.items()}
    np.testing.assert_array_equal(runs["object"].displacement, runs["checkpoint"].displacement)
    assert not np.array_equal(runs["object"].displacement, runs["own"].displacement)
    plain = dataclasses.replace(built_at_one, arch=dataclasses.replace(arch, n_cond_repeat=0))
    with pytest.raises(CheckpointError, match="unconditional"):
        simulate_sync_avoiding(problem, N_STEPS, partitions=partition, surrogates=plain.with_load_parameter(0.3),
                               n_cri=N_CRI)


# --------------------------------------------------------------------------- load jumps

def _step_off(problem, jump_step: int):
    """The cantilever with its load switched off between steps jump_step - 1 and jump_step
    (the body force time function is evaluated at t_n = n dt)."""
    return jaxsync.cantilever(problem.mesh, t_off=(jump_step - 0.5) * problem.dt)


# the default run keeps the saved-every-10 case; the jump at 51 saved every step is also read
# in the default run by test_an_oracle_of_the_unswitched_run_is_only_used_after_the_jump (the
# run synchronized up to n_cri = 70) and test_load_jumps_policy_is_checked_and_saved
@pytest.mark.parametrize("jump, save_every, expected_n_cri",
                         [pytest.param(51, 1, 70, marks=pytest.mark.slow), (53, 10, 80)])
def test_load_jump_keeps_the_run_synchronized_through_it(problem, partition, jump, save_every, expected_n_cri):
    """The first synchronized stretch ends at the first saved step from which the
    networks' n_p n_s input steps all follow the jump (jump + n_p n_s - 1, rounded up to a
    saved step); until then the run is the synchronized one, after it the predictions are
    used (an oracle of the step-off run, so the whole run still equals it)."""
    stepped = _step_off(problem, jump)
    g = np.asarray(stepped.loads[0].time(np.arange(N_STEPS + 1) * problem.dt))
    assert np.argmax(np.abs(np.diff(g))) + 1 == jump  # the test's own reading of the schedule
    assert expected_n_cri == -(-(jump + N_S * N_P - 1) // save_every) * save_every
    ref = jaxsync.simulate(stepped, N_STEPS, partitions=partition)
    traj = simulate_sync_avoiding(stepped, N_STEPS, partitions=partition, save=save_every,
                                  surrogates=oracle(ref, partition), n_cri=N_CRI)
    assert traj.stats.n_cri == expected_n_cri and traj.stats.load_jumps == (jump,)
    assert traj.parameters["last_load_jump"] == jump  # the whole run's, not only its first stretch's
    assert traj.stats.n_synchronized_steps == expected_n_cri
    assert traj.stats.n_predicted_steps == N_STEPS - expected_n_cri
    np.testing.assert_array_equal(traj.synchronized, np.arange(0, N_STEPS + 1, save_every) <= expected_n_cri)
    np.testing.assert_allclose(traj.displacement, ref.displacement[::save_every], rtol=0,
                               atol=1e-13 * np.abs(ref.displacement).max())
    assert "synchronized through the load jump at step" in jaxsync.solve.coupling.describe_run(traj)
    # the paper's way: predicted from N_CRI on, straight through the jump
    through = simulate_sync_avoiding(stepped, N_STEPS, partitions=partition, save=save_every,
                                     surrogates=oracle(ref, partition), n_cri=N_CRI, load_jumps="predict")
    assert through.stats.n_cri == N_CRI and through.stats.load_jumps is None
    assert through.stats.n_synchronized_steps == N_CRI


def test_an_oracle_of_the_unswitched_run_is_only_used_after_the_jump(problem, partition):
    """A predictor that cannot know of the jump (it replays the run whose load stays on):
    synchronized through the jump, the run equals the step-off run up to the new n_cri and
    only departs from it afterwards; predicting through it departs right after N_CRI."""
    jump = 51
    stepped = _step_off(problem, jump)
    ref = jaxsync.simulate(stepped, N_STEPS, partitions=partition)
    blind = oracle(jaxsync.simulate(problem, N_STEPS, partitions=partition), partition)
    scale = np.abs(ref.displacement).max()
    kept = simulate_sync_avoiding(stepped, N_STEPS, partitions=partition, surrogates=blind, n_cri=N_CRI)
    err = np.abs(kept.displacement - ref.displacement).max(axis=(1, 2))
    assert err[:71].max() <= 1e-13 * scale and err[72:].max() > 1e-6 * scale
    through = simulate_sync_avoiding(stepped, N_STEPS, partitions=partition, surrogates=blind, n_cri=N_CRI,
                                     load_jumps="predict")
    before = slice(N_CRI + 2, jump + 1)  # the two runs' loads agree up to the jump
    assert np.abs(through.displacement[before] - ref.displacement[before]).max() <= 1e-13 * scale
    assert np.abs(through.displacement[jump + 2:] - ref.displacement[jump + 2:]).max() > 1e-6 * scale


def test_a_jump_near_the_end_keeps_the_whole_run_synchronized(problem, partition, reference):
    stepped = _step_off(problem, N_STEPS - 5)
    ref = jaxsync.simulate(stepped, N_STEPS, partitions=partition)
    with pytest.warns(RuntimeWarning, match="stays synchronized"):
        traj = simulate_sync_avoiding(stepped, N_STEPS, partitions=partition,
                                      surrogates=oracle(reference, partition, shift=3), n_cri=N_CRI)
    assert traj.stats.n_cri == N_STEPS and traj.stats.n_predicted_steps == 0 and traj.synchronized.all()
    np.testing.assert_allclose(traj.displacement, ref.displacement, rtol=0, atol=1e-13 * np.abs(ref.displacement).max())


def test_load_jumps_policy_is_checked_and_saved(problem, partition, reference, tmp_path):
    with pytest.raises(ProblemError, match="load_jumps='sometimes'.*synchronize"):
        simulate_sync_avoiding(problem, N_STEPS, partitions=partition, surrogates=oracle(reference, partition),
                               n_cri=N_CRI, load_jumps="sometimes")
    traj = simulate_sync_avoiding(problem, N_STEPS, partitions=partition, surrogates=oracle(reference, partition),
                                  n_cri=N_CRI)
    assert traj.stats.load_jumps == () and traj.stats.n_cri == N_CRI  # the ramp never jumps
    traj.save(tmp_path / "a.h5")
    assert jaxsync.Trajectory.load(tmp_path / "a.h5").stats.load_jumps == ()
    stepped = _step_off(problem, 51)
    ref = jaxsync.simulate(stepped, N_STEPS, partitions=partition)
    jumped = simulate_sync_avoiding(stepped, N_STEPS, partitions=partition, surrogates=oracle(ref, partition),
                                    n_cri=N_CRI)
    jumped.save(tmp_path / "b.h5")
    assert jaxsync.Trajectory.load(tmp_path / "b.h5").stats.load_jumps == (51,)
