import numpy as np
import pytest
import scipy.linalg

import fem_reference as ref
import jaxsync
from jaxsync import StabilityError
from jaxsync.fem import check_dt, element_size


def test_cfl_dt_of_one_known_tetrahedron():
    points = np.array([[0, 0, 0], [2.0, 0, 0], [0, 1.5, 0], [0, 0, 3.0]])
    mesh = jaxsync.Mesh(points, np.array([[0, 1, 2, 3]]))
    mat = jaxsync.LinearElastic(2.0e5, 0.25, 1.3)
    problem = jaxsync.Problem(mesh, mat, dirichlet=(jaxsync.Dirichlet(lambda p: p[:, 0] == 0),))
    shortest = 1.5
    expected = 0.9 * (2 * shortest / np.sqrt(24)) / np.sqrt(2.0e5 / (1.3 * (1 - 0.25**2)))
    assert problem.dt == pytest.approx(expected, rel=1e-14)
    assert element_size(points, mesh.tets)[0] == pytest.approx(2 * shortest / np.sqrt(24))


def test_max_stable_dt_equals_generalized_eigenvalue():
    problem = jaxsync.cantilever(jaxsync.box_beam(5.0, 1.0, 1.0, (5, 1, 1)))
    mat = problem.material
    K = ref.stiffness(problem.mesh.points, problem.mesh.tets, mat.E, mat.nu)
    m = ref.lumped_mass(problem.mesh.points, problem.mesh.tets, mat.rho)
    fixed, _ = problem.dirichlet_dofs()
    free = np.setdiff1d(np.arange(K.shape[0]), fixed)
    w2 = scipy.linalg.eigh(K[free][:, free].toarray(), np.diag(m[free]), eigvals_only=True)
    assert jaxsync.max_stable_dt(problem) == pytest.approx(2 / np.sqrt(w2.max()), rel=1e-6)
    # the CFL rule is conservative here
    assert problem.dt < jaxsync.max_stable_dt(problem)


def test_dt_above_the_bound_is_refused():
    problem = jaxsync.cantilever()
    bound = jaxsync.max_stable_dt(problem)
    check_dt(problem, 0.5 * (problem.dt + bound))  # between CFL and bound: accepted
    with pytest.raises(StabilityError, match="above the stability bound"):
        check_dt(problem, 1.01 * bound)
    with pytest.raises(StabilityError, match="positive"):
        check_dt(problem, -1.0)
    with pytest.raises(StabilityError, match="above the stability bound"):
        jaxsync.simulate(problem, 10, dt=1.5 * bound)


def test_mass_scaling_adds_exactly_the_mass_it_reports():
    # a graded beam: short elements near the clamp limit the step
    mesh = jaxsync.box_beam(10.0, 1.0, 1.0, (10, 1, 1))
    points = mesh.points.copy()
    points[:, 0] = 10.0 * (points[:, 0] / 10.0) ** 2
    mesh = jaxsync.Mesh(points, mesh.tets, mesh.facet_sets)
    problem = jaxsync.cantilever(mesh)
    scaled, percent = jaxsync.mass_scaling(problem, beta=2.0)
    m0 = float(np.sum(problem.lumped_mass()))
    m1 = float(np.sum(scaled.lumped_mass()))
    assert percent > 0
    assert 100 * (m1 - m0) / m0 == pytest.approx(percent, rel=1e-12)
    assert scaled.dt == pytest.approx(2.0 * problem.dt, rel=1e-12)
    # elements already above the target keep their density
    h = element_size(mesh.points, mesh.tets)
    c = np.sqrt(1.0e6 / (1 - 0.09))
    untouched = 0.9 * h / c >= 2.0 * problem.dt
    assert untouched.any()
    np.testing.assert_array_equal(scaled.density_scale[untouched], 1.0)
    # scaling to a smaller target changes nothing
    same, zero = jaxsync.mass_scaling(problem, dt_target=0.5 * problem.dt)
    assert zero == 0.0


def test_mass_scaling_arguments():
    problem = jaxsync.cantilever()
    with pytest.raises(StabilityError, match="exactly one"):
        jaxsync.mass_scaling(problem)


def graded_cantilever():
    """A beam whose elements shrink quadratically towards the clamp."""
    mesh = jaxsync.box_beam(10.0, 1.0, 1.0, (10, 1, 1))
    points = mesh.points.copy()
    points[:, 0] = 10.0 * (points[:, 0] / 10.0) ** 2
    return jaxsync.cantilever(jaxsync.Mesh(points, mesh.tets, mesh.facet_sets))


def test_mass_scaling_warns_above_the_threshold():
    import warnings

    problem = graded_cantilever()
    target = 4.0 * problem.dt
    with pytest.warns(jaxsync.MassScalingWarning) as record:
        scaled, percent = jaxsync.mass_scaling(problem, dt_target=target)
    assert percent > 10.0
    message = str(record[0].message)
    assert f"{percent:.1f} %" in message and f"{target:.4e} s" in message
    # the caller's threshold: no warning at or below it, none at all with None
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _, same = jaxsync.mass_scaling(problem, dt_target=target, warn_above_percent=percent)
        jaxsync.mass_scaling(problem, dt_target=target, warn_above_percent=None)
        jaxsync.mass_scaling(problem, dt_target=0.5 * problem.dt)  # nothing added
    assert same == percent
    with pytest.warns(jaxsync.MassScalingWarning):
        jaxsync.mass_scaling(problem, beta=1.05, warn_above_percent=0.0)
    with pytest.raises(StabilityError, match="warn_above_percent"):
        jaxsync.mass_scaling(problem, beta=2.0, warn_above_percent=-1.0)


