"""Prony series of Maxwell branches on the neo-Hookean and HGO laws
(:mod:`jaxsync.fem.viscoelastic`).

References, all independent of the code under test: the exact small-strain response of
the split law with its bulk part (relaxation and creep of uniaxial stress, relaxation of
uniaxial strain), written here from the Laplace transform of the shear relaxation function
by partial fractions; the loss modulus of the Prony series and the dissipation of its
dashpots for a harmonic shear; a NumPy finite-strain reference that integrates the
branches' convolution exactly for a piecewise-linear stress on a 16 times finer grid
(felupe 11.3's ``finite_strain_viscoelastic`` is another model, the multiplicative one of
Shutov: not this one); the single-device run for the partitioned and deep-halo runs; the
uninterrupted run for the resumed one; central finite differences for the gradients.
"""

import jax
import jax.numpy as jnp
import numpy as np

import jaxsync
from jaxsync.fem.stepper import Probe, advance, build_system, initial_state
from jaxsync.fem.viscoelastic import ViscoelasticNeoHookean

E, NU, RHO = 1.0e6, 0.45, 1.0
BETAS, TAUS = (1.0, 2.0), (1.0e-3, 1.0e-2)
MU = E / (2 * (1 + NU))
K = E / (3 * (1 - 2 * NU))


def _law(**changes):
    return ViscoelasticNeoHookean(**{"E": E, "nu": NU, "rho": RHO, "betas": BETAS, "taus": TAUS, **changes})


# --- the exact small-strain response -----------------------------------------------------------

def _shear_modulus_polynomials(mu, betas, taus):
    """(N, D) with s G(s) = mu N(s) / D(s) for G(t) = mu (1 + sum beta_i exp(-t/tau_i))."""
    D = np.poly1d([1.0])
    for tau in taus:
        D = D * np.poly1d([1.0, 1.0 / tau])
    N = D
    for i, beta in enumerate(betas):
        term = np.poly1d([beta, 0.0])
        for j, tau in enumerate(taus):
            if j != i:
                term = term * np.poly1d([1.0, 1.0 / tau])
        N = N + term
    return N, D


def _ramp_response(num, den, t):
    """L^-1[num(s) / (den(s) s^2)](t): the response of the transfer function num/den to the
    unit ramp r(t) = t, by partial fractions (a double pole at 0, the simple roots of den)."""
    h0 = num(0.0) / den(0.0)
    h1 = (num.deriv()(0.0) * den(0.0) - num(0.0) * den.deriv()(0.0)) / den(0.0) ** 2
    poles = den.roots
    residues = num(poles) / (poles**2 * den.deriv()(poles))
    out = h0 * t + h1 + np.sum(residues[None, :] * np.exp(np.outer(t, poles)), axis=1)
    return np.real(out)


def _ramp_and_hold(num, den, amplitude, t_r, t):
    """The response to an input ramped from 0 to ``amplitude`` over t_r, then held."""
    late = np.clip(t - t_r, 0.0, None)
    return amplitude / t_r * (_ramp_response(num, den, t) - np.where(t > t_r, _ramp_response(num, den, late), 0.0))


def _uniaxial_stress_transfer(mu, bulk, betas, taus, *, creep=False):
    """s E(s) = 9 K s G(s) / (3 K + s G(s)) as (num, den); creep: its inverse."""
    N, D = _shear_modulus_polynomials(mu, betas, taus)
    num, den = 9.0 * bulk * mu * N, 3.0 * bulk * D + mu * N
    return (den, num) if creep else (num, den)


def test_the_ramp_response_helper_is_exact_for_a_known_transform():
    """L^-1[1 / ((s + 2) s^2)] = t/2 - 1/4 + exp(-2 t)/4."""
    t = np.linspace(0.0, 3.0, 7)
    np.testing.assert_allclose(_ramp_response(np.poly1d([1.0]), np.poly1d([1.0, 2.0]), t),
                               t / 2 - 0.25 + np.exp(-2 * t) / 4, rtol=0, atol=1e-14)


