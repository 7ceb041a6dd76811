"""Follower pressure (:mod:`jaxsync.fem.forces`), checked against ground truth: scikit-fem's
pressure load assembled on the deformed mesh (P1 and curved P2), the closed-form homogeneous
compression of a neo-Hookean block under a pressure on its deformed faces (and under the dead
load, which differs at finite strain), the energy budget of an undamped run (the pressure's
potential p (V(x) - V(X)) included), and the single-device run for the distributed ones."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize

import jaxsync
from jaxsync.errors import ProblemError
from jaxsync.fem import VTK_TETRA10_ORDER, SolverState, advance, build_system, function_space
from jaxsync.fem.forces import TotalLagrangian, facet_nodes, follower_pressure, load_stiffness
from jaxsync.mesh import Mesh, validated_mesh

E, NU, RHO = 1.0e6, 0.3, 1.0
MU, LAM = E / (2 * (1 + NU)), E * NU / ((1 + NU) * (1 - 2 * NU))


def _block(n=(2, 2, 2), size=(1.0, 1.0, 1.0)):
    """A box with jaxsync.box_beam's facet sets x0 ... z1 and outer = x1 + y1 + z1 (its
    faces off the coordinate planes)."""
    beam = jaxsync.box_beam(*size, n)
    sets = dict(beam.facet_sets)
    sets["outer"] = np.concatenate([sets["x1"], sets["y1"], sets["z1"]])
    return validated_mesh(beam.points, beam.tets, sets)


def _symmetric(mesh, pressure, element="P1", follower=True, **kw):
    """The block on its three symmetry planes, pressure on the other three faces."""
    return jaxsync.Problem(mesh, jaxsync.NeoHookean(E, NU, RHO),
                           dirichlet=[jaxsync.Dirichlet(f"{n}0", components=(i,)) for i, n in enumerate("xyz")],
                           loads=[jaxsync.Pressure(pressure, surface="outer", follower=follower, **kw)],
                           element=element)


def _smooth(X):
    x, y, z = X[:, 0], X[:, 1], X[:, 2]
    return np.stack([0.15 * np.sin(1.3 * y) * z + 0.1 * x * y, 0.12 * np.cos(x + z) - 0.05 * x * z,
                     0.2 * x**2 - 0.1 * np.sin(2 * y)], axis=1)


def _deformed_pressure_load(problem, u, intorder):
    """scikit-fem's -integral of N_a n da over the pressure's facets of the DEFORMED mesh
    (P2: the curved mesh through the deformed edge nodes)."""
    from skfem import LinearForm, asm
    from skfem.helpers import dot

    from jaxsync.fem import boundary_facet_indices
    from jaxsync.mesh import to_skfem

    mesh, space = problem.mesh, problem.space
    x = problem.points + u
    mids = None
    if problem.element == "P2":
        mids = np.stack([x[space.edge_nodes(mesh.tets[:, [a, b]])] for a, b in VTK_TETRA10_ORDER], axis=1)
    deformed = Mesh(x[:mesh.n_nodes], mesh.tets, mesh.facet_sets, mid_nodes=mids)
    dspace = function_space(deformed, problem.element)
    if problem.element == "P2":
        assert dspace.curved
    facets = boundary_facet_indices(deformed, to_skfem(deformed), "outer", what="a pressure")

    @LinearForm
    def unit(v, w):
        return -dot(w.n, v)

    return asm(unit, dspace.facet_basis(facets, intorder=intorder)).reshape(-1, 3)


@pytest.mark.parametrize("element", ["P1", "P2"])
def test_force_is_the_pressure_load_of_the_deformed_mesh(element):
    problem = _symmetric(_block(), 2.5e4, element)
    u = _smooth(problem.points)
    op = follower_pressure(problem)
    force = np.asarray(op.force(jnp.asarray(u), 0.0))
    reference = 2.5e4 * _deformed_pressure_load(problem, u, intorder=1 if element == "P1" else 6)
    np.testing.assert_allclose(force, reference, rtol=0, atol=1e-11 * np.abs(reference).max())
    # at rest: the dead load's vector
    dead = problem.replace(loads=[dataclasses.replace(problem.loads[0], follower=False)])
    np.testing.assert_allclose(np.asarray(op.force(jnp.zeros_like(u), 0.0)), dead.load_vectors()[0][0],
                               rtol=0, atol=1e-11 * np.abs(reference).max())


def test_facets_are_outward_and_the_time_function_scales_the_force():
    mesh = _block()
    space = function_space(mesh, "P1")
    nodes, elements = facet_nodes(space, "outer")
    X = mesh.points
    normal = np.cross(X[nodes[:, 1]] - X[nodes[:, 0]], X[nodes[:, 2]] - X[nodes[:, 0]])
    centroid = X[mesh.tets[elements]].mean(axis=1)
    assert np.all(np.einsum("fi,fi->f", normal, X[nodes[:, 0]] - centroid) > 0)
    problem = _symmetric(mesh, 3.0e4, time=jaxsync.Ramp(2.0))
    op = follower_pressure(problem)
    u = jnp.asarray(_smooth(problem.points))
    np.testing.assert_allclose(np.asarray(op.force(u, 0.5)), 0.25 * np.asarray(op.force(u, 2.0)), rtol=1e-14)


def test_load_stiffness_is_the_derivative_of_the_force():
    problem = _symmetric(_block(), 4.0e4, "P2")
    op = follower_pressure(problem)
    u = _smooth(problem.points)
    K = load_stiffness(op, u)
    v = np.random.default_rng(3).standard_normal(u.shape)
    h = 1e-6
    force = lambda x: np.asarray(op.force(jnp.asarray(x), 0.0))  # noqa: E731
    fd = -(force(u + h * v) - force(u - h * v)) / (2 * h)
    np.testing.assert_allclose(K @ v.ravel(), fd.ravel(), rtol=0, atol=1e-7 * np.abs(fd).max())
    assert abs(K - K.T).max() > 1e-3 * abs(K).max()  # a follower load is not conservative in general


def _cauchy_pressure_stretch(p, follower):
    """The stretch l of the homogeneous compression F = l I of the compressible neo-Hookean
    law (sigma = (mu (l^2 - 1) + lam ln l^3) / l^3) under a pressure p on the deformed faces
    (sigma = -p) or on the reference faces (first Piola P = sigma l^2 = -p)."""
    sigma = lambda s: (MU * (s * s - 1) + LAM * np.log(s**3)) / s**3  # noqa: E731
    if follower:
        return scipy.optimize.brentq(lambda s: sigma(s) + p, 0.5, 1.0, xtol=1e-15)
    return scipy.optimize.brentq(lambda s: sigma(s) * s * s + p, 0.5, 1.0, xtol=1e-15)


@pytest.mark.parametrize("element", ["P1", "P2"])
def test_static_compression_under_follower_and_dead_pressure_is_the_closed_form(element):
    p = 1.0e5  # about 3.6 % compression: the two loads differ by 7 % in the strain
    mesh = _block()
    stretches = {}
    for follower in (True, False):
        problem = _symmetric(mesh, p, element, follower)
        u = jaxsync.steady_state(problem, load_steps=3)
        residuals = u.residuals
        stretch = _cauchy_pressure_stretch(p, follower)
        np.testing.assert_allclose(u, (stretch - 1) * problem.points, rtol=0, atol=1e-13)
        stretches[follower] = stretch
        # Newton with the load stiffness: quadratic convergence
        last = residuals[-1]
        assert len(last) <= 5 and last[-1] < 1e-12 and last[-2] < 1e-5 and last[-1] < 10 * last[-2] ** 2 / last[-3]
    assert abs(stretches[True] - stretches[False]) > 0.05 * (1 - stretches[True])


def _energy_budgets(problem, dts, n_steps):
    """Kinetic + strain energy + the pressure's potential p (V(x) - V(X)) (V the block's
    volume: its faces not loaded lie on the symmetry planes, through the origin) [erg],
    per step of an undamped run of n_steps steps from rest (lumped start, v0 = 0 exactly),
    and the kinetic energy, for each step size in ``dts``: one compiled program, dt traced
    (a program per step size would compile twice)."""
    op = TotalLagrangian().operator(problem)
    tets = jnp.asarray(problem.mesh.tets)
    pressure = float(problem.loads[0].magnitude)

    def volume(u):
        x = (jnp.asarray(problem.points) + u)[tets]
        return jnp.sum(jnp.linalg.det(x[:, 1:] - x[:, :1])) / 6.0

    @jax.jit
    def budget(dt):
        system = build_system(problem, dt, TotalLagrangian())
        d0 = jnp.zeros((problem.n_nodes, 3))
        a0 = jnp.where(system.fixed, 0.0, system.follower.force(d0, 0.0) / system.mass)
        state = SolverState(d0, d0 + 0.5 * dt * dt * a0, jnp.asarray(0, dtype=jnp.int32))
        _, saved = advance(system, state, n_steps + 1, 1)
        d = jnp.concatenate([state.previous[None], state.displacement[None], saved])
        v = (d[2:] - d[:-2]) / (2.0 * dt)
        kinetic = 0.5 * jnp.sum(system.mass[None] * v * v, axis=(1, 2))
        potential = pressure * (jax.vmap(volume)(d[1:-1]) - volume(d0))
        return kinetic + jax.vmap(op.energy)(d[1:-1]) + potential, kinetic

    return [tuple(np.asarray(a) for a in budget(dt)) for dt in dts]


def test_undamped_run_under_follower_pressure_conserves_energy_to_second_order():
    problem = _symmetric(_block((2, 2, 2)), 1.0e5, time=jaxsync.Constant())
    dt0 = float(problem.dt)
    errors = []
    # 200 steps of dt0 and 400 of dt0 / 2, the same time span: both runs are 400 steps long
    # (one compiled program), the first one's budget is read over its first 200 steps
    for k, (budget, kinetic) in zip((1, 2), _energy_budgets(problem, (dt0, dt0 / 2), 400)):
        budget, kinetic = budget[:200 * k + 1], kinetic[:200 * k + 1]
        scale = kinetic.max()
        assert scale > 0
        errors.append(np.abs(budget - budget[0]).max() / scale)
    order = np.log2(errors[0] / errors[1])
    assert 1.8 < order < 2.2, (errors, order)


@pytest.fixture(scope="module")
def follower_references():
    """element -> (the block under a follower pressure, its single-device run, the run under
    the dead load), each built once for every exchange of test_distributed_runs_equal_the_single_device_run."""
    found = {}

    def get(element):
        if element not in found:
            mesh = _block((3, 2, 2), (1.5, 1.0, 1.0))
            problem = _symmetric(mesh, 8.0e4, element, time=jaxsync.Ramp(2e-4)).replace(damping=50.0)
            single = jaxsync.simulate(problem, 200, save=20)
            dead = problem.replace(loads=[dataclasses.replace(problem.loads[0], follower=False)])
            found[element] = (problem, single, np.asarray(jaxsync.simulate(dead, 200, save=20).displacement))
        return found[element]

    return get


@pytest.mark.parametrize("element, sync", [("P1", "psum"), pytest.param("P2", "psum", marks=pytest.mark.slow),
                                           ("P1", "halo"), ("P1", "ppermute"),
                                           pytest.param("P1", "mpi", marks=pytest.mark.mpi)])
def test_distributed_runs_equal_the_single_device_run(element, sync, follower_references):
    problem, single, other = follower_references(element)
    n = 200
    strategy = {"halo": jaxsync.Halo(depth=2), "mpi": jaxsync.Mpi(allreduce="callback", devices=jax.devices()[:1])
                }.get(sync, sync)
    if sync == "mpi":
        pytest.importorskip("mpi4py")
    parted = jaxsync.simulate(problem, n, save=20, partitions=2, sync=strategy)
    ref = np.asarray(single.displacement)
    assert np.abs(ref[-1]).max() > 1e-3  # it moved
    np.testing.assert_allclose(np.asarray(parted.displacement), ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    # the dead load gives another answer at finite strain
    assert np.abs(other - ref).max() > 1e-3 * np.abs(ref).max()


def test_follower_needs_a_hyperelastic_law_and_a_boolean():
    mesh = _block()
    with pytest.raises(ProblemError, match="follower pressure.*hyperelastic"):
        jaxsync.Problem(mesh, jaxsync.LinearElastic(E, NU, RHO),
                        loads=[jaxsync.Pressure(1.0, surface="outer", follower=True)])
    with pytest.raises(ProblemError, match="follower must be True or False"):
        jaxsync.Pressure(1.0, surface="outer", follower="yes")


def test_checkpoint_fingerprint_sees_the_follower_pressure():
    from jaxsync.io.checkpoint import fingerprint

    mesh = _block()
    a = _symmetric(mesh, 1.0e5)
    b = _symmetric(mesh, 2.0e5)
    c = _symmetric(mesh, 1.0e5, follower=False)
    prints = {fingerprint(x, 1e-6, 10) for x in (a, b, c)}
    assert len(prints) == 3


def test_toml_follower_pressure_gives_the_closed_form(tmp_path):
    from jaxsync.app.config import load_config, problem_from_config

    cfg = tmp_path / "block.toml"
    cfg.write_text(f"""
