"""Hyperelastic laws and the total-Lagrangian internal force (:mod:`jaxsync.fem.materials`,
:mod:`jaxsync.fem.forces`), checked against independent ground truth: the linear
solver's K u in the small-strain limit, closed-form stresses of homogeneous deformations
written out here, rigid motions, felupe's assembled force and static solution, the energy
budget of an undamped run, closed-form wave speeds, and finite differences."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsync
from jaxsync.errors import MaterialError, ProblemError, StabilityError
from jaxsync.fem import SolverState, advance, build_system, initial_state
from jaxsync.fem.forces import (
    ElementRecompute,
    HyperelasticForce,
    Preassembled,
    TotalLagrangian,
    check_stable_dt,
    element_wave_speeds,
    exact_stable_dt,
    force_model,
    inverted_elements,
    stable_dt,
    strain_energy,
)
from jaxsync.fem.materials import (
    HolzapfelGasserOgden,
    NearlyIncompressibleNeoHookean,
    NeoHookean,
    helical_fibres,
)

E, NU, RHO = 1.0e6, 0.3, 1.0
MU, LAM = E / (2 * (1 + NU)), E * NU / ((1 + NU) * (1 - 2 * NU))
BULK = LAM + 2 * MU / 3
HGO = dict(mu=3.0e5, k1=2.0e5, k2=0.8, kappa_bulk=1.0e6, rho=1.0)


@pytest.fixture(scope="module")
def beam():
    """A 4 x 1 x 1 cm beam, 4 x 1 x 1 cubes (small: every test here stays fast)."""
    return jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1))


@pytest.fixture(scope="module")
def cube():
    """A 2 x 1 x 1 cm block, 2 x 1 x 1 cubes, for homogeneous deformations."""
    return jaxsync.box_beam(2.0, 1.0, 1.0, (2, 1, 1))


def _centroids(mesh):
    return mesh.points[mesh.tets].mean(axis=1)


def _axial_fibres(mesh):
    """Both families along x (the closed-form uniaxial cases)."""
    return np.tile(np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]), (mesh.n_elements, 1, 1))


def _laws(mesh, fibres="helical"):
    a = helical_fibres(_centroids(mesh), axis=(1.0, 0.0, 0.0), angle=35.0, origin=(0.0, 0.5, 0.5)) \
        if fibres == "helical" else _axial_fibres(mesh)
    return {"neo-hookean": NeoHookean(E, NU, RHO), "nearly-incompressible": NearlyIncompressibleNeoHookean(E, NU, RHO),
            "hgo": HolzapfelGasserOgden(**HGO, fibres=a)}


def _problem(mesh, material, element="P1", **kw):
    return jaxsync.cantilever(mesh, material=material, element=element, **kw)


def _smooth_field(X):
    """A smooth nonlinear displacement shape (n, 3) on points X [cm]."""
    x, y, z = X[:, 0], X[:, 1], X[:, 2]
    return np.stack([0.08 * np.sin(0.7 * x) * (z - 0.3) + 0.03 * y * z, 0.05 * np.cos(x + y) - 0.04 * x * z,
                     0.03 * x**2 / 4 + 0.06 * np.sin(y + 2 * z)], axis=1)


def _rotation(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


# --- closed-form stresses (numpy, written out independently of the package) ---------------

def _cauchy_neo_hookean(F):
    """sigma = mu/J (b - I) + lam ln J / J I."""
    J = np.linalg.det(F)
    return MU / J * (F @ F.T - np.eye(3)) + LAM * np.log(J) / J * np.eye(3)


def _cauchy_nearly_incompressible(F):
    """sigma = mu J^-5/3 (b - I1/3 I) + K/2 (J - 1/J) I."""
    J, b = np.linalg.det(F), F @ F.T
    return MU * J ** (-5 / 3) * (b - np.trace(b) / 3 * np.eye(3)) + BULK / 2 * (J - 1 / J) * np.eye(3)


def _piola_hgo_uniaxial(stretch, lateral, k1, dispersion=0.0):
    """P of F = diag(stretch, lateral, lateral), both fibre families along x: the ground
    matrix plus, in tension only, 2 x 2 k1 E exp(k2 E^2) (kappa F + (1 - 3 kappa) F e1 e1)."""
    F = np.diag([stretch, lateral, lateral])
    J = stretch * lateral**2
    i1 = stretch**2 + 2 * lateral**2
    mu, K, k2 = HGO["mu"], HGO["kappa_bulk"], HGO["k2"]
    P = mu * J ** (-2 / 3) * (F - i1 / 3 * np.linalg.inv(F).T) + K / 2 * (J**2 - 1) * np.linalg.inv(F).T
    if stretch**2 >= 1:
        strain = dispersion * (i1 - 3) + (1 - 3 * dispersion) * (stretch**2 - 1)
        dyad = np.zeros((3, 3))
        dyad[0, 0] = stretch
        P = P + 2 * 2 * k1 * strain * np.exp(k2 * strain**2) * (dispersion * F + (1 - 3 * dispersion) * dyad)
    return P


def _piola(material, F, fibres=None):
    return np.asarray(material.first_piola(jnp.asarray(F), None if fibres is None else jnp.asarray(fibres)))


# op.matvec(u) and op.energy(u) each as one compiled program (op by op, a hyperelastic
# force compiles dozens of small programs)
_matvec = jax.jit(lambda op, u: op.matvec(u))
_energy = jax.jit(lambda op, u: op.energy(u))


# --- the laws ---------------------------------------------------------------------------

@pytest.mark.parametrize("law", ["neo-hookean", "nearly-incompressible", "hgo"])
def test_first_piola_is_the_gradient_of_the_energy(beam, law):
    material = _laws(beam)[law]
    rng = np.random.default_rng(1)
    F = np.eye(3) + 0.25 * rng.standard_normal((50, 3, 3))
    F = F[np.linalg.det(F) > 0.2]
    a = helical_fibres(rng.standard_normal((len(F), 3)), angle=30.0)
    fibres = jnp.asarray(a) if law == "hgo" else None
    P = _piola(material, F, fibres)
    auto = np.asarray(jax.grad(lambda G: jnp.sum(material.energy(G, fibres)))(jnp.asarray(F)))
    np.testing.assert_allclose(P, auto, rtol=1e-10, atol=1e-9 * np.abs(P).max())
    if law == "hgo":  # some families in tension, some in compression: both branches checked
        i4 = np.einsum("nij,nfj->nfi", F, a)
        assert (np.sum(i4**2, axis=-1) > 1).any() and (np.sum(i4**2, axis=-1) < 1).any()


@pytest.mark.parametrize("law, cauchy", [("neo-hookean", _cauchy_neo_hookean),
                                         ("nearly-incompressible", _cauchy_nearly_incompressible)])
def test_homogeneous_stretch_and_shear_give_the_closed_form_stresses(beam, law, cauchy):
    material = _laws(beam)[law]
    for F in (np.diag([1.3, 0.9, 0.95]), np.diag([0.7, 1.1, 1.05]), np.eye(3) + 0.4 * np.outer([1, 0, 0], [0, 1, 0])):
        P = _piola(material, F[None])[0]
        J = np.linalg.det(F)
        np.testing.assert_allclose(P @ F.T / J, cauchy(F), rtol=1e-12, atol=1e-9 * MU)
        np.testing.assert_allclose(float(material.energy(jnp.asarray(F))),
                                   _energy_closed_form(law, F), rtol=1e-12, atol=1e-9 * MU)
    gamma = 0.4  # simple shear: sigma_12 = mu gamma for both laws (J = 1)
    F = np.eye(3) + gamma * np.outer([1, 0, 0], [0, 1, 0])
    sigma = _piola(material, F[None])[0] @ F.T
    assert sigma[0, 1] == pytest.approx(MU * gamma, rel=1e-12)


def _energy_closed_form(law, F):
    J, i1 = np.linalg.det(F), np.sum(F * F)
    if law == "neo-hookean":
        return MU / 2 * (i1 - 3) - MU * np.log(J) + LAM / 2 * np.log(J) ** 2
    return MU / 2 * (J ** (-2 / 3) * i1 - 3) + BULK / 4 * (J**2 - 1 - 2 * np.log(J))


@pytest.mark.parametrize("dispersion", [0.0, 0.1])
def test_hgo_uniaxial_closed_form_fibres_only_in_tension(cube, dispersion):
    material = HolzapfelGasserOgden(**HGO, dispersion=dispersion)
    soft = HolzapfelGasserOgden(**{**HGO, "k1": 0.0}, dispersion=dispersion)
    a = jnp.asarray(_axial_fibres(cube)[:1])
    for stretch, lateral in ((1.25, 0.93), (1.05, 0.99), (0.8, 1.08), (0.95, 1.02)):
        F = np.diag([stretch, lateral, lateral])
        P = _piola(material, F[None], a)[0]
        np.testing.assert_allclose(P, _piola_hgo_uniaxial(stretch, lateral, HGO["k1"], dispersion),
                                   rtol=1e-12, atol=1e-9 * HGO["mu"])
        if stretch < 1:  # compressed fibres carry nothing: the ground matrix alone
            np.testing.assert_allclose(P, _piola(soft, F[None], a)[0], rtol=1e-14, atol=1e-9)
        else:
            assert P[0, 0] > _piola(soft, F[None], a)[0][0, 0] + 1e-3 * HGO["k1"] * (stretch - 1)


def test_material_parameters_are_checked():
    with pytest.raises(MaterialError, match="Poisson"):
        NeoHookean(E, 0.5, RHO)
    with pytest.raises(MaterialError, match="positive"):
        NearlyIncompressibleNeoHookean(-1.0, 0.3, RHO)
    with pytest.raises(MaterialError, match="k1"):
        HolzapfelGasserOgden(**{**HGO, "k1": -1.0})
    with pytest.raises(MaterialError, match="dispersion"):
        HolzapfelGasserOgden(**HGO, dispersion=0.5)
    with pytest.raises(MaterialError, match="unit"):
        HolzapfelGasserOgden(**HGO, fibres=np.ones((3, 2, 3)))
    with pytest.raises(MaterialError, match="fibre directions"):
        HolzapfelGasserOgden(**HGO).first_piola(jnp.eye(3)[None])
    # the small-strain constants: HGO's ground matrix
    m = HolzapfelGasserOgden(**HGO)
    assert float(m.lam) + 2 * float(m.mu) / 3 == pytest.approx(HGO["kappa_bulk"])
    assert float(m.E) / (2 * (1 + float(m.nu))) == pytest.approx(HGO["mu"])


def test_helical_fibres_wind_at_the_angle_around_the_axis():
    centres = np.array([[0.0, 2.0, 0.3], [-1.5, 0.0, 4.0], [0.0, 0.0, 1.0]])  # the last on the axis
    a = helical_fibres(centres, axis=(0.0, 0.0, 2.0), angle=30.0)
    np.testing.assert_allclose(np.linalg.norm(a, axis=-1), 1.0, rtol=1e-14)
    np.testing.assert_allclose(a[:, 0, 2], np.sin(np.pi / 6), rtol=1e-14)  # towards the axis by 30 degrees
    np.testing.assert_allclose(a[:, 1, 2], -np.sin(np.pi / 6), rtol=1e-14)
    radial = centres[:2] * [1, 1, 0] / np.linalg.norm(centres[:2] * [1, 1, 0], axis=1, keepdims=True)
    np.testing.assert_allclose(np.einsum("nfi,ni->nf", a[:2], radial), 0.0, atol=1e-14)  # no radial part
    np.testing.assert_allclose(a[0, 0], [-np.cos(np.pi / 6), 0.0, np.sin(np.pi / 6)], atol=1e-14)  # e_z x e_y


# --- the internal force -----------------------------------------------------------------

@pytest.mark.parametrize("element", ["P1", "P2"])
@pytest.mark.parametrize("law", ["neo-hookean", "nearly-incompressible", "hgo"])
def test_small_strain_limit_is_the_linear_stiffness(beam, element, law):
    """|f_int(eps v) - K eps v| = O(eps^2), K the linear solver's pre-assembled stiffness
    of the law's small-strain E, nu (HGO: the fibres kept in compression)."""
    material = _laws(beam, fibres="axial")[law]
    problem = _problem(beam, material, element)
    linear = _problem(beam, jaxsync.LinearElastic(float(material.E), float(material.nu), RHO), element)
    op, K = TotalLagrangian().operator(problem), Preassembled().operator(linear)
    X = problem.points
    v = _smooth_field(X)
    v[:, 0] += -0.5 * X[:, 0]  # d v_x / dx < 0 everywhere: axial fibres shortened
    errors = []
    for eps in (4e-3, 2e-3, 1e-3):
        u = jnp.asarray(eps * v)
        if law == "hgo":
            F = np.asarray(op.deformation_gradient(u))
            assert np.all(F[..., 0, 0] ** 2 + F[..., 1, 0] ** 2 + F[..., 2, 0] ** 2 < 1)
        errors.append(float(jnp.abs(_matvec(op, u) - _matvec(K, u)).max()))
    order = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all((order > 1.9) & (order < 2.1)), (errors, order)
    assert errors[-1] < 1e-2 * float(jnp.abs(_matvec(K, jnp.asarray(1e-3 * v))).max())


