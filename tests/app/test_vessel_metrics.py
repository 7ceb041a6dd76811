"""Vessel metrics (jaxsync.vessel_metrics) and the vessel section of ``jaxsync report``:
lumen volume and diameter against exact geometry, the loop integral against a polygon's
closed-form area, distensibility against the Lame thick-walled cylinder and jaxsync's
own static solution, the dissipated energy against the damping's energy balance, and
stresses against uniaxial closed forms (linear and neo-Hookean)."""

import dataclasses
import itertools
import json
import os
from importlib import resources

import numpy as np
import pytest
from scipy.optimize import brentq

import jaxsync
from jaxsync import vessel_metrics as vm
from jaxsync.app.config import load_config, problem_from_config
from jaxsync.app.vessel_report import vessel_section
from jaxsync.cli import main
from jaxsync.errors import MeshError, ProblemError
from jaxsync.fem import function_space
from jaxsync.fem.forces import facet_nodes
from jaxsync.mesh.simvascular import write_folder

E, NU, A, B = 1.0e6, 0.3, 0.2, 0.25  # wall modulus [dyn/cm^2], Poisson ratio, lumen and outer radius [cm]
PERIOD, P_LOW, P_HIGH, DAMPING = 0.06, 1.0e4, 2.0e4, 2000.0
MMHG_BARYE = 1333.22387415  # 133.322387415 Pa, the conventional mmHg


def tube_mesh(a=A, b=B, length=0.32, n_r=2, n_theta=16, n_z=4):
    """A structured thick-walled tube along z: (r, theta, z) cells split into 6 tetrahedra
    each (Kuhn), facet sets lumen, outer, inlet (z = 0), outlet (z = length)."""
    r, th, z = np.linspace(a, b, n_r + 1), 2 * np.pi * np.arange(n_theta) / n_theta, np.linspace(0, length, n_z + 1)
    R, T, Z = np.meshgrid(r, th, z, indexing="ij")
    points = np.stack([R * np.cos(T), R * np.sin(T), Z], -1).reshape(-1, 3)

    def node(i, j, k):
        return (i * n_theta + j % n_theta) * (n_z + 1) + k

    tets = []
    for i, j, k in itertools.product(range(n_r), range(n_theta), range(n_z)):
        for perm in itertools.permutations(range(3)):
            corner, corners = [0, 0, 0], [(0, 0, 0)]
            for axis in perm:
                corner[axis] += 1
                corners.append(tuple(corner))
            tets.append([node(i + c[0], j + c[1], k + c[2]) for c in corners])
    tets = np.array(tets)
    x = points[tets]
    flip = np.einsum("ei,ei->e", x[:, 1] - x[:, 0], np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 0])) < 0
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    faces = np.concatenate([tets[:, [0, 1, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 3]], tets[:, [1, 2, 3]]])
    key, count = np.unique(np.sort(faces, 1), axis=0, return_counts=True)
    boundary = key[count == 1]
    ring = np.repeat(np.arange(n_r + 1), n_theta * (n_z + 1))[boundary]
    level = np.tile(np.arange(n_z + 1), (n_r + 1) * n_theta)[boundary]
    sets = {"lumen": boundary[(ring == 0).all(1)], "outer": boundary[(ring == n_r).all(1)],
            "inlet": boundary[(level == 0).all(1)], "outlet": boundary[(level == n_z).all(1)]}
    return jaxsync.Mesh(points, tets, sets)


def lumen(mesh):
    return facet_nodes(function_space(mesh, "P1"), "lumen")[0]


def lame_distensibility(p_min):
    """Plane strain Lame cylinder: u(a) = k a p, k = (1 + nu)((1 - 2 nu) a^2 + b^2) / (E (b^2 - a^2));
    the lumen polygon's diameter scales as its vertices' radius, so (D_max - D_min) / (D_min dp)
    = k / (1 + k p_min). Thin-wall limit: k -> a (1 - nu^2) / (E h), Laplace's dD/D = p D / (2 h E')."""
    k = (1 + NU) * ((1 - 2 * NU) * A ** 2 + B ** 2) / (E * (B ** 2 - A ** 2))
    return k / (1 + k * p_min)


def supports():
    """Plane strain with the rigid motions removed: u_z = 0 at both ends, symmetry planes x = 0, y = 0."""
    return (jaxsync.Dirichlet(lambda x: np.abs(x[:, 0]) < 1e-9, components=(0,)),
            jaxsync.Dirichlet(lambda x: np.abs(x[:, 1]) < 1e-9, components=(1,)),
            jaxsync.Dirichlet("inlet", components=(2,)), jaxsync.Dirichlet("outlet", components=(2,)))


