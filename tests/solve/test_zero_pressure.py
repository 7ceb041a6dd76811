"""The zero-pressure geometry and the prestress of an imaged vessel
(:func:`jaxsync.zero_pressure_geometry`, :func:`jaxsync.prestress`, :class:`jaxsync.Prestressed`,
``jaxsync unload``), checked against: the forward static solution (inflating the unloaded
geometry gives back the imaged nodes), the closed form of an inflated thick-walled
incompressible neo-Hookean tube in plane strain, the response of the zero-pressure route to
a pressure increment (statics and explicit dynamics, one device and two parts), finite
differences of the unloaded radius in the shear modulus, and the mesh read back from the
command line's file."""

import os
import warnings

import numpy as np
import pytest
import scipy.integrate
import scipy.optimize

import jaxsync
from jaxsync.mesh import read_mesh

PRESSURE = 1.6e5  # barye, 120 mmHg
LAW = jaxsync.NearlyIncompressibleNeoHookean(E=6.26e6, nu=0.45)
RADIUS, WALL = 0.175, 0.05
DIAMETER = 2 * (RADIUS + WALL)


@pytest.fixture(scope="module")
def vessel():
    return jaxsync.vessel_mesh(length=0.5, radius=RADIUS, wall=WALL, size=0.07)


def _vessel_problem(mesh, pressure=PRESSURE, material=LAW, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", jaxsync.LockingWarning)
        return jaxsync.Problem(mesh, material, dirichlet=[jaxsync.Dirichlet("inlet"), jaxsync.Dirichlet("outlet")],
                               loads=[jaxsync.Pressure(pressure, surface="lumen", follower=True)], **kw)


@pytest.fixture(scope="module")
def unloaded(vessel):
    return jaxsync.zero_pressure_geometry(_vessel_problem(vessel), tol=1e-12)


def _inflated(problem, geometry, **kw):
    """The imaged problem's loads on the unloaded geometry: the deformed node positions."""
    return geometry.points + np.asarray(jaxsync.steady_state(geometry.problem(problem), tol=1e-13, **kw))


@pytest.fixture(scope="module")
def at_rest(vessel, unloaded):
    """The displacement of the unloaded geometry inflated by the imaging pressure (solved once
    for the tests that need it)."""
    return np.asarray(jaxsync.steady_state(unloaded.problem(_vessel_problem(vessel)), tol=1e-13))


def test_newton_unloaded_vessel_inflates_back_to_the_imaged_nodes(vessel, unloaded, at_rest):
    problem = _vessel_problem(vessel)
    assert unloaded.residuals[-1] <= 1e-12 and unloaded.iterations == len(unloaded.residuals) - 1
    moved = np.abs(unloaded.points - problem.points).max()
    assert moved > 1e-3 * DIAMETER  # the pressure does deform the wall
    assert np.abs(unloaded.points + at_rest - problem.points).max() <= 1e-8 * DIAMETER  # _inflated(problem, unloaded)
    # the unloaded mesh keeps topology and facet sets
    assert np.array_equal(unloaded.mesh.tets, vessel.tets)
    assert all(np.array_equal(unloaded.mesh.facet_sets[k], vessel.facet_sets[k]) for k in vessel.facet_sets)


def test_fixed_point_unloaded_vessel_inflates_back_and_agrees_with_newton(vessel, unloaded):
    problem = _vessel_problem(vessel)
    found = jaxsync.zero_pressure_geometry(problem, method="fixed-point", tol=1e-9)
    assert found.residuals[-1] <= 1e-9 and found.residuals[0] > 1e-3  # it did iterate
    assert np.abs(_inflated(problem, found) - problem.points).max() <= 1e-8 * DIAMETER
    assert np.abs(found.points - unloaded.points).max() <= 1e-8 * DIAMETER


def _annulus(a, b, height, n_r, n_t):
    """A quarter of a thick-walled tube (a <= r <= b, 0 <= theta <= pi/2, 0 <= z <= height),
    a structured grid of hexahedra each split into 6 tetrahedra; facet sets lumen at r = a
    and outer at r = b."""
    r, t, z = np.linspace(a, b, n_r + 1), np.linspace(0, np.pi / 2, n_t + 1), np.array([0.0, height])
    R, T, Z = np.meshgrid(r, t, z, indexing="ij")
    points = np.stack([R * np.cos(T), R * np.sin(T), Z], -1).reshape(-1, 3)
    index = np.arange(len(points)).reshape(n_r + 1, n_t + 1, 2)
    kuhn = [(0, 1, 3, 7), (0, 1, 5, 7), (0, 2, 3, 7), (0, 2, 6, 7), (0, 4, 5, 7), (0, 4, 6, 7)]
    tets, lumen, outer = [], [], []
    for i in range(n_r):
        for j in range(n_t):
            c = [index[i + di, j + dj, dk] for di in (0, 1) for dj in (0, 1) for dk in (0, 1)]
            tets += [[c[q] for q in tet] for tet in kuhn]
            if i == 0:
                lumen += [[c[0], c[2], c[3]], [c[0], c[1], c[3]]]
            if i == n_r - 1:
                outer += [[c[4], c[6], c[7]], [c[4], c[5], c[7]]]
    with warnings.catch_warnings():  # half the Kuhn tetrahedra come out left-handed: re-oriented
        warnings.simplefilter("ignore", jaxsync.MeshWarning)
        return jaxsync.Mesh.from_arrays(points, np.array(tets), {"lumen": np.array(lumen), "outer": np.array(outer)})


def _plane_strain_tube(mesh, material, pressure, height, element="P1"):
    """Symmetry planes x = 0 and y = 0, u_z = 0 on both ends (plane strain, axial stretch 1)."""
    on = lambda axis, value: lambda x: np.abs(x[:, axis] - value) < 1e-12  # noqa: E731
    return jaxsync.Problem(
        mesh, material, element=element, loads=[jaxsync.Pressure(pressure, surface="lumen", follower=True)],
        dirichlet=[jaxsync.Dirichlet(on(1, 0.0), components=(1,)), jaxsync.Dirichlet(on(0, 0.0), components=(0,)),
                   jaxsync.Dirichlet(lambda x: on(2, 0.0)(x) | on(2, height)(x), components=(2,))])


def _closed_form_unloaded_radii(a, b, p, mu):
    """(A, B) of an incompressible neo-Hookean tube in plane strain whose radii under the
    lumen pressure p are (a, b): incompressibility gives r^2 - R^2 = a^2 - A^2 = c, the
    hoop stretch lambda = r / R, equilibrium d sigma_rr/dr = (sigma_tt - sigma_rr) / r with
    sigma_tt - sigma_rr = mu (lambda^2 - lambda^-2), sigma_rr(a) = -p, sigma_rr(b) = 0, so
    p = int_a^b mu (lambda^2 - lambda^-2) / r dr, solved for c."""
    def pressure(A):
        c = a * a - A * A
        return scipy.integrate.quad(lambda r: mu * (r * r / (r * r - c) - (r * r - c) / (r * r)) / r, a, b,
                                    epsabs=0, epsrel=1e-13)[0]

    A = scipy.optimize.brentq(lambda A: pressure(A) - p, 0.2 * a, a, xtol=1e-15)
    return A, np.sqrt(b * b - a * a + A * A)


TUBE = dict(a=0.2, b=0.3, height=0.05, mu=1.0e6, nu=0.4999, p=0.25e6)


def _tube_radii_errors(n_r, n_t):
    """Relative errors of the mean unloaded inner and outer radii against the closed form
    (P2 elements; nu = 0.4999: the compressibility contributes ~p / K = 5e-5)."""
    a, b, h, mu, nu, p = (TUBE[k] for k in ("a", "b", "height", "mu", "nu", "p"))
    A, B = _closed_form_unloaded_radii(a, b, p, mu)
    mesh = _annulus(a, b, h, n_r, n_t)
    law = jaxsync.NearlyIncompressibleNeoHookean(E=2 * mu * (1 + nu), nu=nu)
    found = jaxsync.zero_pressure_geometry(_plane_strain_tube(mesh, law, p, h, "P2"), tol=1e-9)
    imaged = np.linalg.norm(mesh.points[:, :2], axis=1)
    radius = np.linalg.norm(found.mesh.points[:, :2], axis=1)
    return (radius[np.abs(imaged - a) < 1e-9].mean() / A - 1, radius[np.abs(imaged - b) < 1e-9].mean() / B - 1)


TUBE_TOLERANCE = 6e-3
"""The coarse tube's unloaded radii against the closed form: measured 4.2e-3 (inner) and
1.4e-3 (outer) relative with 2 x 6 cells, 1.1e-3 and 3.2e-4 with 4 x 12 (second order in
the mesh size: test_tube_radii_converge_under_refinement)."""


def test_unloaded_tube_radii_match_the_incompressible_closed_form():
    inner, outer = _tube_radii_errors(2, 6)
    assert abs(inner) < TUBE_TOLERANCE and abs(outer) < TUBE_TOLERANCE


@pytest.mark.slow
def test_tube_radii_converge_under_refinement():
    coarse, fine = np.abs(_tube_radii_errors(2, 6)), np.abs(_tube_radii_errors(4, 12))
    assert np.all(fine < coarse / 3)  # second order: 4x smaller at half the size


# the default run checks the gradient of zero_pressure_points against finite differences in
# test_gradient_of_the_unloaded_geometry_on_supports_matches_finite_differences (the same tube)
@pytest.mark.slow
def test_gradient_of_the_unloaded_radius_in_the_shear_modulus_matches_finite_differences():
    import jax

    a, b, h, p = 0.2, 0.3, 0.05, 2.0e5
    mesh = _annulus(a, b, h, 2, 4)
    inner = np.flatnonzero(np.abs(np.linalg.norm(mesh.points[:, :2], axis=1) - a) < 1e-9)
    nu = 0.4

    def radius(mu):  # the law of shear modulus mu (E = 2 mu (1 + nu))
        law = jaxsync.NeoHookean(E=2.0 * mu * (1.0 + nu), nu=nu)
        X = jaxsync.zero_pressure_points(_plane_strain_tube(mesh, law, p, h), tol=1e-13)
        return jax.numpy.mean(jax.numpy.linalg.norm(X[inner, :2], axis=1))

    mu = 1.0e6
    gradient = float(jax.grad(radius)(mu))
    step = 1e-4 * mu
    difference = (float(radius(mu + step)) - float(radius(mu - step))) / (2 * step)
    assert gradient > 0  # a stiffer wall is inflated less, so its unloaded radius is larger
    np.testing.assert_allclose(gradient, difference, rtol=1e-6)


def test_host_solves_under_jit_are_refused_with_the_fix():
    """The differentiable host solves (Newton on the host) cannot be traced by ``jit``: a
    ProblemError that says to differentiate outside jit, not a tracer error."""
    import jax

    mesh = _annulus(0.2, 0.3, 0.05, 2, 4)

    def problem(mu):
        return _plane_strain_tube(mesh, jaxsync.NeoHookean(E=2.8 * mu, nu=0.4), 2.0e5, 0.05)

    for solve, name in ((jaxsync.zero_pressure_points, "zero_pressure_points"),
                        (jaxsync.static_displacement, "static_displacement")):
        with pytest.raises(jaxsync.ProblemError, match=f"{name} solves on the host.*outside jit"):
            jax.jit(lambda mu: solve(problem(mu)).sum())(1.0e6)


# the default run checks the unloaded HGO tube in
# test_prestressed_fibre_law_is_in_equilibrium_and_responds_as_the_unloaded_geometry (the same tube)
@pytest.mark.parametrize("law, element", [pytest.param("hgo", "P1", marks=pytest.mark.slow), ("neo-hookean", "P2")])
def test_unloaded_tube_inflates_back_for_fibre_laws_and_curved_quadratic_elements(law, element):
    a, b, h = 0.2, 0.3, 0.05
    mesh = _annulus(a, b, h, 2, 4)
    if law == "hgo":
        fibres = jaxsync.helical_fibres(mesh.points[mesh.tets].mean(axis=1), axis=(0.0, 0.0, 1.0), angle=40.0)
        material = jaxsync.HolzapfelGasserOgden(mu=3.0e5, k1=2.0e5, k2=0.8, kappa_bulk=3.0e6, fibres=fibres)
    else:
        material = jaxsync.NeoHookean(E=2.6e6, nu=0.3)
    problem = _plane_strain_tube(mesh, material, 1.0e5, h, element)
    found = jaxsync.zero_pressure_geometry(problem, tol=1e-12)
    assert np.abs(found.points - problem.points).max() > 1e-3 * a
    if element == "P2":  # the unloaded edge nodes leave the midpoints: an isoparametric mesh
        assert found.mesh.mid_nodes is not None and found.problem(problem).space.curved
    assert np.abs(_inflated(problem, found) - problem.points).max() <= 1e-8 * 2 * b


# the default run checks the Krylov updates against the direct solution on the same tube in
# test_krylov_updates_with_supports_give_the_direct_solution
@pytest.mark.slow
def test_krylov_newton_updates_give_the_direct_solution():
    a, b, h = 0.2, 0.3, 0.05
    problem = _plane_strain_tube(_annulus(a, b, h, 2, 4), jaxsync.NeoHookean(E=2.6e6, nu=0.3), 2.0e5, h)
    direct = jaxsync.zero_pressure_geometry(problem, tol=1e-12)
    krylov = jaxsync.zero_pressure_geometry(problem, tol=1e-12, linear_solver="krylov")
    assert np.abs(direct.points - problem.points).max() > 1e-2 * a
    assert np.abs(krylov.points - direct.points).max() <= 1e-10 * a


def _hard_tube(pressure):
    """The 2 x 4-element plane-strain tube at ``pressure`` [barye], far above its modulus."""
    mesh = _annulus(0.2, 0.3, 0.05, 2, 4)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", jaxsync.LockingWarning)
        return _plane_strain_tube(mesh, jaxsync.NearlyIncompressibleNeoHookean(E=2.6e6, nu=0.45), pressure, 0.05)


def test_a_solve_that_does_not_converge_is_refused_naming_pressure_and_iteration():
    # 5e7 barye is 19 E: in one increment Newton wanders with the residual near 1
    message = r"did not converge at .*5e\+07 barye on 'lumen'.*Newton iteration 3,.*raise load_steps"
    with pytest.raises(jaxsync.ConvergenceError, match=message) as info:
        jaxsync.zero_pressure_geometry(_hard_tube(5.0e7), load_steps=1, max_iter=3)
    assert info.value.increment == 1 and info.value.residual > 1e-3


def test_a_pressure_whose_every_update_inverts_the_reference_is_refused_naming_pressure_and_iteration():
    # 1e9 barye is 385 E: even 1/1024 of the first Newton update inverts an element
    with pytest.raises(jaxsync.ConvergenceError,
                       match=r"1e\+09 barye on 'lumen'.*Newton iteration 1, every update .* inverts an element"):
        jaxsync.zero_pressure_geometry(_hard_tube(1.0e9), load_steps=1, max_iter=30)


def test_bad_options_and_unsupported_problems_are_refused(vessel):
    problem = _vessel_problem(vessel)
    with pytest.raises(jaxsync.ProblemError, match="method must be one of"):
        jaxsync.zero_pressure_geometry(problem, method="secant")
    with pytest.raises(jaxsync.ProblemError, match="linear_solver"):
        jaxsync.zero_pressure_geometry(problem, linear_solver="cg")
    with pytest.raises(jaxsync.ProblemError, match="hyperelastic law"):
        jaxsync.zero_pressure_geometry(_vessel_problem(vessel, material=jaxsync.LinearElastic(), pressure=0.0)
                                       .replace(loads=()))


@pytest.fixture(scope="module")
def prestressed(vessel):
    return jaxsync.prestress(_vessel_problem(vessel), method="zero-pressure")


def test_prestress_puts_the_imaged_geometry_in_equilibrium(vessel, prestressed):
    problem = _vessel_problem(vessel)
    from jaxsync.solve import out_of_balance

    assert prestressed.residual <= 1e-12
    without = out_of_balance(problem)
    assert without > 0.1  # the imaged geometry alone is far from equilibrium


# the default run checks that MULF puts an imaged geometry in equilibrium in
# test_prestressed_fibre_law_is_in_equilibrium_and_responds_as_the_unloaded_geometry (the tube)
@pytest.mark.slow
def test_mulf_prestress_puts_the_imaged_vessel_in_equilibrium(vessel):
    problem = _vessel_problem(vessel)
    mulf = jaxsync.prestress(problem, method="mulf", tol=1e-13)
    assert mulf.residuals[0] > 1e-3 and mulf.residuals[-1] <= 1e-13
    assert mulf.residual <= 1e-11


def test_prestressed_response_to_a_pressure_increment_is_the_zero_pressure_routes(vessel, unloaded, prestressed):
    increment = 1e-2 * PRESSURE
    loaded = _vessel_problem(vessel, PRESSURE + increment)
    # the zero-pressure route: the unloaded geometry inflated by p + dp, measured from the imaged nodes
    expected = _inflated(loaded, unloaded) - vessel.points
    u = np.asarray(jaxsync.steady_state(loaded.replace(material=prestressed.material), load_steps=1, tol=1e-13))
    assert np.abs(expected).max() > 1e-4 * DIAMETER
    assert np.abs(u - expected).max() <= 1e-6 * np.abs(expected).max()


# the default run checks the prestressed run on two parts; the single-device prestressed run is
# also run in the default run by test_cli_simulate_starts_from_the_zero_pressure_table[prestressed]
@pytest.mark.parametrize("partitions", [pytest.param(None, marks=pytest.mark.slow), 2])
def test_prestressed_dynamics_is_the_zero_pressure_routes_on_one_device_and_two_parts(vessel, unloaded,
                                                                                     prestressed, at_rest,
                                                                                     partitions):
    """40 explicit steps after a 5 % pressure increment: the prestressed imaged vessel (on
    one device, the slow case, or two parts) moves as the unloaded geometry (one device)."""
    increment = 5e-2 * PRESSURE
    loaded = _vessel_problem(vessel, PRESSURE + increment)
    on_unloaded = unloaded.problem(loaded)
    on_unloaded = on_unloaded.replace(initial_displacement=at_rest)  # in equilibrium at the imaging pressure
    imaged = loaded.replace(material=prestressed.material, density_scale=prestressed.density_scale)
    dt = 0.5 * min(on_unloaded.dt, imaged.dt)
    n = 40
    reference = np.asarray(jaxsync.simulate(on_unloaded, n, dt=dt, save=10).displacement)
    expected = unloaded.points + reference - vessel.points
    assert np.abs(expected[-1] - expected[0]).max() > 1e-6 * DIAMETER  # the increment sets the wall moving
    run = np.asarray(jaxsync.simulate(imaged, n, dt=dt, save=10, partitions=partitions).displacement)
    assert np.abs(run - expected).max() <= 1e-6 * np.abs(expected[-1] - expected[0]).max()


def test_prestressed_refuses_a_mismatched_prestrain(vessel):
    law = jaxsync.Prestressed(LAW, np.broadcast_to(np.eye(3), (3, 1, 3, 3)))
    with pytest.raises(jaxsync.ProblemError, match="prestrain has shape"):
        jaxsync.steady_state(_vessel_problem(vessel, material=law))
    with pytest.raises(jaxsync.MaterialError, match="det F0"):
        jaxsync.Prestressed(LAW, -np.broadcast_to(np.eye(3), (3, 1, 3, 3)))


def _config(tmp_path, mesh_file):
    cfg = tmp_path / "vessel.toml"
    cfg.write_text(f"""
[mesh]
file = "{mesh_file}"
[material]
model = "nearly-incompressible-neo-hookean"
E = {LAW.E}
nu = {LAW.nu}
[problem]
kind = "general"
[[dirichlet]]
facet = "inlet"
[[dirichlet]]
facet = "outlet"
[[pressure]]
surface = "lumen"
magnitude = 1.0
follower = true
[zero_pressure]
tol = 1.0e-11
""")
    return cfg


def test_cli_writes_the_unloaded_mesh_with_its_facet_sets_and_does_not_overwrite(tmp_path, vessel, unloaded,
                                                                                  capsys):
    from jaxsync.cli import main
    from jaxsync.mesh import write_mesh

    write_mesh(vessel, tmp_path / "imaged.vtu")
    cfg = _config(tmp_path, "imaged.vtu")
    out = tmp_path / "unloaded.msh"
    assert main(["unload", str(cfg), "--pressure", str(PRESSURE), "-o", str(out)]) == 0
    assert "unloaded geometry (newton)" in capsys.readouterr().out
    written = read_mesh(out)
    assert np.abs(written.points - unloaded.mesh.points).max() <= 1e-10 * DIAMETER
    assert np.array_equal(written.tets, vessel.tets)
    assert sorted(written.facet_sets) == sorted(vessel.facet_sets)
    assert all(np.array_equal(written.facet_sets[k], vessel.facet_sets[k]) for k in vessel.facet_sets)
    before = out.read_bytes()
    assert main(["unload", str(cfg), "--pressure", str(PRESSURE), "-o", str(out)]) == 2
    assert "already exist" in capsys.readouterr().err and out.read_bytes() == before
    # a tenth of the pressure moves the wall about a tenth as far; --force replaces the output
    assert main(["unload", str(cfg), "--pressure", str(PRESSURE / 10), "-o", str(out), "--force"]) == 0
    ratio = np.abs(read_mesh(out).points - vessel.points).max() / np.abs(unloaded.points - vessel.points).max()
    assert 0.05 < ratio < 0.15


def test_write_mesh_round_trips_facet_sets_in_every_format(tmp_path, vessel):
    from jaxsync.mesh import write_mesh

    for ext in (".vtu", ".vtk", ".msh"):
        path = tmp_path / f"mesh{ext}"
        write_mesh(vessel, path)
        back = read_mesh(path)
        np.testing.assert_array_equal(back.tets, vessel.tets)
        np.testing.assert_allclose(back.points, vessel.points, rtol=0, atol=1e-15)
        assert {k: v.tolist() for k, v in back.facet_sets.items()} == {k: v.tolist()
                                                                         for k, v in vessel.facet_sets.items()}
        with pytest.raises(jaxsync.OutputError, match="already exists"):
            write_mesh(vessel, path)
    with pytest.raises(jaxsync.MeshError, match="cannot write a mesh"):
        write_mesh(vessel, os.path.join(tmp_path, "mesh.stl"))


def test_prestressed_force_is_the_gradient_of_its_energy_and_the_identity_prestrain_changes_nothing(vessel,
                                                                                                   prestressed):
    import jax

    from jaxsync.fem.forces import TotalLagrangian, strain_energy

    problem = _vessel_problem(vessel, material=prestressed.material)
    op = TotalLagrangian().operator(problem)
    u = 1e-3 * np.sin(7.0 * vessel.points)
    np.testing.assert_allclose(jax.grad(lambda v: strain_energy(op, v))(u), op.matvec(u), rtol=1e-10,
                               atol=1e-10 * np.abs(np.asarray(op.matvec(u))).max())
    plain = TotalLagrangian().operator(_vessel_problem(vessel))
    identity = TotalLagrangian().operator(_vessel_problem(vessel, material=jaxsync.Prestressed(LAW)))
    np.testing.assert_allclose(identity.matvec(u), plain.matvec(u), rtol=0,
                               atol=1e-12 * np.abs(np.asarray(plain.matvec(u))).max())


def test_a_viscoelastic_wall_is_unloaded_at_rest(vessel, unloaded):
    """The imaged state is relaxed: a Prony series is unloaded with its long-term elastic
    law (the same geometry as that law's), and the recovered geometry inflates back onto
    the image under that law; the problem the result gives carries the viscoelastic law."""
    wall = jaxsync.fem.ViscoelasticNeoHookean(E=LAW.E, nu=LAW.nu, rho=LAW.rho, betas=[1.0, 0.5], taus=[0.01, 0.1])
    imaged = _vessel_problem(vessel, material=wall)
    geometry = jaxsync.zero_pressure_geometry(imaged, tol=1e-12)
    np.testing.assert_allclose(geometry.points, unloaded.points, rtol=0, atol=1e-12 * DIAMETER)
    assert geometry.problem(imaged).material == wall
    relaxed = _vessel_problem(vessel)  # the long-term law, LAW
    np.testing.assert_allclose(_inflated(relaxed, geometry), vessel.points, rtol=0, atol=1e-8 * DIAMETER)


def _supported_vessel(mesh, element="P1", material=LAW):
    """The vessel clamped at its inlet only, on the surrounding tissue (a normal spring on the
    outer wall, a full one on the outlet), under the lumen pressure and every dead load."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", jaxsync.LockingWarning)
        return jaxsync.Problem(
            mesh, material, element=element, dirichlet=[jaxsync.Dirichlet("inlet")],
            loads=[jaxsync.Pressure(PRESSURE, surface="lumen", follower=True),
                   jaxsync.BodyForce((0.0, 2.0e4, -1.0e4), time=jaxsync.Constant()),
                   jaxsync.Traction((1.0e3, 0.0, 5.0e3), surface="outlet"), jaxsync.Pressure(2.0e4, surface="outer")],
            supports=(jaxsync.ElasticSupport(2.0e6, surface="outer", normal_only=True),
                      jaxsync.ElasticSupport(5.0e5, surface="outlet")))


def _newton_with_supports_inflates_back(mesh, element):
    problem = _supported_vessel(mesh, element)
    found = jaxsync.zero_pressure_geometry(problem, tol=1e-12 if element == "P1" else 1e-11)
    assert np.abs(found.points - problem.points).max() > 1e-2 * DIAMETER
    inflated = found.points + np.asarray(jaxsync.steady_state(found.problem(problem), tol=1e-12))
    assert np.abs(inflated - problem.points).max() <= 1e-8 * DIAMETER
    return problem, found


def test_newton_unloads_a_vessel_on_supports_under_dead_loads_and_inflates_back(vessel):
    """The forward static solve (jaxsync.steady_state: springs and dead loads assembled by
    scikit-fem on the unloaded mesh) is the reference."""
    _newton_with_supports_inflates_back(vessel, "P1")


# the default run checks the fixed point against Newton in
# test_fixed_point_unloaded_vessel_inflates_back_and_agrees_with_newton, and Newton with the supports and dead
# loads in test_newton_unloads_a_vessel_on_supports_under_dead_loads_and_inflates_back
@pytest.mark.slow
def test_fixed_point_on_supports_under_dead_loads_agrees_with_newton(vessel):
    problem, found = _newton_with_supports_inflates_back(vessel, "P1")
    fixed_point = jaxsync.zero_pressure_geometry(problem, method="fixed-point", tol=1e-10)
    assert np.abs(fixed_point.points - found.points).max() <= 1e-8 * DIAMETER


@pytest.mark.slow
def test_newton_unloads_a_curved_quadratic_vessel_on_supports_and_inflates_back(vessel):
    _newton_with_supports_inflates_back(vessel, "P2")


def _supported_tube(mu, nu=0.4, element="P1"):
    a, b, h = 0.2, 0.3, 0.05
    law = jaxsync.NeoHookean(E=2.0 * mu * (1.0 + nu), nu=nu)
    problem = _plane_strain_tube(_annulus(a, b, h, 2, 4), law, 2.0e5, h, element)
    return problem.replace(supports=(jaxsync.ElasticSupport(1.0e6, surface="outer", normal_only=True),),
                           loads=problem.loads + (jaxsync.Traction((0.0, 0.0, 0.0), surface="outer"),
                                                  jaxsync.BodyForce((3.0e4, 1.0e4, 0.0), time=jaxsync.Constant())))


def test_krylov_updates_with_supports_give_the_direct_solution():
    problem = _supported_tube(1.0e6)
    direct = jaxsync.zero_pressure_geometry(problem, tol=1e-12)
    krylov = jaxsync.zero_pressure_geometry(problem, tol=1e-12, linear_solver="krylov")
    assert np.abs(krylov.points - direct.points).max() <= 1e-10 * 0.3


def test_gradient_of_the_unloaded_geometry_on_supports_matches_finite_differences():
    """The adjoint of the converged solve carries the supports' and dead loads' tangent."""
    import jax

    weights = np.sin(np.arange(3 * _supported_tube(1.0e6).n_nodes)).reshape(-1, 3)

    def scalar(mu):
        return jax.numpy.sum(weights * jaxsync.zero_pressure_points(_supported_tube(mu), tol=1e-13))

    mu = 1.0e6
    gradient = float(jax.grad(scalar)(mu))
    step = 1e-4 * mu
    difference = (float(scalar(mu + step)) - float(scalar(mu - step))) / (2 * step)
    assert abs(gradient) > 0
    np.testing.assert_allclose(gradient, difference, rtol=1e-6)


def _tube_law(mu, nu=0.4):
    return jaxsync.NeoHookean(E=2.0 * mu * (1.0 + nu), nu=nu)


def _central_difference(f, x, relative=1e-4):
    step = relative * x
    return (float(f(x + step)) - float(f(x - step))) / (2 * step)


def test_prestressed_response_is_differentiable_in_the_shear_modulus():
    """jax.grad of the zero-pressure route's prestressed response to a pressure increment
    (prestress by the Newton solve's adjoint, the increment by static_displacement's)
    against central finite differences."""
    import jax

    a, b, h = 0.2, 0.3, 0.05
    mesh = _annulus(a, b, h, 2, 4)
    weights = np.sin(np.arange(3 * mesh.n_nodes)).reshape(-1, 3)

    def response(mu):
        imaged = _plane_strain_tube(mesh, _tube_law(mu), 2.0e5, h)
        law = jaxsync.prestress(imaged, tol=1e-13).material
        increment = _plane_strain_tube(mesh, law, 2.2e5, h)
        return jax.numpy.sum(weights * jaxsync.static_displacement(increment, load_steps=1, tol=1e-12))

    gradient = float(jax.grad(response)(1.0e6))
    assert abs(gradient) > 0
    np.testing.assert_allclose(gradient, _central_difference(response, 1.0e6), rtol=1e-6)


def test_mulf_prestrain_is_differentiable_in_the_shear_modulus():
    """jax.grad back through the MULF iterations (each static solve by its adjoint) against
    central finite differences of a weighted sum of the prestrain."""
    import jax

    a, b, h = 0.2, 0.3, 0.05
    mesh = _annulus(a, b, h, 2, 4)
    weights = np.cos(np.arange(9 * mesh.n_elements)).reshape(-1, 1, 3, 3)

    def prestrain(mu):
        result = jaxsync.prestress(_plane_strain_tube(mesh, _tube_law(mu), 2.0e5, h), method="mulf", tol=1e-13)
        return jax.numpy.sum(weights * result.material.prestrain)

    gradient = float(jax.grad(prestrain)(1.0e6))
    assert abs(gradient) > 0
    np.testing.assert_allclose(gradient, _central_difference(prestrain, 1.0e6), rtol=1e-6)


@pytest.mark.parametrize("start", ["unloaded", "prestressed"])
def test_cli_simulate_starts_from_the_zero_pressure_table(tmp_path, vessel, start):
    """jaxsync simulate with a [zero_pressure] table runs from the unloaded geometry, or from
    the imaged one with its prestress, as the Python API computes them; a prestressed wall
    held at the imaging pressure stays where it was imaged."""
    from jaxsync.app.config import load_config, problem_from_config
    from jaxsync.cli import main
    from jaxsync.mesh import write_mesh

    write_mesh(vessel, tmp_path / "imaged.vtu")
    cfg = _config(tmp_path, "imaged.vtu")
    # the run holds the imaging pressure (magnitude PRESSURE, constant)
    cfg.write_text(cfg.read_text().replace("magnitude = 1.0", f"magnitude = {PRESSURE}")
                   .replace("[zero_pressure]\n", f'[zero_pressure]\nstart = "{start}"\n'))
    out = tmp_path / "run.h5"
    assert main(["simulate", str(cfg), "--steps", "20", "--save-every", "10", "-o", str(out)]) == 0
    run = jaxsync.Trajectory.load(out)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", jaxsync.LockingWarning)
        imaged, _ = problem_from_config(load_config(cfg))
    if start == "unloaded":
        geometry = jaxsync.zero_pressure_geometry(imaged, tol=1e-11)
        expected = geometry.problem(imaged)
        np.testing.assert_allclose(run.mesh.points, geometry.mesh.points, rtol=0, atol=1e-13 * DIAMETER)
        assert np.abs(run.mesh.points - vessel.points).max() > 1e-3 * DIAMETER
    else:
        result = jaxsync.prestress(imaged, tol=1e-11)
        expected = imaged.replace(material=result.material, density_scale=result.density_scale)
        np.testing.assert_array_equal(run.mesh.points, vessel.points)
    reference = np.asarray(jaxsync.simulate(expected, 20, save=10).displacement)
    scale = np.abs(reference).max() if start == "unloaded" else DIAMETER
    np.testing.assert_allclose(run.displacement, reference, rtol=0, atol=1e-10 * scale)
    if start == "prestressed":  # in equilibrium at the imaging pressure: it stays at rest
        assert np.abs(run.displacement).max() <= 1e-9 * DIAMETER
    else:
        assert np.abs(reference[-1]).max() > 1e-4 * DIAMETER


def _fibre_tube():
    """(mesh, the HGO law with helical fibres, the imaged tube at 1e5 barye)."""
    a, b, h = 0.2, 0.3, 0.05
    mesh = _annulus(a, b, h, 2, 4)
    fibres = jaxsync.helical_fibres(mesh.points[mesh.tets].mean(axis=1), axis=(0.0, 0.0, 1.0), angle=40.0)
    law = jaxsync.HolzapfelGasserOgden(mu=3.0e5, k1=2.0e5, k2=0.8, kappa_bulk=3.0e6, fibres=fibres)
    return mesh, law, _plane_strain_tube(mesh, law, 1.0e5, h)


def test_prestressed_fibre_law_is_in_equilibrium_and_responds_as_the_unloaded_geometry():
    """Prestressed wraps HolzapfelGasserOgden (its fibres those of the stress-free state):
    both routes put the imaged tube in equilibrium at round-off, and the zero-pressure
    route's response to a pressure increment is the unloaded geometry's (forward statics)."""
    b, h = 0.3, 0.05
    mesh, law, imaged = _fibre_tube()
    fibres = law.fibres
    zero_pressure = jaxsync.prestress(imaged, tol=1e-12)
    mulf = jaxsync.prestress(imaged, method="mulf", tol=1e-13)
    assert zero_pressure.residual <= 1e-11 and mulf.residual <= 1e-11
    from jaxsync.solve import out_of_balance

    assert out_of_balance(imaged) > 0.1
    assert np.array_equal(zero_pressure.material.fibres, fibres)
    loaded = _plane_strain_tube(mesh, law, 1.05e5, h)
    unloaded = jaxsync.zero_pressure_geometry(imaged, tol=1e-12)
    expected = unloaded.points + np.asarray(jaxsync.steady_state(unloaded.problem(loaded), tol=1e-12)) - mesh.points
    u = np.asarray(jaxsync.steady_state(loaded.replace(material=zero_pressure.material), load_steps=1, tol=1e-12))
    assert np.abs(expected).max() > 1e-4 * b
    assert np.abs(u - expected).max() <= 1e-6 * np.abs(expected).max()


@pytest.mark.slow
def test_prestressed_fibre_law_runs_alike_on_one_device_and_two_parts():
    _, law, imaged = _fibre_tube()
    result = jaxsync.prestress(imaged, tol=1e-12)
    loaded = _plane_strain_tube(imaged.mesh, law, 1.05e5, 0.05)
    run = loaded.replace(material=result.material, density_scale=result.density_scale)
    one = np.asarray(jaxsync.simulate(run, 40, save=20).displacement)
    two = np.asarray(jaxsync.simulate(run, 40, save=20, partitions=2).displacement)
    assert np.abs(one[-1]).max() > 0
    np.testing.assert_allclose(two, one, rtol=0, atol=1e-12 * np.abs(one).max())
