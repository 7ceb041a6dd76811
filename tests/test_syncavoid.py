import numpy as np
import pytest

import jaxsync
from jaxsync import CheckpointError, ProblemError, StabilityError
from jaxsync.syncavoid import OraclePredictor, _OnlineRunner, shared_dof_layout, simulate_sync_avoiding

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
    return OraclePredictor(future, n_s=N_S, n_past=N_P, n_future=N_F)


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
            traj.parts[p]["predicted_shared_displacement"],
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
    traj = simulate_sync_avoiding(problem, N_STEPS - 10, partitions=part4, save_every=10,
                                  surrogates=oracle(ref4, part4, n_steps=N_STEPS - 10), n_cri=N_CRI)
    np.testing.assert_allclose(traj.displacement, ref4.displacement[::10], rtol=0,
                               atol=1e-13 * np.abs(ref4.displacement).max())
    assert traj.parts[0]["predicted_shared_displacement"].shape[0] == (N_STEPS - 10 - N_CRI) // 10


def test_predicted_phase_has_no_collective(problem, partition, reference):
    from jaxsync.distributed import DistributedRunner
    from jaxsync.solver import build_system

    system = build_system(problem, problem.dt)
    runner = DistributedRunner(problem, system, partition, save_every=1)
    online = _OnlineRunner(runner, oracle(reference, partition), save_every=1)
    n_dof, _ = shared_dof_layout(partition)
    state = runner.from_global(jaxsync.solver.initial_state(problem, system))
    buffer = runner._put(np.zeros((2, N_S * N_P, n_dof)))
    text = online.lowered_text(state, buffer, 2, N_S * N_F).lower()
    for collective in ("all-reduce", "all-gather", "collective-permute", "all-to-all", "reduce-scatter"):
        assert collective not in text
    # while the synchronized program does contain one
    sync_text = runner._compiled(1).lower(runner.parts, state).compile().as_text().lower()
    assert "all-reduce" in sync_text


def test_n_cri_too_small(problem, partition, reference):
    with pytest.raises(ProblemError, match="n_cri=20 is too small"):
        simulate_sync_avoiding(problem, N_STEPS, partitions=partition,
                               surrogates=oracle(reference, partition), n_cri=N_S * N_P)


def test_save_every_must_divide(problem, partition, reference):
    with pytest.raises(ProblemError, match="save_every"):
        simulate_sync_avoiding(problem, N_STEPS, partitions=partition, save_every=3,
                               surrogates=oracle(reference, partition), n_cri=N_CRI)


def test_nan_prediction_names_step_and_part(problem, partition, reference):
    poison = N_CRI + N_S * N_F + 7
    with pytest.raises(StabilityError, match=f"part 1 predicted NaN/Inf for step {poison}") as info:
        simulate_sync_avoiding(problem, N_STEPS, partitions=partition, cycles_per_chunk=1,
                               surrogates=oracle(reference, partition, poison_step=poison),
                               n_cri=N_CRI)
    partial = info.value.trajectory
    # the synchronized part and the first (clean) cycle are kept
    assert partial.n_saved == N_CRI + 1 + N_S * N_F
    assert np.all(np.isfinite(partial.displacement))


