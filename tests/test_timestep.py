import numpy as np
import pytest
import scipy.linalg

import fem_reference as ref
import jaxsync
from jaxsync import StabilityError
from jaxsync.fem.timestep import check_dt, element_size


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
    traj = jaxsync.simulate(scaled, 20, save_every=10)
    assert traj.dt == pytest.approx(2.0 * problem.dt, rel=1e-12)
    with pytest.raises(StabilityError, match="positive and finite"):
        jaxsync.mass_scaling(problem, beta=float("nan"))
