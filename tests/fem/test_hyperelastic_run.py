"""Hyperelastic problems in runs, checkpoints, TOML files and statics: the default step of
the tangent at rest, the stable step and inverted elements checked during a run, the
checkpoint fingerprint of the law, the [material] models of a TOML file and ``jaxsync
simulate``, and Newton's method for the static equilibrium.

References are independent of the code under test: tangent stiffnesses assembled here in
numpy (the ground matrix and the fibres' small-strain stiffness written out) or by felupe,
eigenvalues by numpy, inverted elements by numpy determinants, felupe's Newton solutions
on the same meshes, the paper's CFL formula, and the fingerprint of a linear problem as
the checkpoints written before hyperelastic laws existed hashed it."""

import hashlib
import re

import jax.numpy as jnp
import numpy as np
import pytest

import jaxsync
from jaxsync.app.config import load_config, problem_from_config
from jaxsync.cli import main
from jaxsync.errors import CheckpointError, ConfigError, ConvergenceError, StabilityError
from jaxsync.fem import RunCheck, SolverState, build_system
from jaxsync.fem.forces import TotalLagrangian, inverted_elements
from jaxsync.fem.materials import HolzapfelGasserOgden, NeoHookean, helical_fibres
from jaxsync.io.checkpoint import fingerprint

E, NU, RHO = 1.0e6, 0.3, 1.0
MU, LAM = E / (2 * (1 + NU)), E * NU / ((1 + NU) * (1 - 2 * NU))
HGO = dict(mu=3.0e5, k1=2.0e6, k2=0.8, kappa_bulk=1.0e6, rho=1.0)


@pytest.fixture(scope="module")
def beam():
    return jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1))


def _centroids(mesh):
    return mesh.points[mesh.tets].mean(axis=1)


def _fibres(mesh, angle=35.0):
    return helical_fibres(_centroids(mesh), axis=(1.0, 0.0, 0.0), angle=angle, origin=(0.0, 0.5, 0.5))


def _gradients(points, tets):
    """(m, 4, 3) P1 shape-function gradients and (m,) volumes (numpy)."""
    X = points[tets]
    D = np.concatenate([np.ones((len(tets), 4, 1)), X], axis=2)  # N_a = c_a + g_a . x
    inverse = np.linalg.inv(D)  # columns: coefficients of N_a
    return np.transpose(inverse[:, 1:, :], (0, 2, 1)), np.abs(np.linalg.det(D)) / 6.0


def _linear_stiffness(points, tets, lam, mu):
    """The small-strain stiffness (3n, 3n) of lam, mu, assembled in numpy (node-interleaved)."""
    g, vol = _gradients(points, tets)
    n = len(points)
    K = np.zeros((3 * n, 3 * n))
    for e in range(len(tets)):
        for a in range(4):
            for b in range(4):
                ga, gb = g[e, a], g[e, b]
                block = lam * np.outer(ga, gb) + mu * np.outer(gb, ga) + mu * np.dot(ga, gb) * np.eye(3)
                A, B = tets[e, a], tets[e, b]
                K[3 * A:3 * A + 3, 3 * B:3 * B + 3] += vol[e] * block
    return K


def _fibre_stiffness(points, tets, fibres, k1):
    """The fibres' stiffness at rest: psi_f ~ 2 k1 (a . eps a)^2 per family (kappa = 0), so
    K_f = sum_e V_e sum_f 4 k1 g_f g_f^T with g_f[3 a + i] = a_i (grad N_a . a)."""
    g, vol = _gradients(points, tets)
    n = len(points)
    K = np.zeros((3 * n, 3 * n))
    for e in range(len(tets)):
        dofs = (3 * tets[e][:, None] + np.arange(3)).ravel()
        for a in fibres[e]:
            vec = (np.outer(g[e] @ a, a)).ravel()
            K[np.ix_(dofs, dofs)] += vol[e] * 4.0 * k1 * np.outer(vec, vec)
    return K


