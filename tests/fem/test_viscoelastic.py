"""Prony series of Maxwell branches on the neo-Hookean and HGO laws
(:mod:`jaxsync.fem.materials`).

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
import pytest

import jaxsync
from jaxsync.errors import ConfigError, MaterialError
from jaxsync.fem import Probe, advance, build_system, initial_state
from jaxsync.fem.materials import ViscoelasticHGO, ViscoelasticNeoHookean

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
    law = _law(nu=0.3, taus=taus)  # (P1 elements: away from incompressibility)
    mu, bulk = law.mu, law.bulk
    problem = jaxsync.Problem(mesh=mesh, material=law, dirichlet=(
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
    N, D = _shear_modulus_polynomials(mu, BETAS, taus)
    num, den = bulk * D + 4.0 / 3.0 * mu * N, D  # s M(s) = K + 4/3 s G(s)
    expected = _ramp_and_hold(num, den, eps, t_r, t)
    overstress = float(np.max(expected)) - (bulk + 4 / 3 * mu) * eps
    assert overstress > 0.5 * 4 / 3 * mu * eps  # the branches' stress at its peak, against the shear's
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


# --- large strain: against an independent NumPy integration ----------------------------------------

def _numpy_stress_parts(F, mu, bulk, k1=0.0, k2=1.0, kappa=0.0, fibres=None):
    """{"volumetric", "isochoric", "fibres"} second Piola-Kirchhoff stresses (n, 3, 3) of
    F (n, 3, 3): the split neo-Hookean law and the HGO fibres (NumPy)."""
    C = np.einsum("nki,nkj->nij", F, F)
    J = np.linalg.det(F)
    c_inv = np.linalg.inv(C)
    i1 = np.trace(C, axis1=1, axis2=2)
    eye = np.eye(3)[None]
    parts = {"volumetric": (0.5 * bulk * (J**2 - 1.0))[:, None, None] * c_inv,
             "isochoric": (mu * J ** (-2.0 / 3.0))[:, None, None] * (eye - (i1 / 3.0)[:, None, None] * c_inv),
             "fibres": np.zeros_like(F)}
    for a in ([] if fibres is None else fibres):
        i4 = np.einsum("i,nij,j->n", a, C, a)
        strain = kappa * (i1 - 3.0) + (1.0 - 3.0 * kappa) * (i4 - 1.0)
        slope = np.where(i4 >= 1.0, k1 * strain * np.exp(k2 * strain**2), 0.0)
        parts["fibres"] += 2.0 * slope[:, None, None] * (kappa * eye + (1.0 - 3.0 * kappa) * np.outer(a, a)[None])
    return parts


def _numpy_reference(F_of_t, t, parts_of, branches, refine=16):
    """P (n, 3, 3) at the times t (a uniform grid from 0) of S = sum of the parts + the
    branches' Q, each Q = int beta exp(-(t - s)/tau) dS_part/ds ds integrated exactly for
    S_part linear in time between the points of a grid ``refine`` times finer."""
    fine = np.linspace(0.0, t[-1], refine * (len(t) - 1) + 1)
    h = fine[1] - fine[0]
    parts = parts_of(F_of_t(fine))
    S = sum(parts.values())
    for part, (betas, taus) in branches.items():
        jump = np.diff(parts[part], axis=0, prepend=np.zeros((1, 3, 3)))  # the state starts at rest
        for beta, tau in zip(betas, taus):
            decay, gain = np.exp(-h / tau), beta * tau / h * (1.0 - np.exp(-h / tau))
            q = np.zeros((len(fine), 3, 3))
            q[0] = beta * jump[0]  # a jump at t = 0 passes whole
            for k in range(1, len(fine)):
                q[k] = decay * q[k - 1] + gain * jump[k]
            S = S + q
    return np.einsum("nij,njk->nik", F_of_t(t), S[::refine])


def _point_history(law, F_of_t, t, fibres=None):
    """P (n, 3, 3) of ``law.stress_update`` at the times t (a uniform grid from 0)."""
    dt = float(t[1] - t[0])
    state0 = {k: v[0, 0] for k, v in law.internal_variables(1, 1).items()}

    def step(state, F):
        P, state = law.stress_update(F, None if fibres is None else jnp.asarray(fibres), state, dt)
        return state, P

    return np.asarray(jax.lax.scan(step, state0, jnp.asarray(F_of_t(t)))[1])


def _large_path(H, t_r):
    return lambda t: np.eye(3)[None] + np.minimum(t / t_r, 1.0)[:, None, None] * np.asarray(H)[None]


def test_large_strain_neo_hookean_matches_an_independent_integration():
    """A deformation ramped to F = I + H (stretches up to 1.6, shear) over 3 ms, then held:
    P at every step against the NumPy reference (exact convolution, 16 times finer grid)."""
    H = [[0.6, 0.3, 0.0], [0.0, -0.2, 0.1], [0.05, 0.0, -0.15]]
    t = np.arange(1501) * 2.0e-5
    F_of_t = _large_path(H, 3.0e-3)
    P = _point_history(_law(), F_of_t, t)
    reference = _numpy_reference(F_of_t, t, lambda F: _numpy_stress_parts(F, MU, K),
                                 {"isochoric": (BETAS, TAUS)})
    elastic = _numpy_reference(F_of_t, t, lambda F: _numpy_stress_parts(F, MU, K), {})
    overstress = float(np.max(np.abs(reference - elastic)))
    assert overstress > 0.3 * float(np.max(np.abs(reference)))
    np.testing.assert_allclose(P, reference, rtol=0, atol=1e-4 * overstress)


HGO = dict(mu=3.0e5, k1=3.0e5, k2=1.0, kappa_bulk=1.5e6, rho=1.0, dispersion=0.05)
FIBRES = np.array([[np.cos(0.5), np.sin(0.5), 0.0], [np.cos(0.5), -np.sin(0.5), 0.0]])


def _hgo(**changes):
    return ViscoelasticHGO(**{**HGO, "betas": (0.8, 1.5), "taus": (1.0e-3, 5.0e-3), "fibre_betas": (2.0,),
                              "fibre_taus": (2.0e-3,), **changes})


def test_large_strain_hgo_with_relaxing_fibres_matches_an_independent_integration():
    """The HGO law with two branches on its ground matrix and one on its fibres (both
    families stretched, I4 up to 1.9), against the same NumPy reference."""
    H = [[0.5, 0.2, 0.0], [0.1, 0.1, 0.0], [0.0, 0.05, -0.2]]
    t = np.arange(1001) * 1.0e-5
    F_of_t = _large_path(H, 2.0e-3)
    law = _hgo()
    P = _point_history(law, F_of_t, t, fibres=FIBRES)

    def parts(F):
        return _numpy_stress_parts(F, HGO["mu"], HGO["kappa_bulk"], HGO["k1"], HGO["k2"], HGO["dispersion"], FIBRES)

    reference = _numpy_reference(F_of_t, t, parts, {"isochoric": (law.betas, law.taus),
                                                    "fibres": (law.fibre_betas, law.fibre_taus)})
    matrix_only = _numpy_reference(F_of_t, t, parts, {"isochoric": (law.betas, law.taus)})
    fibre_overstress = float(np.max(np.abs(reference - matrix_only)))
    assert fibre_overstress > 0.1 * float(np.max(np.abs(reference)))  # the fibres' branch matters
    np.testing.assert_allclose(P, reference, rtol=0, atol=1e-4 * float(np.max(np.abs(reference))))


def test_the_instantaneous_law_is_the_elastic_law_with_stiffer_relaxing_parts():
    """first_piola and energy are those of the elastic law whose relaxing parts are (1 +
    sum beta) times stiffer: mu (1 + sum betas) for the neo-Hookean law; for HGO that mu
    and k1 (1 + sum fibre_betas). With no fibre branch the fibres keep their k1; the split
    parts sum to the elastic law's own stress."""
    F = np.eye(3)[None] + 0.15 * np.random.default_rng(3).normal(size=(30, 3, 3))
    a = np.broadcast_to(FIBRES, (30, 2, 3))
    stiff_mu = MU * (1 + sum(BETAS))
    glassy = jaxsync.NearlyIncompressibleNeoHookean(9 * K * stiff_mu / (3 * K + stiff_mu),
                                                     (3 * K - 2 * stiff_mu) / (2 * (3 * K + stiff_mu)), RHO)
    np.testing.assert_allclose(_law().first_piola(F), glassy.first_piola(F), rtol=1e-11, atol=1e-11 * E)
    np.testing.assert_allclose(_law().energy(F), glassy.energy(F), rtol=1e-11)
    law = _hgo()
    glassy = jaxsync.HolzapfelGasserOgden(**{**HGO, "mu": HGO["mu"] * (1 + sum(law.betas)),
                                             "k1": HGO["k1"] * (1 + sum(law.fibre_betas))})
    np.testing.assert_allclose(law.first_piola(F, a), glassy.first_piola(F, a), rtol=1e-11, atol=1e-11 * E)
    np.testing.assert_allclose(law.energy(F, a), glassy.energy(F, a), rtol=1e-11)
    matrix_only = _hgo(fibre_betas=None, fibre_taus=None)
    assert set(matrix_only.internal_variables(2, 1)) == {"Q", "S_iso"}
    glassy = jaxsync.HolzapfelGasserOgden(**{**HGO, "mu": HGO["mu"] * (1 + sum(law.betas))})
    np.testing.assert_allclose(matrix_only.first_piola(F, a), glassy.first_piola(F, a), rtol=1e-11, atol=1e-11 * E)
    elastic = jaxsync.HolzapfelGasserOgden(**HGO)
    parts = elastic.stress_parts(jnp.asarray(F), jnp.asarray(a))
    np.testing.assert_allclose(F @ sum(parts.values()), elastic.first_piola(F, a), rtol=1e-11, atol=1e-11 * E)
    np.testing.assert_allclose(sum(elastic.energy_parts(F, a).values()), elastic.energy(F, a), rtol=1e-12)
    reference = _numpy_stress_parts(F, HGO["mu"], HGO["kappa_bulk"], HGO["k1"], HGO["k2"], HGO["dispersion"], FIBRES)
    for name, value in parts.items():
        np.testing.assert_allclose(value, reference[name], rtol=1e-11, atol=1e-11 * E)


