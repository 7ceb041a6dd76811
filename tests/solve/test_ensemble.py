import dataclasses
import logging

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsync
from jaxsync import ProblemError, StabilityError
from jaxsync.surrogate.training import read_shared_histories

FZ = (0.3, 0.5, 0.7)


def relative_error(a, b):
    return np.abs(np.asarray(a) - np.asarray(b)).max() / np.abs(np.asarray(b)).max()


@pytest.fixture(scope="module")
def mesh():
    return jaxsync.box_beam()


@pytest.fixture(scope="module")
def static(mesh):
    """(n_nodes, 3) static solution of the cantilever at f_z = 0.5 [cm]."""
    return jaxsync.steady_state(jaxsync.cantilever(mesh, body_force=(0, 0, -0.5)))


@pytest.fixture(scope="module")
def problems(mesh, static):
    """The cantilever at three loads; the second one starts from 1.2 times the static solution."""
    out = [jaxsync.cantilever(mesh, body_force=(0, 0, -fz)) for fz in FZ]
    out[1] = out[1].replace(initial_displacement=1.2 * static)
    return out


@pytest.fixture(scope="module")
def part(mesh):
    return jaxsync.partition(mesh, 2)


@pytest.fixture(scope="module")
def generated(problems, part):
    """3 runs of 300 steps in chunks of 100, saved every 10 steps, shared nodes every step."""
    return jaxsync.ensemble(problems, 300, partitions=part, labels=FZ, save=jaxsync.SaveAt(10, 1),
                            executor=jaxsync.HostExecutor(chunk_steps=100))


def test_ensemble_equals_separate_distributed_runs(problems, part, generated):
    assert len(generated) == len(problems)
    for problem, traj in zip(problems, generated):
        ref = jaxsync.simulate(problem, 300, partitions=part, save=jaxsync.SaveAt(10, 1))
        assert traj.displacement.shape == ref.displacement.shape == (31, problem.mesh.n_nodes, 3)
        assert relative_error(traj.displacement, ref.displacement) <= 1e-12
        np.testing.assert_array_equal(traj.times, ref.times)
        assert (traj.save_every, traj.shared_every, traj.shared_stride) == (10, 1, 1)
        assert ref.shared_every == traj.shared_every
        assert len(traj.parts) == len(ref.parts) == 2
        for mine, theirs in zip(traj.parts, ref.parts):
            np.testing.assert_array_equal(mine.shared_nodes, theirs.shared_nodes)
            np.testing.assert_array_equal(mine.elements, theirs.elements)
            assert mine.shared_displacement.shape == theirs.shared_displacement.shape == (301, 3 * mine.n_shared)
            assert relative_error(mine.shared_displacement, theirs.shared_displacement) <= 1e-12
        assert traj.stats.us_per_step > 0 and traj.stats.compile_seconds >= 0


def test_linearity_and_superposition(mesh, static):
    """Independent of simulate: the response is linear in the loads, the Dirichlet values
    and the initial displacement. Runs: f_z = 0.3 and 0.7 from rest; 0.5 from rest; 0.5
    from c u_s; no load from u_s; 0.5 with a prescribed clamp displacement g; no load with g."""
    c = -0.2
    g = (0.0, 1e-3, -2e-3)
    loaded = jaxsync.cantilever(mesh, body_force=(0, 0, -0.5))
    unloaded = jaxsync.cantilever(mesh, body_force=(0, 0, 0))
    moved_clamp = (jaxsync.Dirichlet("x0", value=g),)
    runs = [jaxsync.cantilever(mesh, body_force=(0, 0, -0.3)), jaxsync.cantilever(mesh, body_force=(0, 0, -0.7)),
            loaded, loaded.replace(initial_displacement=c * static), unloaded.replace(initial_displacement=static),
            loaded.replace(dirichlet=moved_clamp), unloaded.replace(dirichlet=moved_clamp)]
    trajs = jaxsync.ensemble(runs, 200, save=5, executor=jaxsync.HostExecutor(chunk_steps=100))
    assert not trajs[0].parts and "load_parameter" not in trajs[0].parameters  # no partitions, no labels
    d = [t.displacement for t in trajs]
    assert np.abs(d[0]).max() > 0
    assert relative_error(d[1], 0.7 / 0.3 * d[0]) <= 1e-11
    assert relative_error(d[3], d[2] + c * d[4]) <= 1e-11
    assert relative_error(d[5], d[2] + d[6]) <= 1e-11
    assert np.all(d[5][:, mesh.facet_nodes("x0")] == np.asarray(g))


