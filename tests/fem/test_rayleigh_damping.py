"""Rayleigh damping C = alpha M + beta K (``Problem.stiffness_damping`` = beta [s]).

References: the modes of the small beam's (M, K), computed here with scipy.linalg.eigh
from the independent assembly of ``fem_reference`` (a mode decays at (alpha + beta
omega^2) / 2); a NumPy central-difference loop written here with the dense K; the
characteristic root of the scheme at z = -1 for the stable step, and runs just below and
above it; the single-device run for the partitioned, deep-halo, traced and oracle-predicted
ones; the uninterrupted run for the resumed one; separate runs for an ensemble; central
finite differences of the law's first Piola stress for the hyperelastic damping force and
of the loss for the gradient in beta."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
import scipy.sparse.linalg as spla

import fem_reference as ref
import jaxsync
from jaxsync.errors import ProblemError, StabilityError

E, NU, RHO = 1.0e6, 0.3, 1.0
ALPHA, BETA = 2.0, 2.0e-4


@pytest.fixture(scope="module")
def beam():
    return jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1))


@pytest.fixture(scope="module")
def modes(beam):
    """(lumped mass per dof (3n,), dense K (3n, 3n), free dofs, omega (ascending),
    mass-orthonormal modes (3n, n_free)) of the beam clamped at x = 0."""
    K = ref.stiffness(beam.points, beam.tets, E, NU).toarray()
    m = ref.lumped_mass(beam.points, beam.tets, RHO)
    free = np.flatnonzero(~np.repeat(np.isclose(beam.points[:, 0], 0.0), 3))
    s = 1.0 / np.sqrt(m[free])
    omega2, vectors = scipy.linalg.eigh(s[:, None] * K[np.ix_(free, free)] * s[None, :])
    phi = np.zeros((len(m), len(free)))
    phi[free] = s[:, None] * vectors
    return m, K, free, np.sqrt(omega2), phi


def _clamped(beam, **changes):
    return jaxsync.Problem(mesh=beam, material=jaxsync.LinearElastic(E, NU, RHO),
                           dirichlet=(jaxsync.Dirichlet("x0"),), **{"damping": ALPHA, "stiffness_damping": BETA,
                                                                     **changes})


def _cantilever(beam, **changes):
    rng = np.random.default_rng(3)
    v0 = 20.0 * rng.standard_normal((beam.n_nodes, 3))  # rings every mode, so that beta K v matters
    return jaxsync.cantilever(beam, **{"body_force": (0.0, 0.0, -2.0e4), "t_ramp": 0.002, "damping": ALPHA,
                                       "stiffness_damping": BETA, "initial_velocity": v0, **changes})


# --- the physics: modal decay, the NumPy loop ----------------------------------------------------

def _decay_rate(q, dt):
    """The decay rate [1/s] of a sampled damped oscillation q(n): q(n+1) = c q(n) + d q(n-1)
    holds exactly for R r^n cos(n theta + phi), with d = -r^2; c and d by least squares."""
    (_, d), *_ = np.linalg.lstsq(np.stack([q[1:-1], q[:-2]], axis=1), q[2:], rcond=None)
    return -np.log(-d) / (2.0 * dt)


@pytest.mark.parametrize("k", [0, 8])
def test_a_mode_decays_at_alpha_plus_beta_omega_squared_over_two(beam, modes, k):
    """Free vibration from mode k: its modal coordinate phi_k^T M d(n) decays at
    (alpha + beta omega_k^2) / 2, to the scheme's accuracy. The damping force takes the
    backward velocity, first-order accurate: the decay rate is off by about
    beta omega^2 dt / 2 relative (the scheme's own rate, -ln|z| / dt of its root z, is met
    to round-off), and halving dt halves that error. Modes 0 and 8 (omega 105 and 874 1/s)
    differ 70-fold in omega^2, so the beta omega^2 term is tested, not only alpha."""
    m, _, _, omega, phi = modes
    w2 = omega[k] ** 2
    exact = 0.5 * (ALPHA + BETA * w2)
    errors = []
    for dt in (1.0e-4, 5.0e-5):
        problem = _clamped(beam, initial_displacement=phi[:, k].reshape(-1, 3))
        run = jaxsync.simulate(problem, int(round(0.05 / dt)), dt=dt, save=1)
        q = np.asarray(run.displacement).reshape(len(run.times), -1) @ (m * phi[:, k])
        rate = _decay_rate(q, dt)
        a, b = 0.5 * ALPHA * dt, BETA * dt * w2  # the root's |z|^2 = (1 - a - b) / (1 + a)
        np.testing.assert_allclose(rate, -np.log((1.0 - a - b) / (1.0 + a)) / (2.0 * dt), rtol=1e-8)
        assert abs(rate - exact) <= BETA * w2 * dt * exact
        errors.append(rate - exact)
    assert 0.45 <= errors[1] / errors[0] <= 0.55  # first order in dt
    assert exact > (1.0 + 0.5 * k) * 0.5 * ALPHA  # beta's share is large in mode 8


def test_equals_a_numpy_central_difference_loop_with_c_alpha_m_plus_beta_k(beam, modes):
    """d(n+1) = (dt^2 (f - K d(n) - beta K (d(n) - d(n-1)) / dt) / m + 2 d(n)
    - (1 - alpha dt / 2) d(n-1)) / (1 + alpha dt / 2) with dense K, from the start
    M_c a0 = f(0) - alpha M_c v0 - K d0 - beta K v0 (consistent mass), to round-off."""
    m, K, free, _, _ = modes
    rng = np.random.default_rng(1)
    d0, v0 = 1e-3 * rng.standard_normal((beam.n_nodes, 3)), 0.05 * rng.standard_normal((beam.n_nodes, 3))
    b, t_ramp = np.array([0.1, -0.2, -0.5]), 0.01
    problem = _clamped(beam, loads=(jaxsync.BodyForce(b, jaxsync.Ramp(t_ramp)),), initial_displacement=d0,
                       initial_velocity=v0)
    dt, n = float(problem.dt), 600
    got = np.asarray(jaxsync.simulate(problem, n, dt=dt, save=1).displacement).reshape(n + 1, -1)

    fixed = np.setdiff1d(np.arange(len(m)), free)
    M = ref.consistent_mass(beam.points, beam.tets, RHO)
    f = ref.body_force(beam.points, beam.tets, b)
    d, v = d0.ravel().copy(), v0.ravel().copy()
    d[fixed] = 0.0
    rhs = f * 0.0 - ALPHA * (M @ v) - K @ d - BETA * (K @ v)  # the ramp is 0 at t = 0
    a0 = np.zeros_like(d)
    a0[free] = spla.spsolve(M[free][:, free].tocsc(), rhs[free])
    prev = d - dt * v + 0.5 * dt**2 * a0
    prev[fixed] = 0.0
    a = 0.5 * ALPHA * dt
    expected = [d]
    for step in range(n):
        force = min(step * dt / t_ramp, 1.0) * f - K @ d - BETA * K @ (d - prev) / dt
        new = (dt**2 * force / m + 2.0 * d - (1.0 - a) * prev) / (1.0 + a)
        new[fixed] = 0.0
        prev, d = d, new
        expected.append(d)
    expected = np.array(expected)
    scale = np.abs(expected).max()
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-11 * scale)
    # beta matters here: the run without it differs
    without = jaxsync.simulate(problem.replace(stiffness_damping=0.0), n, dt=dt, save=1)
    assert np.abs(np.asarray(without.displacement).reshape(n + 1, -1) - expected).max() > 0.05 * scale


# --- the stable step --------------------------------------------------------------------------------

def test_the_stable_step_is_the_damped_bound_and_it_is_tight(beam, modes):
    """With xi = beta omega_max / 2 the bound is (2 / omega_max) (sqrt(1 + xi^2) - xi),
    omega_max from the eigenvalues computed here; beta = 2 / omega_max (xi = 1) lowers it to
    0.414 of 2 / omega_max. The default step runs bounded from a rough field that rings the
    fastest mode; 2 % below the bound decays, 2 % above it diverges (the bound is tight:
    mass-proportional damping alpha, taken with the centred velocity, does not move it)."""
    *_, omega, _ = modes
    beta = 2.0 / omega[-1]
    d0 = 1e-3 * np.random.default_rng(0).standard_normal((beam.n_nodes, 3))
    problem = _clamped(beam, stiffness_damping=beta, initial_displacement=d0)
    bound = (2.0 / omega[-1]) * (np.sqrt(2.0) - 1.0)
    step = problem.time_step
    np.testing.assert_allclose(step.exact, bound, rtol=1e-9)
    np.testing.assert_allclose(jaxsync.max_stable_dt(problem), 2.0 / omega[-1], rtol=1e-9)  # undamped, as named
    # the default step: the paper's CFL step where it is at most alpha_s times the damped
    # bound (a small beta), else alpha_s times that bound
    assert step.rule == "exact" and step.dt == pytest.approx(step.alpha_s * bound, rel=1e-9)
    slight = _clamped(beam, stiffness_damping=1e-6).time_step
    assert slight.rule == "cfl" and slight.dt == _clamped(beam, stiffness_damping=0.0).dt
    assert slight.exact < jaxsync.max_stable_dt(problem)
    # the characteristic polynomial of the fastest mode, A z^2 + B z + C, has its root at z = -1 there
    a, b, h = 0.5 * ALPHA * bound, beta * bound * omega[-1] ** 2, (bound * omega[-1]) ** 2
    assert abs((1.0 + a) + (2.0 - b - h) + (1.0 - a - b)) < 1e-12

    default = jaxsync.simulate(problem, 2000, save=100)
    assert np.abs(default.displacement[-1]).max() < 0.5 * np.abs(d0).max()
    unchecked = jaxsync.HostExecutor(check_stability=False)
    below = jaxsync.simulate(problem, 2000, dt=0.98 * bound, save=100, executor=unchecked)
    assert np.abs(below.displacement[-1]).max() < 0.1 * np.abs(d0).max()
    with pytest.raises(StabilityError, match="diverged"):
        jaxsync.simulate(problem, 2000, dt=1.02 * bound, save=100, executor=unchecked)
    with pytest.raises(StabilityError, match="stiffness-proportional damping"):
        jaxsync.simulate(problem, 10, dt=1.01 * bound)


def test_the_damped_bound_formula():
    from jaxsync.fem import damped_bound

    assert damped_bound(1e-3, 0.0) == 1e-3
    omega = 2.0 / 1e-3
    for beta in (1e-5, 1e-3, 1.0):
        xi = beta * omega / 2.0
        np.testing.assert_allclose(damped_bound(1e-3, beta), (2.0 / omega) * (np.sqrt(1.0 + xi * xi) - xi),
                                   rtol=1e-6 if beta == 1.0 else 1e-12)
    # traced beta: differentiable, d/dbeta (sqrt(b^2 + beta^2) - beta) = beta / sqrt(b^2 + beta^2) - 1
    slope = jax.grad(lambda beta: damped_bound(1e-3, beta))(1e-3)
    np.testing.assert_allclose(slope, 1.0 / np.sqrt(2.0) - 1.0, rtol=1e-12)


# --- every path: partitions, halos, traced, predicted, ensembles, checkpoints, gradients ----------

def test_partitioned_deep_halo_traced_and_predicted_runs_equal_the_single_device_run(beam):
    from jaxsync.solve.coupling import OraclePredictor, simulate_sync_avoiding
    from jaxsync.surrogate.training import shared_dof_layout

    problem = _cantilever(beam)
    dt, n_steps = float(problem.dt), 300
    one = jaxsync.simulate(problem, n_steps, dt=dt, save=1)
    scale = float(np.max(np.abs(one.displacement)))
    partition = jaxsync.partition(beam, 2)
    runs = {
        "psum": jaxsync.simulate(problem, n_steps, dt=dt, save=1, partitions=partition),
        "halo": jaxsync.simulate(problem, n_steps, dt=dt, save=2, partitions=partition, sync=jaxsync.Halo(2)),
        "traced": jaxsync.simulate(problem, n_steps, dt=dt, save=1, partitions=partition,
                                   executor=jaxsync.TracedExecutor()),
    }
    for name, run in runs.items():
        every = n_steps // (len(run.times) - 1)
        np.testing.assert_allclose(run.displacement, one.displacement[::every], rtol=0, atol=1e-12 * scale,
                                   err_msg=name)
    # the predicted phase: an oracle replays the exact shared displacements, so each part's
    # damping force sees the predicted d(n) and d(n-1) and the run equals the synchronized one
    n_s, n_p, n_f, n_cri = 5, 4, 4, 20
    n_dof, counts = shared_dof_layout(partition)
    cycle = n_s * n_f
    future = np.zeros((partition.n_parts, (-(-(n_steps - n_cri) // cycle) + 1) * cycle, n_dof))
    reference = runs["psum"]
    for p, part in enumerate(partition.parts):
        values = np.asarray(reference.displacement)[n_cri + 1:, part.shared_nodes].reshape(n_steps - n_cri, -1)
        future[p, :len(values), :counts[p]] = values
    oracle = OraclePredictor(future, first_step=n_cri + 1, n_s=n_s, n_past=n_p, n_future=n_f)
    online = simulate_sync_avoiding(problem, n_steps, dt=dt, partitions=partition, surrogates=oracle, n_cri=n_cri)
    assert online.stats.n_predicted_steps >= n_steps - n_cri - cycle
    np.testing.assert_allclose(online.displacement, one.displacement, rtol=0, atol=1e-12 * scale)
    # beta matters over these steps
    without = jaxsync.simulate(problem.replace(stiffness_damping=0.0), n_steps, dt=dt, save=1)
    assert float(np.max(np.abs(without.displacement - one.displacement))) > 0.01 * scale


# the default run checks this feature on one device (partitions=None, the same test)
@pytest.mark.parametrize("partitions", [None, pytest.param(2, marks=pytest.mark.slow)])
def test_every_linear_force_model_applies_beta(beam, partitions):
    """The matrix-free element kernel and the one-width ELL layout give the damped run of
    the default grouped stiffness, on one device and on two parts."""
    from jaxsync.fem.forces import Preassembled

    problem = _cantilever(beam)
    dt = float(problem.dt)
    default = jaxsync.simulate(problem, 200, dt=dt, save=50, partitions=partitions)
    scale = float(np.max(np.abs(default.displacement)))
    for mode in ("recompute", Preassembled(layout="ell")):
        run = jaxsync.simulate(problem, 200, dt=dt, save=50, partitions=partitions, mode=mode)
        np.testing.assert_allclose(run.displacement, default.displacement, rtol=0, atol=1e-12 * scale,
                                   err_msg=str(mode))


def test_an_ensemble_of_several_betas_equals_separate_runs_and_names_an_unstable_one(beam):
    """Members that differ in load and in beta (a smaller beta is stable at the first
    one's step) equal their separate runs; a member whose beta puts dt above its
    stability bound is named, with its beta."""
    problems = [_cantilever(beam), _cantilever(beam, body_force=(0.0, 1.0e4, -1.0e4), initial_velocity=None),
                _cantilever(beam).replace(stiffness_damping=0.5 * BETA)]
    dt = float(problems[0].dt)
    together = jaxsync.ensemble(problems, 200, dt=dt, save=50)
    for problem, run in zip(problems, together):
        alone = jaxsync.simulate(problem, 200, dt=dt, save=50)
        scale = float(np.max(np.abs(alone.displacement)))
        np.testing.assert_allclose(run.displacement, alone.displacement, rtol=0, atol=1e-12 * scale)
    assert not np.allclose(together[2].displacement, together[0].displacement, rtol=1e-6)
    with pytest.raises(StabilityError, match=r"member 1 .*beta"):
        jaxsync.ensemble([problems[0], problems[0].replace(stiffness_damping=2 * BETA)], 20, dt=dt, save=10)


def test_a_resumed_run_is_bit_identical_and_the_records_carry_beta(beam, tmp_path):
    from jaxsync.io.checkpoint import fingerprint

    problem = _cantilever(beam)
    dt = float(problem.dt)
    executor = jaxsync.HostExecutor(chunk_steps=100)
    full = jaxsync.simulate(problem, 400, dt=dt, save=50, executor=executor)
    path = tmp_path / "run.ckpt.h5"
    jaxsync.simulate(problem, 200, dt=dt, save=50, executor=executor, checkpoint=str(path))
    resumed = jaxsync.simulate(problem, 400, dt=dt, save=50, executor=executor, checkpoint=str(path))
    np.testing.assert_array_equal(resumed.displacement, full.displacement)
    assert full.parameters["stiffness_damping"] == BETA
    # a checkpoint of another beta is not this run's
    assert fingerprint(problem, dt, 50) != fingerprint(problem.replace(stiffness_damping=0.0), dt, 50)
    assert fingerprint(problem, dt, 50) != fingerprint(problem.replace(stiffness_damping=2 * BETA), dt, 50)
    # the trajectory file keeps it
    out = tmp_path / "run.h5"
    full.save(str(out))
    assert jaxsync.Trajectory.load(str(out)).parameters["stiffness_damping"] == BETA


# the default run checks this feature on one device (partitions=None, the same test)
@pytest.mark.parametrize("partitions", [None, pytest.param(2, marks=pytest.mark.slow)])
def test_the_gradient_in_beta_matches_finite_differences(beam, partitions):
    problem = _cantilever(beam)
    dt = float(problem.dt)

    @jax.jit  # one program for the gradient and one for both finite-difference runs
    def loss(beta):
        run = jaxsync.simulate(problem.replace(stiffness_damping=beta), 150, dt=dt, save=150,
                               partitions=partitions)
        return jnp.sum(run.displacement[-1] ** 2)

    g = jax.grad(loss)(BETA)
    h = 1e-4 * BETA
    fd = (loss(BETA + h) - loss(BETA - h)) / (2 * h)
    assert abs(float(fd)) > 0
    np.testing.assert_allclose(g, fd, rtol=1e-6)


# --- hyperelastic laws -------------------------------------------------------------------------------

def _finite_difference_stress(law, F, rate, eps=1e-6):
    return (law.first_piola(F + eps * rate) - law.first_piola(F - eps * rate)) / (2 * eps)


@pytest.mark.parametrize("law", [jaxsync.NeoHookean(E, NU, RHO),
                                 jaxsync.fem.StandardLinearSolid(E, NU, RHO, beta=1.5, tau=2e-3)],
                         ids=["neo-hookean", "standard-linear-solid"])
def test_the_viscous_stress_is_beta_times_the_tangent_applied_to_the_rate(beam, law):
    """The element kernel's damping stress beta dP/dF[grad v] against central differences
    of the law's first_piola (for the standard linear solid: its instantaneous response),
    and the assembled damping force against central differences of f_int along v."""
    from jaxsync.fem.forces import TotalLagrangian

    problem = jaxsync.Problem(mesh=beam, material=law, dirichlet=(jaxsync.Dirichlet("x0"),))
    op = TotalLagrangian().operator(problem)
    rng = np.random.default_rng(2)
    u = jnp.asarray(0.05 * rng.standard_normal((beam.n_nodes, 3)))
    v = jnp.asarray(3.0 * rng.standard_normal((beam.n_nodes, 3)))
    F = op.deformation_gradient(u)
    expected = BETA * _finite_difference_stress(law, F, op.gradient(v))
    np.testing.assert_allclose(op.viscous_stress(F, v, BETA), expected, rtol=0,
                               atol=1e-7 * float(jnp.max(jnp.abs(expected))))
    eps = 1e-6
    along = BETA * (op.matvec(u + eps * v) - op.matvec(u - eps * v)) / (2 * eps)
    if not law.internal_variables(1, 1):
        damped = op.damped_matvec(u, v, BETA) - op.matvec(u)
    else:  # the law with state: its update's force, with and without the damping
        state = law.internal_variables(beam.n_elements, 1)
        damped = op.update(u, state, 1e-5, v, BETA)[0] - op.update(u, state, 1e-5)[0]
    np.testing.assert_allclose(damped, along, rtol=0, atol=1e-7 * float(jnp.max(jnp.abs(along))))


def test_a_hyperelastic_partitioned_run_equals_the_single_device_run(beam):
    problem = _cantilever(beam, material=jaxsync.NeoHookean(E, NU, RHO))
    dt = float(problem.dt)
    one = jaxsync.simulate(problem, 300, dt=dt, save=50)
    two = jaxsync.simulate(problem, 300, dt=dt, save=50, partitions=2)
    scale = float(np.max(np.abs(one.displacement)))
    np.testing.assert_allclose(two.displacement, one.displacement, rtol=0, atol=1e-12 * scale)
    without = jaxsync.simulate(problem.replace(stiffness_damping=0.0), 300, dt=dt, save=50)
    assert float(np.max(np.abs(without.displacement - one.displacement))) > 0.01 * scale
    # its default step is the damped one of the tangent at rest
    undamped = problem.replace(stiffness_damping=0.0).time_step
    np.testing.assert_allclose(problem.time_step.exact, np.sqrt(undamped.exact**2 + BETA**2) - BETA, rtol=1e-12)


# --- the error estimate's modal propagator -----------------------------------------------------------

def test_the_error_propagator_rings_down_as_the_run(beam):
    """Each mode of the propagator is the run's scalar recursion: the modal coordinates of a
    free run (with alpha and beta) follow its 2 x 2 transition step by step."""
    from jaxsync.solve.coupling import ErrorPropagator

    d0 = 1e-3 * np.random.default_rng(4).standard_normal((beam.n_nodes, 3))
    problem = _clamped(beam, initial_displacement=d0)
    dt = float(problem.dt)
    propagator = ErrorPropagator.build(problem, jaxsync.partition(beam, 2), dt, n_modes=10)
    run = jaxsync.simulate(problem, 200, dt=dt, save=1)
    q = np.einsum("tnc,nck->tk", np.asarray(run.displacement), propagator.modes * propagator.mass[..., None])
    state = np.stack([q[1], q[0]], axis=-1)  # (q(1), q(0)) per mode
    for n in range(2, 201):
        state = np.einsum("kij,kj->ki", propagator.transition, state)
        np.testing.assert_allclose(state[:, 0], q[n], rtol=0, atol=1e-9 * np.abs(q).max())


# --- input --------------------------------------------------------------------------------------------

def test_bad_beta_is_refused_and_the_toml_key_is_read(beam):
    for bad in (-1e-4, float("nan"), "0.1"):
        with pytest.raises(ProblemError, match="stiffness_damping"):
            _clamped(beam, stiffness_damping=bad)
    from jaxsync.app.config import problem_from_config

    config = {"mesh": {"length": 4.0, "divisions": [4, 1, 1]}, "problem": {"kind": "cantilever", "damping": 0.5,
                                                                          "stiffness_damping": 3.0e-5}}
    problem, _ = problem_from_config(config)
    assert problem.stiffness_damping == 3.0e-5 and problem.damping == 0.5
    problem, _ = problem_from_config({"problem": {"kind": "cantilever"}})
    assert problem.stiffness_damping == 0.0  # a file without the key: none


def test_without_beta_the_step_is_unchanged_and_a_force_model_without_the_damping_force_is_refused(beam):
    """beta = 0 builds no damping term (the step of C = alpha M, bit for bit); a force model
    whose operator has no damped_matvec cannot run beta > 0 and says so."""
    import types

    from jaxsync.fem import build_system
    from jaxsync.fem.forces import Preassembled

    class MatvecOnly:  # a force model of one's own that knows no damping force
        name = "matvec-only"

        def operator(self, problem):
            return types.SimpleNamespace(matvec=Preassembled().operator(problem).matvec)

        def part_operators(self, problem, parts, n_local):
            return Preassembled().part_operators(problem, parts, n_local)

        def max_stable_dt(self, problem):
            return Preassembled().max_stable_dt(problem)

    assert build_system(_clamped(beam, stiffness_damping=0.0), 1e-4).stiffness_damping is None
    assert build_system(_clamped(beam, stiffness_damping=0.0), 1e-4, MatvecOnly()).stiffness_damping is None
    with pytest.raises(ProblemError, match="damped_matvec"):
        build_system(_clamped(beam), 1e-4, MatvecOnly())
