"""Deep halos (jaxsync.parallel.exchange): the tables checked against a breadth-first search
written here, the algorithm replayed in NumPy on those tables against a global SciPy
run, and the SPMD runs equal to the psum-synchronized solver to round-off."""

import argparse

import numpy as np
import pytest

import fem_reference as ref
import jaxsync
from jaxsync import ConfigError, PartitionError, ProblemError
from jaxsync.parallel import partition_from_elements
from jaxsync.parallel.exchange import halo_partition

MATERIAL = jaxsync.LinearElastic(1.0e6, 0.3, 1.0)
BODY_FORCE = np.array([0.1, -0.2, -0.5])


@pytest.fixture(scope="module")
def mesh():
    return jaxsync.box_beam(8.0, 1.0, 1.0, (8, 2, 2))


@pytest.fixture(scope="module")
def problem(mesh):
    rng = np.random.default_rng(3)
    return jaxsync.Problem(
        mesh, MATERIAL, dirichlet=(jaxsync.Dirichlet("x0"),),
        loads=(jaxsync.BodyForce(BODY_FORCE, jaxsync.Constant()),), damping=0.7,
        initial_displacement=1e-3 * rng.standard_normal((mesh.n_nodes, 3)),
        initial_velocity=1e-2 * rng.standard_normal((mesh.n_nodes, 3)))


def neighbours(mesh):
    """Node graph as Python sets (two nodes are neighbours when an element holds both)."""
    out = [set() for _ in range(mesh.n_nodes)]
    for tet in mesh.tets:
        for a in tet:
            out[a].update(int(b) for b in tet if b != a)
    return out


def within(sources, graph, distance):
    """Nodes within ``distance`` edges of ``sources`` (breadth-first search)."""
    seen, frontier = set(sources), set(sources)
    for _ in range(distance):
        frontier = {b for a in frontier for b in graph[a]} - seen
        seen |= frontier
    return seen


@pytest.mark.parametrize("n_parts", [2, 4, 8])
def test_halo_tables_are_the_rings_around_the_owned_nodes(mesh, n_parts):
    base = jaxsync.partition(mesh, n_parts, seed=0)
    graph = neighbours(mesh)
    for depth in (1, 2, 3):
        halo = halo_partition(base, depth)
        # every node has one owner: the lowest part whose elements touch it
        touching = [set() for _ in range(mesh.n_nodes)]
        for e, tet in enumerate(mesh.tets):
            for a in tet:
                touching[a].add(int(base.element_part[e]))
        assert [min(t) for t in touching] == halo.owner.tolist()
        owned_all = np.concatenate([p.nodes[o] for p, o in zip(halo.parts, halo.owned_local)])
        assert np.array_equal(np.sort(owned_all), np.arange(mesh.n_nodes))
        in_halo = set()
        for part, owned in zip(halo.parts, halo.owned_local):
            mine = set(np.flatnonzero(halo.owner == part.index).tolist())
            assert set(part.nodes[owned].tolist()) == mine
            assert set(part.nodes.tolist()) == within(mine, graph, depth)
            inner = within(mine, graph, depth - 1)
            touching_inner = [e for e, tet in enumerate(mesh.tets) if inner & set(tet.tolist())]
            assert part.elements.tolist() == touching_inner
            assert np.array_equal(part.nodes[part.local_tets], mesh.tets[part.elements])
            in_halo |= set(part.nodes.tolist()) - mine
        assert halo.halo_nodes.tolist() == sorted(in_halo)
        for part in halo.parts:  # a part lists exactly its local nodes in the interface
            expected = [i for i, node in enumerate(part.nodes) if node in in_halo]
            assert part.shared_local.tolist() == expected
            assert np.array_equal(halo.halo_nodes[part.shared_interface], part.nodes[part.shared_local])
        assert halo.redundancy() >= 1.0


