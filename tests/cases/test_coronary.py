"""The coronary problem (jaxsync.cases.coronary): the pulsatile waveform, the problem's
material, clamps and load, its TOML description, mass scaling, and a static lumen-pressure
solve against the thick-walled cylinder (Lame)."""

import warnings
from importlib import resources

import numpy as np
import pytest

import jaxsync
from jaxsync.app.config import load_config, problem_from_config
from jaxsync.cases import DEFAULT_WAVEFORM, MMHG, coronary, coronary_waveform
from jaxsync.errors import MeshError, ProblemError
from jaxsync.fem import max_stable_dt

PERIOD, T_RAMP = 0.833, 1.0
E, NU = 6.26e6, 0.4


@pytest.fixture(scope="module")
def vessel():
    """A small straight vessel with the facet sets inlet, outlet, lumen, outer."""
    return jaxsync.vessel_mesh(length=0.6, radius=0.175, wall=0.05, size=0.05)


def samples_after_ramp(times, period, t_ramp, cycles=(0, 1, 3)):
    """Times k period + t_i that are past the ramp, for some cycles after it."""
    first = int(np.ceil(t_ramp / period))
    return [(first + k) * period + np.asarray(times) for k in cycles]


# --- the waveform -------------------------------------------------------------------

def test_default_waveform_spans_80_to_120_mmhg():
    times, values = DEFAULT_WAVEFORM
    assert min(values) == 1.067e5 and max(values) == 1.6e5   # the paper's numbers
    assert min(values) == pytest.approx(80 * MMHG, rel=1e-3)
    assert max(values) == pytest.approx(120 * MMHG, rel=1e-3)
    assert times[0] == 0.0 and np.all(np.diff(times) > 0) and times[-1] < PERIOD


def test_waveform_reproduces_samples_and_is_periodic():
    times, values = DEFAULT_WAVEFORM
    g = coronary_waveform()
    for t in samples_after_ramp(times, PERIOD, T_RAMP):
        np.testing.assert_allclose(np.asarray(g(t)), values, rtol=1e-12)
    t = np.linspace(T_RAMP, T_RAMP + 3 * PERIOD, 201)
    np.testing.assert_allclose(np.asarray(g(t + PERIOD)), np.asarray(g(t)), rtol=1e-10)
    wave = np.asarray(g(t))
    assert wave.min() >= 1.067e5 - 1e-6 and wave.max() <= 1.6e5 + 1e-6


def test_ramp_multiplies_the_waveform():
    times, values = DEFAULT_WAVEFORM
    g = coronary_waveform()
    t = np.linspace(0.0, T_RAMP, 57)
    periodic = np.interp(np.mod(t, PERIOD), [*times, PERIOD], [*values, values[0]])
    np.testing.assert_allclose(np.asarray(g(t)), t / T_RAMP * periodic, rtol=1e-12, atol=1e-9)
    assert float(g(0.0)) == 0.0
    assert float(g(0.5 * PERIOD)) == pytest.approx(0.5 * PERIOD * float(g(1.5 * PERIOD + PERIOD)))


def test_user_samples_period_and_ramp():
    times, values = [0.0, 0.2, 0.5], [2.0, 5.0, 3.0]
    g = coronary_waveform((times, values), period=0.6, t_ramp=0.25)
    for t in samples_after_ramp(times, 0.6, 0.25):
        np.testing.assert_allclose(np.asarray(g(t)), values, rtol=1e-12)
    assert float(g(1.2 + 0.55)) == pytest.approx(2.5)   # back to the first sample at the period
    assert float(g(0.1)) == pytest.approx(0.1 / 0.25 * 3.5)