def static_diameter(mesh, p):
    problem = jaxsync.Problem(mesh=mesh, material=jaxsync.LinearElastic(E=E, nu=NU), dirichlet=supports(),
                              loads=(jaxsync.Pressure(p, surface="lumen"),))
    return vm.lumen_geometry(mesh.points + jaxsync.steady_state(problem), lumen(mesh))[2]


# ------------------------------------------------------------------ geometry, exact


def test_tube_volume_area_and_diameter_are_exact_and_scale_exactly():
    n, length = 16, 0.32
    mesh = tube_mesh(n_theta=n, length=length)
    tri = lumen(mesh)
    loops = vm.boundary_loops(tri)
    assert len(loops) == 2 and sorted(len(e) for e in loops) == [n, n]  # the two open ends
    V, area, D = vm.lumen_geometry(mesh.points, tri)
    # the lumen is a prism over a regular n-gon of circumradius A
    np.testing.assert_allclose(V, n * A ** 2 * np.sin(2 * np.pi / n) / 2 * length, rtol=1e-13)
    np.testing.assert_allclose(area, n * 2 * A * np.sin(np.pi / n) * length, rtol=1e-13)
    np.testing.assert_allclose(D, 2 * A * np.cos(np.pi / n), rtol=1e-13)
    s = 1.137
    radial = mesh.points * [s, s, 1.0]
    isotropic = mesh.points * s
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    moved = mesh.points @ (q * np.sign(np.linalg.det(q))).T + [0.3, -1.0, 2.0]  # rotation + translation
    V2, A2, D2 = vm.lumen_geometry(np.stack([radial, isotropic, moved]), tri)
    np.testing.assert_allclose(V2, [s ** 2 * V, s ** 3 * V, V], rtol=1e-12)
    np.testing.assert_allclose(A2, [s * area, s ** 2 * area, area], rtol=1e-12)
    np.testing.assert_allclose(D2, [s * D, s * D, D], rtol=1e-12)


def test_a_bifurcation_is_closed_at_its_three_ends():
    mesh = jaxsync.vessel_mesh(length=3.0, size=0.1, branch=True)  # lumen radius 0.175 cm
    tri = vm.lumen_triangles(mesh)
    assert len(vm.boundary_loops(tri)) == 3  # inlet and two outlets
    _, _, D = vm.lumen_geometry(mesh.points, tri)
    assert D == pytest.approx(0.35, rel=0.02)  # flat facets on the circle: slightly below 2 r


def test_closed_surface_needs_no_cap_and_linearized_volume_is_first_order():
    box = jaxsync.box_beam(2.0, 1.5, 0.5, divisions=(2, 2, 1))
    space = function_space(box, "P1")
    surface = np.concatenate([facet_nodes(space, name)[0] for name in ("x0", "x1", "y0", "y1", "z0", "z1")])
    assert vm.boundary_loops(surface) == []
    np.testing.assert_allclose(vm.enclosed_volume(box.points, surface), 2.0 * 1.5 * 0.5, rtol=1e-13)
    # u = eps X: the exact volume is (1 + eps)^3 V; to first order (1 + 3 eps) V, whatever the side of the normal
    eps = 1e-3
    np.testing.assert_allclose(vm.enclosed_volume(box.points * (1 + eps), surface), (1 + eps) ** 3 * 1.5, rtol=1e-12)
    for oriented in (surface, surface[:, ::-1]):
        np.testing.assert_allclose(vm.linearized_volume(box.points, oriented, eps * box.points),
                                   (1 + 3 * eps) * 1.5, rtol=1e-12)


def test_loop_work_is_the_polygon_area_of_an_elliptic_loop():
    a, b, v0, p0 = 0.3, 2.0e3, 4.0, 1.5e4
    for n in (7, 64):
        theta = 2 * np.pi * np.arange(n) / n
        volume, pressure = v0 + a * np.cos(theta), p0 - b * np.sin(theta)  # clockwise in (V, p): dissipative
        inscribed = n / 2 * np.sin(2 * np.pi / n) * a * b  # the affine image of a regular n-gon in a circle
        np.testing.assert_allclose(vm.loop_work(pressure, volume), inscribed, rtol=1e-13)
        np.testing.assert_allclose(vm.loop_work(pressure[::-1], volume[::-1]), -inscribed, rtol=1e-13)
    np.testing.assert_allclose(vm.loop_work(pressure, volume), np.pi * a * b, rtol=2e-3)  # n = 64
    with pytest.raises(ProblemError, match="equal length"):
        vm.loop_work(pressure, volume[:-1])