def _bound(K, mass, fixed):
    """2 / omega_max of K over the lumped mass (3n,) on the free dofs (numpy)."""
    free = np.setdiff1d(np.arange(len(mass)), fixed)
    s = 1.0 / np.sqrt(mass[free])
    return 2.0 / np.sqrt(np.linalg.eigvalsh(K[np.ix_(free, free)] * s[:, None] * s[None, :])[-1])


def _nodal_mass(points, tets, rho):
    _, vol = _gradients(points, tets)
    m = np.zeros(len(points))
    np.add.at(m, tets.ravel(), np.repeat(rho * vol / 4.0, 4))
    return np.repeat(m, 3)


# --- 1. the default step --------------------------------------------------------------------

def test_default_step_of_hgo_includes_the_fibres(beam):
    """Problem.dt of HGO is below alpha_s times the exact bound of the tangent at rest with the
    fibres (assembled here in numpy), while the step of the small-strain constants alone (the
    ground matrix, as Problem.dt gave before) is above that bound."""
    fibres = _fibres(beam)
    problem = jaxsync.cantilever(beam, material=HolzapfelGasserOgden(**HGO, fibres=fibres))
    m = problem.material
    K = _linear_stiffness(beam.points, beam.tets, float(m.lam), float(m.mu))
    K += _fibre_stiffness(beam.points, beam.tets, fibres, HGO["k1"])
    fixed, _ = problem.dirichlet_dofs()
    true = _bound(K, _nodal_mass(beam.points, beam.tets, HGO["rho"]), fixed)
    step = problem.time_step
    assert step.law == "HolzapfelGasserOgden"
    assert step.exact == pytest.approx(true, rel=1e-9)
    assert problem.dt <= 0.9 * true * (1 + 1e-12)
    assert jaxsync.max_stable_dt(problem) == pytest.approx(true, rel=1e-9)
    ground = jaxsync.cantilever(beam, material=jaxsync.LinearElastic(float(m.E), float(m.nu), HGO["rho"]))
    assert ground.dt > true  # the small-strain step would be unstable
    from jaxsync.fem import check_dt

    check_dt(problem, 0.99 * true)
    with pytest.raises(StabilityError, match="HolzapfelGasserOgden tangent stiffness at rest"):
        check_dt(problem, 1.01 * true)
    with pytest.raises(StabilityError, match="above the stability bound"):
        jaxsync.simulate(problem, 10, dt=1.01 * true)


def test_default_step_of_neo_hookean_is_that_of_its_tangent(beam):
    """At rest neo-Hookean's tangent is the linear stiffness of E, nu: its exact bound is the
    numpy one, and the step is 0.9 times the element rule (below the bound)."""
    problem = jaxsync.cantilever(beam, material=NeoHookean(E, NU, RHO), element="P1")
    fixed, _ = problem.dirichlet_dofs()
    true = _bound(_linear_stiffness(beam.points, beam.tets, LAM, MU), _nodal_mass(beam.points, beam.tets, RHO),
                  fixed)
    step = problem.time_step
    assert step.exact == pytest.approx(true, rel=1e-9)
    assert step.rule == "element"
    assert step.dt == pytest.approx(0.9 * jaxsync.stable_dt(problem, alpha_s=1.0, rule="element"), rel=1e-14)
    assert 0.5 * 0.9 * true < step.dt <= 0.9 * true
    assert "NeoHookean" in problem.summary()


def test_linear_elastic_default_step_is_the_papers_rule():
    """LinearElastic keeps the paper's CFL rule: 0.9 min_e h_e / sqrt(E / (rho (1 - nu^2))),
    h_e = 2 (shortest edge) / sqrt(24), to the last bit."""
    problem = jaxsync.cantilever()
    p = problem.mesh.points[problem.mesh.tets]
    edges = np.min([np.linalg.norm(p[:, i] - p[:, j], axis=1) for i in range(4) for j in range(i + 1, 4)], axis=0)
    expected = np.min(0.9 * (2.0 * edges / np.sqrt(24.0)) / np.sqrt(E / (RHO * (1.0 - NU**2))))
    assert problem.time_step.rule == "cfl" and problem.time_step.law is None
    assert problem.dt == expected