def test_batch_compiles_once(problems, caplog):
    """Three runs, four chunks: one compilation of the batched stepper."""
    jax.clear_caches()  # count from a cold start, whatever ran before
    with jax.log_compiles(), caplog.at_level(logging.WARNING):
        trajs = jaxsync.ensemble(problems, 200, save=5, executor=jaxsync.HostExecutor(chunk_steps=50))
    compiled = [r for r in caplog.records if "_advance_runs" in r.getMessage() and "XLA compilation" in r.getMessage()]
    assert len(compiled) == 1
    assert len(trajs) == 3 and trajs[0].n_saved == 41


def test_labels_are_load_parameters(generated, tmp_path):
    for fz, traj in zip(FZ, generated):
        assert traj.parameters["load_parameter"] == fz
        path = tmp_path / f"run_{fz}.h5"
        traj.save(path)
        back = jaxsync.Trajectory.load(path)
        assert back.parameters["load_parameter"] == fz
        assert read_shared_histories(back).load_parameter == fz
        assert read_shared_histories(traj).load_parameter == fz


@pytest.mark.parametrize("other, what", [
    (lambda mesh: jaxsync.cantilever(jaxsync.box_beam(25.0, 1.0, 1.0, (25, 1, 2))), "mesh"),
    (lambda mesh: jaxsync.cantilever(mesh, t_off=3.0), "load time functions"),
    (lambda mesh: jaxsync.cantilever(mesh, material=jaxsync.NeoHookean(1.0e6, 0.3, 1.0)), "material law"),
    (lambda mesh: jaxsync.cantilever(mesh).replace(dirichlet=(jaxsync.Dirichlet("x0"),
                                                              jaxsync.Dirichlet("x1", components=(1,)))),
     "constrained dofs"),
    (lambda mesh: jaxsync.cantilever(mesh).replace(supports=(jaxsync.ElasticSupport(1e3, surface="z0"),)),
     "elastic supports"),
    (lambda mesh: jaxsync.cantilever(mesh).replace(density_scale=np.full(mesh.n_elements, 2.0)), "density_scale"),
])
def test_refuses_problems_of_other_systems(mesh, other, what):
    """What the runs must share; material, density and damping values may differ (below)."""
    runs = [jaxsync.cantilever(mesh), jaxsync.cantilever(mesh, body_force=(0, 0, -0.6)), other(mesh)]
    with pytest.raises(ProblemError, match=f"problem 2 .*{what}.*jaxsync.simulate"):
        jaxsync.ensemble(runs, 10)


def test_refuses_bad_arguments(mesh):
    runs = [jaxsync.cantilever(mesh), jaxsync.cantilever(mesh, body_force=(0, 0, -0.6))]
    with pytest.raises(ProblemError, match="2 labels for 3 problems"):
        jaxsync.ensemble(runs + [runs[0]], 10, labels=(0.5, 0.6))
    with pytest.raises(ProblemError, match="at least one problem"):
        jaxsync.ensemble([], 10)
    with pytest.raises(ProblemError, match="not a multiple of save_every"):
        jaxsync.ensemble(runs, 10, save=3)
    with pytest.raises(ProblemError, match="shared_every needs a distributed run"):
        jaxsync.ensemble(runs, 10, save=jaxsync.SaveAt(2, 1))
    with pytest.raises(StabilityError, match="stability bound"):
        jaxsync.ensemble(runs, 10, dt=100 * runs[0].dt)


def test_divergence_names_the_run(mesh):
    """Run 1 carries an absurd load: its tip passes the blow-up limit within a few dozen steps."""
    runs = [jaxsync.cantilever(mesh), jaxsync.cantilever(mesh, body_force=(0, 0, -1e12)),
            jaxsync.cantilever(mesh, body_force=(0, 0, -0.6))]
    with pytest.raises(StabilityError, match=r"run 1 \(label 1e\+12\) of the ensemble diverged") as info:
        jaxsync.ensemble(runs, 100, save=jaxsync.SaveAt(5, 1), executor=jaxsync.HostExecutor(chunk_steps=50),
                         labels=(0.5, 1e12, 0.6), partitions=2)
    err = info.value
    assert err.run == 1 and err.runs == (1,)
    assert len(err.trajectories) == 3 and err.trajectory is err.trajectories[1]
    n_saved = err.trajectory.n_saved
    assert 1 < n_saved < 21
    for traj in err.trajectories:
        assert traj.n_saved == n_saved and np.isfinite(traj.displacement).all()
        assert all(p.shared_displacement.shape[0] == (n_saved - 1) * 5 + 1 for p in traj.parts)