@pytest.mark.parametrize("element", ["P1", "P2"])
def test_homogeneous_stretch_loads_only_the_end_faces(cube, element):
    """u = (F - I) X: no force at interior nodes; on the end faces the resultants +/- P_11 A,
    P from the closed-form HGO stress (fibres along x, in tension)."""
    material = HolzapfelGasserOgden(**HGO, fibres=_axial_fibres(cube))
    problem = _problem(cube, material, element)
    X = problem.points
    stretch, lateral = 1.2, 0.95
    F = np.diag([stretch, lateral, lateral])
    f = np.asarray(_matvec(TotalLagrangian().operator(problem), jnp.asarray(X @ (F - np.eye(3)).T)))
    P = _piola_hgo_uniaxial(stretch, lateral, HGO["k1"])
    right, left = np.isclose(X[:, 0], 2.0), np.isclose(X[:, 0], 0.0)
    np.testing.assert_allclose(f[right].sum(axis=0), P[:, 0] * 1.0, rtol=1e-12, atol=1e-9 * abs(P[0, 0]))
    np.testing.assert_allclose(f[left].sum(axis=0), -P[:, 0] * 1.0, rtol=1e-12, atol=1e-9 * abs(P[0, 0]))
    inside = ~np.any(np.isclose(X, [0.0, 0.0, 0.0]) | np.isclose(X, [2.0, 1.0, 1.0]), axis=1)
    assert inside.any() or element == "P1"
    assert np.abs(f[inside]).max(initial=0.0) < 1e-9 * abs(P[0, 0])
    # the lateral faces carry the lateral stress P_22 per unit area
    top = np.isclose(X[:, 2], 1.0)
    assert f[top, 2].sum() == pytest.approx(P[2, 2] * 2.0, rel=1e-12)