def _uniaxial_stress_history(law, n_steps, dt, *, stretch=None, nominal_stress=None):
    """A material point in uniaxial stress, F = diag(l1, lt, lt), P_22 = 0 solved by Newton
    at every step: either l1 = stretch(t) given (relaxation) or P_11 = nominal_stress(t)
    given (creep). Returns (t, l1, lt, P_11) of every step."""
    state0 = {k: v[0, 0] for k, v in law.internal_variables(1, 1).items()}

    def stress(x, state):
        F = jnp.diag(jnp.stack([x[0], x[1], x[1]]))
        return law.stress_update(F, None, state, dt)

    def step(carry, t):
        state, x = carry
        for _ in range(8):  # Newton on the unknown stretches
            if stretch is not None:
                x = x.at[0].set(stretch(t))
                g = lambda lt: stress(jnp.stack([x[0], lt]), state)[0][1, 1]  # noqa: E731
                x = x.at[1].add(-g(x[1]) / jax.grad(g)(x[1]))
            else:
                g = lambda y: jnp.stack([stress(y, state)[0][0, 0] - nominal_stress(t),  # noqa: E731
                                         stress(y, state)[0][1, 1]])
                x = x - jnp.linalg.solve(jax.jacfwd(g)(x), g(x))
        P, state = stress(x, state)
        return (state, x), (x[0], x[1], P[0, 0])

    t = jnp.arange(n_steps, dtype=float) * dt
    _, (l1, lt, p11) = jax.jit(lambda: jax.lax.scan(step, (state0, jnp.ones(2)), t))()
    return np.asarray(t), np.asarray(l1), np.asarray(lt), np.asarray(p11)


def test_uniaxial_stress_relaxation_matches_the_small_strain_closed_form():
    """A strain of 1e-4 ramped over 0.5 ms, then held: the Cauchy stress P_11 / lt^2
    against sigma(t) = int E(t - s) d eps/ds ds, E the uniaxial relaxation modulus of
    the split law (bulk K constant, shear mu (1 + sum beta_i exp(-t/tau_i)))."""
    law, eps, t_r, dt = _law(), 1.0e-4, 5.0e-4, 1.0e-5
    t, l1, lt, p11 = _uniaxial_stress_history(law, 5000, dt, stretch=lambda t: 1.0 + eps * jnp.minimum(t / t_r, 1.0))
    sigma = p11 / lt**2
    expected = _ramp_and_hold(*_uniaxial_stress_transfer(MU, K, BETAS, TAUS), eps, t_r, t)
    peak = float(np.max(np.abs(expected)))
    e_inf = 9 * K * MU / (3 * K + MU)
    assert peak > 2.0 * e_inf * eps  # a strong relaxation: at its peak more than twice the relaxed stress
    np.testing.assert_allclose(sigma, expected, rtol=0, atol=3e-4 * peak)
    np.testing.assert_allclose(sigma[-1], expected[-1], rtol=1e-4)  # the tail, where it has nearly relaxed
    assert abs(expected[-1] - e_inf * eps) < 0.02 * e_inf * eps  # towards the relaxed modulus


def test_uniaxial_creep_under_a_constant_stress_matches_the_closed_form():
    """A nominal stress ramped to 100 dyn/cm^2 over 0.5 ms, then held: the strain l1 - 1
    creeps as eps(t) = int J(t - s) d sigma/ds ds, J the creep compliance (the inverse
    transform of 1 / (s E(s)))."""
    law, sigma0, t_r, dt = _law(), 100.0, 5.0e-4, 1.0e-5
    t, l1, lt, _ = _uniaxial_stress_history(law, 5000, dt, nominal_stress=lambda t: sigma0 * jnp.minimum(t / t_r, 1.0))
    expected = _ramp_and_hold(*_uniaxial_stress_transfer(MU, K, BETAS, TAUS, creep=True), sigma0, t_r, t)
    e_inf = 9 * K * MU / (3 * K + MU)
    assert expected[-1] > 2.0 * expected[np.searchsorted(t, t_r)]  # the strain more than doubles while held
    np.testing.assert_allclose(l1 - 1.0, expected, rtol=0, atol=3e-4 * expected[-1])
    np.testing.assert_allclose(l1[-1] - 1.0, expected[-1], rtol=1e-4)
    assert 0.8 * sigma0 / e_inf < expected[-1] < sigma0 / e_inf  # creeping towards the relaxed compliance


