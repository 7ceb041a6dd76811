import jax
import numpy as np
import pytest

import jaxsync
from jaxsync import PartitionError
from jaxsync.parallel import partition_from_elements


@pytest.fixture(scope="module")
def problem():
    return jaxsync.cantilever()


@pytest.fixture(scope="module")
def references(problem):
    return {mode: jaxsync.simulate(problem, 2000, save=10, mode=mode)
            for mode in ("preassembled", "recompute")}


def relative_error(a, b):
    return np.abs(a - b).max() / np.abs(b).max()


def test_two_devices_are_available():
    assert len(jax.devices()) == 2


@pytest.mark.parametrize("mode", ["preassembled", "recompute"])
@pytest.mark.parametrize("n_parts", [1, 2, 4])
def test_distributed_equals_single_device(problem, references, mode, n_parts):
    traj = jaxsync.simulate(problem, 2000, save=10, partitions=n_parts, mode=mode)
    assert relative_error(traj.displacement, references[mode].displacement) <= 1e-12
    assert len(traj.parts) == n_parts


def test_modes_agree(references):
    """The element-recompute force equals the stored K (summation order differs)."""
    a, b = references["preassembled"].displacement, references["recompute"].displacement
    assert relative_error(b, a) <= 1e-10


def test_dirichlet_nodes_on_part_boundaries(problem):
    """Two parts split at mid-length, except that the first cell (at the clamp) is split
    across its diagonal, so the interface cuts the clamped face: clamped nodes are shared."""
    mesh = problem.mesh
    centroid = mesh.points[mesh.tets].mean(axis=1)
    element_part = (centroid[:, 0] > 12.5).astype(int)
    at_clamp = centroid[:, 0] < 1.0
    element_part[at_clamp] = (centroid[at_clamp, 1] + centroid[at_clamp, 2] > 1.0).astype(int)
    part = partition_from_elements(mesh, element_part)
    fixed, _ = problem.dirichlet_dofs()
    assert np.intersect1d(fixed // 3, part.shared_nodes).size > 0
    for mode in ("preassembled", "recompute"):
        reference = jaxsync.simulate(problem, 2000, save=10, mode=mode)
        traj = jaxsync.simulate(problem, 2000, save=10, partitions=part, mode=mode)
        assert relative_error(traj.displacement, reference.displacement) <= 1e-12
        assert np.all(traj.displacement[:, fixed // 3] == 0.0)


def test_shared_displacement_is_the_global_displacement(problem, tmp_path):
    traj = jaxsync.simulate(problem, 400, save=1, partitions=2)
    path = tmp_path / "d.h5"
    traj.save(path)
    back = jaxsync.Trajectory.load(path)
    part = jaxsync.partition(problem.mesh, 2)
    import h5py

    with h5py.File(path) as f:
        assert int(f.attrs["n_parts"]) == 2
        for p in part.parts:
            nodes = f[f"parts/{p.index}/shared_nodes"][...]
            shared = f[f"parts/{p.index}/shared_displacement"][...]
            np.testing.assert_array_equal(nodes, p.shared_nodes)
            assert shared.shape == (401, 3 * p.n_shared)
            np.testing.assert_array_equal(shared, back.displacement[:, nodes].reshape(401, -1))


def test_several_parts_per_device_and_checkpoint_resume(problem, tmp_path):
    full = jaxsync.simulate(problem, 3000, save=30, executor=jaxsync.HostExecutor(chunk_steps=600), partitions=4)
    ckpt = tmp_path / "c.h5"
    jaxsync.simulate(problem, 1200, save=30, executor=jaxsync.HostExecutor(chunk_steps=600), partitions=4,
                     checkpoint=ckpt)
    resumed = jaxsync.simulate(problem, 3000, save=30, executor=jaxsync.HostExecutor(chunk_steps=600), partitions=4,
                               checkpoint=ckpt)
    np.testing.assert_array_equal(resumed.displacement, full.displacement)


def test_partition_of_another_mesh_is_refused(problem):
    other = jaxsync.partition(jaxsync.box_beam(divisions=(10, 1, 1)), 2)
    with pytest.raises(PartitionError, match="another mesh"):
        jaxsync.simulate(problem, 10, partitions=other)


def test_unknown_mode_is_refused(problem):
    with pytest.raises(jaxsync.ProblemError, match="mode"):
        jaxsync.simulate(problem, 10, partitions=2, mode="fast")


def test_element_forces_equal_stiffness_times_u():
    import jax.numpy as jnp

    from jaxsync.fem.forces import ElementStiffness

    mesh = jaxsync.box_beam(3.0, 1.0, 1.0, (3, 2, 1))
    mat = jaxsync.LinearElastic(2.0e5, 0.35, 1.0)
    problem = jaxsync.Problem(mesh, mat)
    K = problem.operators.stiffness(mat.lam, mat.mu)
    u = np.random.default_rng(3).standard_normal((mesh.n_nodes, 3))
    op = ElementStiffness(jnp.asarray(mesh.points), jnp.asarray(mesh.tets), jnp.ones(mesh.n_elements),
                          mat.lam, mat.mu)
    np.testing.assert_allclose(op.matvec(jnp.asarray(u)), (K @ u.ravel()).reshape(-1, 3),
                               rtol=1e-12, atol=1e-12 * abs(K).max())


@pytest.mark.parametrize("n_parts", [2, 4])
def test_ppermute_neighbour_exchange_equals_psum(problem, references, n_parts):
    """sync="ppermute" (neighbour exchange between devices) gives the psum's result; with 4
    parts on the 2 devices, each device first sums its own two parts."""
    traj = jaxsync.simulate(problem, 2000, save=10, partitions=n_parts, sync="ppermute")
    assert relative_error(traj.displacement, references["preassembled"].displacement) <= 1e-12


@pytest.mark.parametrize("n_parts,n_devices", [(8, 8), (8, 4), (6, 3), (4, 1)])
def test_neighbour_exchange_tables_sum_every_shared_node(n_parts, n_devices):
    """Replay the exchange of the tables in NumPy on a mesh that METIS cuts in several
    directions (parts meet at edges and corners): every device must end with the sum over
    all parts at each of its shared nodes, and only device pairs that share nodes talk."""
    from jaxsync.parallel.exchange import neighbour_exchange

    mesh = jaxsync.box_beam(4.0, 4.0, 4.0, (4, 4, 4))
    part = jaxsync.partition(mesh, n_parts, seed=1)
    plan = neighbour_exchange(part, n_devices)
    per_device = n_parts // n_devices
    rng = np.random.default_rng(0)
    n_i = part.n_interface
    partial = rng.normal(size=(n_parts, n_i + 1, 3))
    for p in part.parts:  # a part contributes only at its own shared nodes
        keep = np.zeros(n_i + 1, bool)
        keep[p.shared_interface] = True
        partial[p.index, ~keep] = 0.0
    exact = partial.sum(axis=0)
    local = partial.reshape(n_devices, per_device, n_i + 1, 3).sum(axis=1)
    total = local.copy()
    for i, k in enumerate(plan.offsets):
        for d in range(n_devices):
            e = (d + k) % n_devices
            np.add.at(total[e], plan.receive[i, e], local[d][plan.send[i, d]])
    devices_of = {}
    for p in part.parts:
        for node in p.shared_interface:
            devices_of.setdefault(int(node), set()).add(p.index // per_device)
    for node, devices in devices_of.items():
        for d in devices:
            np.testing.assert_allclose(total[d, node], exact[node], rtol=1e-12, atol=1e-12)
    # offsets are exactly those at which some pair of devices shares a node
    talking = {(e - d) % n_devices for devices in devices_of.values() for d in devices
               for e in devices if d != e}
    assert set(plan.offsets) == talking
    assert (n_devices == 1) == (plan.offsets == ())