def test_bad_branches_are_refused_with_the_fix():
    for changes, match in [(dict(betas=(1.0, -0.5)), r"betas\[1\].*>= 0"), (dict(taus=(1e-3, 0.0)), r"taus\[1\]"),
                           (dict(taus=(1e-3,)), "2 entries and taus 1"), (dict(betas=(), taus=()), "empty"),
                           (dict(betas=None, taus=None), "needs its Maxwell branches"),
                           (dict(taus=None), "give both betas and taus")]:
        with pytest.raises(MaterialError, match=match):
            _law(**changes)
    with pytest.raises(MaterialError, match="fibre_taus"):
        _hgo(fibre_taus=(1e-3, 2e-3))
    with pytest.raises(MaterialError, match="k1"):
        _hgo(k1=-1.0)


# --- runs: partitions, executors, checkpoints, gradients, TOML ----------------------------------------

@pytest.fixture(scope="module")
def beam():
    return jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1))


def _cantilever(beam, material=None, **changes):
    material = _law(nu=0.3, taus=(2.0e-3, 1.0e-2), **changes) if material is None else material
    return jaxsync.cantilever(beam, material=material, body_force=(0.0, 0.0, -2.0e4), t_ramp=0.002, damping=50.0)


def _hgo_cantilever(beam):
    fibres = jaxsync.helical_fibres(beam.points[beam.tets].mean(axis=1), axis=(1.0, 0.0, 0.0), angle=30.0,
                                    origin=(0.0, 0.5, 0.5))
    law = _hgo(mu=4.0e5, k1=4.0e5, kappa_bulk=2.0e6, fibres=fibres)
    return _cantilever(beam, material=law)