# --- 2. the run-time check --------------------------------------------------------------------

def _felupe_bound(points, tets, u, fixed):
    """2 / omega_max of felupe's tangent of neo-Hookean at u over the lumped mass."""
    fem = pytest.importorskip("felupe")
    field = fem.FieldContainer([fem.Field(fem.RegionTetra(fem.Mesh(points, tets, "tetra")), dim=3)])
    field[0].values[:] = u
    K = fem.SolidBody(fem.NeoHookeCompressible(mu=MU, lmbda=LAM), field).assemble.matrix().toarray()
    return _bound(K, _nodal_mass(points, tets, RHO), fixed)


def test_run_refuses_a_step_above_the_bound_of_the_deformed_state():
    """A block squeezed along x by a prescribed end motion: dt is below the bound at rest but
    above that of the compressed state. The run stops at the first check (every chunk of
    20 steps) whose state has a bound (felupe's tangent, numpy eigenvalues) below dt, the
    state checked before it having one above dt; the snapshots before are kept."""
    mesh = jaxsync.box_beam(2.0, 1.0, 1.0, (4, 2, 2))
    problem = jaxsync.Problem(mesh=mesh, material=NeoHookean(E, NU, RHO), damping=50.0, dirichlet=(
        jaxsync.Dirichlet("x0"), jaxsync.Dirichlet("x1", (-0.8, 0.0, 0.0), (0,), time=jaxsync.Ramp(0.05))))
    fixed, _ = problem.dirichlet_dofs()
    dt = 0.97 * problem.time_step.exact
    at_rest = _felupe_bound(mesh.points, mesh.tets, np.zeros((mesh.n_nodes, 3)), fixed)
    assert dt < at_rest
    with pytest.raises(StabilityError) as info:
        jaxsync.simulate(problem, 400, dt=dt, save=10, executor=jaxsync.HostExecutor(chunk_steps=20))
    error = info.value
    message = str(error)
    step = int(re.search(r"state at step (\d+)", message).group(1))
    bound = float(re.search(r"2/omega_max = ([0-9.e+-]+) s", message).group(1))
    assert f"t = {step * dt:.6g} s" in message and "rerun with dt <=" in message
    traj = error.trajectory
    assert traj.result == jaxsync.Result.DIVERGED and np.all(np.isfinite(traj.displacement))
    assert traj.n_saved == step // 10 + 1 and 0 < step < 400
    refused = _felupe_bound(mesh.points, mesh.tets, traj.displacement[-1], fixed)
    passed = _felupe_bound(mesh.points, mesh.tets, traj.displacement[-3], fixed)  # the check before
    assert bound == pytest.approx(refused, rel=5e-5)  # the message shows 5 digits
    assert refused < dt <= passed


def test_an_inverting_load_stops_the_run_naming_the_elements(beam):
    """A body force far beyond what the beam carries folds elements: the run stops with the
    inverted elements (numpy determinants of the last snapshot kept: the folded state, all
    elements positive one step before) and every snapshot saved before."""
    problem = jaxsync.cantilever(beam, material=NeoHookean(E, NU, RHO), body_force=(0.0, 0.0, -1.0e7),
                                 t_ramp=0.01, damping=0.0)
    with pytest.raises(StabilityError, match="inverted") as info:
        jaxsync.simulate(problem, 400, save=1, executor=jaxsync.HostExecutor(chunk_steps=100))
    error = info.value
    traj = error.trajectory
    assert traj.result == jaxsync.Result.DIVERGED and np.all(np.isfinite(traj.displacement))
    X = beam.points[beam.tets]

    def ratio(u):
        x = (beam.points + u)[beam.tets]
        return np.linalg.det(x[:, 1:] - x[:, :1]) / np.linalg.det(X[:, 1:] - X[:, :1])

    expected = np.flatnonzero(ratio(traj.displacement[-1]) <= 0)
    assert len(expected) > 0 and np.all(ratio(traj.displacement[-2]) > 0)
    np.testing.assert_array_equal(error.elements, expected)
    step = traj.n_saved - 1
    assert f"at step {step} (t = {step * problem.dt:.6g} s)" in str(error)
    assert ", ".join(str(e) for e in expected) in str(error)