def replay(problem, halo, depth, cycles, d0, dm1):
    """The deep-halo algorithm in NumPy/SciPy on the tables of ``halo``: every part steps
    ``depth`` times alone with the stiffness of its own elements, then both displacement
    levels of its non-owned nodes are read from their owners through the interface.
    Returns the global field (owned values) after every cycle, (cycles, n_dofs)."""
    mesh = problem.mesh
    m_all = ref.lumped_mass(mesh.points, mesh.tets, MATERIAL.rho).reshape(-1, 3)
    f_all = ref.body_force(mesh.points, mesh.tets, BODY_FORCE).reshape(-1, 3)
    fixed_dofs, _ = problem.dirichlet_dofs()
    fixed_all = np.zeros(mesh.n_dofs, dtype=bool)
    fixed_all[fixed_dofs] = True
    fixed_all = fixed_all.reshape(-1, 3)
    dt, a = float(problem.dt), 0.5 * 0.7 * float(problem.dt)
    state = []
    for part in halo.parts:
        dofs = (3 * part.nodes[:, None] + np.arange(3)).ravel()
        K = ref.stiffness(mesh.points, mesh.tets[part.elements], MATERIAL.E, MATERIAL.nu)[dofs][:, dofs]
        state.append([K, d0.reshape(-1, 3)[part.nodes].copy(), dm1.reshape(-1, 3)[part.nodes].copy()])
    out = []
    for _ in range(cycles):
        for part, s in zip(halo.parts, state):
            K, d, prev = s
            for _ in range(depth):
                force = (K @ d.ravel()).reshape(-1, 3)
                new = (dt**2 * (f_all[part.nodes] - force) / m_all[part.nodes] + 2 * d
                       - (1 - a) * prev) / (1 + a)
                new[fixed_all[part.nodes]] = 0.0
                prev, d = d, new
            s[1], s[2] = d, prev
        interface = np.zeros((halo.n_interface, 6))  # owners write, everyone reads
        for part, owned, s in zip(halo.parts, halo.owned_local, state):
            levels = np.hstack([s[1], s[2]])
            mine = np.isin(part.shared_local, owned)
            interface[part.shared_interface[mine]] += levels[part.shared_local[mine]]
        field = np.zeros((mesh.n_nodes, 3))
        for part, owned, s in zip(halo.parts, halo.owned_local, state):
            levels = np.hstack([s[1], s[2]])
            levels[part.shared_local] = interface[part.shared_interface]
            s[1], s[2] = levels[:, :3], levels[:, 3:]
            field[part.nodes[owned]] = s[1][owned]
        out.append(field.ravel())
    return np.array(out)