@pytest.mark.parametrize("element", ["P1", "P2"])
@pytest.mark.parametrize("law", ["neo-hookean", "nearly-incompressible", "hgo"])
def test_objectivity_and_rigid_motions(beam, element, law):
    material = _laws(beam)[law]
    op = TotalLagrangian().operator(_problem(beam, material, element))
    X = op.points
    u = 3.0 * _smooth_field(np.asarray(X))  # finite strain
    R = _rotation([1.0, 2.0, -0.5], 1.1)
    c = np.array([0.3, -2.0, 1.5])
    x = np.asarray(X) + u
    u_rotated = x @ R.T + c - np.asarray(X)
    energy = float(_energy(op, jnp.asarray(u)))
    f = np.asarray(_matvec(op, jnp.asarray(u)))
    assert abs(energy) > 1e-3 * MU
    assert float(_energy(op, jnp.asarray(u_rotated))) == pytest.approx(energy, rel=1e-11)
    np.testing.assert_allclose(np.asarray(_matvec(op, jnp.asarray(u_rotated))), f @ R.T, rtol=1e-9,
                               atol=1e-10 * np.abs(f).max())
    rigid = np.asarray(X) @ (R - np.eye(3)).T + c  # a finite rotation and a translation
    assert np.abs(np.asarray(_matvec(op, jnp.asarray(rigid)))).max() < 1e-10 * np.abs(f).max()
    assert abs(float(_energy(op, jnp.asarray(rigid)))) < 1e-10 * energy