def test_a_partitioned_run_and_its_state_equal_the_single_device_run(beam, tmp_path):
    """Two parts, host executor, the state merged into a checkpoint: the single device's
    displacements and, element by element, its branch stresses; the branches change the
    run (against the long-term elastic law)."""
    from jaxsync.io.checkpoint import fingerprint, load_checkpoint

    problem = _cantilever(beam)
    dt = float(problem.dt)
    executor = jaxsync.HostExecutor(chunk_steps=100)
    one = jaxsync.simulate(problem, 200, dt=dt, save=50, executor=executor, checkpoint=str(tmp_path / "one.h5"))
    two = jaxsync.simulate(problem, 200, dt=dt, save=50, executor=executor, partitions=2,
                           checkpoint=str(tmp_path / "two.h5"))
    scale = float(np.max(np.abs(one.displacement)))
    np.testing.assert_allclose(two.displacement, one.displacement, rtol=0, atol=1e-12 * scale)
    key = fingerprint(problem, dt, 50)
    state_one, state_two = (load_checkpoint(str(tmp_path / f"{n}.h5"), key, 200)[0] for n in ("one", "two"))
    assert set(state_one.internal) == {"Q", "S_iso"} and state_one.internal["Q"].shape == (beam.n_elements, 1, 2, 3, 3)
    for name in ("Q", "S_iso"):
        size = float(np.max(np.abs(state_one.internal[name])))
        assert size > 0
        np.testing.assert_allclose(state_two.internal[name], state_one.internal[name], rtol=0, atol=1e-10 * size)
    elastic = jaxsync.simulate(problem.replace(material=problem.material.elastic_law()), 200, dt=dt, save=50)
    assert float(np.max(np.abs(elastic.displacement - one.displacement))) > 0.02 * scale