def test_run_check_refuses_an_inverted_state_directly(beam):
    problem = jaxsync.cantilever(beam, material=NeoHookean(E, NU, RHO))
    system = build_system(problem, problem.dt, TotalLagrangian())
    check = RunCheck(problem, system, float(problem.dt))
    u = np.zeros((problem.n_nodes, 3))
    assert check.check(SolverState(jnp.asarray(u), jnp.asarray(u), jnp.asarray(0))) >= problem.dt
    node = int(np.flatnonzero(np.all(np.isclose(beam.points, [2.0, 1.0, 1.0]), axis=1))[0])
    u[node] = [-1.6, -1.7, -1.8]
    with pytest.raises(StabilityError, match="at step 7 ") as info:
        check.check(SolverState(jnp.asarray(u), jnp.asarray(u), jnp.asarray(7)))
    np.testing.assert_array_equal(info.value.elements, inverted_elements(problem, u))
    assert "at step 0, the last state checked" in str(info.value)


# --- 3. checkpoint fingerprints ----------------------------------------------------------------

def _fingerprint_before(problem, dt, save_every):
    """The fingerprint of a linear P1 problem without supports or histories as it was
    hashed before hyperelastic laws existed (the checkpoints already on disk)."""
    h = hashlib.sha256()
    for arr in (problem.mesh.points, problem.mesh.tets):
        h.update(np.ascontiguousarray(arr).tobytes())
    m = problem.material
    dofs, values = problem.dirichlet_dofs()
    h.update(np.asarray([m.E, m.nu, m.rho, problem.damping, dt, save_every], dtype=float).tobytes())
    h.update(dofs.tobytes())
    h.update(values.tobytes())
    for v in problem.load_vectors()[0]:
        h.update(np.asarray(v, dtype=float).tobytes())
    return h.hexdigest()


def test_fingerprint_holds_the_law_its_parameters_and_fibres(beam):
    linear = jaxsync.cantilever(beam)
    assert fingerprint(linear, 1e-4, 10) == _fingerprint_before(linear, 1e-4, 10)
    neo = linear.replace(material=NeoHookean(E, NU, RHO))
    near = linear.replace(material=jaxsync.NearlyIncompressibleNeoHookean(E, NU, RHO))
    hgo = linear.replace(material=HolzapfelGasserOgden(**HGO, fibres=_fibres(beam)))
    variants = [linear, neo, near, hgo,
                hgo.replace(material=hgo.material.replace(k1=HGO["k1"] * (1 + 1e-12))),
                hgo.replace(material=hgo.material.replace(dispersion=0.1)),
                hgo.replace(material=hgo.material.replace(fibres=_fibres(beam, angle=36.0))),
                neo.replace(material=NeoHookean(E, NU, 1.001))]
    prints = [fingerprint(p, 1e-4, 10) for p in variants]
    assert len(set(prints)) == len(prints)
    same = linear.replace(material=HolzapfelGasserOgden(**HGO, fibres=_fibres(beam)))
    assert fingerprint(same, 1e-4, 10) == prints[3]


def test_a_neo_hookean_checkpoint_never_resumes_another_law(beam, tmp_path):
    path = tmp_path / "run.ckpt.h5"
    neo = jaxsync.cantilever(beam, material=NeoHookean(E, NU, RHO))
    dt = 0.5 * float(neo.dt)  # stable for all three laws
    jaxsync.simulate(neo, 20, dt=dt, save=10, checkpoint=str(path))
    for other in (neo.replace(material=jaxsync.LinearElastic(E, NU, RHO)),
                  neo.replace(material=HolzapfelGasserOgden(**HGO, fibres=_fibres(beam)))):
        with pytest.raises(CheckpointError, match="different problem"):
            jaxsync.simulate(other, 20, dt=dt, save=10, checkpoint=str(path))
    again = jaxsync.simulate(neo, 20, dt=dt, save=10, checkpoint=str(path))  # the same law resumes
    assert again.n_saved == 3


