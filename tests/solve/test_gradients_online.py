"""Gradients through the synchronization-avoiding solver (jaxsync.solve.gradients.
sync_avoiding_trajectory, reached by simulate_sync_avoiding inside jax.grad / jit).

The traced program is checked against the host-driven solver (simulate_sync_avoiding
with concrete values, whose own tests compare it with the synchronized run): the same
trajectory in value; and its gradients against central finite differences of its values
(the compiled forward program, equal to the solver's by the first test; the slow run also
differentiates the host-driven solver itself), in the material, the damping and the
surrogate weights."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsync
from jaxsync import ProblemError
from jaxsync.solve.coupling import simulate_sync_avoiding
from jaxsync.surrogate import Surrogate

N_S, N_P, N_F = 5, 3, 4
N_CRI = 40  # history n_s n_p = 15 steps, so 25 synchronized steps before it
N_STEPS = N_CRI + 3 * N_S * N_F + 10  # three refill cycles of 20 steps and a partial one
E0, ALPHA0 = 1.0e6, 0.5


@pytest.fixture(scope="module")
def problem():
    return jaxsync.cantilever()


@pytest.fixture(scope="module")
def partition(problem):
    return jaxsync.partition(problem.mesh, 2)


@pytest.fixture(scope="module")
def surrogate(problem, partition):
    """An untrained float64 LSTM per part, normalized with the synchronized run's shared
    displacements (so that its predictions have their size: a smooth, non-trivial map)."""
    reference = jaxsync.simulate(with_parameters(problem, E0, ALPHA0), N_STEPS, partitions=partition)
    s = Surrogate.initialized(partition, N_S, n_hidden=6, n_layers=1, n_past=N_P, n_future=N_F,
                              dtype="float64", seed=3)
    mean, std = np.zeros(s.mean.shape), np.ones(s.std.shape)
    for p, part in enumerate(partition.parts):
        values = reference.displacement[:, part.shared_nodes].reshape(N_STEPS + 1, -1)
        mean[p, :values.shape[1]] = values.mean(axis=0)
        std[p, :values.shape[1]] = values.std(axis=0) + 1e-3 * np.abs(values).max()
    return dataclasses.replace(s, mean=jnp.asarray(mean), std=jnp.asarray(std))


def with_parameters(problem, E, alpha, fz=None):
    """The cantilever with Young's modulus E, damping alpha and (given fz) the body force
    (0, 0, fz) on the same time function."""
    changes = {}
    if fz is not None:
        (load,) = problem.loads
        changes["loads"] = (jaxsync.BodyForce((0.0, 0.0, fz), load.time),)
    return problem.replace(material=jaxsync.LinearElastic(E, 0.3, 1.0), damping=alpha, **changes)


def tip_node(mesh):
    x = mesh.points
    return int(np.argmax(x[:, 0] - 1e-3 * np.abs(x[:, 1]) - 1e-3 * np.abs(x[:, 2])))


def online(problem, partition, surrogate, E, alpha, fz=None, **kwargs):
    # a concrete dt (the base problem's CFL step): the default one follows a traced E, and a
    # traced dt leaves the steps where loads jump unknown
    with jax.ensure_compile_time_eval():
        dt = float(problem.dt)
    return simulate_sync_avoiding(with_parameters(problem, E, alpha, fz), N_STEPS, partitions=partition,
                                  surrogates=surrogate, n_cri=N_CRI, dt=dt, **kwargs)


def make_loss(problem, partition, **kwargs):
    tip = tip_node(problem.mesh)

    def loss(E, alpha, surrogate, fz=None):
        traj = online(problem, partition, surrogate, E, alpha, fz, **kwargs)
        # the tip's vertical history after the switch: the predicted phase's motion
        return jnp.sum(traj.displacement[N_CRI:, tip, 2] ** 2) / 1e-8

    return loss


@pytest.mark.parametrize("save_every", [pytest.param(1, marks=pytest.mark.slow), 10])
def test_traced_run_equals_the_solver(problem, partition, surrogate, save_every):
    # save_every=10 does not divide the 25 steps before the recorded history: a save falls
    # inside it (the traced program's split of the synchronized phase)
    solver = online(problem, partition, surrogate, E0, ALPHA0, save=save_every)
    traced = jax.jit(lambda E: online(problem, partition, surrogate, E, ALPHA0,
                                      save=save_every).displacement)(E0)
    assert traced.shape == solver.displacement.shape == (N_STEPS // save_every + 1, problem.mesh.n_nodes, 3)
    scale = np.abs(solver.displacement).max()
    # the predictions moved the run off the synchronized one (the check is not vacuous)
    synced = jaxsync.simulate(with_parameters(problem, E0, ALPHA0), N_STEPS, save=save_every)
    assert np.abs(solver.displacement - synced.displacement).max() > 1e-3 * scale
    np.testing.assert_allclose(np.asarray(traced), solver.displacement, rtol=0, atol=1e-12 * scale)


def random_direction(tree, seed):
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    keys = jax.random.split(jax.random.PRNGKey(seed), len(leaves))
    return treedef.unflatten([jax.random.normal(k, x.shape, x.dtype) for k, x in zip(keys, leaves)])


def moved(surrogate, direction, h):
    params = jax.tree_util.tree_map(lambda w, d: w + h * d, surrogate.params, direction)
    return dataclasses.replace(surrogate, params=params)


def test_gradients_equal_finite_differences(problem, partition, surrogate):
    """d/dE, d/dalpha, d/d(load) (surrogates fixed) and d/d(weights) along a random
    direction (solver in the loop) against central differences of the compiled forward
    program."""
    loss = make_loss(problem, partition)
    fz0 = -0.5
    gE, ga, gw, gf = jax.jit(jax.grad(loss, (0, 1, 2, 3)))(E0, ALPHA0, surrogate, fz0)
    direction = random_direction(surrogate.params, 7)
    slope = sum(float(jnp.vdot(g, d)) for g, d in zip(jax.tree_util.tree_leaves(gw.params),
                                                       jax.tree_util.tree_leaves(direction)))
    value = jax.jit(lambda E, alpha, h, fz: loss(E, alpha, moved(surrogate, direction, h), fz))
    hE, ha, hw, hf = 1e-4 * E0, 1e-3, 1e-5, 1e-4

    def central(i, h):
        x = [E0, ALPHA0, 0.0, fz0]
        plus, minus = list(x), list(x)
        plus[i] += h
        minus[i] -= h
        return (float(value(*plus)) - float(value(*minus))) / (2 * h)

    assert min(abs(float(gE)), abs(float(ga)), abs(slope), abs(float(gf))) > 0
    assert float(gE) == pytest.approx(central(0, hE), rel=1e-6)
    assert float(ga) == pytest.approx(central(1, ha), rel=1e-6)
    assert slope == pytest.approx(central(2, hw), rel=1e-6)
    assert float(gf) == pytest.approx(central(3, hf), rel=1e-6)
    # no synchronization after n_cri: only the network of the part that holds the tip moves
    # it (the other part's predictions reach the tip through nothing)
    holds_tip = [tip_node(problem.mesh) in set(part.nodes.tolist()) for part in partition.parts]
    assert sum(holds_tip) == 1
    for p in range(partition.n_parts):
        size = sum(float(jnp.vdot(g[p], g[p])) for g in jax.tree_util.tree_leaves(gw.params))
        assert (size > 0) if holds_tip[p] else (size == 0.0)


@pytest.mark.slow
def test_gradients_equal_finite_differences_of_the_solver(problem, partition, surrogate):
    """The same derivatives against central differences of the host-driven solver."""
    loss = make_loss(problem, partition)
    gE, gw = jax.jit(jax.grad(loss, (0, 2)))(E0, ALPHA0, surrogate)
    direction = random_direction(surrogate.params, 7)
    slope = sum(float(jnp.vdot(g, d)) for g, d in zip(jax.tree_util.tree_leaves(gw.params),
                                                       jax.tree_util.tree_leaves(direction)))
    hE, hw = 1e-4 * E0, 1e-5
    fdE = (float(loss(E0 + hE, ALPHA0, surrogate)) - float(loss(E0 - hE, ALPHA0, surrogate))) / (2 * hE)
    fdw = (float(loss(E0, ALPHA0, moved(surrogate, direction, hw)))
           - float(loss(E0, ALPHA0, moved(surrogate, direction, -hw)))) / (2 * hw)
    assert float(gE) == pytest.approx(fdE, rel=1e-6)
    assert slope == pytest.approx(fdw, rel=1e-6)


@pytest.mark.slow
def test_checkpointed_gradient_equals_plain_reverse_mode(problem, partition, surrogate):
    adjoints = {True: jaxsync.Recompute(), False: jaxsync.StoreAll()}
    grad = {c: jax.jit(jax.grad(make_loss(problem, partition, executor=jaxsync.TracedExecutor(adjoints[c])),
                                (0, 1, 2)))(E0, ALPHA0, surrogate) for c in (True, False)}
    for a, b in zip(jax.tree_util.tree_leaves(grad[True]), jax.tree_util.tree_leaves(grad[False])):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-10,
                                   atol=1e-12 * float(np.abs(np.asarray(b)).max(initial=0.0)))


def test_resync_tolerance_refused_in_a_traced_run(problem, partition, surrogate):
    with pytest.raises(ProblemError, match="resync_tolerance"):
        jax.grad(make_loss(problem, partition, resync_tolerance="2%"))(E0, ALPHA0, surrogate)


def test_fine_tuning_in_the_loop_lowers_the_window_error(problem, partition, surrogate):
    """Solver-in-the-loop fine-tuning (jaxsync.solve.fine_tune_in_the_loop): its window loss is the
    relative error of the host-driven online run against the synchronized one, and Adam on
    the networks' weights lowers it."""
    from jaxsync.solve import FineTuneConfig, fine_tune_in_the_loop

    base = with_parameters(problem, E0, ALPHA0)
    config = FineTuneConfig(n_iterations=6, window_cycles=2, learning_rate=3e-3, n_starts=1, n_validation=1,
                            validate_every=3)
    window = N_S * N_P + 2 * N_S * N_F  # 15 synchronized steps, two cycles of 20
    result = fine_tune_in_the_loop(base, surrogate, partition, n_steps=N_STEPS, config=config)
    assert result.window_starts.tolist() == [0]
    # the loss of the given weights, from the solvers themselves
    online = simulate_sync_avoiding(base, window, partitions=partition, surrogates=surrogate,
                                    n_cri=N_S * N_P, save=N_S, dt=float(problem.dt))
    synced = jaxsync.simulate(base, N_STEPS, save=N_S)
    amplitude = np.abs(synced.displacement).max()
    first = N_P + 1  # the saves after the synchronized history (t = 0 is the first row)
    expected = np.mean((online.displacement[first:] - synced.displacement[first:window // N_S + 1]) ** 2)
    assert result.amplitude == pytest.approx(amplitude, rel=1e-12)
    assert result.validation[0, 1] == pytest.approx(expected / amplitude ** 2, rel=1e-9)
    assert result.loss_history[0] == pytest.approx(result.validation[0, 1], rel=1e-9)
    # fine-tuning lowered it, and the kept weights are the best validated ones
    assert result.validation[:, 0].tolist() == [0, 3, 6]
    assert result.best_iteration > 0 and result.improvement < 0.9
    tuned = simulate_sync_avoiding(base, window, partitions=partition, surrogates=result.surrogate,
                                   n_cri=N_S * N_P, save=N_S, dt=float(problem.dt))
    tuned_error = np.mean((tuned.displacement[first:] - synced.displacement[first:window // N_S + 1]) ** 2)
    assert tuned_error / amplitude ** 2 == pytest.approx(result.validation[:, 1].min(), rel=1e-9)


def test_fine_tuning_refuses_surrogates_of_another_partition(problem, surrogate):
    from jaxsync import CheckpointError
    from jaxsync.solve import FineTuneConfig, fine_tune_in_the_loop

    with pytest.raises(CheckpointError, match="partition they were trained on"):
        fine_tune_in_the_loop(problem, surrogate, jaxsync.partition(problem.mesh, 4), n_steps=N_STEPS,
                              config=FineTuneConfig(n_iterations=1, n_starts=1, n_validation=1))