def test_full_system_oracle_reproduces_the_reference(problem):
    from jaxsync.syncavoid import simulate_full_system

    reference = jaxsync.simulate(problem, N_STEPS)
    n_dof = problem.mesh.n_dofs
    length = N_S * N_F
    n_cycles = -(-(N_STEPS - N_CRI) // length)
    future = np.zeros((1, n_cycles * length, n_dof))
    future[0, :N_STEPS - N_CRI] = reference.displacement[N_CRI + 1:].reshape(N_STEPS - N_CRI, -1)
    future[0, :, :3] += 1e-3  # node 0 is clamped: the network's values there are reported
    oracle_all = OraclePredictor(future, n_s=N_S, n_past=N_P, n_future=N_F)
    traj = simulate_full_system(problem, reference, oracle_all, n_cri=N_CRI)
    assert traj.n_saved == N_STEPS + 1
    np.testing.assert_array_equal(traj.displacement[:, 1:], reference.displacement[:, 1:])
    assert traj.parameters["dirichlet_max_abs_predicted"] == pytest.approx(1e-3)
    assert traj.synchronized.sum() == N_CRI + 1


def test_full_system_needs_one_replica_over_all_dofs(problem, partition, reference, tmp_path):
    import jax

    from jaxsync.surrogate import LSTMArchitecture, SurrogateCheckpoint, init_replicas
    from jaxsync.syncavoid import simulate_full_system

    counts = (12, 12)
    arch = LSTMArchitecture(n_dof=12, n_hidden=4, n_layers=1, n_past=N_P, n_future=N_F)
    params = jax.tree_util.tree_map(np.asarray, init_replicas(jax.random.key(0), arch, counts))
    ckpt = SurrogateCheckpoint(arch=arch, params=params, mean=np.zeros((2, 12), np.float32),
                               std=np.ones((2, 12), np.float32), dof_counts=counts, n_s=N_S)
    with pytest.raises(CheckpointError, match="one surrogate over all 312 dofs"):
        simulate_full_system(problem, jaxsync.simulate(problem, N_STEPS), ckpt, n_cri=N_CRI)


def test_surrogates_of_another_partition_are_refused(problem, reference):
    import jax

    from jaxsync.surrogate import LSTMArchitecture, SurrogateCheckpoint, init_replicas

    other = jaxsync.partition(problem.mesh, 4)
    counts = tuple(3 * p.n_shared for p in other.parts)
    arch = LSTMArchitecture(n_dof=max(counts), n_hidden=4, n_layers=1, n_past=N_P, n_future=N_F)
    params = jax.tree_util.tree_map(np.asarray, init_replicas(jax.random.key(0), arch, counts))
    ckpt = SurrogateCheckpoint(arch=arch, params=params, mean=np.zeros((4, arch.n_dof), np.float32),
                               std=np.ones((4, arch.n_dof), np.float32), dof_counts=counts, n_s=N_S,
                               shared_nodes=tuple(p.shared_nodes for p in other.parts))
    with pytest.raises(CheckpointError, match="partition has 2 parts"):
        simulate_sync_avoiding(problem, N_STEPS, partitions=2, surrogates=ckpt, n_cri=N_CRI)


def test_trained_surrogates_run_online_and_metrics_are_consistent(problem, partition, reference):
    """Tiny replicas trained on the synchronized run drive the online solver; the error
    metrics computed from the run agree with their definitions."""
    import jax

    from jaxsync.metrics import l2_error, predictions_by_node, shared_node_errors
    from jaxsync.surrogate import (LSTMArchitecture, SurrogateCheckpoint, TrainConfig,
                                   build_dataset, stack_replicas, train_replicas)

    long_ref = jaxsync.simulate(problem, 400, partitions=partition)
    data = stack_replicas([build_dataset([long_ref.parts[p]["shared_displacement"]], N_S, N_P, N_F,
                                         train_fraction=1.0) for p in range(2)])
    arch = LSTMArchitecture(n_dof=data.n_dof_max, n_hidden=8, n_layers=1, n_past=N_P, n_future=N_F)
    result = train_replicas(data, arch, TrainConfig(n_epochs=3), jax.random.key(0), progress=False)
    ckpt = SurrogateCheckpoint.from_result(result, N_S, [p.shared_nodes for p in partition.parts])
    online = simulate_sync_avoiding(problem, 400, partitions=partition, surrogates=ckpt, n_cri=N_CRI)
    assert np.all(np.isfinite(online.displacement))
    np.testing.assert_array_equal(online.displacement[:N_CRI + 1], long_ref.displacement[:N_CRI + 1])
    predictions, holds, steps = predictions_by_node(online, partition)
    assert steps[0] == N_CRI + 1 and len(steps) == 400 - N_CRI
    errs = shared_node_errors(long_ref.displacement[steps][:, partition.shared_nodes], predictions, holds)
    # the global displacement at a shared node is the mean of the parts' predictions
    node = partition.shared_nodes[0]
    np.testing.assert_allclose(online.displacement[steps, node],
                               predictions[holds[:, 0], :, 0].mean(axis=0), rtol=1e-12)
    assert np.all(errs.es >= 0) and errs.es.shape == (len(steps),)
    assert l2_error(long_ref.displacement, online.displacement)[:N_CRI + 1].max() == 0.0


def untrained(partition):
    from jaxsync.syncavoid import SurrogatePredictor

    return SurrogatePredictor.initialized(partition, N_S, n_hidden=4, n_layers=1, n_past=N_P,
                                          n_future=N_F, seed=3)


def test_resync_tolerance_never_reached_changes_nothing(problem, partition):
    net = untrained(partition)
    plain = simulate_sync_avoiding(problem, N_STEPS, partitions=partition, surrogates=net,
                                   n_cri=N_CRI, cycles_per_chunk=1)
    watched = simulate_sync_avoiding(problem, N_STEPS, partitions=partition, surrogates=net,
                                     n_cri=N_CRI, resync_tolerance=np.inf)
    np.testing.assert_array_equal(watched.displacement, plain.displacement)
    np.testing.assert_array_equal(watched.synchronized, plain.synchronized)
    assert watched.parameters["resynchronized_at"] == []


def test_es_hat_above_tolerance_resynchronizes(problem, partition, tmp_path):
    """Untrained networks disagree at once: after each predicted cycle the run goes back
    to one state (mean over the parts) and runs n_p n_s synchronized steps, which equal a
    single-device run from that state; the triggering es_hat is eq. 26 of the metrics."""
    import jax

    from jaxsync.metrics import predictions_by_node, shared_node_errors
    from jaxsync.solver import SolverState, advance, build_system

    traj = simulate_sync_avoiding(problem, N_STEPS, partitions=partition, surrogates=untrained(partition),
                                  n_cri=N_CRI, resync_tolerance=1e-12)
    cycle, history = N_S * N_F, N_S * N_P  # 20, 20
    steps = np.arange(N_STEPS + 1)
    expected = ((steps <= N_CRI) | ((steps > N_CRI + cycle) & (steps <= N_CRI + cycle + history))
                | (steps > N_CRI + 2 * cycle + history))
    np.testing.assert_array_equal(traj.synchronized, expected)
    assert traj.parameters["resynchronized_at"] == [N_CRI + cycle, N_CRI + 2 * cycle + history]
    # the re-synchronized steps continue the mean state with the synchronized solver
    start = N_CRI + cycle
    system = build_system(problem, problem.dt)
    state = SolverState(traj.displacement[start], traj.displacement[start - 1], start)
    _, saved = jax.jit(advance, static_argnums=(2, 3))(system, state, history, 1)
    scale = np.abs(saved).max()
    assert np.abs(np.asarray(saved) - traj.displacement[start + 1:start + history + 1]).max() <= 1e-12 * scale
    # the trigger is es_hat of the first predicted cycle
    predictions, holds, _ = predictions_by_node(traj, partition)
    first = predictions[:, :cycle]
    es_hat = shared_node_errors(np.zeros(first.shape[1:]), first, holds).es_hat
    assert traj.parameters["es_hat_trigger"][0] == pytest.approx(es_hat.max(), rel=1e-12)
    assert es_hat.max() > 1e-12
    traj.save(tmp_path / "resync.h5")
    loaded = jaxsync.Trajectory.load(tmp_path / "resync.h5")
    assert loaded.parameters["resynchronized_at"] == traj.parameters["resynchronized_at"]
    np.testing.assert_array_equal(loaded.synchronized, traj.synchronized)


def test_resync_tolerance_is_checked(problem, partition, reference):
    for bad in (0.0, -1.0, float("nan"), "small"):
        with pytest.raises(ProblemError, match="resync_tolerance"):
            simulate_sync_avoiding(problem, N_STEPS, partitions=partition, surrogates=untrained(partition),
                                   n_cri=N_CRI, resync_tolerance=bad)
    with pytest.raises(ProblemError, match="OraclePredictor"):
        simulate_sync_avoiding(problem, N_STEPS, partitions=partition,
                               surrogates=oracle(reference, partition), n_cri=N_CRI, resync_tolerance=1e-3)
    from jaxsync.syncavoid import SurrogatePredictor

    three_past = SurrogatePredictor.initialized(partition, N_S, n_hidden=4, n_layers=1, n_past=3,
                                                n_future=N_F)  # re-synchronizes 15 steps
    with pytest.raises(ProblemError, match="n_p \\* n_s = 15"):
        simulate_sync_avoiding(problem, 100, partitions=partition, surrogates=three_past, n_cri=40,
                               save_every=10, resync_tolerance=1e-3)
