"""State that a material carries: the internal variables of the finite-strain standard
linear solid (:class:`jaxsync.fem.materials.StandardLinearSolid`) through the element
kernel, the solver state, partitioned runs, checkpoints and gradients.

References: the relaxation of a held stretch against the closed form of the model,
written here with numpy (the isochoric and volumetric neo-Hookean stresses of the
stretch and the branch's convolution integral, integrated by the trapezoid rule on a
fine grid); beta = 0 against the elastic :class:`jaxsync.NearlyIncompressibleNeoHookean`;
the instantaneous law against the elastic law of (1 + beta) times the shear modulus; the
single-device run for the partitioned one; the uninterrupted run for the resumed one;
central finite differences for the gradient."""

import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsync
from jaxsync.errors import MaterialError
from jaxsync.fem import Probe, advance, build_system, initial_state
from jaxsync.fem.materials import StandardLinearSolid
from jaxsync.io.checkpoint import load_checkpoint

E, NU, RHO, BETA, TAU = 1.0e6, 0.3, 1.0, 1.5, 2.0e-3


def _sls(**changes):
    return StandardLinearSolid(**{"E": E, "nu": NU, "rho": RHO, "beta": BETA, "tau": TAU, **changes})


# --- the closed form of a held uniaxial stretch -------------------------------------------------

def _stresses(stretch, mu, bulk):
    """(S_vol, S_iso) 11-components [dyn/cm^2] of F = diag(stretch, 1, 1) (numpy)."""
    J = stretch
    c_inv = 1.0 / stretch**2
    i1 = stretch**2 + 2.0
    s_iso = mu * J ** (-2.0 / 3.0) * (1.0 - i1 / 3.0 * c_inv)
    s_vol = 0.5 * bulk * (J * J - 1.0) * c_inv
    return s_vol, s_iso


def test_a_held_stretch_relaxes_as_the_closed_form():
    """A unit cube, every node prescribed: x = 0 held, x = 1 pulled to a 5 % stretch over
    t_r, then held. The reaction on x = 1 is P_11 times the unit area, P_11 = lambda
    (S_vol + S_iso + Q), with Q(t) = beta int_0^t exp(-(t - s)/tau) dS_iso/ds ds: after
    t_r, Q(t) = Q(t_r) exp(-(t - t_r)/tau), relaxing from the instantaneous stress to
    S_vol + S_iso."""
    mesh = jaxsync.box_beam(1.0, 1.0, 1.0, (1, 1, 1))
    eps, t_r, dt = 0.05, 0.2 * TAU, 1.0e-6
    law = _sls()
    problem = jaxsync.Problem(mesh=mesh, material=law, dirichlet=(
        jaxsync.Dirichlet("x0"), jaxsync.Dirichlet("x1", value=(eps, 0.0, 0.0), time=jaxsync.Ramp(t_r))))
    system = build_system(problem, dt)
    state = initial_state(problem, system)
    assert set(state.internal) == {"Q", "S_iso"} and state.internal["Q"].shape == (mesh.n_elements, 1, 3, 3)
    pulled = jnp.asarray(np.isclose(problem.points[:, 0], 1.0))
    probe = Probe(per_step=lambda s, force, updated, new: jnp.sum(jnp.where(pulled, force[:, 0], 0.0)),
                  initial=lambda s: jnp.zeros(()), finish=lambda total: total)
    n = int(round(5 * TAU / dt))
    run = jax.jit(lambda st: advance(system, st, n, 1, probe=probe))
    final, (_, reaction) = run(state)
    t = np.arange(n) * dt  # the force of step k is that of d(k), at t_k
    reaction = np.asarray(reaction)

    mu, bulk = law.mu, law.bulk
    stretch = 1.0 + eps * np.clip(t / t_r, 0.0, 1.0)
    s_vol, s_iso = _stresses(stretch, mu, bulk)
    s = np.linspace(0.0, t_r, 20001)  # the branch's integral over the ramp, then its decay
    _, s_iso_ramp = _stresses(1.0 + eps * s / t_r, mu, bulk)
    rate = np.gradient(s_iso_ramp, s)
    q_ramp = np.array([np.trapezoid(np.where(s <= tk, BETA * np.exp(-(tk - s) / TAU) * rate, 0.0), s)
                       for tk in t[t <= t_r]])
    q_held = BETA * np.trapezoid(np.exp(-(t_r - s) / TAU) * rate, s)  # Q(t_r)
    q = np.concatenate([q_ramp, q_held * np.exp(-(t[t > t_r] - t_r) / TAU)])
    expected = stretch * (s_vol + s_iso + q)
    overstress = float(np.max(np.abs(stretch * q)))
    assert overstress > 0.3 * float(np.max(np.abs(expected)))  # a strong relaxation
    np.testing.assert_allclose(reaction, expected, rtol=0, atol=2e-4 * overstress)
    relaxed = stretch[-1] * (s_vol[-1] + s_iso[-1])
    assert abs(reaction[-1] - relaxed) < 0.01 * overstress  # five relaxation times: S_vol + S_iso
    # the state holds the branch stress of the last force, that of d(n - 1) at t[-1] (P1: one
    # point per element)
    np.testing.assert_allclose(np.asarray(final.internal["Q"])[:, 0, 0, 0], q[-1], rtol=2e-4)


