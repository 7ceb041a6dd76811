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
    from jaxsync.fem import TimeFunction, load_jumps

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
                        jaxsync.BodyForce(time=jaxsync.Periodic([0.0, 0.5], [0.0, 0.0], 1.0))], n_steps, dt)
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


# ----------------------------------------------------------------------------- checked when built

INF, NAN = float("inf"), float("nan")


@pytest.mark.parametrize("build, error, match", [
    (lambda: jaxsync.LinearElastic(INF, 0.3, 1.0), MaterialError, r"LinearElastic\.E .* finite"),
    (lambda: jaxsync.LinearElastic(1e6, 0.3, NAN), MaterialError, r"LinearElastic\.rho .* finite"),
    (lambda: jaxsync.LinearElastic("1e6", 0.3, 1.0), MaterialError, "must be a number"),
    (lambda: jaxsync.NeoHookean(1e6, 0.3, INF), MaterialError, r"NeoHookean\.rho .* finite"),
    (lambda: jaxsync.HolzapfelGasserOgden(mu=3e5, k1=INF, k2=0.8, kappa_bulk=1e6), MaterialError, "k1"),
    (lambda: jaxsync.Pressure(NAN), ProblemError, r"Pressure\.magnitude must be a finite number"),
    (lambda: jaxsync.Pressure(1.0, surface=3), ProblemError, "Pressure.surface"),
    (lambda: jaxsync.BodyForce((0.0, 0.0, INF)), ProblemError, r"BodyForce\.vector .* must be finite"),
    (lambda: jaxsync.BodyForce(np.array([0.0, NAN, 1.0])), ProblemError, r"BodyForce\.vector"),
    (lambda: jaxsync.BodyForce((0.0, 0.0, -1.0), time=2.0), ProblemError, r"BodyForce\.time must be a time func"),
    (lambda: jaxsync.Traction((0.0, "x", 1.0)), ProblemError, r"Traction\.vector .* numbers"),
    (lambda: jaxsync.Ramp(INF), ProblemError, r"Ramp\.t_end must be a finite number"),
    (lambda: jaxsync.StepOff(NAN), ProblemError, r"StepOff\.t_off"),
    (lambda: jaxsync.Periodic([0.0, 0.5], [1.0, NAN], 1.0), ProblemError, r"Periodic\.values must be finite"),
    (lambda: jaxsync.Periodic([0.0, 0.5], [1.0, 2.0], INF), ProblemError, r"Periodic\.period"),
    (lambda: jaxsync.ElasticSupport(INF), ProblemError, r"ElasticSupport\.stiffness"),
    (lambda: jaxsync.Dirichlet("x0", value=(0.0, NAN, 0.0)), ProblemError, r"Dirichlet\.value"),
    (lambda: jaxsync.Dirichlet("x0", components=(0, 3)), ProblemError, r"Dirichlet\.components"),
    (lambda: jaxsync.Dirichlet(42), ProblemError, r"Dirichlet\.where"),
])
def test_parameters_are_checked_when_built_and_named(build, error, match):
    with pytest.raises(error, match=match):
        build()


def test_problem_level_numbers_are_checked_and_named():
    mesh = jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1))
    with pytest.raises(ProblemError, match=r"Problem\.damping .* finite"):
        jaxsync.cantilever(mesh, damping=INF)
    u0 = np.zeros((mesh.n_nodes, 3))
    u0[3, 1] = NAN
    with pytest.raises(ProblemError, match=r"Problem\.initial_displacement must be finite, got nan at index \(3, 1\)"):
        jaxsync.cantilever(mesh, initial_displacement=u0)


def test_checks_let_jax_rebuild_the_objects():
    import jax

    load = jaxsync.BodyForce(np.array([0.0, 0.0, -1.0]), jaxsync.Ramp(0.5))
    stacked = jax.tree_util.tree_map(lambda x: np.stack([x, x]), load)  # an ensemble's members
    assert stacked.vector.shape == (2, 3)
    grad = jax.grad(lambda m: jaxsync.Pressure(m, jaxsync.Ramp(1.0)).magnitude * 2.0)(3.0)
    assert float(grad) == 2.0
    assert jax.tree_util.tree_structure(jaxsync.LinearElastic()).num_leaves == 3


# ----------------------------------------------------------------------------- free rigid-body motions