def test_bad_input_is_named():
    mesh = tube_mesh()
    problem = jaxsync.Problem(mesh=mesh, material=jaxsync.LinearElastic(E=E, nu=NU), dirichlet=supports(),
                              loads=(jaxsync.Pressure(2.0, jaxsync.Ramp(0.5), surface="lumen"),))
    surface, p = vm.lumen_pressure(problem, [0.0, 0.25, 1.0])
    assert surface == "lumen" and p.tolist() == [0.0, 1.0, 2.0]
    with pytest.raises(vm.NotAVessel, match="'outer'.*\\['lumen'\\]"):
        vm.lumen_pressure(problem, [0.0], surface="outer")
    with pytest.raises(MeshError, match="no facet set named 'nope'"):
        vm.lumen_triangles(mesh, "nope")
    with pytest.raises(ProblemError, match="does not fit 2 snapshots"):
        vm.pressure_diameter_loop(problem, np.zeros((3, mesh.n_nodes, 3)), [0.0, 1.0])


def test_metrics_of_a_synthetic_loop_and_the_last_cycle():
    period, t = 0.5, np.linspace(0.0, 1.25, 126)
    assert vm.pulse_period(jaxsync.Ramp(0.2) * jaxsync.Periodic([0.0, 0.25], [1.0, 2.0], period)) == period
    assert vm.pulse_period(jaxsync.StepOff(1.0, jaxsync.Periodic([0.0, 0.25], [1.0, 2.0], 0.3))) == 0.3
    assert vm.pulse_period(jaxsync.Ramp(0.2)) is None
    cycle = vm.last_cycle(t, period)
    np.testing.assert_array_equal(cycle, np.arange(75, 126))  # t = 0.75 .. 1.25
    assert vm.last_cycle(t, 2.0) is None and vm.last_cycle(t, None) is None
    phase = 2 * np.pi * t / period
    p = 1.0e5 + 2.0e4 * np.sin(phase)
    d = 0.4 * (1 + 0.05 * np.sin(phase - 0.3))  # lags the pressure: a dissipative loop
    v = np.pi / 4 * d ** 2 * 3.0
    loop = vm.PressureDiameterLoop("lumen", t, p, v, np.ones_like(t), d, v, period, cycle)
    m = vm.vessel_metrics(loop)
    assert m.full_cycle and (m.t_start, m.t_end) == (t[75], t[-1])
    pc, dc, vc = p[cycle], d[cycle], v[cycle]
    np.testing.assert_allclose(m.distensibility, (dc.max() - dc.min()) / (dc.min() * (pc.max() - pc.min())))
    np.testing.assert_allclose(m.volume_compliance, np.ptp(vc) / np.ptp(pc))
    np.testing.assert_allclose(m.hysteresis, vm.loop_work(pc, vc))
    assert m.hysteresis > 0
    assert m.to_dict()["distensibility_per_mmHg"] == pytest.approx(m.distensibility * MMHG_BARYE)


# ------------------------------------------------------------------ stress and strain


def homogeneous(mesh, F, times=(1.0,)):
    """(T, n, 3) displacements (F_t - I) X of the deformation gradients F_t = I + t (F - I)."""
    return np.stack([mesh.points @ (np.eye(3) + s * (np.asarray(F) - np.eye(3))).T - mesh.points for s in times])


def test_linear_uniaxial_stress_is_E_times_strain():
    box = jaxsync.box_beam(1.0, 1.0, 1.0, divisions=(1, 1, 1))
    e = 2e-3
    sigma = vm.cauchy_stress(jaxsync.LinearElastic(E=E, nu=NU), box, homogeneous(box, np.diag([1 + e, 1 - NU * e,
                                                                                           1 - NU * e]))[0])
    np.testing.assert_allclose(sigma, np.broadcast_to(np.diag([E * e, 0.0, 0.0]), sigma.shape), atol=1e-9 * E * e)
    mises, principal, strain = vm.element_peaks(jaxsync.LinearElastic(E=E, nu=NU), box,
                                                homogeneous(box, np.diag([1 + e, 1 - NU * e, 1 - NU * e])))
    np.testing.assert_allclose(mises, E * e, rtol=1e-10)
    np.testing.assert_allclose(principal, E * e, rtol=1e-10)
    np.testing.assert_allclose(strain, e + e * e / 2, rtol=1e-10)