# --- the law against the elastic laws it reduces to ----------------------------------------------

def test_without_its_branch_the_law_is_the_nearly_incompressible_neo_hookean():
    F = jnp.eye(3)[None] + 0.2 * jax.random.normal(jax.random.PRNGKey(1), (40, 3, 3))
    elastic = jaxsync.NearlyIncompressibleNeoHookean(E, NU, RHO)
    np.testing.assert_allclose(_sls(beta=0.0).first_piola(F), elastic.first_piola(F), rtol=1e-12, atol=1e-12 * E)
    state = _sls(beta=0.0).internal_variables(40, 1)
    state = {k: v[:, 0] for k, v in state.items()}
    P, _ = _sls(beta=0.0).stress_update(F, None, state, 1e-5)
    np.testing.assert_allclose(P, elastic.first_piola(F), rtol=1e-12, atol=1e-12 * E)
    # instantaneously: the elastic law of shear modulus (1 + beta) mu, the same bulk modulus
    law = _sls()
    mu, bulk = (1.0 + BETA) * law.mu, law.bulk
    glassy = jaxsync.NearlyIncompressibleNeoHookean(9 * bulk * mu / (3 * bulk + mu),
                                                     (3 * bulk - 2 * mu) / (2 * (3 * bulk + mu)), RHO)
    np.testing.assert_allclose(law.first_piola(F), glassy.first_piola(F), rtol=1e-11, atol=1e-11 * E)


@pytest.fixture(scope="module")
def beam():
    return jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1))


def _cantilever(beam, **changes):
    return jaxsync.cantilever(beam, material=_sls(**changes), body_force=(0.0, 0.0, -2.0e4), t_ramp=0.002,
                              damping=50.0)


def test_the_stable_step_is_that_of_the_instantaneous_stiffness(beam):
    law = _sls()
    mu, bulk = (1.0 + BETA) * law.mu, law.bulk
    glassy = jaxsync.NearlyIncompressibleNeoHookean(9 * bulk * mu / (3 * bulk + mu),
                                                     (3 * bulk - 2 * mu) / (2 * (3 * bulk + mu)), RHO)
    problem = _cantilever(beam)
    np.testing.assert_allclose(problem.dt, problem.replace(material=glassy).dt, rtol=1e-9)


def test_beta_zero_runs_as_the_elastic_law_and_beta_changes_the_run(beam):
    dt = float(_cantilever(beam).dt)
    without = jaxsync.simulate(_cantilever(beam, beta=0.0), 300, dt=dt, save=50)
    elastic = jaxsync.simulate(_cantilever(beam).replace(material=jaxsync.NearlyIncompressibleNeoHookean(E, NU, RHO)),
                               300, dt=dt, save=50)
    scale = float(np.max(np.abs(elastic.displacement)))
    np.testing.assert_allclose(without.displacement, elastic.displacement, rtol=0, atol=1e-11 * scale)
    stiffer = jaxsync.simulate(_cantilever(beam), 300, dt=dt, save=50)
    assert float(np.max(np.abs(stiffer.displacement - elastic.displacement))) > 0.05 * scale


# --- partitions, checkpoints, gradients -------------------------------------------------------------

def test_a_partitioned_run_and_its_state_equal_the_single_device_run(beam, tmp_path):
    problem = _cantilever(beam)
    dt = float(problem.dt)
    executor = jaxsync.HostExecutor(chunk_steps=100)
    one = jaxsync.simulate(problem, 300, dt=dt, save=50, executor=executor, checkpoint=str(tmp_path / "one.h5"))
    two = jaxsync.simulate(problem, 300, dt=dt, save=50, executor=executor, partitions=2,
                           checkpoint=str(tmp_path / "two.h5"))
    scale = float(np.max(np.abs(one.displacement)))
    np.testing.assert_allclose(two.displacement, one.displacement, rtol=0, atol=1e-12 * scale)
    # the merged state of the parts is the single-device state, element by element
    from jaxsync.io.checkpoint import fingerprint

    key = fingerprint(problem, dt, 50)
    state_one, _, _ = load_checkpoint(str(tmp_path / "one.h5"), key, 300)
    state_two, _, _ = load_checkpoint(str(tmp_path / "two.h5"), key, 300)
    q = np.asarray(state_one.internal["Q"])
    assert q.shape == (beam.n_elements, 1, 3, 3) and np.max(np.abs(q)) > 0
    for name in ("Q", "S_iso"):
        np.testing.assert_allclose(state_two.internal[name], state_one.internal[name], rtol=0,
                                   atol=1e-10 * np.max(np.abs(q)))
    # a traced (differentiable) partitioned run carries the state too
    traced = jaxsync.simulate(problem, 300, dt=dt, save=50, partitions=2, executor=jaxsync.TracedExecutor())
    np.testing.assert_allclose(traced.displacement, one.displacement, rtol=0, atol=1e-12 * scale)