@pytest.mark.parametrize("samples, kwargs, match", [
    (([0.0, 0.3, 0.2], [1.0, 2.0, 3.0]), {}, "increasing"),
    (([0.0, 0.3, 0.5], [1.0, 2.0]), {}, "same length"),
    (([0.0, 0.5, 0.9], [1.0, 2.0, 3.0]), {}, r"\[0, period"),
    (([0.0, 0.3], [1.0, 2.0]), {"period": 0.0}, "period must be positive"),
    (([0.0, 0.3], [1.0, 2.0]), {"period": -1.0}, "period must be positive"),
    (([0.0, 0.3], [1.0, 2.0]), {"t_ramp": 0.0}, "t_ramp .* must be positive, got 0.0 s"),
    ([1.0, 2.0, 3.0], {}, "pair"),
    (3, {}, "pair"),
])
def test_bad_samples_are_refused(samples, kwargs, match):
    with pytest.raises(ProblemError, match=match):
        coronary_waveform(samples, **kwargs)


# --- the problem --------------------------------------------------------------------

def test_coronary_problem_definition(vessel):
    problem = coronary(vessel)
    m = problem.material
    assert (m.E, m.nu, m.rho) == (E, NU, 1.0) and problem.damping == 0.5
    clamped = np.union1d(vessel.facet_nodes("inlet"), vessel.facet_nodes("outlet"))
    dofs, values = problem.dirichlet_dofs()
    np.testing.assert_array_equal(dofs, np.sort((3 * clamped[:, None] + np.arange(3)).ravel()))
    assert not np.any(values)
    (load,) = problem.loads
    assert isinstance(load, jaxsync.Pressure) and load.surface == "lumen" and load.magnitude == 1.0
    t = np.linspace(0.0, 4.0, 97)
    np.testing.assert_allclose(np.asarray(load.time(t)), np.asarray(coronary_waveform()(t)))
    assert problem.initial_displacement is None and problem.density_scale is None


def test_coronary_options(vessel):
    material = jaxsync.LinearElastic(1.0e6, 0.3, 1.1)
    samples = ([0.0, 0.4], [1.0e5, 1.5e5])
    problem = coronary(vessel, waveform=samples, period=0.8, t_ramp=0.5, material=material,
                       damping=0.0, outlets=["outlet"])
    assert problem.material is material and problem.damping == 0.0
    np.testing.assert_allclose(np.asarray(problem.loads[0].time(np.array([0.2, 2.0, 2.2]))),
                               [0.4 * 1.25e5, 1.5e5, 1.25e5])
    g = jaxsync.Constant()
    assert coronary(vessel, waveform=g).loads[0].time is g


def test_coronary_pressure_inflates_the_wall(vessel):
    """The lumen pressure pushes the wall outwards (static response to 1 barye)."""
    u = np.asarray(jaxsync.steady_state(coronary(vessel)))
    x = vessel.points
    mid = np.flatnonzero(np.abs(x[:, 2] - 0.3) < 0.1)
    u_r = np.sum(u[mid, :2] * x[mid, :2], axis=1) / np.hypot(x[mid, 0], x[mid, 1])
    assert np.all(u_r > 0)


def test_missing_facet_sets_are_named(vessel):
    with pytest.raises(MeshError, match=r"lacks the facet set\(s\) outlet_3, outlet_4 .*"
                                        r"coronary_mesh writes inlet, outlet_1"):
        coronary(vessel, outlets=["outlet", "outlet_3", "outlet_4"])
    bare = jaxsync.Mesh(vessel.points, vessel.tets, {"outer": vessel.facet_sets["outer"]})
    with pytest.raises(MeshError, match="inlet, outlet, lumen"):
        coronary(bare)
    with pytest.raises(ProblemError, match="outlets"):
        coronary(vessel, outlets=[])


def test_default_mesh_comes_from_the_coronary_tree(vessel, monkeypatch):
    """mesh=None calls jaxsync.cases.coronary_mesh() with its defaults (stubbed here)."""
    import jaxsync.cases as cases

    calls = []
    monkeypatch.setattr(cases, "coronary_mesh", lambda *args, **kwargs: calls.append((args, kwargs)) or vessel)
    assert coronary().mesh is vessel and calls == [((), {})]