def test_neo_hookean_uniaxial_stress_against_the_closed_form():
    law = jaxsync.NeoHookean(E=E, nu=NU)
    mu, lam = E / (2 * (1 + NU)), E * NU / ((1 + NU) * (1 - 2 * NU))

    def cauchy(l1, l2):  # sigma = mu / J (b - I) + lam ln J / J I, b = diag(l1^2, l2^2, l2^2)
        J = l1 * l2 * l2
        return mu / J * (np.array([l1, l2, l2]) ** 2 - 1) + lam * np.log(J) / J

    l1 = 1.25
    l2 = brentq(lambda x: cauchy(l1, x)[1], 0.5, 1.0)  # free lateral faces: uniaxial stress
    box = jaxsync.box_beam(1.0, 1.0, 1.0, divisions=(1, 1, 1))
    sigma = vm.cauchy_stress(law, box, homogeneous(box, np.diag([l1, l2, l2])))
    s11 = cauchy(l1, l2)[0]
    np.testing.assert_allclose(sigma, np.broadcast_to(np.diag([s11, 0.0, 0.0]), sigma.shape), atol=1e-9 * s11)
    mises, principal, strain = vm.element_peaks(law, box, homogeneous(box, np.diag([l1, l2, l2])))
    np.testing.assert_allclose([mises.min(), mises.max(), principal.max()], s11, rtol=1e-10)
    np.testing.assert_allclose(strain, (l1 ** 2 - 1) / 2, rtol=1e-12)
    # quadratic elements: the same homogeneous field at their 4 quadrature points
    p2 = function_space(box, "P2")
    u = p2.points @ (np.diag([l1, l2, l2]) - np.eye(3)).T
    sigma2 = vm.cauchy_stress(law, p2, u)
    assert sigma2.shape == (1, box.n_elements, 4, 3, 3)
    np.testing.assert_allclose(sigma2, np.broadcast_to(np.diag([s11, 0.0, 0.0]), sigma2.shape), atol=1e-9 * s11)


def test_holzapfel_gasser_ogden_stress_with_its_fibres_against_the_closed_form():
    mu, k1, k2, bulk, beta = 3.0e4, 2.3632e4, 0.8393, 3.0e6, np.radians(29.0)
    box = jaxsync.box_beam(1.0, 1.0, 1.0, divisions=(1, 1, 1))
    families = np.array([[np.cos(beta), np.sin(beta), 0.0], [np.cos(beta), -np.sin(beta), 0.0]])
    law = jaxsync.HolzapfelGasserOgden(mu=mu, k1=k1, k2=k2, kappa_bulk=bulk,
                                       fibres=np.broadcast_to(families, (box.n_elements, 2, 3)))
    F = np.diag([1.2, 0.93, 0.95])
    J, b = np.linalg.det(F), F @ F.T
    # sigma = mu J^(-5/3) dev b + K/2 (J - 1/J) I + sum_i 2 k1 E_i exp(k2 E_i^2) (F a_i)(F a_i)^T / J, E_i = I4_i - 1
    expected = mu * J ** (-5 / 3) * (b - np.trace(b) / 3 * np.eye(3)) + 0.5 * bulk * (J - 1 / J) * np.eye(3)
    for a in families:
        fa = F @ a
        strain = fa @ fa - 1.0
        assert strain > 0  # both families in tension
        expected += 2 * k1 * strain * np.exp(k2 * strain ** 2) * np.outer(fa, fa) / J
    sigma = vm.cauchy_stress(law, box, homogeneous(box, F))
    np.testing.assert_allclose(sigma, np.broadcast_to(expected, sigma.shape), rtol=1e-11, atol=1e-9 * mu)
    with pytest.raises(ProblemError, match=f"do not fit the {box.n_elements} elements"):
        vm.cauchy_stress(law, box, homogeneous(box, F), fibres=families)


