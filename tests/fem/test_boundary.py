"""Tractions, elastic (Robin) supports and prescribed displacement histories, against
hand-assembled references, an analytic static solution, a NumPy central-difference
reference of the dashpot update, an exact rigid motion and finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsync
from jaxsync import ElasticSupport, ProblemError, Traction
from jaxsync.fem import TimeFunction
from jaxsync.pytree import pytree_dataclass


@pytree_dataclass
class Linear(TimeFunction):
    """g(t) = t / duration for every t (negative times too): a constant-velocity history."""

    duration: float = 1.0

    def __call__(self, t):
        return jnp.asarray(t, dtype=float) / self.duration


def triangle_area_and_normal(points, tri):
    a, b, c = points[tri]
    cross = np.cross(b - a, c - a)
    return 0.5 * np.linalg.norm(cross), cross / np.linalg.norm(cross)


def outward(mesh, tri, normal):
    """``normal`` flipped to point away from the mesh's centroid side of the face."""
    centre = mesh.points.mean(axis=0)
    return normal if np.dot(mesh.points[tri].mean(axis=0) - centre, normal) > 0 else -normal


# --------------------------------------------------------------------------- traction


def test_traction_nodal_forces_equal_a_hand_assembled_reference():
    mesh = jaxsync.box_beam(4.0, 1.0, 2.0, (4, 2, 3))
    vector = np.array([0.3, -1.2, 2.5])
    problem = jaxsync.Problem(mesh, loads=[Traction(tuple(vector), surface="x1")],
                              dirichlet=[jaxsync.Dirichlet("x0")])
    got = np.asarray(problem.load_vectors()[0][0])
    expected = np.zeros((mesh.n_nodes, 3))
    for tri in mesh.facet_set("x1"):  # P1: a third of the triangle's area at each vertex
        area, _ = triangle_area_and_normal(mesh.points, tri)
        expected[tri] += area / 3.0 * vector
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-14)
    assert got.sum(axis=0) == pytest.approx(vector * 1.0 * 2.0, rel=1e-13)  # total: traction times area


def test_traction_on_an_interior_or_unknown_surface_is_refused():
    mesh = jaxsync.box_beam(2.0, 1.0, 1.0, (2, 1, 1))
    with pytest.raises(Exception, match="facet set"):
        jaxsync.Problem(mesh, loads=[Traction((0, 0, 1), surface="nowhere")])
    with pytest.raises(ProblemError, match="3 components"):
        Traction((0, 1), surface="x1")


# --------------------------------------------------------------------------- elastic support, static


def column(normal_only: bool, traction=1.0e3, k_s=5.0e4):
    """A 1 x 1 x 3 column on springs at z = 0 (its face z0), rollers on its sides, pushed
    down by a traction on its top face z1: uniaxial strain."""
    mesh = jaxsync.box_beam(1.0, 1.0, 3.0, (2, 2, 6))
    rollers = [jaxsync.Dirichlet("x0", components=(0,)), jaxsync.Dirichlet("x1", components=(0,)),
               jaxsync.Dirichlet("y0", components=(1,)), jaxsync.Dirichlet("y1", components=(1,))]
    return jaxsync.Problem(mesh, jaxsync.LinearElastic(1.0e6, 0.3, 1.0), dirichlet=rollers,
                           loads=[Traction((0.0, 0.0, -traction), jaxsync.Constant(), surface="z1")],
                           supports=[ElasticSupport(k_s, surface="z0", normal_only=normal_only)])


@pytest.mark.parametrize("normal_only", [False, True])
def test_column_on_springs_has_the_analytic_uniaxial_strain_solution(normal_only):
    traction, k_s = 1.0e3, 5.0e4
    problem = column(normal_only, traction, k_s)
    u = jaxsync.steady_state(problem)
    m = problem.material
    z = problem.mesh.points[:, 2]
    # springs carry the load: u_z(0) = -t / k_s; the column shortens at strain -t / (lambda + 2 mu)
    exact = -traction / k_s - traction * z / (m.lam + 2 * m.mu)
    np.testing.assert_allclose(u[:, 2], exact, rtol=0, atol=1e-12 * np.abs(exact).max())
    np.testing.assert_allclose(u[:, :2], 0.0, atol=1e-12 * np.abs(exact).max())