def test_a_held_uniaxial_strain_of_a_block_relaxes_as_the_closed_form():
    """A unit cube, every node prescribed (uniaxial strain 1e-4 ramped over 0.2 ms, then
    held), two branches: the reaction on x = 1 against sigma_11 = int M(t - s) d eps/ds ds,
    M(t) = K + 4/3 mu (1 + sum beta_i exp(-t/tau_i))."""
    mesh = jaxsync.box_beam(1.0, 1.0, 1.0, (1, 1, 1))
    eps, t_r, dt, taus = 1.0e-4, 2.0e-4, 2.0e-6, (2.0e-4, 2.0e-3)
    problem = jaxsync.Problem(mesh=mesh, material=_law(taus=taus), dirichlet=(
        jaxsync.Dirichlet("x0"), jaxsync.Dirichlet("x1", value=(eps, 0.0, 0.0), time=jaxsync.Ramp(t_r))))
    system = build_system(problem, dt)
    state = initial_state(problem, system)
    assert state.internal["Q"].shape == (mesh.n_elements, 1, 2, 3, 3)
    pulled = jnp.asarray(np.isclose(problem.points[:, 0], 1.0))
    probe = Probe(per_step=lambda s, force, updated, new: jnp.sum(jnp.where(pulled, force[:, 0], 0.0)),
                  initial=lambda s: jnp.zeros(()), finish=lambda total: total)
    n = int(round(5 * taus[1] / dt))
    _, (_, reaction) = jax.jit(lambda st: advance(system, st, n, 1, probe=probe))(state)
    t = np.arange(n) * dt
    N, D = _shear_modulus_polynomials(MU, BETAS, taus)
    num, den = K * D + 4.0 / 3.0 * MU * N, D  # s M(s) = K + 4/3 s G(s)
    expected = _ramp_and_hold(num, den, eps, t_r, t)
    overstress = float(np.max(expected)) - (K + 4 / 3 * MU) * eps
    assert overstress > 0.5 * 4 / 3 * MU * eps  # the branches' stress at its peak, against the shear's
    np.testing.assert_allclose(np.asarray(reaction), expected, rtol=0, atol=3e-4 * float(np.max(expected)))


def test_the_energy_dissipated_per_cycle_is_the_loop_area_and_the_loss_modulus():
    """A harmonic shear gamma = gamma_0 sin(omega t) at small strain, steady state (ten
    cycles after the start, the transient exp(-t/tau) gone): the work of the stress over
    one cycle (the hysteresis loop's area, int P_12 d gamma), the dissipation of the
    dashpots over it (int sum_i Q_i,12^2 / (beta_i mu tau_i) dt) and pi G'' gamma_0^2
    with the loss modulus G'' = mu sum_i beta_i omega tau_i / (1 + (omega tau_i)^2)."""
    law, gamma0 = _law(), 1.0e-3
    omega = 1.0 / np.sqrt(TAUS[0] * TAUS[1])  # between the two relaxation times: both branches dissipate
    period = 2 * np.pi / omega
    per_cycle = 4000
    dt = period / per_cycle
    n = 12 * per_cycle
    state0 = {k: v[0, 0] for k, v in law.internal_variables(1, 1).items()}

    def step(state, t):
        F = jnp.eye(3).at[0, 1].set(gamma0 * jnp.sin(omega * t))
        P, state = law.stress_update(F, None, state, dt)
        return state, (P[0, 1], state["Q"][:, 0, 1])

    _, (p12, q12) = jax.jit(lambda: jax.lax.scan(step, state0, jnp.arange(n + 1, dtype=float) * dt))()
    p12, q12 = np.asarray(p12), np.asarray(q12)
    cycle = slice(n - per_cycle, n + 1)
    t = np.arange(n + 1)[cycle] * dt
    gamma = gamma0 * np.sin(omega * t)
    loop_area = np.trapezoid(p12[cycle], gamma)
    dissipated = np.trapezoid(np.sum(q12[cycle] ** 2 / (np.asarray(BETAS) * MU * np.asarray(TAUS)), axis=1), t)
    loss = MU * sum(b * omega * tau / (1 + (omega * tau) ** 2) for b, tau in zip(BETAS, TAUS))
    closed = np.pi * loss * gamma0**2
    assert loop_area > 0.1 * np.pi * MU * gamma0**2  # a wide loop
    np.testing.assert_allclose(loop_area, closed, rtol=2e-3)
    np.testing.assert_allclose(dissipated, closed, rtol=2e-3)
    np.testing.assert_allclose(loop_area, dissipated, rtol=2e-3)