def test_peaks_by_region_where_and_when():
    length = 2.0
    box = jaxsync.box_beam(length, 1.0, 1.0, divisions=(2, 1, 1))
    x = box.points[:, 0]
    ea, eb = 1e-3, 3e-3  # u_x piecewise linear in x: strain ea in the left half, eb in the right
    ux = np.where(x <= 1.0, ea * x, ea + eb * (x - 1.0))
    base = np.zeros(box.points.shape)
    base[:, 0] = ux
    factors = np.array([0.0, 1.0, 0.5])
    d = factors[:, None, None] * base
    times = np.array([0.0, 0.1, 0.2])
    centroids = box.points[box.tets].mean(axis=1)
    left = np.flatnonzero(centroids[:, 0] < 1.0)
    regions = {"left": left, "right": np.flatnonzero(centroids[:, 0] > 1.0)}
    law = jaxsync.LinearElastic(E=E, nu=NU)
    mu, lam = E / (2 * (1 + NU)), E * NU / ((1 + NU) * (1 - 2 * NU))
    peaks = vm.region_peaks(vm.element_peaks(law, box, d), times, box, regions)
    for name, eps in (("left", ea), ("right", eb)):
        r = peaks[name]
        assert r.n_elements == len(regions[name])
        np.testing.assert_allclose(r.von_mises.value, 2 * mu * eps, rtol=1e-10)  # s = 2 mu dev(eps e1 e1)
        np.testing.assert_allclose(r.max_principal_stress.value, (lam + 2 * mu) * eps, rtol=1e-10)
        np.testing.assert_allclose(r.max_principal_strain.value, eps + eps ** 2 / 2, rtol=1e-10)
        assert r.von_mises.snapshot == 1 and r.von_mises.time == 0.1
        assert r.von_mises.element in regions[name]
        np.testing.assert_allclose(r.von_mises.location, centroids[r.von_mises.element])
        np.testing.assert_allclose(r.history, 2 * mu * eps * factors, rtol=1e-10, atol=1e-12)
    # the regions of the facet sets: the elements with three vertices on x = 0
    by_facets = vm.region_peaks(vm.element_peaks(law, box, d), times, box)
    assert by_facets["wall"].n_elements == box.n_elements
    on_x0 = np.flatnonzero((np.abs(box.points[box.tets][..., 0]) < 1e-12).sum(axis=1) == 3)
    assert by_facets["x0"].n_elements == on_x0.size
    assert by_facets["x0"].von_mises.element in on_x0
    assert by_facets["wall"].von_mises.value == pytest.approx(2 * mu * eb)
    with pytest.raises(ProblemError, match="region 'bad'"):
        vm.region_peaks(vm.element_peaks(law, box, d), times, box, {"bad": [box.n_elements]})


# ------------------------------------------------------------------ a vessel run and the report


@pytest.fixture(scope="module")
def vessel_run(tmp_path_factory):
    """A short tube in plane strain under a slow pulse (period 0.06 s, 50 times the wall's
    radial period ~1.2 ms; heavily damped): quasi-static. Three periods, the first ramped."""
    folder = tmp_path_factory.mktemp("vessel")
    write_folder(tube_mesh(), folder / "tube")
    samples = np.linspace(0.0, PERIOD, 25, endpoint=False)
    values = 0.5 * (P_LOW + P_HIGH) - 0.5 * (P_HIGH - P_LOW) * np.cos(2 * np.pi * samples / PERIOD)
    toml = folder / "vessel.toml"
    toml.write_text(f"""
[mesh]
file = "tube"
[material]
E = {E}
nu = {NU}
rho = 1.0
[problem]
kind = "general"
damping = {DAMPING}
[[dirichlet]]
plane = {{ axis = 0, value = 0.0 }}
components = [0]
[[dirichlet]]
plane = {{ axis = 1, value = 0.0 }}
components = [1]
[[dirichlet]]
facet = "inlet"
components = [2]
[[dirichlet]]
facet = "outlet"
components = [2]
[[pressure]]
surface = "lumen"
t_ramp = {PERIOD}
period = {PERIOD}
times = {[float(v) for v in samples]}
values = {[float(v) for v in values]}
""")
    problem, _ = problem_from_config(load_config(toml))
    n_steps = int(3 * PERIOD / problem.dt) // 50 * 50
    trajectory = jaxsync.simulate(problem, n_steps, save=50, partitions=2)  # parts: a report can compare it
    trajectory.save(folder / "vessel.h5")
    return toml, folder / "vessel.h5", problem, trajectory, (samples, values)