@pytest.mark.parametrize("element", ["P1", "P2"])
def test_internal_force_matches_felupe(beam, element):
    """The assembled internal force of felupe's NeoHookeCompressible (same mu, lambda, same
    mesh and quadrature) for a nonlinear displacement field."""
    fem = pytest.importorskip("felupe")
    from jaxsync.fem import vtk_cells

    problem = _problem(beam, NeoHookean(E, NU, RHO), element)
    X = problem.points
    u = 3.0 * _smooth_field(X)
    f = np.asarray(_matvec(TotalLagrangian().operator(problem), jnp.asarray(u)))
    _, cells = vtk_cells(problem.space)  # felupe's tetra10 numbers its edge nodes as VTK does
    mesh = fem.Mesh(X, cells, "tetra" if element == "P1" else "tetra10")
    # felupe's own 4-point rule has its points to 7 digits (a 1e-8 difference for this field):
    # give it the rule's exact points, ((5 + 3 sqrt 5) / 20, (5 - sqrt 5) / 20 ...), weights 1/24
    a, b = (5 + 3 * np.sqrt(5)) / 20, (5 - np.sqrt(5)) / 20
    keast = fem.quadrature.Scheme(np.array([[b, b, b], [a, b, b], [b, a, b], [b, b, a]]), np.full(4, 1 / 24))
    region = fem.RegionTetra(mesh) if element == "P1" else fem.RegionQuadraticTetra(mesh, quadrature=keast)
    field = fem.FieldContainer([fem.Field(region, dim=3)])
    field[0].values[:] = u
    solid = fem.SolidBody(fem.NeoHookeCompressible(mu=MU, lmbda=LAM), field)
    reference = np.asarray(solid.assemble.vector().toarray()).reshape(-1, 3)
    assert np.abs(f - reference).max() <= 1e-8 * np.abs(reference).max()
    # the stored energy: felupe's psi at its quadrature points times its dV (felupe's psi
    # omits the constant -3 mu / 2 that makes ours zero at rest)
    psi = fem.NeoHookeCompressible(mu=MU, lmbda=LAM).function([field.extract()[0], None])[0] - 1.5 * MU
    assert float(strain_energy(problem, u)) == pytest.approx(float(np.sum(psi * region.dV)), rel=1e-10)