# --- 4. TOML and the command line --------------------------------------------------------------

_BEAM = """
[mesh]
length = 4.0
divisions = [4, 1, 1]
[problem]
body_force = [0.0, 0.0, -2.0e4]
t_ramp = 0.002
[run]
n_steps = 40
save_every = 20
"""


def test_toml_material_models(tmp_path, beam):
    cfg = tmp_path / "neo.toml"
    cfg.write_text(_BEAM + '[material]\nmodel = "neo-hookean"\nE = 2.0e6\nnu = 0.35\nrho = 1.1\n')
    problem, _ = problem_from_config(load_config(cfg))
    assert problem.material == NeoHookean(2.0e6, 0.35, 1.1)
    cfg.write_text(_BEAM + '[material]\nmodel = "nearly-incompressible-neo-hookean"\nE = 3.0e5\nnu = 0.4\n')
    problem, _ = problem_from_config(load_config(cfg))
    assert problem.material == jaxsync.NearlyIncompressibleNeoHookean(3.0e5, 0.4, 1.0)
    cfg.write_text(_BEAM + '[material]\nmodel = "holzapfel-gasser-ogden"\nmu = 3.0e4\nk1 = 2.3632e4\nk2 = 0.8393\n'
                   'kappa_bulk = 3.0e6\ndispersion = 0.1\nfibre_angle = 29.0\nfibre_axis = [1.0, 0.0, 0.0]\n'
                   'fibre_origin = [0.0, 0.5, 0.5]\n')
    with pytest.warns(jaxsync.LockingWarning):  # K = 100 mu: nu = 0.495 on P1 elements
        problem, _ = problem_from_config(load_config(cfg))
    m = problem.material
    assert isinstance(m, HolzapfelGasserOgden)
    assert (m.mu, m.k1, m.k2, m.kappa_bulk, m.rho, m.dispersion) == (3.0e4, 2.3632e4, 0.8393, 3.0e6, 1.0, 0.1)
    np.testing.assert_array_equal(m.fibres, _fibres(beam, angle=29.0))
    cfg.write_text(_BEAM)
    problem, _ = problem_from_config(load_config(cfg))
    assert problem.material == jaxsync.LinearElastic(1.0e6, 0.3, 1.0)


@pytest.mark.parametrize("material, message", [
    ('model = "rubber"', 'model = "rubber" is not a material model; allowed: "linear-elastic", "neo-hookean", '
                         '"nearly-incompressible-neo-hookean", "holzapfel-gasser-ogden"'),
    ('model = "holzapfel-gasser-ogden"\nE = 1.0e6', "key(s) E are not parameters of model = "
                                                   '"holzapfel-gasser-ogden"; its keys: model, mu, k1, k2'),
    ('model = "neo-hookean"\nk1 = 1.0', 'key(s) k1 are not parameters of model = "neo-hookean"; its keys: '
                                       "model, E, nu, rho"),
    ('mu = 1.0', 'key(s) mu are not parameters of model = "linear-elastic"'),
    ('model = "holzapfel-gasser-ogden"\nmu = 1.0\nk1 = 1.0\nk2 = 1.0\nkappa_bulk = 1.0\nfibre_angle = 30.0',
     'model = "holzapfel-gasser-ogden" needs fibre_axis'),
    ('model = "neo-hookean"\nnu = 0.5', "Poisson"),
    ('model = "neo-hookean"\nE = "1e6"', "write E = 1e6 without the quotes"),
])
def test_bad_material_tables_name_the_key(tmp_path, capsys, material, message):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(_BEAM + "[material]\n" + material + "\n")
    if "Poisson" not in message:
        with pytest.raises(ConfigError, match=re.escape(message)):
            load_config(cfg)
    assert main(["simulate", str(cfg), "-o", str(tmp_path / "x.h5"), "--no-progress"]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "x.h5").exists()


