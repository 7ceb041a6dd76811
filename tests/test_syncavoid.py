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


def oracle(reference, partition, shift=0, poison_step=None):
    """Replays the synchronized run's shared displacements after N_CRI (optionally shifted
    by some steps, or with NaN from a step on)."""
    n_dof, counts = shared_dof_layout(partition)
    length = N_S * N_F
    n_cycles = -(-(N_STEPS - N_CRI) // length)
    future = np.zeros((partition.n_parts, n_cycles * length, n_dof))
    for p, part in enumerate(partition.parts):
        values = reference.displacement[N_CRI + 1:, part.shared_nodes].reshape(N_STEPS - N_CRI, -1)
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
                                  surrogates=_oracle_for(ref4, part4, N_STEPS - 10), n_cri=N_CRI)
    np.testing.assert_allclose(traj.displacement, ref4.displacement[::10], rtol=0,
                               atol=1e-13 * np.abs(ref4.displacement).max())
    assert traj.parts[0]["predicted_shared_displacement"].shape[0] == (N_STEPS - 10 - N_CRI) // 10


def _oracle_for(reference, partition, n_steps):
    n_dof, counts = shared_dof_layout(partition)
    length = N_S * N_F
    n_cycles = -(-(n_steps - N_CRI) // length)
    future = np.zeros((partition.n_parts, n_cycles * length, n_dof))
    for p, part in enumerate(partition.parts):
        values = reference.displacement[N_CRI + 1:, part.shared_nodes].reshape(n_steps - N_CRI, -1)
        future[p, :len(values), :counts[p]] = values
    return OraclePredictor(future, n_s=N_S, n_past=N_P, n_future=N_F)


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