def test_distensibility_matches_static_solutions_and_the_lame_cylinder(vessel_run):
    _, _, problem, trajectory, _ = vessel_run
    loop = vm.pressure_diameter_loop(problem, trajectory.displacement, trajectory.times)
    m = vm.vessel_metrics(loop)
    assert m.full_cycle and m.t_end == pytest.approx(3 * PERIOD, abs=problem.dt * 50)
    # jaxsync's static solution at the cycle's two extreme pressures (a direct solve, no dynamics):
    # quasi-static to the damping's phase lag, alpha omega_p / omega_0^2 ~ 1e-3
    d_low, d_high = (static_diameter(problem.mesh, p) for p in (m.p_min, m.p_max))
    static = (d_high - d_low) / (d_low * (m.p_max - m.p_min))
    assert m.distensibility == pytest.approx(static, rel=5e-3)
    assert m.d_min == pytest.approx(d_low, rel=1e-4) and m.d_max == pytest.approx(d_high, rel=1e-4)
    # P1 against the Lame cylinder: second order in h. The static distensibility of this mesh (2 layers,
    # 16 sides) is 3.7 % stiff; refined twice (4 layers, 32 sides) 0.95 %: the ratio ~4 of O(h^2)
    lame = lame_distensibility(m.p_min)
    coarse_error = abs(static / lame - 1)
    fine = tube_mesh(n_r=4, n_theta=32)
    fine_error = abs((static_diameter(fine, P_HIGH) / static_diameter(fine, P_LOW) - 1)
                     / (P_HIGH - P_LOW) / lame_distensibility(P_LOW) - 1)
    assert coarse_error < 0.05 and fine_error < 0.015 and 3.0 < coarse_error / fine_error < 5.0
    assert m.distensibility == pytest.approx(lame, rel=0.05)


def damping_energy(problem, trajectory, cycle):
    """The integral of alpha v^T M v dt over the snapshots ``cycle`` [erg]: lumped M, v by
    central differences of the snapshots, trapezoids."""
    mesh, t, d = problem.mesh, np.asarray(trajectory.times), np.asarray(trajectory.displacement)
    x = mesh.points[mesh.tets]
    volumes = np.abs(np.einsum("ei,ei->e", x[:, 1] - x[:, 0], np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]))) / 6
    mass = np.zeros(mesh.n_nodes)
    np.add.at(mass, mesh.tets.ravel(), np.repeat(volumes / 4, 4))
    v = np.gradient(d, t, axis=0)
    power = DAMPING * np.einsum("tni,n,tni->t", v, mass, v)
    return np.sum(0.5 * (power[cycle][1:] + power[cycle][:-1]) * np.diff(t[cycle]))


def test_hysteresis_is_the_energy_the_damping_dissipates(vessel_run):
    _, _, problem, trajectory, _ = vessel_run
    loop = vm.pressure_diameter_loop(problem, trajectory.displacement, trajectory.times)
    m = vm.vessel_metrics(loop)
    # energy balance over a periodic cycle: the pressure's work = integral of alpha v^T M v dt (lumped M)
    dissipated = damping_energy(problem, trajectory, loop.cycle)
    assert m.hysteresis == pytest.approx(dissipated, rel=0.01)  # sampled every 50 steps: 0.2 % measured
    # the dead load's work is p dV_lin; the exact enclosed volume's loop differs at O(strain) (6.5 % here)
    c = loop.cycle
    exact = vm.loop_work(loop.pressure[c], loop.volume[c])
    assert abs(exact / m.hysteresis - 1) > 0.01


def pulse_problem(material, follower):
    samples = np.linspace(0.0, PERIOD, 25, endpoint=False)
    values = 0.5 * (P_LOW + P_HIGH) - 0.5 * (P_HIGH - P_LOW) * np.cos(2 * np.pi * samples / PERIOD)
    pressure = jaxsync.Pressure(1.0, jaxsync.Ramp(PERIOD) * jaxsync.Periodic(samples, values, PERIOD),
                                surface="lumen", follower=follower)
    return jaxsync.Problem(mesh=tube_mesh(), material=material, dirichlet=supports(), loads=(pressure,),
                           damping=DAMPING)


def test_the_work_volume_follows_the_load():
    law = jaxsync.NeoHookean(E=E, nu=NU)
    mesh = tube_mesh()
    d = np.stack([s * mesh.points * [1.0, 1.0, 0.0] for s in (0.0, 0.05, 0.1)])  # radial growth
    follower = vm.pressure_diameter_loop(pulse_problem(law, True), d, [0.0, 0.01, 0.02])
    dead = vm.pressure_diameter_loop(pulse_problem(law, False), d, [0.0, 0.01, 0.02])
    np.testing.assert_array_equal(follower.work_volume, follower.volume)
    np.testing.assert_allclose(dead.work_volume, vm.linearized_volume(mesh.points, lumen(mesh), d))
    np.testing.assert_allclose(dead.work_volume / dead.volume[0], [1.0, 1.1, 1.2])  # first order in s
    np.testing.assert_allclose(dead.volume / dead.volume[0], [1.0, 1.05 ** 2, 1.1 ** 2])
    assert follower.period == PERIOD and follower.cycle is None  # shorter than a period