# --- mass scaling and the TOML configuration -------------------------------------------

def test_mass_scaling_to_a_larger_step(vessel):
    problem = coronary(vessel)
    target = 2.5 * problem.dt
    scaled, added_percent = jaxsync.mass_scaling(problem, dt_target=target, warn_above_percent=None)
    assert scaled.dt == pytest.approx(target)
    assert added_percent > 0
    total = float(np.sum(scaled.lumped_mass())) / float(np.sum(problem.lumped_mass()))
    assert 100 * (total - 1) == pytest.approx(added_percent)
    assert max_stable_dt(scaled, tol=1e-8) >= target


def test_packaged_toml_is_the_coronary_problem(vessel, tmp_path):
    path = resources.files("jaxsync") / "data" / "coronary.toml"
    msh = tmp_path / "tube.msh"
    jaxsync.vessel_mesh(msh, length=0.6, radius=0.175, wall=0.05, size=0.05)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", jaxsync.MassScalingWarning)
        from_toml, run = problem_from_config(load_config(str(path)), mesh_file=str(msh))
    reference = coronary(jaxsync.read_mesh(str(msh)))
    assert from_toml.material == reference.material and from_toml.damping == reference.damping
    for got, want in zip(from_toml.dirichlet_dofs(), reference.dirichlet_dofs()):
        np.testing.assert_array_equal(got, want)
    (load,), (want,) = from_toml.loads, reference.loads
    assert (load.surface, load.magnitude) == (want.surface, want.magnitude)
    t = np.linspace(0.0, 4.0, 301)
    np.testing.assert_allclose(np.asarray(load.time(t)), np.asarray(want.time(t)), rtol=1e-14)
    scaled, percent = jaxsync.mass_scaling(reference, dt_target=5e-6, warn_above_percent=None)
    assert run.mass_scaling_dt == 5e-6 and run.added_mass_percent == pytest.approx(percent)
    np.testing.assert_allclose(from_toml.density_scale, scaled.density_scale)


def test_stiffness_damping_of_the_coronary_problem_from_python_and_toml(vessel, tmp_path):
    """beta reaches the problem from coronary(...) and from the TOML file alike, and lowers
    the exact stable step to (2 / omega) (sqrt(1 + xi^2) - xi), xi = beta omega / 2."""
    beta = 5.0e-7
    undamped = coronary(vessel, damping=0.0)
    damped = coronary(vessel, damping=0.0, stiffness_damping=beta)
    assert damped.stiffness_damping == beta and undamped.stiffness_damping == 0.0
    omega = 2.0 / max_stable_dt(undamped, tol=1e-10)
    xi = beta * omega / 2
    assert xi > 0.05  # the damping matters to the step
    from jaxsync.fem import stable_step

    assert stable_step(damped).exact == pytest.approx(2.0 / omega * (np.sqrt(1 + xi * xi) - xi), rel=1e-7)
    with pytest.raises(ProblemError, match="stiffness_damping"):
        coronary(vessel, stiffness_damping=-1.0)
    msh = tmp_path / "tube.msh"
    jaxsync.vessel_mesh(msh, length=0.6, radius=0.175, wall=0.05, size=0.05)
    config = load_config(str(resources.files("jaxsync") / "data" / "coronary.toml"))
    config["run"].pop("mass_scaling_dt")
    config["problem"]["stiffness_damping"] = beta
    from_toml, _ = problem_from_config(config, mesh_file=str(msh))
    reference = coronary(jaxsync.read_mesh(str(msh)), stiffness_damping=beta)
    assert from_toml.stiffness_damping == reference.stiffness_damping == beta


