"""The timed programs (jaxsync.perf.kernels) compute what the timing says they compute:
each variant against an independent reference (the public solver, the step with K = 0,
the element forces' own mat-vec, a NumPy loop), the SPMD programs against the runner and
the per-part predictor. No test times anything."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsync
from jaxsync.fem import SolverState, build_system, initial_state
from jaxsync.fem.forces import Preassembled, element_forces
from jaxsync.perf import kernels
from jaxsync.solve.executors import DistributedRunner

N_STEPS = 12
FUSED = Preassembled(product="fused")  # the product the timing kernels time (long runs)


@pytest.fixture(scope="module")
def problem():
    return jaxsync.cantilever(jaxsync.box_beam(25.0, 1.0, 1.0, (8, 1, 1)))


@pytest.fixture(scope="module")
def start(problem):
    system = build_system(problem, problem.dt)
    return system, initial_state(problem, system)


def run(variant, system, state, scale, *extra, n_steps=N_STEPS):
    return jax.jit(variant, static_argnums=3)(system, state, jnp.asarray(scale, dtype=float), n_steps, *extra)


def test_local_step_is_the_solvers_step(problem, start):
    system, state = start
    # the timed programs hold the fused product, which a short run would not choose
    reference = jaxsync.simulate(problem, N_STEPS, save=N_STEPS, mode=FUSED).displacement[-1]
    out = run(kernels.local_step, system, state, 0.0)
    np.testing.assert_allclose(np.asarray(out.displacement), reference, rtol=1e-12, atol=1e-300)
    assert int(out.step) == N_STEPS


def test_scaled_force_is_the_real_step_at_1_and_no_force_at_0(start):
    system, _ = start
    d = jnp.asarray(1e-3 * np.random.default_rng(0).normal(size=system.mass.shape))
    state = SolverState(d, d, jnp.asarray(0, dtype=jnp.int32))  # deformed: K d matters
    real = run(kernels.local_step, system, state, 0.0)
    at_one = run(kernels.step_with_scaled_force, system, state, 1.0)
    np.testing.assert_allclose(np.asarray(at_one.displacement), np.asarray(real.displacement), rtol=1e-12)
    # the reference for "no internal force": the real step of a system whose K is zero
    k_zero = dataclasses.replace(system.stiffness, blocks=jax.tree_util.tree_map(jnp.zeros_like,
                                                                                system.stiffness.blocks))
    without_k = run(kernels.local_step, dataclasses.replace(system, stiffness=k_zero), state, 0.0)
    for variant in (kernels.step_with_scaled_force, kernels.step_without_force):
        out = run(variant, system, state, 0.0)
        np.testing.assert_allclose(np.asarray(out.displacement), np.asarray(without_k.displacement),
                                   rtol=1e-12, atol=1e-300)
    assert not np.allclose(np.asarray(without_k.displacement), np.asarray(real.displacement), rtol=1e-3)


def test_scaled_force_keeps_the_matvec_in_the_compiled_program(start):
    """A zero scale passed at run time cannot be folded: the compiled force variant does
    the mat-vec's work on top of the update (XLA's own operation count)."""
    system, state = start

    def flops(variant):
        lowered = jax.jit(variant, static_argnums=3).lower(system, state, jnp.zeros(()), N_STEPS)
        analysis = lowered.compile().cost_analysis()
        analysis = analysis[0] if isinstance(analysis, (list, tuple)) else analysis
        return analysis["flops"]

    slots = sum(c.size for c in jax.tree_util.tree_leaves(system.stiffness.columns))  # blocks stored
    assert flops(kernels.step_with_scaled_force) - flops(kernels.step_without_force) >= 9 * slots


def test_scatter_only_sums_element_forces_into_the_nodes(problem):
    """Recompute mode: with scale 1 and d(n) = 0 one scatter step adds the element forces
    of u into the nodes, which is K u (ElementStiffness.matvec); and for any d(n), the
    scatter-add against a NumPy ``add.at``."""
    system = build_system(problem, problem.dt, "recompute")
    k = system.stiffness
    n = problem.mesh.n_nodes
    u = jnp.asarray(np.random.default_rng(0).normal(size=(n, 3)))
    forces = element_forces(k.points, k.tets, u, k.lam, k.mu)
    zero = SolverState(jnp.zeros((n, 3)), jnp.zeros((n, 3)), jnp.asarray(0, dtype=jnp.int32))
    out = run(kernels.scatter_only, system, zero, 1.0, forces, n_steps=1)
    np.testing.assert_allclose(np.asarray(out.displacement), np.asarray(k.matvec(u)), rtol=1e-10, atol=1e-12)

    d0 = np.random.default_rng(1).normal(size=(n, 3))
    state = SolverState(jnp.asarray(d0), jnp.zeros((n, 3)), jnp.asarray(0, dtype=jnp.int32))
    out = run(kernels.scatter_only, system, state, 1.0, forces, n_steps=1)
    element = (np.asarray(forces) + d0[0, 0]) * np.asarray(k.weight)[:, None, None]
    nodal = np.zeros((n, 3))
    np.add.at(nodal, np.asarray(k.tets).ravel(), element.reshape(-1, 3))
    np.testing.assert_allclose(np.asarray(out.displacement), d0 + nodal, rtol=1e-12)
    np.testing.assert_array_equal(np.asarray(out.previous), d0)


def test_scaled_carry_and_no_step(start):
    system, _ = start
    shape = system.mass.shape
    state = SolverState(jnp.full(shape, 1.0), jnp.full(shape, 1.0), jnp.asarray(0, dtype=jnp.int32))
    out = run(kernels.scaled_carry, system, state, 1.0)
    d, prev = 1.0, 1.0  # d(n+1) = d(n) + d(n-1): Fibonacci
    for _ in range(N_STEPS):
        d, prev = d + prev, d
    assert np.all(np.asarray(out.displacement) == d) and np.all(np.asarray(out.previous) == prev)
    assert int(out.step) == N_STEPS
    same = run(kernels.no_step, system, state, 0.5)
    assert np.all(np.asarray(same.displacement) == 1.5) and int(same.step) == 0
    assert set(kernels.LOCAL_VARIANTS) == {"full", "other", "force", "scatter", "empty", "call"}


def test_distributed_programs_are_the_runners(problem, start):
    """The timed synchronized program computes the distributed solver's states; without
    synchronization it does not; the no-step program leaves the state as it is."""
    system, state = start
    part = jaxsync.partition(problem.mesh, 2, seed=0)
    reference = jaxsync.simulate(problem, N_STEPS, save=N_STEPS, partitions=part, mode=FUSED).displacement[-1]
    runner = DistributedRunner(problem, system, part, save_every=N_STEPS)
    local = runner.from_global(state)
    timed, _ = kernels.distributed_step(runner, N_STEPS, True)(runner.parts, local)
    np.testing.assert_allclose(runner.to_global(timed).displacement, reference, rtol=1e-12, atol=1e-300)
    unsynchronized, _ = kernels.distributed_step(runner, N_STEPS, False)(runner.parts, local)
    assert not np.allclose(runner.to_global(unsynchronized).displacement, reference, rtol=1e-6, atol=0)
    idle = kernels.distributed_no_step(runner)(runner.parts, local)
    np.testing.assert_array_equal(np.asarray(idle.displacement), np.asarray(local.displacement))


def test_prediction_programs_match_each_parts_predictor(problem, start):
    from jaxsync.solve.executors import PredictedPhase
    from jaxsync.surrogate import Surrogate
    from jaxsync.surrogate.training import shared_dof_layout

    system, _ = start
    part = jaxsync.partition(problem.mesh, 2, seed=0)
    predictor = Surrogate.initialized(part, 3, n_hidden=4, n_layers=1, n_past=2, n_future=2)
    runner = DistributedRunner(problem, system, part, save_every=6)
    n_dof, _ = shared_dof_layout(part)
    buffers = np.random.default_rng(0).normal(size=(2, 3 * 2, n_dof))
    phase = PredictedPhase(runner, predictor, save_every=6)
    together = np.asarray(kernels.prediction_program(runner.device_mesh)(phase.predictor, runner.put(buffers)))
    assert together.shape == (2, 3 * 2, n_dof)
    for p in range(2):
        own = jax.tree_util.tree_map(lambda x: np.asarray(x)[p], predictor)
        reference = np.asarray(own.predict(jnp.asarray(buffers[p]), 0))
        np.testing.assert_allclose(together[p], reference, rtol=1e-5, atol=1e-6)
        alone = np.asarray(kernels.part_prediction()(own, jnp.asarray(buffers[p])))
        np.testing.assert_allclose(alone, reference, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(kernels.no_prediction()(jnp.asarray(buffers[0]))), buffers[0])