def test_a_damped_run_settles_on_the_spring_solution_and_distributed_equals_single():
    problem = column(True).replace(damping=40.0)
    u = jaxsync.steady_state(problem)
    run = jaxsync.simulate(problem, 60_000, save=60_000)
    assert np.abs(np.asarray(run.displacement[-1]) - u).max() <= 1e-6 * np.abs(u).max()
    short = jaxsync.simulate(problem, 400, save=20)
    for sync in ("psum", jaxsync.Halo(2)):
        parts = jaxsync.simulate(problem, 400, save=20, partitions=2, sync=sync)
        np.testing.assert_allclose(parts.displacement, short.displacement, rtol=0,
                                   atol=1e-12 * np.abs(short.displacement).max())


def test_the_exact_stability_bound_sees_the_springs():
    soft, stiff = column(False, k_s=1.0), column(False, k_s=5.0e10)
    assert jaxsync.max_stable_dt(stiff) < 0.5 * jaxsync.max_stable_dt(soft)
    # the default step stays below the bound with the springs in it
    assert stiff.dt <= jaxsync.max_stable_dt(stiff)


# --------------------------------------------------------------------------- dashpot, dynamic


def hand_surface_matrices(mesh, surface, normal_only):
    """Consistent surface matrices of one face set, hand-assembled: P1 triangles,
    integral N_i N_j = A / 12 (1 + delta_ij); lumped: A / 3 at each vertex."""
    n = mesh.n_nodes
    S = np.zeros((3 * n, 3 * n))
    lumped = np.zeros((n, 3, 3))
    for tri in mesh.facet_set(surface):
        area, normal = triangle_area_and_normal(mesh.points, tri)
        normal = outward(mesh, tri, normal)
        P = np.outer(normal, normal) if normal_only else np.eye(3)
        for a, i in enumerate(tri):
            lumped[i] += area / 3.0 * P
            for b, j in enumerate(tri):
                S[3 * i:3 * i + 3, 3 * j:3 * j + 3] += area / 12.0 * (2.0 if a == b else 1.0) * P
    return S, lumped


@pytest.mark.parametrize("normal_only", [False, True])
def test_spring_and_dashpot_run_equals_a_numpy_central_difference(normal_only):
    """The solver's update with supports against the textbook form written here:
    (M + dt/2 C) d+ = dt^2 (f - K d) + 2 M d - (M - dt/2 C) d-, C = alpha M + B, with the
    support matrices assembled by hand."""
    k_s, c_s, alpha = 2.0e5, 3.0e3, 0.7
    box = jaxsync.box_beam(1.0, 1.0, 2.0, (2, 2, 4))
    # turned so that the support's normal is oblique: its dashpot couples the components of
    # the edge nodes where the x0 face prescribes one of them
    angle = 0.4
    turn = np.array([[np.cos(angle), 0.0, np.sin(angle)], [0.0, 1.0, 0.0], [-np.sin(angle), 0.0, np.cos(angle)]])
    mesh = jaxsync.Mesh(points=box.points @ turn.T, tets=box.tets, facet_sets=box.facet_sets)
    problem = jaxsync.Problem(mesh, jaxsync.LinearElastic(1.0e6, 0.3, 1.0),
                              dirichlet=[jaxsync.Dirichlet("x0", components=(0,))], damping=alpha,
                              loads=[Traction((2.0e2, 0.0, -1.0e3), jaxsync.Ramp(0.01), surface="z1")],
                              supports=[ElasticSupport(k_s, c_s, surface="z0", normal_only=normal_only)])
    dt, n_steps = float(problem.dt), 300
    run = jaxsync.simulate(problem, n_steps)
    # the reference
    m = problem.material
    S, B_nodes = hand_surface_matrices(mesh, "z0", normal_only)
    K = problem.operators.stiffness(m.lam, m.mu).toarray() + k_s * S
    mass = np.repeat(np.asarray(problem.lumped_mass()), 3)
    B = np.zeros_like(K)
    for i in range(mesh.n_nodes):
        B[3 * i:3 * i + 3, 3 * i:3 * i + 3] = c_s * B_nodes[i]
    C = alpha * np.diag(mass) + B
    f0 = np.asarray(problem.load_vectors()[0][0]).reshape(-1)
    fixed, _ = problem.dirichlet_dofs()
    free = np.setdiff1d(np.arange(3 * mesh.n_nodes), fixed)
    lhs = np.diag(mass) + 0.5 * dt * C
    d, prev = np.zeros(3 * mesh.n_nodes), np.asarray(run.displacement[0]).reshape(-1) * 0.0
    prev = -np.zeros_like(d)  # start at rest, unloaded (the ramp is 0 at t = 0)
    out = [d.copy()]
    for n in range(n_steps):
        load = np.clip(n * dt / 0.01, 0, 1) * f0
        rhs = dt * dt * (load - K @ d) + 2 * mass * d - (np.diag(mass) - 0.5 * dt * C) @ prev
        new = np.zeros_like(d)
        new[free] = np.linalg.solve(lhs[np.ix_(free, free)], rhs[free] - lhs[np.ix_(free, fixed)] @ new[fixed])
        prev, d = d, new
        out.append(d.copy())
    reference = np.asarray(out).reshape(n_steps + 1, -1, 3)
    scale = np.abs(reference).max()
    assert scale > 0
    np.testing.assert_allclose(np.asarray(run.displacement), reference, rtol=0, atol=1e-11 * scale)