# the default run checks partitioned viscoelastic runs in
# test_a_partitioned_run_and_its_state_equal_the_single_device_run and the relaxing fibres in
# test_large_strain_hgo_with_relaxing_fibres_matches_an_independent_integration
@pytest.mark.slow
def test_the_hgo_law_with_relaxing_fibres_runs_partitioned_as_on_one_device(beam):
    """The traced executor on two parts against one device, for ViscoelasticHGO with
    branches on the ground matrix and the fibres; its fibre branches change the run."""
    problem = _hgo_cantilever(beam)
    dt = float(problem.dt)
    one = jaxsync.simulate(problem, 200, dt=dt, save=50)
    traced = jaxsync.simulate(problem, 200, dt=dt, save=50, partitions=2, executor=jaxsync.TracedExecutor())
    scale = float(np.max(np.abs(one.displacement)))
    np.testing.assert_allclose(traced.displacement, one.displacement, rtol=0, atol=1e-12 * scale)
    elastic_fibres = problem.replace(material=problem.material.replace(fibre_betas=None, fibre_taus=None))
    other = jaxsync.simulate(elastic_fibres, 200, dt=dt, save=50)
    assert float(np.max(np.abs(other.displacement - one.displacement))) > 1e-3 * scale


def test_a_resumed_run_is_bit_identical(beam, tmp_path):
    problem = _cantilever(beam)
    dt = float(problem.dt)
    executor = jaxsync.HostExecutor(chunk_steps=100)
    full = jaxsync.simulate(problem, 400, dt=dt, save=50, executor=executor)
    path = tmp_path / "run.ckpt.h5"
    jaxsync.simulate(problem, 200, dt=dt, save=50, executor=executor, checkpoint=str(path))
    resumed = jaxsync.simulate(problem, 400, dt=dt, save=50, executor=executor, checkpoint=str(path))
    np.testing.assert_array_equal(resumed.displacement, full.displacement)
    # another Prony series does not resume from it
    from jaxsync.io.checkpoint import fingerprint

    assert fingerprint(problem, dt, 50) != fingerprint(_cantilever(beam, betas=(1.0, 2.5)), dt, 50)