# --- members that differ in material, damping, loads and initial conditions ------------------------

QUIET = jaxsync.HostExecutor(progress=False)
BETA = 2.0e-5  # [s], about a tenth of the cantilever's step


def _members(case: str, static):
    """Three members of the cantilever. ``"E"``: E, rho, alpha, load factors and initial
    displacements differ (one stiffness, E as its scale); ``"E, nu"``: E, nu, rho, beta, load
    factors and initial velocities differ (stiffness blocks per member)."""
    material = {"E": np.array([0.8e6, 1.0e6, 1.3e6]), "rho": np.array([1.2, 1.0, 0.9])}
    if case == "E":
        return jaxsync.Members(material=material, damping=np.array([0.5, 0.1, 2.0]),
                               load_scale=np.array([[0.6], [1.0], [1.4]]),
                               initial_displacement=np.array([0.0, 0.5, -0.3])[:, None, None] * static)
    material["nu"] = np.array([0.22, 0.3, 0.38])
    return jaxsync.Members(material=material, stiffness_damping=np.array([BETA, 0.5 * BETA, 2 * BETA]),
                           load_scale=np.array([1.0, 0.7, 1.2]),
                           initial_velocity=np.array([0.0, 2.0, -1.0])[:, None, None] * static)


@pytest.mark.parametrize("case", ["E", "E, nu"])
def test_members_equal_their_own_problems_run_one_by_one(mesh, static, case):
    """Each member's trajectory equals jaxsync.simulate of its own Problem at the ensemble's
    step; the same members given as problems give the same; the default step is the
    smallest member's."""
    base = jaxsync.cantilever(mesh)
    members = _members(case, static)
    together = jaxsync.ensemble(base, 200, members=members, save=20, executor=QUIET)
    own = [members.problem(base, r) for r in range(3)]
    dt = together[0].dt
    smallest = min(float(p.dt) for p in own)
    if case == "E":  # nu shared: every member's exact bound, so the default is the smallest member's own
        assert dt == pytest.approx(smallest, rel=1e-12)
    else:  # nu differs: a lower bound on each member's, within a factor of it
        assert 0.6 * smallest <= dt <= smallest
    as_problems = jaxsync.ensemble(own, 200, dt=dt, save=20, executor=QUIET)
    for r, (problem, traj, again) in enumerate(zip(own, together, as_problems)):
        alone = jaxsync.simulate(problem, 200, dt=dt, save=20, executor=QUIET)
        assert traj.displacement.shape == alone.displacement.shape == (11, mesh.n_nodes, 3)
        assert np.abs(alone.displacement).max() > 0
        assert relative_error(traj.displacement, alone.displacement) <= 1e-12, r
        assert relative_error(again.displacement, alone.displacement) <= 1e-12, r
        for name in ("E", "nu", "rho", "damping", "stiffness_damping"):
            assert traj.parameters[name] == pytest.approx(alone.parameters[name], rel=1e-15), name
            assert again.parameters[name] == pytest.approx(alone.parameters[name], rel=1e-15), name
    assert len({round(t.parameters["E"]) for t in together}) == 3