def test_dashpot_dissipates_energy():
    """Without external work, springs or mass damping, the total energy of a free
    vibration falls where a dashpot acts and stays put (to round-off) where none does."""
    mesh = jaxsync.box_beam(1.0, 1.0, 2.0, (2, 2, 4))
    z = mesh.points[:, 2]
    v0 = np.zeros((mesh.n_nodes, 3))
    v0[:, 0] = 10.0 * z  # a shear motion
    energies = {}
    for c_s in (0.0, 1.0e3):
        problem = jaxsync.Problem(mesh, jaxsync.LinearElastic(1.0e6, 0.3, 1.0), initial_velocity=v0,
                                  dirichlet=[jaxsync.Dirichlet("z0", components=(2,))],
                                  supports=[ElasticSupport(0.0, c_s, surface="z0")])
        run = jaxsync.simulate(problem, 2000, save=1)
        d = np.asarray(run.displacement).reshape(len(run.displacement), -1)
        K = problem.operators.stiffness(problem.material.lam, problem.material.mu)
        m = np.repeat(np.asarray(problem.lumped_mass()), 3)
        v = (d[2:] - d[:-2]) / (2 * float(problem.dt))
        energy = 0.5 * np.einsum("ti,i,ti->t", v, m, v) + 0.5 * np.einsum("ti,ti->t", d[1:-1], (K @ d[1:-1].T).T)
        energies[c_s] = energy
    assert np.ptp(energies[0.0]) <= 2e-3 * energies[0.0][0]  # the scheme's own O(dt^2) wiggle
    assert energies[1.0e3][-1] < 0.5 * energies[1.0e3][0]


def test_bad_supports_are_refused():
    mesh = jaxsync.box_beam(2.0, 1.0, 1.0, (2, 1, 1))
    with pytest.raises(ProblemError, match="stiffness must be >= 0"):
        ElasticSupport(-1.0, surface="x1")
    with pytest.raises(ProblemError, match="unknown support"):
        jaxsync.Problem(mesh, supports=["x1"])


# --------------------------------------------------------------------------- prescribed histories


def test_a_prescribed_history_is_followed_exactly():
    problem = jaxsync.cantilever()
    tip = jaxsync.Dirichlet("x1", value=(0.0, 0.0, 0.02), time=jaxsync.Periodic([0.0, 0.2, 0.4], [0.0, 1.0, 0.0], 0.4))
    problem = problem.replace(dirichlet=problem.dirichlet + (tip,))
    run = jaxsync.simulate(problem, 2000, save=10)
    nodes = problem.mesh.facet_nodes("x1")
    g = np.interp(np.mod(run.times, 0.4), [0.0, 0.2, 0.4], [0.0, 1.0, 0.0])
    # to round-off of the time t = n dt at which the solver evaluates g
    np.testing.assert_allclose(np.asarray(run.displacement)[:, nodes, 2], np.repeat(0.02 * g[:, None], len(nodes),
                                                                                   axis=1), rtol=1e-13, atol=1e-18)
    np.testing.assert_array_equal(np.asarray(run.displacement)[:, nodes, :2], 0.0)
    assert np.abs(np.asarray(run.displacement)[:, :, 2]).max() >= 0.02 * 0.99  # the beam moves with it