@pytest.mark.parametrize("n_parts", [2, 4, 8])
def test_numpy_replay_of_the_halo_tables_equals_the_global_run(problem, n_parts):
    mesh = problem.mesh
    rng = np.random.default_rng(n_parts)
    fixed_dofs, _ = problem.dirichlet_dofs()
    d0, dm1 = 1e-3 * rng.standard_normal(mesh.n_dofs), 1e-3 * rng.standard_normal(mesh.n_dofs)
    d0[fixed_dofs] = dm1[fixed_dofs] = 0.0
    K = ref.stiffness(mesh.points, mesh.tets, MATERIAL.E, MATERIAL.nu)
    m = ref.lumped_mass(mesh.points, mesh.tets, MATERIAL.rho)
    f = ref.body_force(mesh.points, mesh.tets, BODY_FORCE)
    steps = 12
    expected = ref.central_difference(K, m, lambda t: f, 0.7, float(problem.dt), d0, dm1, fixed_dofs,
                                      np.zeros(len(fixed_dofs)), steps)
    scale = np.abs(expected).max()
    base = jaxsync.partition(mesh, n_parts, seed=0)
    for depth in (1, 2, 3):
        got = replay(problem, halo_partition(base, depth), depth, steps // depth, d0, dm1)
        assert np.abs(got - expected[depth::depth]).max() <= 1e-12 * scale
    # the depth matters: parts one layer too thin drift from the first cycle on
    thin = replay(problem, halo_partition(base, 1), 2, steps // 2, d0, dm1)
    assert np.abs(thin - expected[2::2]).max() > 1e-6 * scale


# the default run checks both modes and both part counts in [2-preassembled] and [4-recompute]
@pytest.mark.parametrize("n_parts, mode", [
    (2, "preassembled"),
    pytest.param(2, "recompute", marks=pytest.mark.slow),
    pytest.param(4, "preassembled", marks=pytest.mark.slow),
    (4, "recompute"),
    pytest.param(8, "preassembled", marks=pytest.mark.slow),
    pytest.param(8, "recompute", marks=pytest.mark.slow),
])
def test_deep_halos_equal_the_psum_run_to_round_off(problem, n_parts, mode):
    part = jaxsync.partition(problem.mesh, n_parts, seed=0)
    reference = jaxsync.simulate(problem, 24, save=6, executor=jaxsync.HostExecutor(progress=False), partitions=part,
                                 mode=mode, sync="psum")
    scale = np.abs(reference.displacement).max()
    for depth in (1, 2, 3):
        run = jaxsync.simulate(problem, 24, save=6, executor=jaxsync.HostExecutor(progress=False),
                               sync=jaxsync.Halo(depth), partitions=part, mode=mode)
        assert np.abs(run.displacement - reference.displacement).max() <= 1e-12 * scale


def test_saves_inside_an_exchange_cycle_and_chunks(problem):
    part = jaxsync.partition(problem.mesh, 4, seed=0)
    reference = jaxsync.simulate(problem, 24, save=1, executor=jaxsync.HostExecutor(progress=False), partitions=part)
    scale = np.abs(reference.displacement).max()
    # a save every step inside cycles of 4 steps (owned nodes are right at every step),
    # and chunks of 8 steps (the state crosses chunk boundaries after an exchange)
    run = jaxsync.simulate(problem, 24, save=1, executor=jaxsync.HostExecutor(progress=False, chunk_steps=8),
                           sync=jaxsync.Halo(4), partitions=part)
    assert np.abs(run.displacement - reference.displacement).max() <= 1e-12 * scale
    run = jaxsync.simulate(problem, 24, save=2, executor=jaxsync.HostExecutor(progress=False), sync=jaxsync.Halo(4),
                           partitions=part)
    assert np.abs(run.displacement - reference.displacement[::2]).max() <= 1e-12 * scale
    # the parts' element lists stay the element partition's (not the grown ones)
    assert [p.elements.tolist() for p in run.parts] == [p.elements.tolist() for p in part.parts]


def test_deep_halo_input_errors_name_the_fix(problem):
    part = jaxsync.partition(problem.mesh, 2, seed=0)
    with pytest.raises(PartitionError, match="divide one another.*halo_depth=1 or save_every=6"):
        jaxsync.simulate(problem, 12, save=3, sync=jaxsync.Halo(2), partitions=part)
    with pytest.raises(ProblemError, match="multiple of 4; use n_steps=12"):
        jaxsync.simulate(problem, 10, save=2, sync=jaxsync.Halo(4), partitions=part)
    with pytest.raises(ProblemError, match="partitions=n_parts"):
        jaxsync.simulate(problem, 12, sync="halo")
    with pytest.raises(PartitionError, match="positive integer"):
        jaxsync.simulate(problem, 12, partitions=part, sync=jaxsync.Halo(0))
    with pytest.raises(ConfigError, match="needs --sync halo"):  # the command line's two options
        from jaxsync.cli.common import sync_of

        sync_of(argparse.Namespace(sync="psum", halo_depth=2))
    with pytest.raises(ConfigError, match="sync='psum' or 'ppermute'"):
        jaxsync.simulate(problem, 12, save=jaxsync.SaveAt(6, 1), partitions=part, sync="halo")


def test_a_part_that_owns_nothing_is_refused():
    mesh = jaxsync.box_beam(2.0, 1.0, 1.0, (2, 1, 1))
    element_part = np.zeros(mesh.n_elements, dtype=np.int64)
    element_part[0] = 1  # one element, every node of which part 0 also touches
    base = partition_from_elements(mesh, element_part)
    with pytest.raises(PartitionError, match="part 1 owns no node"):
        halo_partition(base, 1)


def test_the_cost_model_reads_a_halo_exchange_pattern(mesh):
    from jaxsync.perf.costmodel import communication_pattern

    halo = halo_partition(jaxsync.partition(mesh, 4, seed=0), 2)
    pattern = communication_pattern(halo, dofs_per_node=6)
    assert pattern.n_interface == halo.n_interface and pattern.dofs_per_node == 6
    held = {p.index: set(p.shared_interface.tolist()) for p in halo.parts}
    for p, neighbours in enumerate(pattern.neighbours):  # nodes both parts hold, counted by hand
        expected = {q: len(held[p] & held[q]) for q in held if q != p and held[p] & held[q]}
        assert dict(neighbours) == expected