def test_a_short_ensemble_compiles_the_compact_product(mesh, static):
    """The stiffness product's form as for one run of n_runs * n_steps steps: compact below
    COMPACT_SLOT_STEPS, fused above it and where the length is not given; both give every
    member's K u to round-off."""
    from jaxsync.fem.forces import COMPACT_SLOT_STEPS
    from jaxsync.solve import batched_system, default_dt, member_system, setup_of_members

    base = jaxsync.cantilever(mesh)
    slots = int(np.prod(base.operators.block_ell[0].shape))
    short, long = int(COMPACT_SLOT_STEPS // (3 * slots)) - 1, int(COMPACT_SLOT_STEPS // (3 * slots)) + 1
    u = np.random.default_rng(1).standard_normal((base.n_nodes, 3))
    for case in ("E", "E, nu"):
        setup = setup_of_members(base, _members(case, static))
        dt = default_dt(setup)
        forms = {n: batched_system(setup, dt, n) for n in (short, long, None)}
        assert [forms[n][0].stiffness.compact for n in (short, long, None)] == [True, False, False], case
        for r in range(3):
            products = [member_system(system, jax.tree_util.tree_map(lambda x, r=r: x[r], runs)).stiffness.matvec(u)
                        for system, runs in forms.values()]
            assert relative_error(products[0], products[1]) <= 1e-14, case


@pytest.mark.parametrize("case", ["E", "E, nu"])
def test_vectorised_setup_equals_each_members_own_system(mesh, static, case):
    """The batched system's member r (stiffness, lumped mass, damping, beta, loads,
    prescribed values, the supports' springs and dashpots) and its start equal
    build_system and initial_state of member r's own Problem."""
    from jaxsync.fem import build_system, initial_state
    from jaxsync.solve import batched_system, default_dt, initial_states, member_system, setup_of_members

    base = jaxsync.cantilever(mesh).replace(supports=(jaxsync.ElasticSupport(2.0e3, 50.0, surface="z0"),))
    members = _members(case, static)
    members = dataclasses.replace(members, damping=np.array([0.5, 0.1, 2.0]))  # with the supports' dashpots
    setup = setup_of_members(base, members)
    dt = default_dt(setup)
    system, runs = batched_system(setup, dt)
    states = initial_states(setup, system, runs)
    u = np.random.default_rng(0).standard_normal((3, base.n_nodes, 3))
    for r in range(3):
        mine = member_system(system, jax.tree_util.tree_map(lambda x, r=r: x[r], runs))
        problem = members.problem(base, r)
        own = build_system(problem, dt)
        for v in u:
            expected = np.asarray(own.stiffness.matvec(v))
            assert relative_error(mine.stiffness.matvec(v), expected) <= 1e-14
            assert relative_error(mine.spring.matvec(v), own.spring.matvec(v)) <= 1e-15
        for name in ("mass", "damping", "stiffness_damping", "dt", "load_vectors", "fixed", "fixed_values"):
            if getattr(own, name) is None:  # no beta: none in the batch either
                assert getattr(mine, name) is None, name
                continue
            np.testing.assert_allclose(getattr(mine, name), getattr(own, name), rtol=1e-15, atol=0, err_msg=name)
        for a, b in zip(jax.tree_util.tree_leaves(mine.dashpot), jax.tree_util.tree_leaves(own.dashpot)):
            np.testing.assert_allclose(a, b, rtol=1e-14, atol=1e-14 * np.abs(b).max())
        start = initial_state(problem, own)
        for name in ("displacement", "previous"):
            expected = getattr(start, name)
            scale = max(float(np.abs(expected).max()), 1e-30)
            np.testing.assert_allclose(getattr(states, name)[r], expected, rtol=0, atol=1e-12 * scale, err_msg=name)


def test_gradient_in_each_members_E_matches_finite_differences(mesh):
    """A batched inverse problem: three noisy observations of the tip deflection history fitted
    at once; jax.grad of the loss summed over the members with respect to their E
    equals central finite differences of it."""
    base = jaxsync.cantilever(mesh)
    tip = mesh.facet_nodes("x1")
    truth = np.array([0.9e6, 1.1e6, 1.25e6])
    observed = jaxsync.ensemble(base, 300, members=jaxsync.Members(material={"E": truth}), save=30, executor=QUIET)
    dt = observed[0].dt
    noise = np.random.default_rng(1).normal(0.0, 1e-4, (3, 10, len(tip), 3))
    data = jnp.asarray(np.stack([t.displacement[1:, tip] for t in observed]) + noise)

    @jax.jit
    def loss(E):
        runs = jaxsync.ensemble(base, 300, members=jaxsync.Members(material={"E": E}), dt=dt, save=30)
        predicted = jnp.stack([t.displacement[1:, tip] for t in runs])
        return 1e4 * jnp.sum((predicted - data) ** 2)

    guess = np.array([1.0e6, 1.0e6, 1.0e6])
    gradient = np.asarray(jax.jit(jax.grad(loss))(jnp.asarray(guess)))
    assert np.all(gradient != 0)
    for r in range(3):
        h = 1e-5 * guess[r]
        step = np.zeros(3)
        step[r] = h
        fd = (float(loss(jnp.asarray(guess + step))) - float(loss(jnp.asarray(guess - step)))) / (2 * h)
        assert gradient[r] == pytest.approx(fd, rel=1e-6), r


def test_a_member_above_its_stability_bound_is_named(mesh):
    from jaxsync.solve import member_bounds, setup_of_members

    base = jaxsync.cantilever(mesh)
    dt = float(base.dt)
    with pytest.raises(StabilityError, match=r"member 2 of the ensemble \(E=4e\+06\).*above its stability bound"):
        jaxsync.ensemble(base, 10, members=jaxsync.Members(material={"E": np.array([1e6, 0.5e6, 4e6])}), dt=dt)
    members = jaxsync.Members(material={"E": np.array([1e6, 4e6, 1e6]), "nu": np.array([0.3, 0.3, 0.25])})
    with pytest.raises(StabilityError, match=r"member 1 of the ensemble \(E=4e\+06, nu=0.3\).*stability bound"):
        jaxsync.ensemble(base, 10, members=members, dt=dt)
    bounds, exact = member_bounds(setup_of_members(base, members))
    assert not exact  # nu differs: the bound from the unit operators' eigenvalues, below each member's own
    for r in range(3):
        own = float(jaxsync.max_stable_dt(members.problem(base, r)))
        assert 0.6 * own <= bounds[r] <= own


def test_members_refuse_bad_input(mesh):
    base = jaxsync.cantilever(mesh)
    E = np.array([1e6, 2e6])
    for members, message in [
        (jaxsync.Members(material={"E": E}, damping=np.array([0.1, 0.2, 0.3])),
         r"damping has shape \(3,\); with 2 runs .* must be \(2,\)"),
        (jaxsync.Members(material={"E": np.array([1e6, -2e6])}), r"Young's modulus.*run 1 is -2e\+06: give E > 0"),
        (jaxsync.Members(material={"nu": np.array([0.3, 0.5])}), r"Poisson ratio.*run 1 is 0.5: give -1 < nu < 0.5"),
        (jaxsync.Members(material={"k1": E}), r"LinearElastic does not have.*\['E', 'nu', 'rho'\]"),
        (jaxsync.Members(material={"E": E}, load_scale=np.ones((2, 3))), r"load_scale has shape \(2, 3\)"),
        (jaxsync.Members(initial_displacement=np.zeros((2, 5, 3))), r"initial_displacement has shape \(2, 5, 3\)"),
        (jaxsync.Members(damping=np.array([-0.1, 0.2])), r"damping alpha.*run 0 is -0.1"),
        (jaxsync.Members(), "at least one per-run array"),
    ]:
        with pytest.raises(ProblemError, match=message):
            jaxsync.ensemble(base, 10, members=members)
    with pytest.raises(ProblemError, match="must be a dict"):
        jaxsync.Members(material=[1e6])
    with pytest.raises(ProblemError, match="ONE problem"):
        jaxsync.ensemble([base, base], 10, members=jaxsync.Members(damping=np.array([0.1, 0.2])))
    with pytest.raises(ProblemError, match="2 labels for 3 runs"):
        jaxsync.ensemble(base, 10, members=jaxsync.Members(damping=np.array([0.1, 0.2, 0.3])), labels=(1, 2))


def test_hyperelastic_members_equal_their_own_problems(mesh):
    """A neo-Hookean cantilever under a large load: members differing in E, nu and load
    equal their own problems run one by one (the law's parameters vmapped)."""
    base = jaxsync.cantilever(mesh, material=jaxsync.NeoHookean(1.0e6, 0.3, 1.0), body_force=(0.0, 0.0, -500.0),
                              t_ramp=0.01)
    members = jaxsync.Members(material={"E": np.array([0.9e6, 1.2e6]), "nu": np.array([0.3, 0.35])},
                              load_scale=np.array([1.0, 1.5]))
    together = jaxsync.ensemble(base, 150, members=members, save=50, executor=QUIET)
    dt = together[0].dt
    assert dt == pytest.approx(min(float(members.problem(base, r).dt) for r in range(2)), rel=1e-12)
    for r, traj in enumerate(together):
        alone = jaxsync.simulate(members.problem(base, r), 150, dt=dt, save=50, executor=QUIET)
        assert np.abs(alone.displacement).max() > 1e-3  # deflections where the law is nonlinear
        assert relative_error(traj.displacement, alone.displacement) <= 1e-12, r
        assert traj.parameters["material"] == "NeoHookean" and traj.parameters["E"] == members.material["E"][r]