def test_the_gradient_in_every_beta_and_tau_matches_finite_differences(beam):
    problem = _cantilever(beam)
    dt = float(problem.dt)
    params = np.array([*BETAS, 2.0e-3, 1.0e-2])

    @jax.jit
    def loss(p):
        law = _law(nu=0.3, betas=(p[0], p[1]), taus=(p[2], p[3]))
        run = jaxsync.simulate(problem.replace(material=law), 100, dt=dt, save=100)
        return jnp.sum(run.displacement[-1] ** 2)

    grad = np.asarray(jax.grad(loss)(jnp.asarray(params)))
    for i in range(4):
        h = 1e-4 * params[i]
        up, down = params.copy(), params.copy()
        up[i] += h
        down[i] -= h
        fd = (float(loss(jnp.asarray(up))) - float(loss(jnp.asarray(down)))) / (2 * h)
        assert abs(fd) > 0
        np.testing.assert_allclose(grad[i], fd, rtol=1e-5)


_BEAM = """
[mesh]
length = 4.0
divisions = [4, 1, 1]
[problem]
body_force = [0.0, 0.0, -2.0e4]
t_ramp = 0.002
[run]
n_steps = 40
"""


def test_toml_models_and_their_errors(tmp_path):
    from jaxsync.app.config import load_config, problem_from_config

    cfg = tmp_path / "visco.toml"
    cfg.write_text(_BEAM + '[material]\nmodel = "viscoelastic-neo-hookean"\nE = 2.0e6\nnu = 0.35\n'
                   'betas = [1.0, 2.0]\ntaus = [1.0e-3, 1.0e-2]\n')
    problem, _ = problem_from_config(load_config(cfg))
    assert problem.material == ViscoelasticNeoHookean(2.0e6, 0.35, 1.0, (1.0, 2.0), (1.0e-3, 1.0e-2))
    cfg.write_text(_BEAM + '[material]\nmodel = "viscoelastic-hgo"\nmu = 3.0e5\nk1 = 2.0e5\nk2 = 0.8\n'
                   'kappa_bulk = 1.5e6\nbetas = [1.0]\ntaus = [2.0e-3]\nfibre_betas = [0.5]\nfibre_taus = [1.0e-3]\n'
                   'fibre_angle = 29.0\nfibre_axis = [1.0, 0.0, 0.0]\nfibre_origin = [0.0, 0.5, 0.5]\n')
    problem, _ = problem_from_config(load_config(cfg))
    m = problem.material
    assert isinstance(m, ViscoelasticHGO) and (m.betas, m.taus, m.fibre_betas, m.fibre_taus) == (
        (1.0,), (2.0e-3,), (0.5,), (1.0e-3,))
    centres = problem.mesh.points[problem.mesh.tets].mean(axis=1)
    np.testing.assert_array_equal(m.fibres, jaxsync.helical_fibres(centres, axis=(1.0, 0.0, 0.0), angle=29.0,
                                                                   origin=(0.0, 0.5, 0.5)))
    for keys, error, match in [("betas = [1.0, -1.0]\ntaus = [1.0, 1.0]", MaterialError, r"betas\[1\]"),
                               ("betas = [1.0]\ntaus = [0.0]", MaterialError, r"taus\[0\]"),
                               ("betas = [1.0, 2.0]\ntaus = [1.0]", MaterialError, "2 entries and taus 1"),
                               ("taus = [1.0]", MaterialError, "give both betas and taus"),
                               ("betas = []\ntaus = []", ConfigError, "empty")]:
        cfg.write_text(_BEAM + f'[material]\nmodel = "viscoelastic-neo-hookean"\n{keys}\n')
        with pytest.raises(error, match=match):
            problem_from_config(load_config(cfg))


