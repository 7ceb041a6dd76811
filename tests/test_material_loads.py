import jax.numpy as jnp
import numpy as np
import pytest

import jaxsync
from jaxsync import MaterialError, ProblemError


def test_lame_parameters():
    m = jaxsync.LinearElastic(1.0e6, 0.3, 1.0)
    assert m.mu == pytest.approx(1.0e6 / 2.6)
    assert m.lam == pytest.approx(1.0e6 * 0.3 / (1.3 * 0.4))
    assert float(m.wave_speed) == pytest.approx(np.sqrt(1.0e6 / 0.91))


@pytest.mark.parametrize("kwargs, match", [
    (dict(E=0.0), "Young"), (dict(E=-1.0), "Young"), (dict(rho=0.0), "density"),
    (dict(nu=0.5), "Poisson"), (dict(nu=-1.0), "Poisson"), (dict(nu=float("nan")), "Poisson"),
])
def test_material_validation(kwargs, match):
    base = dict(E=1.0e6, nu=0.3, rho=1.0)
    base.update(kwargs)
    with pytest.raises(MaterialError, match=match):
        jaxsync.LinearElastic(**base)


def test_material_is_a_pytree():
    import jax

    m = jaxsync.LinearElastic(2.0, 0.25, 3.0)
    leaves, tree = jax.tree_util.tree_flatten(m)
    assert leaves == [2.0, 0.25, 3.0]
    assert jax.tree_util.tree_unflatten(tree, leaves) == m


def test_ramp():
    g = jaxsync.Ramp(2.0)
    t = np.array([0.0, 0.5, 2.0, 5.0])
    np.testing.assert_allclose(g(t), [0.0, 0.25, 1.0, 1.0])
    with pytest.raises(ProblemError):
        jaxsync.Ramp(0.0)


def test_step_off():
    g = jaxsync.StepOff(3.0, jaxsync.Ramp(1.0))
    np.testing.assert_allclose(g(np.array([0.5, 2.0, 2.999, 3.0, 4.0])), [0.5, 1, 1, 0, 0])


def test_periodic_matches_numpy_interp():
    times = np.array([0.0, 0.2, 0.5, 0.8])
    values = np.array([1.0, 3.0, 2.0, 1.5])
    period = 1.0
    g = jaxsync.Periodic(times, values, period)
    t = np.linspace(0, 3.3, 71)
    ref = np.interp(np.mod(t, period), np.append(times, period), np.append(values, values[0]))
    np.testing.assert_allclose(g(t), ref, rtol=1e-12)


def test_periodic_validation():
    with pytest.raises(ProblemError, match="increasing"):
        jaxsync.Periodic([0.0, 0.5, 0.4], [1, 2, 3], 1.0)
    with pytest.raises(ProblemError, match="period"):
        jaxsync.Periodic([0.0, 2.0], [1, 2], 1.0)


def test_product_of_time_functions():
    g = jaxsync.Ramp(1.0) * jaxsync.Periodic([0.0, 0.5], [1.0, 3.0], 1.0)
    t = jnp.array([0.25, 0.5, 1.5])
    np.testing.assert_allclose(g(t), [0.25 * 2.0, 0.5 * 3.0, 3.0])


def test_body_force_needs_three_components():
    with pytest.raises(ProblemError, match="3 components"):
        jaxsync.BodyForce((0.0, 1.0))


@pytest.mark.parametrize("face, normal", [("x1", (1.0, 0, 0)), ("z0", (0, 0, -1.0))])
def test_pressure_resultant_on_a_mesh_of_thousands_of_nodes(face, normal):
    """A uniform pressure p on a face of area A has the resultant -p A n. On meshes of
    more than ~1290 nodes the facet lookup used to overflow int32 and refuse every
    pressure ("not a face of any element")."""
    import jaxsync

    mesh = jaxsync.box_beam(4.0, 2.0, 3.0, (24, 8, 10))  # 25 * 9 * 11 = 2475 nodes
    assert mesh.n_nodes > 2000
    area = {"x1": 2.0 * 3.0, "z0": 4.0 * 2.0}[face]
    problem = jaxsync.Problem(mesh, jaxsync.LinearElastic(1e6, 0.3, 1.0),
                              dirichlet=(jaxsync.Dirichlet("x0"),),
                              loads=(jaxsync.Pressure(2.5, surface=face),))
    vectors, _ = problem.load_vectors()
    force = np.asarray(vectors[0]).reshape(-1, 3)
    np.testing.assert_allclose(force.sum(axis=0), -2.5 * area * np.asarray(normal), atol=1e-10)
    # the force sits on that face only
    on_face = np.zeros(mesh.n_nodes, bool)
    on_face[mesh.facet_nodes(face)] = True
    assert np.abs(force[~on_face]).max() <= 1e-12 * np.abs(force).max()


def test_load_jumps_against_a_loop():
    """The jump steps of a step-off, a ramp shorter than a step, a smooth periodic load and
    a constant one, each checked against a plain loop over the steps."""
    from jaxsync.fem.loads import TimeFunction, load_jumps

    dt, n_steps = 1e-3, 400
    t_off = 0.2505  # between steps 250 and 251
    cases = {
        "step_off": jaxsync.BodyForce(time=jaxsync.StepOff(t_off, jaxsync.Ramp(0.05))),
        "short_ramp_after_zero": jaxsync.BodyForce(time=jaxsync.Ramp(0.4 * dt)),
        "smooth": jaxsync.BodyForce(time=jaxsync.Periodic(np.linspace(0, 0.5, 41),
                                                          np.sin(np.linspace(0, np.pi, 41)) ** 2, 0.5)),
        "constant": jaxsync.BodyForce(time=jaxsync.Constant()),
    }
    expected = {"step_off": [251], "short_ramp_after_zero": [1], "smooth": [], "constant": []}
    for name, load in cases.items():
        g = [float(load.time(k * dt)) for k in range(n_steps + 1)]
        scale = max(abs(v) for v in g)
        loop = [k for k in range(1, n_steps + 1) if abs(g[k] - g[k - 1]) > 0.05 * scale]
        assert loop == expected[name], name
        np.testing.assert_array_equal(load_jumps([load], n_steps, dt), loop)
    # several loads: the union; a zero time function has none
    union = load_jumps([cases["step_off"], cases["short_ramp_after_zero"],
                        jaxsync.BodyForce(time=jaxsync.StepOff(0.0))], n_steps, dt)
    np.testing.assert_array_equal(union, [1, 251])
    # a time function written for one scalar t, as the stepper calls it (a constant too)
    class Switch(TimeFunction):
        def __call__(self, t):
            return 2.0 if isinstance(t, float) and t > 1e9 else jnp.where(t < 0.1005, 0.0, 3.0)

    class Unit(TimeFunction):
        def __call__(self, t):
            return 1.0

    np.testing.assert_array_equal(load_jumps([jaxsync.BodyForce(time=Switch())], n_steps, dt), [101])
    np.testing.assert_array_equal(load_jumps([jaxsync.BodyForce(time=Unit())], n_steps, dt), [])
    # a smaller threshold sees the smooth load's steepest steps (about 2 pi dt / T = 1.3 % of its range)
    assert len(load_jumps([cases["smooth"]], n_steps, dt, fraction=0.005)) > 0
