"""Quadratic tetrahedra (P2): masses, patch tests, convergence against the Lame cylinder,
beam theory, the stable step, and P2 through partitions, halos, gradients, the predicted
phase, checkpoints, files and quadratic meshes read as they are."""

import meshio
import numpy as np
import pytest

import jaxsync
from jaxsync import Traction
from jaxsync.fem import consistent_mass, function_space, lumped_mass, vtk_cells

E, NU = 1.0e6, 0.3


def beam(divisions=(4, 2, 2), length=2.0):
    return jaxsync.box_beam(length, 1.0, 1.0, divisions)


def test_lumped_masses_are_positive_and_sum_to_the_total():
    mesh = beam()
    p2 = function_space(mesh, "P2")
    rows = np.asarray(consistent_mass(p2).sum(axis=1)).ravel()
    assert rows.min() < 0  # row sums would give negative vertex masses
    m = lumped_mass(p2)
    assert m.min() > 0 and m.sum() == pytest.approx(mesh.volumes().sum(), rel=1e-13)
    # HRZ on one straight tetrahedron: 1/36 of its mass at each vertex, 4/27 at each edge node
    one = jaxsync.Mesh(points=np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float), tets=[[0, 1, 2, 3]])
    m1 = lumped_mass(function_space(one, "P2")) / one.volumes().sum()
    np.testing.assert_allclose(m1[:4], 1 / 36, rtol=1e-12)
    np.testing.assert_allclose(m1[4:], 4 / 27, rtol=1e-12)
    # P1 keeps its row sums: a quarter of each element's volume
    np.testing.assert_allclose(lumped_mass(mesh), np.asarray(consistent_mass(mesh).sum(axis=1)).ravel()[::3],
                               rtol=1e-12)