def test_packaged_toml_generates_the_coronary_tree(tmp_path):
    """Without --mesh the packaged file meshes the generated tree: the facet sets the
    problem needs, about the element count it asks for, the same mesh as the generator."""
    path = resources.files("jaxsync") / "data" / "coronary.toml"
    config = load_config(str(path))
    config["run"].pop("mass_scaling_dt")  # the mesh is what is tested here
    problem, _ = problem_from_config(config)
    generated = jaxsync.coronary_mesh(target_elements=config["mesh"]["target_elements"])
    np.testing.assert_array_equal(problem.mesh.tets, generated.tets)
    for name in ("inlet", "outlet", "lumen", "outer", *(f"outlet_{k}" for k in range(1, 7))):
        assert len(problem.mesh.facet_sets[name]) > 0, name
    config["mesh"]["generate"] = "sphere"
    with pytest.raises(jaxsync.ConfigError, match="coronary_tree"):
        problem_from_config(config)

# --- thick-walled cylinder (Lame) -----------------------------------------------------

def lame_radial(r, p, a, b):
    """Plane-strain radial displacement [cm] of a cylinder (radii a < b) under internal
    pressure p: (1 + nu) p a^2 / (E (b^2 - a^2)) ((1 - 2 nu) r + b^2 / r)."""
    return (1 + NU) * p * a**2 / (E * (b**2 - a**2)) * ((1 - 2 * NU) * r + b**2 / r)


def lame_errors(size, *, a=0.175, wall=0.05, length=0.6, p=1.0e5):
    """Relative errors of u_r against Lame at the mid-length lumen and outer nodes of a
    straight tube whose ends slide radially (u_z = 0 there: plane strain everywhere)."""
    b = a + wall
    mesh = jaxsync.vessel_mesh(length=length, radius=a, wall=wall, size=size)
    x, inlet = mesh.points, mesh.facet_nodes("inlet")

    def pin(target):  # the inlet node nearest to target: rigid-body motion in the x-y plane
        node = x[inlet[np.argmin(np.linalg.norm(x[inlet] - target, axis=1))]]
        return lambda points: np.all(points == node, axis=1)

    dirichlet = [jaxsync.Dirichlet("inlet", components=(2,)),
                 jaxsync.Dirichlet("outlet", components=(2,)),
                 jaxsync.Dirichlet(pin([b, 0.0, 0.0]), components=(1,)),
                 jaxsync.Dirichlet(pin([-b, 0.0, 0.0]), components=(1,)),
                 jaxsync.Dirichlet(pin([0.0, b, 0.0]), components=(0,))]
    problem = jaxsync.Problem(mesh, jaxsync.LinearElastic(E, NU, 1.0), dirichlet=dirichlet,
                              loads=[jaxsync.Pressure(p, surface="lumen")])
    u = np.asarray(jaxsync.steady_state(problem))
    mid = np.flatnonzero(np.abs(x[:, 2] - length / 2) < 0.25 * length)
    errors = {}
    for name in ("lumen", "outer"):
        nodes = np.intersect1d(mesh.facet_nodes(name), mid)
        r = np.hypot(x[nodes, 0], x[nodes, 1])
        u_r = np.sum(u[nodes, :2] * x[nodes, :2], axis=1) / r
        errors[name] = u_r / lame_radial(r, p, a, b) - 1.0
    return errors


def test_lumen_pressure_matches_lame_and_converges():
    """Linear tetrahedra are too stiff: on the coarse mesh (one element across the wall,
    size 0.05 cm) u_r is about 9 % low on average, on the refined one (size 0.025 cm)
    about 2.5 % low, the error falling about like h^2."""
    coarse, fine = lame_errors(0.05), lame_errors(0.025)
    for name in ("lumen", "outer"):
        assert abs(np.mean(coarse[name])) < 0.12, name
        assert abs(np.mean(fine[name])) < 0.04, name
        assert np.abs(fine[name]).max() < 0.12, name
        assert abs(np.mean(fine[name])) < 0.5 * abs(np.mean(coarse[name])), name