def test_static_uniaxial_solution_of_felupe_is_in_equilibrium(cube):
    """felupe's Newton solution of a clamped block stretched by 30 % satisfies our discrete
    equilibrium: f_int = 0 on its free dofs."""
    fem = pytest.importorskip("felupe")
    mesh = jaxsync.box_beam(2.0, 1.0, 1.0, (4, 2, 2))
    problem = _problem(mesh, NeoHookean(E, NU, RHO))
    fm = fem.Mesh(problem.points, mesh.tets, "tetra")
    field = fem.FieldContainer([fem.Field(fem.RegionTetra(fm), dim=3)])
    _, loadcase = fem.dof.uniaxial(field, clamped=True, move=0.6, right=2.0, return_loadcase=True)
    solid = fem.SolidBody(fem.NeoHookeCompressible(mu=MU, lmbda=LAM), field)
    result = fem.newtonraphson(field, items=[solid], tol=1e-12, verbose=0, **loadcase)
    u = result.x[0].values
    assert np.abs(u).max() == pytest.approx(0.6)
    f = np.asarray(_matvec(TotalLagrangian().operator(problem), jnp.asarray(u))).ravel()
    reaction = np.abs(f[loadcase["dof0"]]).max()
    assert reaction > 0.05 * MU
    assert np.abs(f[loadcase["dof1"]]).max() < 1e-10 * reaction


# the default run checks this feature for P2 (the same test) and, for P1, through the two-part runs of
# test_follower.py::test_distributed_runs_equal_the_single_device_run
@pytest.mark.parametrize("element", [pytest.param("P1", marks=pytest.mark.slow), "P2"])
def test_part_operators_sum_to_the_whole_mesh_force(beam, element):
    """Each part's force on its own elements (padded, stacked), summed at the nodes: the
    whole mesh's force."""
    from jaxsync.parallel import PartLayout

    problem = _problem(beam, _laws(beam)["hgo"], element)
    layout = PartLayout.of(jaxsync.partition(problem, 2, seed=0))
    stacked = TotalLagrangian().part_operators(problem, layout.parts, layout.n_local)
    u = 2.0 * _smooth_field(problem.points)
    forces = jax.jit(jax.vmap(lambda o, x: o.matvec(x)))(stacked, layout.split(jnp.asarray(u)))
    total = np.zeros_like(u)
    for k, part in enumerate(layout.parts):
        np.add.at(total, part.nodes, np.asarray(forces[k, :part.n_local]))
    whole = np.asarray(_matvec(TotalLagrangian().operator(problem), jnp.asarray(u)))
    np.testing.assert_allclose(total, whole, rtol=1e-12, atol=1e-12 * np.abs(whole).max())


# --- wiring ------------------------------------------------------------------------------

