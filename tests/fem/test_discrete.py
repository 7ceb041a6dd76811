"""The problem lowered once (``Problem.discrete``): its arrays against a lowering written
here with NumPy, one lowering per problem for a whole run, traced values traced and
concrete ones concrete, and the stability bounds that problems on one mesh share."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsync

E, NU, RHO = 1.0e5, 0.3, 1.0


def _problem(**changes):
    mesh = jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1))
    problem = jaxsync.Problem(
        mesh, jaxsync.LinearElastic(E, NU, RHO),
        dirichlet=[jaxsync.Dirichlet("x0"),
                   jaxsync.Dirichlet("x1", value=(0.02, 0.0, 0.0), components=(0,), time=jaxsync.Ramp(0.01))],
        loads=[jaxsync.BodyForce((0.0, 0.0, -3.0), time=jaxsync.Constant()),
               jaxsync.Pressure(magnitude=50.0, surface="z1", time=jaxsync.Ramp(0.01))],
        damping=2.0)
    return problem.replace(**changes) if changes else problem


def _facet_nodes(mesh, name):
    return np.unique(mesh.facet_set(name))


def test_lowered_problem_equals_a_numpy_lowering():
    problem = _problem()
    mesh, lowered = problem.mesh, problem.discrete
    # the lumped mass: rho V / 4 at each vertex of each tetrahedron
    mass = np.zeros(mesh.n_nodes)
    np.add.at(mass, mesh.tets, np.repeat(RHO * mesh.volumes()[:, None] / 4.0, 4, axis=1))
    np.testing.assert_allclose(lowered.mass, mass, rtol=1e-13)
    # the body force b V / 4 at each vertex; the pressure's total is -p times the face's area along z
    body = np.zeros((mesh.n_nodes, 3))
    np.add.at(body[:, 2], mesh.tets, np.repeat(-3.0 * mesh.volumes()[:, None] / 4.0, 4, axis=1))
    np.testing.assert_allclose(lowered.load_vectors[0], body, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(lowered.load_vectors[1].sum(axis=0), [0.0, 0.0, -50.0 * 4.0], rtol=1e-12, atol=1e-10)
    assert len(lowered.load_times) == 2
    # the prescribed dofs: all of x0's, x of x1's (that condition follows its time function)
    clamped, pulled = _facet_nodes(mesh, "x0"), _facet_nodes(mesh, "x1")
    fixed = np.zeros((mesh.n_nodes, 3), bool)
    fixed[clamped] = True
    fixed[pulled, 0] = True
    np.testing.assert_array_equal(lowered.fixed, fixed)
    np.testing.assert_array_equal(lowered.fixed_values, np.zeros((mesh.n_nodes, 3)))
    moving = np.zeros((1, mesh.n_nodes, 3))
    moving[0, pulled, 0] = 0.02
    np.testing.assert_array_equal(lowered.moving, moving)
    assert lowered.moving_times == (jaxsync.Ramp(0.01),)
    dofs, values = problem.dirichlet_dofs()
    np.testing.assert_array_equal(dofs, np.flatnonzero(fixed))
    np.testing.assert_array_equal(values, moving.reshape(-1)[np.flatnonzero(fixed)])
    assert lowered.damping == 2.0


def test_lowered_arrays_are_read_only():
    lowered = _problem().discrete
    with pytest.raises(ValueError, match="read-only"):
        lowered.fixed[0, 0] = False
    with pytest.raises(ValueError, match="read-only"):
        lowered.fixed_values[0, 0] = 1.0


def test_a_run_lowers_its_problem_once(monkeypatch):
    """The explicit system, the parts' systems, the default step, the error estimate and
    the checkpoint's fingerprint of one run all read the one lowering."""
    import sys

    calls = []
    lower = sys.modules[jaxsync.fem.DiscreteProblem.__module__].lower  # what Problem.discrete calls
    monkeypatch.setattr(f"{jaxsync.fem.DiscreteProblem.__module__}.lower",
                        lambda problem: calls.append(problem) or lower(problem))
    problem = _problem()
    jaxsync.simulate(problem, 20, save=10)
    jaxsync.simulate(problem, 20, save=10, partitions=2)
    assert [p is problem for p in calls] == [True]


def test_a_concrete_problem_lowered_inside_a_traced_function_stays_concrete():
    problem = _problem()
    system = jax.jit(lambda scale: jnp.sum(jaxsync.fem.build_system(problem, 1e-4).load_vectors) * scale)
    assert np.isfinite(float(system(2.0)))
    lowered = problem.discrete  # lowered during the trace above, kept
    assert isinstance(lowered, jaxsync.fem.DiscreteProblem)
    for leaf in jax.tree_util.tree_leaves(lowered):
        assert not isinstance(leaf, jax.core.Tracer)
    np.testing.assert_allclose(np.sum(lowered.load_vectors) * 2.0, float(system(2.0)), rtol=1e-12)


def test_traced_values_are_lowered_traced():
    """The lowered loads and mass follow a traced magnitude and density (their derivatives
    against central differences)."""
    problem = _problem()

    def total(x):
        p = problem.replace(material=jaxsync.LinearElastic(E, NU, x[0]),
                            loads=[jaxsync.Pressure(magnitude=x[1], surface="z1")])
        return jnp.sum(p.discrete.load_vectors[0, :, 2]) + jnp.sum(p.discrete.mass)

    x = np.array([1.3, 70.0])
    grad = jax.grad(total)(jnp.asarray(x))
    h = 1e-3
    for k in range(2):
        step = np.zeros(2)
        step[k] = h
        fd = (total(jnp.asarray(x + step)) - total(jnp.asarray(x - step))) / (2 * h)
        np.testing.assert_allclose(grad[k], fd, rtol=1e-9)


def test_problems_on_one_mesh_share_their_stability_bounds(monkeypatch):
    """A problem derived with another E solves no eigenvalue problem again (its bound is
    sqrt(E / E') times the first), another nu does, and so do new operators."""
    import scipy.linalg

    solves = []
    eigvalsh = scipy.linalg.eigvalsh
    monkeypatch.setattr(scipy.linalg, "eigvalsh", lambda *a, **k: solves.append(1) or eigvalsh(*a, **k))
    problem = _problem()
    exact = jaxsync.max_stable_dt(problem)
    assert len(solves) == 1
    stiffer = problem.replace(material=jaxsync.LinearElastic(4.0 * E, NU, RHO))
    assert stiffer.operators is problem.operators
    assert jaxsync.max_stable_dt(stiffer) == pytest.approx(exact / 2.0, rel=1e-13)
    assert len(solves) == 1
    # the bound of the stiffer problem, solved from scratch on fresh operators
    fresh = jaxsync.Problem(problem.mesh, stiffer.material, dirichlet=problem.dirichlet, loads=problem.loads)
    assert fresh.operators is not problem.operators
    assert jaxsync.max_stable_dt(fresh) == pytest.approx(exact / 2.0, rel=1e-12)
    assert len(solves) == 2
    jaxsync.max_stable_dt(problem.replace(material=jaxsync.LinearElastic(E, 0.25, RHO)))
    assert len(solves) == 3
