import numpy as np
import pytest

import jaxsync
from jaxsync import PartitionError
from jaxsync.fem import lumped_mass
from jaxsync.parallel import partition_from_elements


@pytest.fixture(scope="module")
def mesh():
    return jaxsync.box_beam(8.0, 2.0, 1.0, (8, 2, 2))


@pytest.mark.parametrize("n_parts", [1, 2, 3, 5])
def test_partition_invariants(mesh, n_parts):
    part = jaxsync.partition(mesh, n_parts, seed=1)
    assert part.n_parts == n_parts
    # every element in exactly one part
    all_elements = np.concatenate([p.elements for p in part.parts])
    np.testing.assert_array_equal(np.sort(all_elements), np.arange(mesh.n_elements))
    # shared exactly when elements of two or more parts touch the node (brute force)
    touching = [set() for _ in range(mesh.n_nodes)]
    for e, tet in enumerate(mesh.tets):
        for node in tet:
            touching[node].add(int(part.element_part[e]))
    expected_shared = [i for i, s in enumerate(touching) if len(s) >= 2]
    np.testing.assert_array_equal(part.shared_nodes, expected_shared)
    for k, node in enumerate(part.shared_nodes):
        np.testing.assert_array_equal(part.sharing_parts[k], sorted(touching[node]))
    for p in part.parts:
        np.testing.assert_array_equal(p.nodes, np.unique(mesh.tets[p.elements]))
        np.testing.assert_array_equal(p.nodes[p.local_tets], mesh.tets[p.elements])
        np.testing.assert_array_equal(p.shared_nodes, np.intersect1d(p.nodes, expected_shared))
        np.testing.assert_array_equal(part.shared_nodes[p.shared_interface], p.shared_nodes)
    # per-part lumped masses sum to the global lumped mass
    total = np.zeros(mesh.n_nodes)
    for p in part.parts:
        sub = jaxsync.Mesh(mesh.points[p.nodes], p.local_tets)
        np.add.at(total, p.nodes, lumped_mass(sub))
    np.testing.assert_allclose(total, lumped_mass(mesh), rtol=1e-13)


def test_partition_is_deterministic(mesh):
    a = jaxsync.partition(mesh, 4, seed=7)
    b = jaxsync.partition(mesh, 4, seed=7)
    np.testing.assert_array_equal(a.element_part, b.element_part)


def test_summary(mesh):
    text = jaxsync.partition(mesh, 2).summary()
    assert "interface:" in text and "shared" in text
    assert len(text.splitlines()) == 5


def test_dirichlet_local(mesh):
    part = jaxsync.partition(mesh, 3)
    dofs = np.array([0, 1, 2, 3 * 17 + 2, 3 * (mesh.n_nodes - 1)])
    for p, local in zip(part.parts, part.dirichlet_local(dofs)):
        global_dofs = 3 * p.nodes[local // 3] + local % 3
        np.testing.assert_array_equal(global_dofs, [d for d in dofs if d // 3 in set(p.nodes)])


@pytest.mark.parametrize("n_parts, match", [(0, "positive"), (-2, "positive"), (2.5, "positive"),
                                            (10_000, "cannot split")])
def test_bad_part_counts(mesh, n_parts, match):
    with pytest.raises(PartitionError, match=match):
        jaxsync.partition(mesh, n_parts)


def test_metis_empty_part_is_an_error():
    mesh = jaxsync.box_beam()  # 150 elements: METIS leaves parts empty at 150 parts
    with pytest.raises(PartitionError, match="empty") as caught:
        jaxsync.partition(mesh, 150)
    message = str(caught.value)  # a count and a few ids, not a list of every empty part
    assert message.count(",") < 12 and "of the 150 parts empty" in message and "1 per part" in message, message


def test_partition_from_elements_rejects_bad_assignments(mesh):
    with pytest.raises(PartitionError):
        partition_from_elements(mesh, np.zeros(3, dtype=int))