def test_cli_simulates_a_hyperelastic_toml(tmp_path, beam):
    cfg = tmp_path / "hgo.toml"
    cfg.write_text(_BEAM + '[material]\nmodel = "holzapfel-gasser-ogden"\nmu = 3.0e5\nk1 = 2.0e5\nk2 = 0.8\n'
                   'kappa_bulk = 1.0e6\nfibre_angle = 35.0\nfibre_axis = [1.0, 0.0, 0.0]\n'
                   'fibre_origin = [0.0, 0.5, 0.5]\n')
    out = tmp_path / "hgo.h5"
    assert main(["simulate", str(cfg), "-o", str(out), "--no-progress"]) == 0
    traj = jaxsync.Trajectory.load(out)
    material = HolzapfelGasserOgden(mu=3.0e5, k1=2.0e5, k2=0.8, kappa_bulk=1.0e6, fibres=_fibres(beam))
    problem = jaxsync.cantilever(beam, material=material, body_force=(0.0, 0.0, -2.0e4), t_ramp=0.002)
    expected = jaxsync.simulate(problem, 40, save=20)
    assert traj.dt == pytest.approx(float(problem.dt), rel=1e-14)
    assert np.abs(expected.displacement[-1]).max() > 1e-3
    np.testing.assert_allclose(traj.displacement, expected.displacement, rtol=1e-12, atol=1e-15)


# --- 5. statics by Newton's method -------------------------------------------------------------

def _felupe_static(points, tets, boundaries, body=None, steps=10):
    """felupe's Newton solution of neo-Hookean (NeoHookeCompressible, same mu, lambda), the
    prescribed values and the body force ramped in ``steps`` increments."""
    fem = pytest.importorskip("felupe")
    field = fem.FieldContainer([fem.Field(fem.RegionTetra(fem.Mesh(points, tets, "tetra")), dim=3)])
    bounds = {name: fem.Boundary(field[0], fx=where) for name, (where, _) in boundaries.items()}
    dof0, dof1 = fem.dof.partition(field, bounds)
    solid = fem.SolidBody(fem.NeoHookeCompressible(mu=MU, lmbda=LAM), field)
    for s in np.linspace(1.0 / steps, 1.0, steps):
        for name, (_, value) in boundaries.items():
            bounds[name].value = s * np.asarray(value)
        items = [solid] + ([] if body is None else [fem.SolidBodyForce(field, values=np.asarray(body), scale=s)])
        result = fem.newtonraphson(field, items=items, dof1=dof1, dof0=dof0,
                                   ext0=fem.dof.apply(field, bounds, dof0), tol=1e-12, verbose=0)
    return result.x[0].values


def test_newton_stretch_matches_felupe_and_converges_quadratically():
    mesh = jaxsync.box_beam(2.0, 1.0, 1.0, (4, 2, 2))
    problem = jaxsync.Problem(mesh=mesh, material=NeoHookean(E, NU, RHO),
                              dirichlet=(jaxsync.Dirichlet("x0"), jaxsync.Dirichlet("x1", (0.6, 0.0, 0.0))))
    u = jaxsync.steady_state(problem)
    history = u.residuals
    reference = _felupe_static(mesh.points, mesh.tets, {
        "left": (lambda x: np.isclose(x, 0.0), (0.0, 0.0, 0.0)), "right": (lambda x: np.isclose(x, 2.0), (0.6, 0, 0))})
    assert np.abs(reference).max() == pytest.approx(0.6)
    assert np.abs(u - reference).max() <= 1e-8 * 0.6
    assert len(history) == 10 and all(h[-1] <= 1e-10 for h in history)
    for residuals in history:  # quadratic: log(r2 / r1) / log(r1 / r0) ~ 2
        r = np.asarray(residuals)
        assert len(r) == 3 and r[0] < 0.1, residuals
        order = np.log(r[2] / r[1]) / np.log(r[1] / r[0])
        assert 1.7 < order < 2.3, residuals  # (r2 sits near round-off: 1e-15)