def test_a_resumed_run_is_bit_identical_to_the_uninterrupted_one(beam, tmp_path):
    problem = _cantilever(beam)
    dt = float(problem.dt)
    executor = jaxsync.HostExecutor(chunk_steps=100)
    full = jaxsync.simulate(problem, 400, dt=dt, save=50, executor=executor)
    path = tmp_path / "run.ckpt.h5"
    jaxsync.simulate(problem, 200, dt=dt, save=50, executor=executor, checkpoint=str(path))
    with h5py.File(path, "r") as f:
        assert {"internal.Q", "internal.S_iso"} <= set(f)
    resumed = jaxsync.simulate(problem, 400, dt=dt, save=50, executor=executor, checkpoint=str(path))
    np.testing.assert_array_equal(resumed.displacement, full.displacement)
    # the same resume with the branch's state dropped would not be: the state matters
    from jaxsync.io.checkpoint import fingerprint

    state, _, _ = load_checkpoint(str(path), fingerprint(problem, dt, 50), 400)
    assert np.max(np.abs(np.asarray(state.internal["Q"]))) > 0


def test_the_gradient_in_tau_and_beta_matches_finite_differences(beam):
    problem = _cantilever(beam)
    dt = float(problem.dt)

    @jax.jit  # one program for the gradient and one for every finite-difference run
    def loss(tau, beta):
        run = jaxsync.simulate(problem.replace(material=_sls(tau=tau, beta=beta)), 100, dt=dt, save=100)
        return jnp.sum(run.displacement[-1] ** 2)

    g_tau, g_beta = jax.grad(loss, argnums=(0, 1))(TAU, BETA)
    h_tau, h_beta = 1e-4 * TAU, 1e-4 * BETA
    fd_tau = (loss(TAU + h_tau, BETA) - loss(TAU - h_tau, BETA)) / (2 * h_tau)
    fd_beta = (loss(TAU, BETA + h_beta) - loss(TAU, BETA - h_beta)) / (2 * h_beta)
    assert abs(float(fd_tau)) > 0 and abs(float(fd_beta)) > 0
    np.testing.assert_allclose(g_tau, fd_tau, rtol=1e-5)
    np.testing.assert_allclose(g_beta, fd_beta, rtol=1e-5)


def test_bad_parameters_are_refused():
    with pytest.raises(MaterialError, match="tau"):
        _sls(tau=0.0)
    with pytest.raises(MaterialError, match="beta"):
        _sls(beta=-0.5)


# the default run checks this feature for the standard linear solid (prony=False, the same test)
@pytest.mark.parametrize("prony", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_a_predicted_phase_carries_the_state(beam, prony):
    """A synchronization-avoiding run whose surrogate replays the synchronized run's exact
    shared displacements (an oracle) reproduces that run to round-off: each part's
    predicted steps update its elements' branch stresses as the synchronized steps do
    (the standard linear solid, and a two-branch Prony series)."""
    from jaxsync.fem.materials import ViscoelasticNeoHookean
    from jaxsync.solve.coupling import OraclePredictor, simulate_sync_avoiding
    from jaxsync.surrogate.training import shared_dof_layout

    problem = _cantilever(beam)
    if prony:
        problem = problem.replace(material=ViscoelasticNeoHookean(E, NU, RHO, betas=(BETA, 0.5), taus=(TAU, 5 * TAU)))
    dt = float(problem.dt)
    partition = jaxsync.partition(beam, 2)
    n_s, n_p, n_f, n_cri, n_steps = 5, 4, 4, 20, 300
    reference = jaxsync.simulate(problem, n_steps, dt=dt, partitions=partition)
    n_dof, counts = shared_dof_layout(partition)
    cycle = n_s * n_f
    # one cycle more than the steps: n_cri moves past the ramp's kinks, so the last cycle reaches beyond n_steps
    future = np.zeros((partition.n_parts, (-(-(n_steps - n_cri) // cycle) + 1) * cycle, n_dof))
    for p, part in enumerate(partition.parts):
        values = np.asarray(reference.displacement)[n_cri + 1:, part.shared_nodes].reshape(n_steps - n_cri, -1)
        future[p, :len(values), :counts[p]] = values
    oracle = OraclePredictor(future, first_step=n_cri + 1, n_s=n_s, n_past=n_p, n_future=n_f)
    online = simulate_sync_avoiding(problem, n_steps, dt=dt, partitions=partition, surrogates=oracle, n_cri=n_cri)
    # every step after the first synchronized phase predicted (n_cri moved past the load's ramp kinks)
    assert online.stats.n_predicted_steps == n_steps - online.stats.n_cri >= n_steps - n_cri - cycle
    scale = float(np.max(np.abs(reference.displacement)))
    np.testing.assert_allclose(online.displacement, reference.displacement, rtol=0, atol=1e-12 * scale)
    # the branch matters over these steps: the elastic law's run differs
    elastic = jaxsync.simulate(problem.replace(material=_sls(beta=0.0)), n_steps, dt=dt, partitions=partition)
    assert float(np.max(np.abs(elastic.displacement - reference.displacement))) > 1e-3 * scale