def test_mass_scaled_problem_runs_at_the_target_step_by_default():
    problem = graded_cantilever()
    scaled, _ = jaxsync.mass_scaling(problem, beta=2.0, warn_above_percent=None)
    traj = jaxsync.simulate(scaled, 20, save=10)
    assert traj.dt == pytest.approx(2.0 * problem.dt, rel=1e-12)
    with pytest.raises(StabilityError, match="positive and finite"):
        jaxsync.mass_scaling(problem, beta=float("nan"))


def _with_nu(problem, nu):
    return problem.replace(material=jaxsync.LinearElastic(1.0e6, nu, 1.0))


@pytest.mark.parametrize("nu", [0.45, 0.49, 0.499])
def test_default_step_of_nearly_incompressible_tissue_is_stable(nu):
    # the paper's CFL rule ignores the dilatational wave speed: at these nu it lies above
    # the exact bound (3.28e-4 s against 2.98e-4 s at nu = 0.45) and every run diverged
    problem = _with_nu(jaxsync.cantilever(), nu)
    bound = jaxsync.max_stable_dt(problem)
    assert jaxsync.cfl_dt(problem) > bound  # the case the default must not follow
    step = problem.time_step
    assert step.rule == "exact"
    assert problem.dt == pytest.approx(0.9 * bound, rel=1e-12)
    assert problem.dt <= bound
    assert "exact stability bound" in problem.summary()
    traj = jaxsync.simulate(problem, 20_000, save=100)
    u = np.asarray(traj.displacement)
    assert np.isfinite(u).all()
    # ground truth: a ramped load's response stays within twice the static deflection
    static = np.abs(np.asarray(jaxsync.steady_state(problem))).max()
    assert np.abs(u).max() <= 2.0 * static


def test_default_step_keeps_the_paper_rule_where_it_is_below_the_bound():
    for problem in (jaxsync.cantilever(), _with_nu(jaxsync.cantilever(), 0.4)):
        step = problem.time_step
        assert step.rule == "cfl"
        assert problem.dt == jaxsync.cfl_dt(problem)  # bit-identical: the paper's cases keep their dt
        assert step.cfl <= 0.9 * step.exact
        assert "paper's CFL rule" in step.describe()


def test_exact_bound_against_a_dense_generalized_eigenproblem_at_high_nu():
    # independent reference: the lumped-mass generalized eigenproblem of a NumPy assembly
    problem = _with_nu(jaxsync.cantilever(jaxsync.box_beam(5.0, 1.0, 1.0, (5, 1, 1))), 0.49)
    mat = problem.material
    K = ref.stiffness(problem.mesh.points, problem.mesh.tets, mat.E, mat.nu)
    m = ref.lumped_mass(problem.mesh.points, problem.mesh.tets, mat.rho)
    fixed, _ = problem.dirichlet_dofs()
    free = np.setdiff1d(np.arange(K.shape[0]), fixed)
    w2 = scipy.linalg.eigh(K[free][:, free].toarray(), np.diag(m[free]), eigvals_only=True)
    assert problem.time_step.exact == pytest.approx(2 / np.sqrt(w2.max()), rel=1e-10)
    assert problem.dt == pytest.approx(0.9 * 2 / np.sqrt(w2.max()), rel=1e-10)


def test_sparse_exact_bound_equals_the_dense_one():
    # above the dense size the bound comes from Lanczos: the same number
    from jaxsync.fem import DENSE_EIGEN_DOFS

    problem = _with_nu(jaxsync.cantilever(jaxsync.box_beam(25.0, 1.0, 1.0, (25, 2, 2))), 0.45)
    sparse = jaxsync.max_stable_dt(problem)
    assert 3 * problem.mesh.n_nodes > DENSE_EIGEN_DOFS
    K = problem.operators.stiffness(problem.material.lam, problem.material.mu)
    m = np.repeat(np.asarray(problem.lumped_mass()), 3)
    fixed, _ = problem.dirichlet_dofs()
    free = np.setdiff1d(np.arange(K.shape[0]), fixed)
    w2 = scipy.linalg.eigh(K[free][:, free].toarray(), np.diag(m[free]), eigvals_only=True)
    assert sparse == pytest.approx(2 / np.sqrt(w2.max()), rel=1e-9)


def test_default_step_follows_traced_stiffness_and_density():
    import jax

    problem = _with_nu(jaxsync.cantilever(), 0.49)

    def dt_of(E, rho):
        return problem.replace(material=jaxsync.LinearElastic(E, 0.49, rho)).dt

    dE, drho = jax.grad(dt_of, argnums=(0, 1))(1.0e6, 1.0)
    # dt = 0.9 * 2 / omega_max scales as sqrt(rho / E)
    assert float(dE) == pytest.approx(-0.5 * problem.dt / 1.0e6, rel=1e-12)
    assert float(drho) == pytest.approx(0.5 * problem.dt, rel=1e-12)
    with pytest.raises(jaxsync.ProblemError, match="traced nu"):
        jax.grad(lambda nu: problem.replace(material=jaxsync.LinearElastic(1e6, nu, 1.0)).dt)(0.49)


def test_divergence_names_the_step_that_works():
    problem = _with_nu(jaxsync.cantilever(), 0.45)
    bound = jaxsync.max_stable_dt(problem)
    with pytest.raises(StabilityError, match=f"dt <= {0.9 * bound:.4e}"):
        jaxsync.simulate(problem, 2000, dt=1.1 * bound, executor=jaxsync.HostExecutor(check_stability=False))
    with pytest.raises(StabilityError, match=f"use dt <= {0.9 * bound:.4e}"):
        jaxsync.simulate(problem, 10, dt=1.1 * bound)