def test_newton_bent_cantilever_matches_felupe(beam):
    """A cantilever bent by a body force to a 4 cm tip deflection (the linear solution: 6.3 cm)."""
    mesh = jaxsync.box_beam(4.0, 1.0, 1.0, (8, 2, 2))
    problem = jaxsync.cantilever(mesh, material=NeoHookean(E, NU, RHO), body_force=(0.0, 0.0, -3.0e4))
    u = jaxsync.steady_state(problem)
    reference = _felupe_static(mesh.points, mesh.tets, {"left": (lambda x: np.isclose(x, 0.0), (0.0, 0.0, 0.0))},
                               body=(0.0, 0.0, -3.0e4))
    linear = jaxsync.steady_state(problem.replace(material=jaxsync.LinearElastic(E, NU, RHO)))
    assert np.abs(reference).max() > 3.0 and np.abs(linear).max() > 1.4 * np.abs(reference).max()
    assert np.abs(u - reference).max() <= 1e-8 * np.abs(reference).max()


def test_newton_that_does_not_converge_says_where_and_what_to_do(beam):
    mesh = jaxsync.box_beam(4.0, 1.0, 1.0, (8, 2, 2))
    problem = jaxsync.cantilever(mesh, material=NeoHookean(E, NU, RHO), body_force=(0.0, 0.0, -3.0e4))
    with pytest.raises(ConvergenceError) as info:
        jaxsync.steady_state(problem, load_steps=1, max_iter=3)
    error = info.value
    assert error.increment == 1 and error.residual > 1e-10
    message = str(error)
    assert "load increment 1 of 1" in message and f"{error.residual:.3e}" in message
    assert "raise load_steps (for instance to 2) or max_iter" in message
    np.testing.assert_array_equal(error.displacement, np.zeros((problem.n_nodes, 3)))
    assert isinstance(error, jaxsync.JaxsyncError)
    with pytest.raises(jaxsync.ProblemError, match="load_steps"):
        jaxsync.steady_state(problem, load_steps=0)
    free = jaxsync.Problem(mesh=mesh, material=NeoHookean(E, NU, RHO), loads=problem.loads)
    with pytest.raises(jaxsync.ProblemError, match="singular"):
        jaxsync.steady_state(free)


# --- 6. dynamics against felupe -------------------------------------------------------------------

def test_explicit_run_matches_a_central_difference_loop_on_felupes_force():
    """A neo-Hookean cantilever bent by a ramped body force (finite strain: the 4 cm beam's
    tip swings down by 2-3 cm), undamped and damped: jaxsync's run equals a
    central-difference loop written here in numpy whose internal force is felupe's
    (NeoHookeCompressible, same mu, lambda), with the lumped mass (a quarter of each
    element's mass at each vertex) and the body force (a quarter of b V_e) assembled here."""
    fem = pytest.importorskip("felupe")
    mesh = jaxsync.box_beam(4.0, 1.0, 1.0, (8, 2, 2))
    X, tets = mesh.points, mesh.tets
    body = np.array([0.0, 0.0, -1.5e4])
    t_ramp, n_steps = 0.05, 600  # about one period of the first bending mode
    field = fem.FieldContainer([fem.Field(fem.RegionTetra(fem.Mesh(X, tets, "tetra")), dim=3)])
    solid = fem.SolidBody(fem.NeoHookeCompressible(mu=MU, lmbda=LAM), field)

    def felupe_force(u):
        field[0].values[:] = u
        return np.asarray(solid.assemble.vector(field).toarray()).reshape(-1, 3)

    _, volumes = _gradients(X, tets)
    mass, force = np.zeros(len(X)), np.zeros((len(X), 3))
    np.add.at(mass, tets.ravel(), np.repeat(RHO * volumes / 4.0, 4))
    np.add.at(force, tets.ravel(), np.repeat(volumes / 4.0, 4)[:, None] * body)
    clamped = np.isclose(X[:, 0], 0.0)
    for damping in (0.0, 300.0):
        problem = jaxsync.cantilever(mesh, material=NeoHookean(E, NU, RHO), body_force=tuple(body), t_ramp=t_ramp,
                                     damping=damping)
        dt = problem.dt
        run = np.asarray(jaxsync.simulate(problem, n_steps, save=100).displacement)
        d, previous, saved = np.zeros((len(X), 3)), np.zeros((len(X), 3)), [np.zeros((len(X), 3))]
        half = 0.5 * damping * dt
        for n in range(n_steps):  # g(0) = 0: the run starts at rest with zero acceleration
            g = min(n * dt / t_ramp, 1.0)
            new = (dt * dt * (g * force - felupe_force(d)) / mass[:, None] + 2 * d - (1 - half) * previous) / (1 + half)
            new[clamped] = 0.0
            d, previous = new, d
            if (n + 1) % 100 == 0:
                saved.append(d)
        reference = np.asarray(saved)
        assert np.abs(reference[:, :, 2]).max() > 1.0  # finite strain
        np.testing.assert_allclose(run, reference, rtol=0, atol=1e-11 * np.abs(reference).max())  # measured 1e-13