def test_problem_takes_hyperelastic_materials_and_every_mode_runs_them(beam):
    problem = _problem(beam, NeoHookean(E, NU, RHO))
    assert "E=" in problem.summary()
    for model in (TotalLagrangian(), force_model("total-lagrangian"), Preassembled(), ElementRecompute(),
                  force_model("preassembled"), force_model("recompute")):
        assert isinstance(model.operator(problem), HyperelasticForce)
    linear = _problem(beam, jaxsync.LinearElastic(E, NU, RHO))
    with pytest.raises(ProblemError, match="NeoHookean"):
        TotalLagrangian().operator(linear)
    with pytest.raises(ProblemError, match="material"):
        jaxsync.Problem(mesh=beam, material="rubber")
    with pytest.raises(ProblemError, match="fibre"):
        TotalLagrangian().operator(_problem(beam, HolzapfelGasserOgden(**HGO)))
    with pytest.raises(ProblemError, match="elements"):
        TotalLagrangian().operator(_problem(beam, HolzapfelGasserOgden(**HGO, fibres=_axial_fibres(beam)[:5])))
    # the linear fast path is untouched
    assert not isinstance(Preassembled().operator(linear), HyperelasticForce)
    # the element masses the stable step uses add up to the problem's lumped mass (P2: HRZ)
    for element in ("P1", "P2"):
        problem = _problem(beam, NeoHookean(E, NU, 1.7), element)
        op = TotalLagrangian().operator(problem)
        nodal = np.zeros(problem.n_nodes)
        np.add.at(nodal, np.asarray(op.cells), 1.7 * np.asarray(op.unit_mass))
        np.testing.assert_allclose(nodal, np.asarray(problem.lumped_mass()), rtol=1e-12)


def test_simulate_runs_a_hyperelastic_problem_through_the_seam(beam):
    """jaxsync.simulate with the default mode equals the stepper driven by hand with
    TotalLagrangian, and differs from the linear run at this finite load."""
    problem = _problem(beam, NeoHookean(E, NU, RHO), body_force=(0.0, 0.0, -2.0e4), t_ramp=0.002)
    dt = 0.5 * stable_dt(problem)
    trajectory = jaxsync.simulate(problem, 100, dt=dt, save=100)
    system = build_system(problem, dt, TotalLagrangian())
    state, saved = advance(system, initial_state(problem, system), 1, 100)
    np.testing.assert_allclose(np.asarray(trajectory.displacement)[-1], np.asarray(saved[-1]), rtol=1e-12,
                               atol=1e-14)
    linear = jaxsync.simulate(problem.replace(material=jaxsync.LinearElastic(E, NU, RHO)), 100, dt=dt, save=100)
    tip = np.abs(np.asarray(linear.displacement)[-1]).max()
    assert tip > 0.05  # a finite deflection of a 4 cm beam ...
    assert np.abs(np.asarray(linear.displacement)[-1] - np.asarray(saved[-1])).max() > 1e-3 * tip  # ... nonlinear


@pytest.mark.slow  # ~10 s each (compiling the shard_map program); the parts' forces: the test above
@pytest.mark.parametrize("element", ["P1", "P2"])
def test_distributed_run_equals_the_single_device_run(beam, element):
    """Two parts under shard_map (2 emulated devices), each forming its own elements' HGO
    forces, synchronized by psum: the single-device trajectory."""
    problem = _problem(beam, _laws(beam)["hgo"], element, body_force=(0.0, 0.0, -2.0e4), t_ramp=0.002)
    dt = 0.5 * stable_dt(problem, rule="element")
    one = np.asarray(jaxsync.simulate(problem, 40, dt=dt, save=40).displacement)[-1]
    two = np.asarray(jaxsync.simulate(problem, 40, dt=dt, save=40, partitions=2).displacement)[-1]
    assert np.abs(one).max() > 1e-3
    np.testing.assert_allclose(two, one, rtol=1e-12, atol=1e-12 * np.abs(one).max())


# --- dynamics and the stable step --------------------------------------------------------

def _energy_history(problem, dt, n_steps):
    """((n_steps + 1,) kinetic (central velocities, lumped mass) plus strain energy [erg],
    and the kinetic energy alone) of a run from rest at the initial displacement, started
    with the lumped mass's own acceleration (d(-1) = d0 + dt^2 / 2 a0, so that v0 = 0 exactly
    and the energy at step 0 is the strain energy: what is measured is the scheme's error)."""
    system = build_system(problem, dt, TotalLagrangian())
    op = TotalLagrangian().operator(problem)
    d0 = jnp.asarray(problem.initial_displacement)
    a0 = jnp.where(system.fixed, 0.0, -op.matvec(d0) / system.mass)
    state = SolverState(d0, d0 + 0.5 * dt * dt * a0, jnp.asarray(0, dtype=jnp.int32))
    _, saved = jax.jit(lambda s: advance(system, s, n_steps + 1, 1))(state)
    d = jnp.concatenate([state.previous[None], state.displacement[None], saved])
    v = (d[2:] - d[:-2]) / (2.0 * dt)
    kinetic = 0.5 * jnp.sum(system.mass[None] * v * v, axis=(1, 2))
    return np.asarray(kinetic + jax.vmap(op.energy)(d[1:-1])), np.asarray(kinetic)