def lowest_frequencies(problem, lumped: bool, k: int = 3) -> np.ndarray:
    """The k lowest natural frequencies [Hz] of the clamped problem, with the consistent or
    the lumped mass (scipy shift-invert)."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    K = problem.operators.stiffness(problem.material.lam, problem.material.mu)
    fixed, _ = problem.dirichlet_dofs()
    free = np.setdiff1d(np.arange(K.shape[0]), fixed)
    M = (sp.diags(np.repeat(problem.lumped_mass(), 3)) if lumped else problem.operators.M_1).tocsr()
    w2 = spla.eigsh(K[free][:, free].tocsc(), k=k, M=M[free][:, free].tocsc(), sigma=0, which="LM")[0]
    return np.sqrt(np.sort(w2)) / (2 * np.pi)


def test_hrz_lumping_shifts_the_frequencies_at_second_order():
    """The lumped P2 mass against the consistent one: the cantilever's lowest frequencies
    differ by less than 1 % relative, and by about 4x less on a mesh twice as fine."""
    shifts = []
    for divisions in ((12, 1, 1), (24, 2, 2)):
        problem = jaxsync.cantilever(jaxsync.box_beam(12.0, 1.0, 1.0, divisions), element="P2")
        consistent, lumped = (lowest_frequencies(problem, flag) for flag in (False, True))
        shifts.append(np.abs(lumped - consistent) / consistent)
    assert shifts[0].max() < 1e-2, shifts
    rate = np.log2(shifts[0] / shifts[1])
    assert np.all(rate > 1.7), rate


def rollers(faces=("x0", "y0", "z0")):
    return [jaxsync.Dirichlet(face, components=(axis,)) for axis, face in enumerate(faces)]


@pytest.mark.parametrize("element", ["P1", "P2"])
def test_uniaxial_stress_patch_test_is_exact(element):
    sigma = 2.0e3
    mesh = beam((3, 2, 2), 1.5)
    problem = jaxsync.Problem(mesh, jaxsync.LinearElastic(E, NU, 1.0), element=element, dirichlet=rollers(),
                              loads=[Traction((sigma, 0.0, 0.0), jaxsync.Constant(), surface="x1")])
    u = jaxsync.steady_state(problem)
    x = problem.points
    exact = np.stack([sigma * x[:, 0] / E, -NU * sigma * x[:, 1] / E, -NU * sigma * x[:, 2] / E], axis=1)
    np.testing.assert_allclose(u, exact, rtol=0, atol=1e-13 * np.abs(exact).max())


def hanging_column(element):
    """A column clamped in z at its top, rollers on its sides, under its own weight:
    uniaxial strain, u_z quadratic in z."""
    mesh = jaxsync.box_beam(1.0, 1.0, 2.0, (2, 2, 4))
    sides = [jaxsync.Dirichlet(f, components=(c,)) for f, c in (("x0", 0), ("x1", 0), ("y0", 1), ("y1", 1))]
    return jaxsync.Problem(mesh, jaxsync.LinearElastic(E, NU, 1.0), element=element,
                           dirichlet=sides + [jaxsync.Dirichlet("z1", components=(2,))],
                           loads=[jaxsync.BodyForce((0.0, 0.0, -1.0e3), jaxsync.Constant())])


def test_p2_reproduces_a_quadratic_field_exactly_and_p1_does_not():
    errors = {}
    for element in ("P1", "P2"):
        problem = hanging_column(element)
        u = jaxsync.steady_state(problem)
        m = problem.material
        z = problem.points[:, 2]
        # (lambda + 2 mu) u'' = -b_z = 1e3, u(2) = 0, u'(0) = 0 (free bottom)
        exact = 1.0e3 * (z**2 - 4.0) / (2.0 * (m.lam + 2 * m.mu))
        errors[element] = np.abs(u[:, 2] - exact).max() / np.abs(exact).max()
    assert errors["P2"] < 1e-12
    assert errors["P1"] > 1e-3


def lame_cylinder(size: float, element: str):
    """Plane-strain thick cylinder (radii 1 and 2), internal pressure p, the outer wall on
    springs k (a Robin condition): u_r = A r + B / r with
    2 (lambda + mu) A - 2 mu B / a^2 = -p and 2 (lambda + mu) A - 2 mu B / b^2 = -k (A b + B / b)."""
    mesh = jaxsync.vessel_mesh(None, length=4.0, radius=1.0, wall=1.0, size=size, order=2)
    p, k = 1.0e4, 2.0e5
    problem = jaxsync.Problem(mesh, jaxsync.LinearElastic(E, NU, 1.0), element=element,
                              dirichlet=[jaxsync.Dirichlet(face, components=(2,)) for face in ("inlet", "outlet")],
                              loads=[jaxsync.Pressure(p, jaxsync.Constant(), surface="lumen")],
                              supports=[jaxsync.ElasticSupport(k, surface="outer")])
    lam, mu = problem.material.lam, problem.material.mu
    a, b = 1.0, 2.0
    A, B = np.linalg.solve([[2 * (lam + mu), -2 * mu / a**2], [2 * (lam + mu) + k * b, -2 * mu / b**2 + k / b]],
                           [-p, 0.0])
    return problem, lambda r: A * r + B / r


def lame_error(size: float, element: str) -> tuple[float, float]:
    """(relative root-mean-square nodal error against the Lame cylinder, h = n_elements^(-1/3))."""
    problem, exact = lame_cylinder(size, element)
    u = jaxsync.steady_state(problem)
    x = problem.points
    r = np.hypot(x[:, 0], x[:, 1])
    # the exact field is radial with u_z = 0; the discrete u_z is error too
    exact_u = np.stack([exact(r) * x[:, 0] / r, exact(r) * x[:, 1] / r, 0.0 * r], axis=1)
    error = np.sqrt(np.mean(np.sum((u - exact_u) ** 2, axis=1))) / np.abs(exact(r)).max()
    return error, problem.mesh.n_elements ** (-1.0 / 3.0)


def test_p2_is_ten_times_more_accurate_than_p1_on_the_coarse_lame_cylinder():
    """The fast check of test_convergence_rates_against_the_lame_cylinder (slow): on its
    coarsest mesh (size 0.7, 691 elements) the curved P2 error is below a tenth of P1's
    (measured 0.011 against 0.18), and P1's rate from sizes 0.7 and 0.5 (691 and 1 836
    elements) is second order (measured 2.3). P2's third order needs the three meshes: from
    the two coarse ones it is pre-asymptotic (measured 4.1)."""
    (p1_coarse, h_coarse), (p1_fine, h_fine) = lame_error(0.7, "P1"), lame_error(0.5, "P1")
    p2_coarse, _ = lame_error(0.7, "P2")
    rate = np.log(p1_coarse / p1_fine) / np.log(h_coarse / h_fine)
    assert 1.6 < rate < 2.4, (p1_coarse, p1_fine, rate)
    assert p2_coarse < 0.1 * p1_coarse, (p2_coarse, p1_coarse)


@pytest.mark.slow  # 33 s; the default run: test_p2_is_ten_times_more_accurate_than_p1_on_the_coarse_lame_cylinder
def test_convergence_rates_against_the_lame_cylinder():
    """Root-mean-square nodal error against h = n_elements^(-1/3) on three unstructured
    meshes: second order for P1, third for (isoparametric, curved-wall) P2."""
    errors = {"P1": [], "P2": []}
    widths = []
    for size in (0.7, 0.5, 0.35):
        for element in errors:
            error, width = lame_error(size, element)
            errors[element].append(error)
        widths.append(width)
    rates = {e: np.polyfit(np.log(widths), np.log(v), 1)[0] for e, v in errors.items()}
    assert 1.6 < rates["P1"] < 2.4, (errors, rates)
    assert 2.6 < rates["P2"] < 3.4, (errors, rates)
    assert errors["P2"][-1] < 0.1 * errors["P1"][-1]


def test_cantilever_tip_within_3_percent_of_beam_theory_where_p1_is_far_off():
    """The paper's cantilever on a 2 x 2 cross-section: Euler-Bernoulli's tip deflection
    q L^4 / (8 E I); P1 locks in bending (more than 20 % off), P2 does not."""
    mesh = jaxsync.box_beam(25.0, 1.0, 1.0, (25, 2, 2))
    theory = 0.5 * 25.0**4 / (8 * E / 12.0)
    tips = {e: -jaxsync.steady_state(jaxsync.cantilever(mesh).replace(element=e))[:, 2].min() for e in ("P1", "P2")}
    assert abs(tips["P1"] - theory) > 0.2 * theory
    assert abs(tips["P2"] - theory) < 0.03 * theory


def test_p2_step_is_the_exact_bound_and_runs_stably():
    problem = jaxsync.cantilever(beam((6, 1, 1), 6.0)).replace(element="P2")
    step = problem.time_step
    assert step.rule == "exact" and problem.dt == pytest.approx(0.9 * jaxsync.max_stable_dt(problem), rel=1e-12)
    assert "P2 elements take their step from the exact bound" in step.describe()
    run = jaxsync.simulate(problem, 20_000, save=1000)
    assert np.isfinite(np.asarray(run.displacement)).all()
    assert np.abs(np.asarray(run.displacement)).max() < 2 * np.abs(jaxsync.steady_state(problem)).max()
    with pytest.raises(jaxsync.StabilityError, match="above"):
        jaxsync.simulate(problem, 10, dt=1.01 * jaxsync.max_stable_dt(problem))
    with pytest.raises(jaxsync.ProblemError, match="P1 CFL rule"):
        jaxsync.mass_scaling(problem, beta=2.0)
    with pytest.raises(jaxsync.ProblemError, match="preassembled"):
        jaxsync.simulate(problem, 10, mode="recompute")


@pytest.fixture(scope="module")
def p2_beam_run():
    problem = jaxsync.cantilever(beam((8, 2, 1), 8.0)).replace(element="P2")
    return problem, jaxsync.simulate(problem, 150, save=10)


# psum in the default run; the P1 partition with ppermute and the deep halos in the slow run
@pytest.mark.parametrize("exchange", ["psum", pytest.param("ppermute-p1-partition", marks=pytest.mark.slow),
                                      pytest.param("halo", marks=pytest.mark.slow)])
def test_distributed_p2_equals_the_single_device_run(p2_beam_run, exchange):
    problem, single = p2_beam_run
    scale = np.abs(np.asarray(single.displacement)).max()
    partitions, sync = {
        "psum": (2, "psum"),
        # a P1 partition: its parts take the edge nodes too
        "ppermute-p1-partition": (jaxsync.partition(problem.mesh, 2), "ppermute"),
        "halo": (jaxsync.partition(problem, 2), jaxsync.Halo(2)),
    }[exchange]
    run = jaxsync.simulate(problem, 150, save=10, partitions=partitions, sync=sync)
    np.testing.assert_allclose(np.asarray(run.displacement), np.asarray(single.displacement), rtol=0,
                               atol=1e-12 * scale)
    assert run.element == "P2" and max(int(n.max()) for n in (p.shared_nodes for p in run.parts)) >= \
        problem.mesh.n_nodes  # edge nodes are shared too


@pytest.fixture(scope="module")
def p2_gradient_case():
    import jax

    problem = jaxsync.cantilever(beam((4, 1, 1), 4.0)).replace(element="P2")
    dt = float(problem.dt)
    tip = int(np.argmax(problem.points[:, 0]))

    def loss(E_, partitions=None):
        p = problem.replace(material=jaxsync.LinearElastic(E_, NU, 1.0))
        return jaxsync.simulate(p, 120, dt=dt, save=120, partitions=partitions).displacement[-1, tip, 2]

    # compiled: one program for the gradient, one for both finite-difference runs (eager, each
    # run's values compile anew)
    return jax.jit(loss, static_argnums=1), float(jax.jit(jax.grad(loss))(E))


def test_p2_gradient_against_finite_differences(p2_gradient_case):
    loss, g = p2_gradient_case
    h = 1e-3 * E
    fd = (float(loss(E + h)) - float(loss(E - h))) / (2 * h)
    assert g == pytest.approx(fd, rel=1e-6)


@pytest.mark.slow
def test_p2_partitioned_gradient_equals_the_single_device_one(p2_gradient_case):
    import jax

    loss, g = p2_gradient_case
    g2 = float(jax.jit(jax.grad(lambda e: loss(e, 2)))(E))
    assert g2 == pytest.approx(g, rel=1e-10)


def test_p2_predicted_phase_with_an_oracle_reproduces_the_synchronized_run(tmp_path):
    """The predicted phase overwrites the shared nodes, edge nodes among them, with an
    oracle's values: it must give back the synchronized run."""
    from jaxsync.solve.coupling import OraclePredictor
    from jaxsync.surrogate.training import shared_dof_layout

    problem = jaxsync.cantilever(beam((8, 2, 1), 8.0)).replace(element="P2")
    part = jaxsync.partition(problem, 2)
    n_s, n_p, n_f, n_steps, n_cri = 2, 3, 4, 64, 16
    reference = jaxsync.simulate(problem, n_steps, partitions=part)
    n_dof, _ = shared_dof_layout(part)
    future = np.zeros((2, n_steps + 1 + n_s * n_f, n_dof))
    for p, history in enumerate(reference.parts):
        future[p, :n_steps + 1, :history.shared_displacement.shape[1]] = history.shared_displacement
    oracle = OraclePredictor(future, first_step=0, n_s=n_s, n_past=n_p, n_future=n_f)
    online = jaxsync.simulate_sync_avoiding(problem, n_steps, surrogates=oracle, partitions=part, n_cri=n_cri)
    scale = np.abs(np.asarray(reference.displacement)).max()
    np.testing.assert_allclose(np.asarray(online.displacement), np.asarray(reference.displacement), rtol=0,
                               atol=1e-12 * scale)
    # the report on P2 trajectories: nodes named by coordinates are the P2 nodes nearest
    from jaxsync.app.plots import constrained_nodes, write_report

    tip_edge = (8.0, 0.25, 1.0)  # the midpoint of an edge of the free end: an edge node
    fixed = constrained_nodes(None, online.space, reference.displacement)
    summary = write_report(reference, online, part, tmp_path / "report", nodes={"edge": tip_edge},
                           fixed_nodes=fixed)
    (row,) = summary["node_errors"]
    assert row["node"] >= problem.mesh.n_nodes and row["coordinates"] == list(tip_edge)
    assert set(fixed) == set(np.unique(problem.dirichlet_dofs()[0] // 3))


def test_p2_checkpoint_resumes_exactly(tmp_path):
    problem = jaxsync.cantilever(beam((4, 1, 1), 4.0)).replace(element="P2")
    ckpt = tmp_path / "run.ckpt.h5"
    full = jaxsync.simulate(problem, 600, save=20)
    jaxsync.simulate(problem, 200, save=20, checkpoint=ckpt)
    resumed = jaxsync.simulate(problem, 600, save=20, checkpoint=ckpt)
    np.testing.assert_array_equal(np.asarray(resumed.displacement), np.asarray(full.displacement))


def test_quadratic_mesh_files_read_as_they_are_and_p2_results_write_as_tetra10(tmp_path):
    mesh = beam((3, 1, 1), 3.0)
    space = function_space(mesh, "P2")
    kind, cells = vtk_cells(space)
    assert kind == "tetra10"
    path = tmp_path / "beam10.vtu"
    meshio.write(str(path), meshio.Mesh(space.points, [("tetra10", cells)]))
    read = jaxsync.read_mesh(path)
    assert read.mid_nodes is not None and read.n_nodes == mesh.n_nodes
    problem = jaxsync.Problem(read, jaxsync.LinearElastic(E, NU, 1.0),
                              dirichlet=[jaxsync.Dirichlet(lambda x: x[:, 0] < 1e-9)],
                              loads=[jaxsync.BodyForce((0.0, 0.0, -1.0), jaxsync.Constant())])
    assert problem.element == "P2" and not problem.space.curved  # straight edges: the same space
    twin = jaxsync.Problem(mesh, jaxsync.LinearElastic(E, NU, 1.0), element="P2",
                           dirichlet=[jaxsync.Dirichlet(lambda x: x[:, 0] < 1e-9)],
                           loads=[jaxsync.BodyForce((0.0, 0.0, -1.0), jaxsync.Constant())])
    np.testing.assert_allclose(problem.points, twin.points, rtol=0, atol=1e-15)
    np.testing.assert_allclose(jaxsync.steady_state(problem), jaxsync.steady_state(twin), rtol=0, atol=1e-15)
    # results: HDF5 round trip, XDMF and VTU with tetra10 cells
    run = jaxsync.simulate(problem, 40, save=20)
    run.save(tmp_path / "run.h5")
    back = jaxsync.Trajectory.load(tmp_path / "run.h5")
    assert back.element == "P2" and back.mesh.mid_nodes is not None
    np.testing.assert_array_equal(back.points, run.points)
    run.to_xdmf(tmp_path / "run.xdmf")
    with meshio.xdmf.TimeSeriesReader(str(tmp_path / "run.xdmf")) as reader:
        points, cell_blocks = reader.read_points_cells()
        _, point_data, _ = reader.read_data(2)
    assert cell_blocks[0].type == "tetra10" and len(points) == problem.n_nodes
    np.testing.assert_allclose(point_data["displacement"], np.asarray(run.displacement[2]), rtol=0, atol=0)
    pvd = run.to_vtu(tmp_path / "vtu" / "run")
    last = meshio.read(str(tmp_path / "vtu" / "run" / "run_000002.vtu"))
    assert pvd.endswith(".pvd") and last.cells[0].type == "tetra10"
    np.testing.assert_array_equal(last.point_data["displacement"], np.asarray(run.displacement[2]))