# --- 7. mass scaling of a hyperelastic law ----------------------------------------------------------

def test_mass_scaling_raises_every_element_step_of_the_tangent_to_the_target():
    """Each element's own step, 2 / omega_e of its small-strain stiffness (the tangent at
    rest, assembled here in numpy) over its scaled lumped mass, is the target where it was
    below it (and unchanged elsewhere); the scaled problem's default step is the target
    (alpha_s = 0.9 times the element rule), its added mass that of the densities."""
    from jaxsync.mesh import validated_mesh

    beam = jaxsync.box_beam(4.0, 1.0, 1.0, (6, 2, 2))
    graded = beam.points * [1.0, 1.0, 1.0]
    graded[:, 0] = 4.0 * (beam.points[:, 0] / 4.0) ** 1.5  # smaller elements towards the clamp
    mesh = validated_mesh(graded, beam.tets, beam.facet_sets)
    problem = jaxsync.cantilever(mesh, material=NeoHookean(E, NU, RHO))
    g, vol = _gradients(mesh.points, mesh.tets)

    def own_steps(scale):
        steps = []
        for e in range(mesh.n_elements):
            K = np.zeros((12, 12))
            for a in range(4):
                for b in range(4):
                    ga, gb = g[e, a], g[e, b]
                    K[3 * a:3 * a + 3, 3 * b:3 * b + 3] = vol[e] * (LAM * np.outer(ga, gb) + MU * np.outer(gb, ga)
                                                                    + MU * np.dot(ga, gb) * np.eye(3))
            m = RHO * scale[e] * vol[e] / 4.0
            steps.append(2.0 / np.sqrt(np.linalg.eigvalsh(K / m)[-1]))
        return np.asarray(steps)

    before = own_steps(np.ones(mesh.n_elements))
    target = 1.5 * problem.dt
    scaled, percent = jaxsync.mass_scaling(problem, dt_target=target, warn_above_percent=None)
    after = own_steps(np.asarray(scaled.density_scale))
    small = 0.9 * before < target
    assert 0 < small.sum() < mesh.n_elements
    np.testing.assert_allclose(0.9 * after[small], target, rtol=1e-9)
    np.testing.assert_allclose(after[~small], before[~small], rtol=1e-12)
    assert scaled.dt == pytest.approx(target, rel=1e-9) and scaled.time_step.rule == "element"
    assert percent == pytest.approx(100 * (np.sum(vol * scaled.density_scale) / vol.sum() - 1), rel=1e-12)
    np.testing.assert_allclose(scaled.element_steps(), after, rtol=1e-9)
    # P2 elements scale too (the element rule needs no P1 size)
    p2, _ = jaxsync.mass_scaling(problem.replace(element="P2"), beta=1.3, warn_above_percent=None)
    assert p2.dt == pytest.approx(1.3 * problem.replace(element="P2").dt, rel=1e-9)