# the default run checks this feature (a neo-Hookean P1 run, with a follower pressure's potential) in
# test_follower.py::test_undamped_run_under_follower_pressure_conserves_energy_to_second_order
@pytest.mark.slow
@pytest.mark.parametrize("element", ["P1", "P2"])
def test_undamped_run_conserves_energy_to_second_order(element):
    """Free vibration from a finite initial deformation (5 % stretch and a bend, at rest),
    clamped, undamped: the energy stays within O(dt^2) of the initial strain energy."""
    mesh = jaxsync.box_beam(10.0, 1.0, 1.0, (10, 1, 1))
    base = _problem(mesh, NeoHookean(E, NU, RHO), element, body_force=(0.0, 0.0, 0.0), damping=0.0)
    X = base.points
    u0 = np.stack([0.05 * X[:, 0], np.zeros(len(X)), 0.02 * X[:, 0] ** 2], axis=1)
    problem = base.replace(initial_displacement=u0, loads=())
    initial = float(strain_energy(problem, u0))
    dt0 = stable_dt(problem, u0)
    errors = []
    for k in (2, 4):  # the same time span, 100 steps of dt0
        history, kinetic = _energy_history(problem, dt0 / k, 50 * k)
        errors.append(np.abs(history - initial).max() / initial)
        assert kinetic.max() > 0.3 * initial  # the energy does change hands
    order = np.log2(errors[0] / errors[1])
    print(errors, order)
    assert 1.8 < order < 2.2, (errors, order)


def test_stable_step_of_the_reference_state_is_the_linear_rule(beam):
    """At u = 0: the CFL rule with c = sqrt((lam + 2 mu) / rho) (HGO: plus 8 k1 along the
    two aligned fibre families), and the exact bound of the linear solver's K."""
    h = jaxsync.fem.element_size(beam.points, beam.tets)
    problem = _problem(beam, NeoHookean(E, NU, RHO))
    assert stable_dt(problem) == pytest.approx(0.9 * h.min() / np.sqrt((LAM + 2 * MU) / RHO), rel=1e-12)
    hgo = HolzapfelGasserOgden(**HGO, fibres=_axial_fibres(beam))
    c = np.sqrt((HGO["kappa_bulk"] + 4 * HGO["mu"] / 3 + 8 * HGO["k1"]) / HGO["rho"])
    assert stable_dt(_problem(beam, hgo)) == pytest.approx(0.9 * h.min() / c, rel=1e-10)
    assert float(hgo.dilatational_wave_speed) == pytest.approx(c, rel=1e-12)
    for element in ("P1", "P2"):
        problem = _problem(beam, NeoHookean(E, NU, RHO), element)
        linear = _problem(beam, jaxsync.LinearElastic(E, NU, RHO), element)
        exact = exact_stable_dt(problem)
        assert exact == pytest.approx(jaxsync.max_stable_dt(linear), rel=1e-9)
        assert TotalLagrangian().max_stable_dt(problem) == pytest.approx(exact, rel=1e-12)
        element_rule = stable_dt(problem, rule="element", alpha_s=1.0)
        assert 0.5 * exact < element_rule <= exact  # Irons' bound: never above the exact one


@pytest.mark.parametrize("s", [0.85, 1.15])
def test_stable_step_follows_the_tangent_under_dilation(beam, s):
    """u = (s - 1) X: the spatial P-wave modulus of neo-Hookean is mu s^2 + mu + lam - 3 lam
    ln s (over rho_0), the element size s h_0; the element rule stays below the exact bound
    of the deformed state's tangent."""
    problem = _problem(beam, NeoHookean(E, NU, RHO))
    u = (s - 1.0) * problem.points
    h = jaxsync.fem.element_size(beam.points, beam.tets)
    c = np.sqrt((MU * s**2 + MU + LAM - 3 * LAM * np.log(s)) / RHO)
    np.testing.assert_allclose(element_wave_speeds(problem, u), c, rtol=1e-10)
    assert stable_dt(problem, u) == pytest.approx(0.9 * s * h.min() / c, rel=1e-10)
    exact = exact_stable_dt(problem, u)
    assert stable_dt(problem, u, rule="element", alpha_s=1.0) <= exact * (1 + 1e-12)