@pytest.mark.slow  # a hyperelastic run of 10 000 steps: ~30 s on 2 cores
def test_hysteresis_of_a_follower_pressure_is_the_damping_energy():
    problem = pulse_problem(jaxsync.NeoHookean(E=E, nu=NU), True)
    trajectory = jaxsync.simulate(problem, int(2 * PERIOD / problem.dt) // 50 * 50, save=50)
    loop = vm.pressure_diameter_loop(problem, trajectory.displacement, trajectory.times)
    m = vm.vessel_metrics(loop)
    assert m.hysteresis == pytest.approx(damping_energy(problem, trajectory, loop.cycle), rel=0.01)  # 0.16 %


def test_report_writes_the_vessel_section(vessel_run, tmp_path, capsys):
    toml, h5, problem, trajectory, (samples, values) = vessel_run
    out = tmp_path / "report"
    assert main(["report", str(h5), "--config", str(toml), "-o", str(out)]) == 0
    for name in ("pressure_diameter.png", "wall_stress.png"):
        assert (out / name).stat().st_size > 10_000
    entry = json.loads((out / "summary.json").read_text())["vessel"]
    assert not entry["skipped"] and entry["surface"] == "lumen" and entry["material"] == "LinearElastic"
    loop = entry["loop"]
    t = np.asarray(loop["times"])
    np.testing.assert_allclose(t, trajectory.times)
    # the pressure: the ramp times the periodic samples, linearly interpolated (numpy, not jaxsync)
    expected = np.minimum(t / PERIOD, 1.0) * np.interp(np.mod(t, PERIOD), np.append(samples, PERIOD),
                                                       np.append(values, values[0]))
    np.testing.assert_allclose(loop["pressure"], expected, rtol=1e-12)
    assert loop["diameter"][0] == pytest.approx(2 * A * np.cos(np.pi / 16), rel=1e-13)  # the polygon's 2 x apothem
    metrics = entry["metrics"]
    cycle = slice(loop["cycle"][0], loop["cycle"][1] + 1)
    assert t[cycle][-1] - t[cycle][0] == pytest.approx(PERIOD, abs=50 * problem.dt)
    assert metrics["p_min"] == pytest.approx(np.min(expected[cycle])) and metrics["p_max"] == pytest.approx(
        np.max(expected[cycle]))
    assert metrics["distensibility"] == pytest.approx(lame_distensibility(metrics["p_min"]), rel=0.05)
    assert metrics["distensibility_per_mmHg"] == pytest.approx(metrics["distensibility"] * MMHG_BARYE)
    assert metrics["hysteresis"] > 0
    peaks = entry["peaks"]
    assert set(peaks) == {"wall", "lumen", "outer", "inlet", "outlet"}
    # the Lame cylinder's von Mises stress falls with the radius: the peak is on the lumen side, at the
    # pressure's peak, and equals Lame's at the element's centroid radius (P1: one constant stress per
    # element; 0.5 % measured)
    wall = peaks["wall"]["von_mises"]
    assert peaks["lumen"]["von_mises"]["value"] == wall["value"] > peaks["outer"]["von_mises"]["value"]
    p_peak = expected[wall["snapshot"]]
    assert p_peak > 0.97 * P_HIGH
    r = np.hypot(*wall["location"][:2])
    c = p_peak * A ** 2 / (B ** 2 - A ** 2)
    s_rr, s_tt = c * (1 - B ** 2 / r ** 2), c * (1 + B ** 2 / r ** 2)
    s_zz = NU * (s_rr + s_tt)  # plane strain
    lame_mises = np.sqrt(0.5 * ((s_rr - s_tt) ** 2 + (s_tt - s_zz) ** 2 + (s_zz - s_rr) ** 2))
    assert wall["value"] == pytest.approx(lame_mises, rel=0.03)
    printed = capsys.readouterr().out
    assert "distensibility" in printed and "peak von Mises" in printed
    # the figures: titled, units on every axis, a legend; the loop drawn is the entry's, in mm and mmHg
    again, drawn = vessel_section(problem, trajectory)
    assert set(drawn) == {"pressure_diameter.png", "wall_stress.png"}
    for name, fig in drawn.items():
        fig.canvas.draw()
        assert fig.get_suptitle() or all(ax.get_title() for ax in fig.axes), name
        assert all("[" in ax.get_xlabel() and "[" in ax.get_ylabel() for ax in fig.axes), name
        assert any(ax.get_legend() for ax in fig.axes), name
    bold = drawn["pressure_diameter.png"].axes[0].lines[1]
    np.testing.assert_allclose(bold.get_xdata(), 10 * np.asarray(loop["diameter"])[cycle])
    np.testing.assert_allclose(bold.get_ydata(), np.asarray(loop["pressure"])[cycle] / MMHG_BARYE)
    assert again["metrics"] == pytest.approx(metrics)


def test_the_comparison_report_holds_the_reference_vessel_section(vessel_run, tmp_path, capsys):
    toml, h5, _, trajectory, _ = vessel_run
    # an "online" run that stayed synchronized throughout: the comparison has no predicted snapshot
    online = dataclasses.replace(trajectory, synchronized=np.ones(trajectory.n_saved, bool), parts=tuple(
        dataclasses.replace(p, predicted_shared_displacement=np.zeros((0, 3 * p.n_shared))) for p in trajectory.parts))
    online.save(tmp_path / "online.h5")
    assert main(["report", str(h5), str(tmp_path / "online.h5"), "--config", str(toml), "-o", str(tmp_path / "r")]) == 0
    assert main(["report", str(h5), "--config", str(toml), "-o", str(tmp_path / "alone")]) == 0
    both = json.loads((tmp_path / "r" / "summary.json").read_text())
    alone = json.loads((tmp_path / "alone" / "summary.json").read_text())
    assert both["n_predicted"] == 0 and both["vessel"] == alone["vessel"]
    assert {"pressure_diameter.png", "wall_stress.png", "l2_error.png"} <= set(os.listdir(tmp_path / "r"))
    assert "vessel (lumen 'lumen')" in capsys.readouterr().out


def test_a_problem_without_pressure_is_skipped_with_a_note(tmp_path, capsys):
    problem = jaxsync.cantilever()
    trajectory = jaxsync.simulate(problem, 20, save=10)
    with pytest.raises(vm.NotAVessel, match="no pressure load"):
        vm.lumen_pressure(problem, trajectory.times)
    entry, made = vessel_section(problem, trajectory)
    assert entry["skipped"] and "no pressure load" in entry["note"] and made == {}
    h5 = tmp_path / "cantilever.h5"
    trajectory.save(h5)
    config = resources.files("jaxsync") / "data" / "cantilever.toml"
    out = tmp_path / "report"
    assert main(["report", str(h5), "--config", str(config), "-o", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["vessel"]["skipped"] and "no pressure load" in summary["vessel"]["note"]
    assert sorted(os.listdir(out)) == ["summary.json"]
    assert "note: no vessel section" in capsys.readouterr().out
    # one trajectory and no problem: refused, nothing written
    assert main(["report", str(h5), "-o", str(tmp_path / "none")]) != 0
    assert "--config" in capsys.readouterr().err
    assert main(["report", str(h5), "--config", str(config), "--node", "3", "-o", str(tmp_path / "none")]) != 0
    assert "--node and --train-until-step" in capsys.readouterr().err
    assert not (tmp_path / "none").exists()


def test_report_of_a_simulate_trajectory_needs_no_config(vessel_run, tmp_path, capsys):
    """jaxsync simulate records its configuration in the trajectory, so jaxsync report
    writes the vessel section from the trajectory alone: the same as with --config; an
    older trajectory (without the record) still reports with --config."""
    toml, _, _, trajectory, _ = vessel_run
    h5 = tmp_path / "run.h5"
    n_steps = (trajectory.n_saved - 1) * trajectory.save_every
    assert main(["simulate", str(toml), "--steps", str(n_steps), "--save-every", str(trajectory.save_every),
                 "-o", str(h5)]) == 0
    run = jaxsync.Trajectory.load(h5)
    assert json.loads(run.parameters["config"]) == load_config(toml)
    assert main(["report", str(h5), "-o", str(tmp_path / "alone")]) == 0
    assert main(["report", str(h5), "--config", str(toml), "-o", str(tmp_path / "given")]) == 0
    alone = json.loads((tmp_path / "alone" / "summary.json").read_text())["vessel"]
    given = json.loads((tmp_path / "given" / "summary.json").read_text())["vessel"]
    assert not alone["skipped"] and alone == given
    assert (tmp_path / "alone" / "pressure_diameter.png").stat().st_size > 10_000
    old = dataclasses.replace(run, parameters={k: v for k, v in run.parameters.items() if k != "config"})
    old.save(tmp_path / "old.h5")
    capsys.readouterr()
    assert main(["report", str(tmp_path / "old.h5"), "-o", str(tmp_path / "none")]) != 0
    assert "--config" in capsys.readouterr().err and not (tmp_path / "none").exists()
    assert main(["report", str(tmp_path / "old.h5"), "--config", str(toml), "-o", str(tmp_path / "again")]) == 0
    assert json.loads((tmp_path / "again" / "summary.json").read_text())["vessel"] == given