def test_a_rigid_motion_at_constant_velocity_is_exact_everywhere():
    """Both ends prescribed to move at velocity v (g(t) = t), the body started at velocity
    v: every node moves rigidly, u(t) = v t, exactly (the start is consistent: the
    prescribed dofs sit at g(-dt) before the first step)."""
    mesh = jaxsync.box_beam(3.0, 1.0, 1.0, (3, 1, 1))
    v = np.array([0.5, -0.2, 0.1])
    ends = [jaxsync.Dirichlet(face, value=tuple(v), time=Linear(1.0)) for face in ("x0", "x1")]
    # no mass-proportional damping: it would brake a rigid motion (C v = alpha M v)
    problem = jaxsync.Problem(mesh, jaxsync.LinearElastic(1.0e6, 0.3, 1.0), dirichlet=ends, damping=0.0,
                              initial_velocity=np.tile(v, (mesh.n_nodes, 1)))
    run = jaxsync.simulate(problem, 500, save=5)
    exact = np.asarray(run.times)[:, None, None] * v[None, None, :]
    np.testing.assert_allclose(np.asarray(run.displacement), np.broadcast_to(exact, run.displacement.shape),
                               rtol=0, atol=1e-12 * np.abs(exact).max())


def test_histories_supports_and_tractions_are_differentiable():
    """d/d(k_s), d/d(traction) and d/d(prescribed amplitude) of a tip value against central
    finite differences, through the traced executor."""
    mesh = jaxsync.box_beam(2.0, 1.0, 1.0, (4, 2, 2))
    tip = int(np.argmax(mesh.points[:, 0] + 1e-3 * mesh.points[:, 2]))

    def make(k_s, load, amplitude):
        return jaxsync.Problem(mesh, jaxsync.LinearElastic(1.0e6, 0.3, 1.0), damping=1.0,
                               dirichlet=[jaxsync.Dirichlet("x0", value=jnp.stack([0.0, 0.0, amplitude]),
                                                            time=jaxsync.Ramp(0.02))],
                               loads=[Traction(jnp.stack([0.0, 0.0, -load]), jaxsync.Ramp(0.01), surface="x1")],
                               supports=[ElasticSupport(k_s, 50.0, surface="z0", normal_only=True)])

    dt = float(make(1.0e4, 10.0, 1e-3).dt)

    @jax.jit  # one program for the six finite-difference runs (eager, each run's values compile anew)
    def tip_z(k_s, load, amplitude):
        return jaxsync.simulate(make(k_s, load, amplitude), 400, dt=dt, save=400).displacement[-1, tip, 2]

    x0 = (1.0e4, 10.0, 1e-3)
    grads = jax.jit(jax.grad(tip_z, argnums=(0, 1, 2)))(*x0)
    for i, h in enumerate((1e1, 1e-2, 1e-6)):
        up, down = list(x0), list(x0)
        up[i] += h
        down[i] -= h
        fd = (float(tip_z(*up)) - float(tip_z(*down))) / (2 * h)
        assert float(grads[i]) == pytest.approx(fd, rel=1e-6, abs=1e-12)


def test_toml_takes_tractions_supports_and_histories(tmp_path):
    from jaxsync.app.config import load_config, problem_from_config

    path = tmp_path / "case.toml"
    path.write_text("""
[mesh]
length = 2.0
divisions = [4, 2, 2]
[problem]
kind = "general"
damping = 1.0
[[dirichlet]]
facet = "x0"
value = [0.0, 0.0, 0.001]
t_ramp = 0.5
[[traction]]
surface = "x1"
vector = [0.0, 0.0, -10.0]
[[support]]
surface = "z0"
stiffness = 1.0e4
damping = 50.0
normal_only = true
""")
    problem, _ = problem_from_config(load_config(path))
    assert isinstance(problem.loads[0], Traction) and problem.loads[0].vector == (0.0, 0.0, -10.0)
    support = problem.supports[0]
    assert (support.stiffness, support.damping, support.surface, support.normal_only) == (1.0e4, 50.0, "z0", True)
    assert isinstance(problem.dirichlet[0].time, jaxsync.Ramp)
    assert "elastic support on 'z0'" in problem.summary() and "1 traction" in problem.summary()
    path.write_text(path.read_text().replace("normal_only = true", 'normal_only = "yes"'))
    with pytest.raises(jaxsync.ConfigError, match="normal_only"):
        load_config(path)