@pytest.fixture(scope="module")
def halo_beam_run():
    """(the cantilever on an 8 x 1 x 1 beam, its step, its single-device run of 120 steps)."""
    mesh = jaxsync.box_beam(4.0, 1.0, 1.0, (8, 1, 1))
    problem = _cantilever(mesh)
    dt = float(problem.dt)
    return problem, dt, jaxsync.simulate(problem, 120, dt=dt, save=12)


# the default run checks deep halos carrying the state in the first case (depth 3, host executor), and the
# traced executor carrying the state of two parts in
# test_internal_variables.py::test_a_partitioned_run_and_its_state_equal_the_single_device_run
@pytest.mark.parametrize("depth, traced", [(3, False), pytest.param(2, True, marks=pytest.mark.slow)])
def test_deep_halos_carry_the_state_and_equal_the_single_device_run(monkeypatch, halo_beam_run, depth, traced):
    """Deep halos of depth 3 and 2 (host and traced executors) against one device: each
    part carries the state of its halo elements too, and the exchange copies that of the
    shared elements from their owners. Without that copy (patched out) depth 3 drifts:
    the outer halo elements' state went through displacements that were wrong there."""
    from jaxsync.fem import SolverState
    from jaxsync.parallel.exchange import halo_partition, refresh_halo

    problem, dt, one = halo_beam_run
    mesh = problem.mesh
    scale = float(np.max(np.abs(one.displacement)))
    grown = halo_partition(jaxsync.partition(mesh, 2), 3)
    assert grown.n_element_interface > 0 and all(len(p.elements) < mesh.n_elements for p in grown.parts)
    executor = jaxsync.TracedExecutor() if traced else jaxsync.HostExecutor(chunk_steps=60)
    run = jaxsync.simulate(problem, 120, dt=dt, save=12, partitions=2, sync=jaxsync.Halo(depth), executor=executor)
    np.testing.assert_allclose(run.displacement, one.displacement, rtol=0, atol=1e-12 * scale)
    if traced:
        return
    refresh = refresh_halo

    def without_the_state(part, state, n_interface, across=None, n_element_interface=0):
        s = refresh(part, SolverState(state.displacement, state.previous, state.step), n_interface, across)
        return SolverState(s.displacement, s.previous, s.step, state.internal)

    monkeypatch.setattr("jaxsync.parallel.exchange._halo.refresh_halo", without_the_state)
    drifted = jaxsync.simulate(problem, 120, dt=dt, save=12, partitions=2, sync=jaxsync.Halo(3))
    assert float(np.max(np.abs(drifted.displacement - one.displacement))) > 1e-6 * scale


def test_the_stable_step_is_that_of_the_instantaneous_stiffness(beam):
    """The default step of each law is that of the elastic law with its relaxing parts
    (1 + sum beta) times stiffer (the neo-Hookean shear modulus; the HGO matrix and fibres)."""
    problem = _cantilever(beam)
    law = problem.material
    mu = law.mu * (1 + sum(law.betas))
    glassy = jaxsync.NearlyIncompressibleNeoHookean(9 * law.bulk * mu / (3 * law.bulk + mu),
                                                     (3 * law.bulk - 2 * mu) / (2 * (3 * law.bulk + mu)), law.rho)
    np.testing.assert_allclose(problem.dt, problem.replace(material=glassy).dt, rtol=1e-9)
    assert problem.dt < 0.8 * problem.replace(material=law.elastic_law()).dt  # not the long-term law's step
    problem = _hgo_cantilever(beam)
    law = problem.material
    glassy = jaxsync.HolzapfelGasserOgden(law.mu * (1 + sum(law.betas)), law.k1 * (1 + sum(law.fibre_betas)), law.k2,
                                          law.kappa_bulk, law.rho, law.dispersion, law.fibres)
    np.testing.assert_allclose(problem.dt, problem.replace(material=glassy).dt, rtol=1e-9)