def test_free_rigid_motions_are_counted_against_a_rank_computed_here():
    from jaxsync.fem import free_rigid_motions

    mesh = jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1))
    corner = lambda p: np.all(np.isclose(p, 0.0), axis=1)  # noqa: E731
    edge = lambda p: np.isclose(p[:, 0], 0.0) & np.isclose(p[:, 1], 0.0)  # noqa: E731 - a line of nodes
    cases = [([], [], 6), ([jaxsync.Dirichlet("x0")], [], 0), ([jaxsync.Dirichlet(corner)], [], 3),
             ([jaxsync.Dirichlet(edge)], [], 1), ([jaxsync.Dirichlet("x0", components=(0,))], [], 3),
             ([], [jaxsync.ElasticSupport(1e3, surface="x0")], 0),
             ([], [jaxsync.ElasticSupport(1e3, surface="x0", normal_only=True)], 3)]
    for dirichlet, supports, n_free in cases:
        problem = jaxsync.Problem(mesh, dirichlet=dirichlet, supports=supports)
        free = free_rigid_motions(problem)
        assert free.shape == (mesh.n_nodes, 3, n_free), (dirichlet, supports)
        # a reference: the rigid motions (numpy, written here) that vanish on the constrained dofs
        x = mesh.points - mesh.points.mean(axis=0)
        modes = np.concatenate([np.tile(np.eye(3), (mesh.n_nodes, 1)).reshape(mesh.n_nodes, 3, 3),
                                np.stack([np.cross(np.eye(3)[k], x) for k in range(3)], axis=2)], axis=2)
        rows = [modes.reshape(-1, 6)[problem.dirichlet_dofs()[0]]]
        for s in supports:
            nodes = mesh.facet_nodes(s.surface)
            rows.append((modes[nodes][:, 0] * -1.0) if s.normal_only else modes[nodes].reshape(-1, 6))
        constraints = np.concatenate(rows)
        assert 6 - np.linalg.matrix_rank(constraints, tol=1e-9) == n_free


def test_a_load_that_drives_a_free_motion_warns_and_a_balanced_one_does_not():
    import warnings

    from jaxsync.fem import RigidBodyWarning

    mesh = jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1))
    free = r"the loads drive .*\(translation along z; 6 of the 6 .*Dirichlet conditions: none"
    with pytest.warns(RigidBodyWarning, match=free):
        jaxsync.Problem(mesh, loads=[jaxsync.BodyForce((0.0, 0.0, -1.0))])
    corner = lambda p: np.all(np.isclose(p, 0.0), axis=1)  # noqa: E731
    with pytest.warns(RigidBodyWarning, match="rotation about y.*a predicate selects 1 node"):
        jaxsync.Problem(mesh, dirichlet=[jaxsync.Dirichlet(corner)], loads=[jaxsync.BodyForce((0.0, 0.0, -1.0))])
    with pytest.warns(RigidBodyWarning, match="the initial velocity drives"):
        jaxsync.Problem(mesh, initial_velocity=np.ones((mesh.n_nodes, 3)))
    with warnings.catch_warnings():
        warnings.simplefilter("error", RigidBodyWarning)
        # equal and opposite pressures: no net force, no moment
        jaxsync.Problem(mesh, loads=[jaxsync.Pressure(1.0, surface="x0"), jaxsync.Pressure(1.0, surface="x1")])
        jaxsync.cantilever(mesh)  # clamped: nothing free
        jaxsync.Problem(mesh, dirichlet=[jaxsync.Dirichlet(corner)])  # free, but nothing drives it


def test_shapes_and_kinds_are_refused_when_built():
    mesh = jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1))
    with pytest.raises(ProblemError, match=r"Dirichlet\.value \[cm\] must have 3 components"):
        jaxsync.Dirichlet("x0", value=(0.0, 0.0))
    with pytest.raises(ProblemError, match=r"Dirichlet\.value must have 3 components"):
        jaxsync.Dirichlet("x0", value=np.zeros(2))
    assert jaxsync.Dirichlet("x0", value=0.0).value == 0.0  # one number for all three
    with pytest.raises(MaterialError, match=r"LinearElastic\.E .* must be a number"):
        jaxsync.LinearElastic([1.0e6], 0.3, 1.0)
    with pytest.raises(ProblemError, match=r"StepOff\.t_off must be positive"):
        jaxsync.StepOff(-1.0)
    # a single load, condition or support counts as a list of one
    one = jaxsync.Problem(mesh, dirichlet=jaxsync.Dirichlet("x0"), loads=jaxsync.BodyForce((0.0, 0.0, -1.0)),
                          supports=jaxsync.ElasticSupport(1.0, surface="x1"))
    assert len(one.dirichlet) == len(one.loads) == len(one.supports) == 1
    with pytest.raises(ProblemError, match="unknown load"):
        jaxsync.Problem(mesh, dirichlet=[jaxsync.Dirichlet("x0")], loads=[3.0])