def test_check_stable_dt_refuses_a_step_above_the_current_bound(beam):
    problem = _problem(beam, NeoHookean(E, NU, RHO))
    compressed = -0.2 * problem.points  # 20 % smaller, stiffer
    at_rest, squeezed = stable_dt(problem, alpha_s=1.0), stable_dt(problem, compressed, alpha_s=1.0)
    assert squeezed < at_rest
    dt = 0.5 * (at_rest + squeezed)
    assert check_stable_dt(problem, np.zeros_like(compressed), dt) == pytest.approx(at_rest)
    with pytest.raises(StabilityError, match="above the stable step"):
        check_stable_dt(problem, compressed, dt)


def test_inverted_elements_are_found(beam):
    problem = _problem(beam, NeoHookean(E, NU, RHO))
    assert len(inverted_elements(problem, np.zeros((problem.n_nodes, 3)))) == 0
    u = np.zeros((problem.n_nodes, 3))
    node = int(np.flatnonzero(np.all(np.isclose(beam.points, [2.0, 1.0, 1.0]), axis=1))[0])
    u[node] = [-1.6, -1.7, -1.8]  # pushed through the block
    x = beam.points + u
    e = x[beam.tets]
    X = beam.points[beam.tets]
    ratio = np.linalg.det(e[:, 1:] - e[:, :1]) / np.linalg.det(X[:, 1:] - X[:, :1])
    expected = np.flatnonzero(ratio <= 0)
    assert len(expected) > 0
    np.testing.assert_array_equal(inverted_elements(problem, u), expected)
    with pytest.raises(StabilityError, match="inverted"):
        stable_dt(problem, u)


# --- gradients ---------------------------------------------------------------------------

@pytest.mark.parametrize("law, names", [("neo-hookean", ("E", "nu")), ("nearly-incompressible", ("E", "nu")),
                                        ("hgo", ("mu", "k1", "k2", "kappa_bulk", "dispersion"))])
def test_gradient_of_the_internal_force_wrt_parameters(beam, law, names):
    material = _laws(beam)[law]
    if law == "hgo":
        material = material.replace(dispersion=0.1)
    for element in ("P1", "P2"):
        problem = _problem(beam, material, element)
        op = TotalLagrangian().operator(problem)
        u = jnp.asarray(3.0 * _smooth_field(problem.points))
        w = jnp.asarray(np.random.default_rng(2).standard_normal(u.shape))
        base = op.material

        @jax.jit  # one program for the value and every difference (op by op they dispatch slowly)
        def scalar(params, op=op, base=base, u=u, w=w):
            return jnp.sum(w * dataclasses.replace(op, material=dataclasses.replace(base, **params)).matvec(u))

        params = {n: jnp.asarray(float(getattr(base, n))) for n in names}
        grads = jax.jit(jax.grad(scalar))(params)
        for n in names:
            step = 1e-6 * max(abs(float(params[n])), 1e-3)
            plus = float(scalar({**params, n: params[n] + step}))
            minus = float(scalar({**params, n: params[n] - step}))
            fd = (plus - minus) / (2 * step)
            assert float(grads[n]) == pytest.approx(fd, rel=1e-6, abs=1e-9 * abs(float(scalar(params))) / step), n


def test_gradient_of_a_short_explicit_run_wrt_E(beam):
    base = _problem(beam, NeoHookean(E, NU, RHO), body_force=(0.0, 0.0, -2.0e4), t_ramp=0.002)
    dt = 0.5 * stable_dt(base)
    w = jnp.asarray(np.random.default_rng(3).standard_normal((base.n_nodes, 3)))

    @jax.jit  # one program for both finite-difference runs
    def loss(young):
        problem = base.replace(material=NeoHookean(young, NU, RHO))
        system = build_system(problem, dt, TotalLagrangian())
        state, _ = advance(system, initial_state(problem, system), 1, 60)
        return jnp.sum(w * state.displacement)

    g = float(jax.jit(jax.grad(loss))(jnp.asarray(E)))
    step = 1e-4 * E
    fd = (float(loss(jnp.asarray(E + step))) - float(loss(jnp.asarray(E - step)))) / (2 * step)
    assert g == pytest.approx(fd, rel=1e-6)
    assert abs(g) > 0