[mesh]
length = 1.0
divisions = [2, 2, 2]
[material]
model = "neo-hookean"
E = {E}
nu = {NU}
[problem]
kind = "general"
""" + "".join(f"""
[[dirichlet]]
facet = "{n}0"
components = [{i}]
[[pressure]]
surface = "{n}1"
magnitude = 1.0e5
follower = true
""" for i, n in enumerate("xyz")))
    problem, _ = problem_from_config(load_config(cfg))
    assert [load.follower for load in problem.loads] == [True] * 3
    u = jaxsync.steady_state(problem, load_steps=2)
    np.testing.assert_allclose(u, (_cauchy_pressure_stretch(1.0e5, True) - 1) * problem.points, rtol=0, atol=1e-13)
    cfg.write_text(cfg.read_text().replace("follower = true", 'follower = "yes"'))
    with pytest.raises(jaxsync.ConfigError, match="follower"):
        load_config(cfg)


def test_steady_state_refuses_traced_inputs_with_the_implicit_function_route():
    problem = _symmetric(_block(), 1.0e5)

    def tip(E):
        u = jaxsync.steady_state(problem.replace(material=jaxsync.NeoHookean(E, NU, RHO)))
        return u[-1, 0]

    with pytest.raises(ProblemError, match="implicit function theorem"):
        jax.grad(tip)(E)
