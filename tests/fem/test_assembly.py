import numpy as np
import pytest
import scipy.linalg
import scipy.sparse

import fem_reference as ref
import jaxsync
from jaxsync.fem import (
    BlockEll,
    assemble_unit_operators,
    block_ell_values,
    body_force_vectors,
    consistent_mass,
    element_blocks,
    lumped_mass,
    node_adjacency,
    pressure_vector,
)


@pytest.fixture(scope="module")
def mesh():
    return jaxsync.box_beam(4.0, 1.0, 2.0, (4, 1, 2))


def test_stiffness_matches_textbook_assembly(mesh):
    ops = assemble_unit_operators(mesh)
    mat = jaxsync.LinearElastic(3.0e5, 0.27, 1.1)
    K = ops.stiffness(mat.lam, mat.mu)
    K_ref = ref.stiffness(mesh.points, mesh.tets, mat.E, mat.nu)
    assert abs(K - K_ref).max() <= 1e-10 * abs(K_ref).max()


def test_unconstrained_stiffness_is_spd_with_six_rigid_modes(mesh):
    ops = assemble_unit_operators(mesh)
    K = ops.stiffness(1.0, 1.0).toarray()
    np.testing.assert_allclose(K, K.T, atol=1e-12 * abs(K).max())
    w = scipy.linalg.eigvalsh(K)
    assert w.min() > -1e-10 * w.max()
    assert np.sum(w < 1e-9 * w.max()) == 6
    # the six zero modes are the rigid motions
    p = mesh.points
    rigid = [np.tile(e, (len(p), 1)).ravel() for e in np.eye(3)]
    rigid += [np.cross(e, p).ravel() for e in np.eye(3)]
    for r in rigid:
        assert np.linalg.norm(K @ r) <= 1e-10 * w.max() * np.linalg.norm(r)


def test_mass_matrices(mesh):
    M = consistent_mass(mesh)
    M_ref = ref.consistent_mass(mesh.points, mesh.tets, 1.0)
    assert abs(M - M_ref).max() <= 1e-12
    lumped = lumped_mass(mesh)
    np.testing.assert_allclose(np.repeat(lumped, 3), np.asarray(M.sum(axis=1)).ravel(), rtol=1e-12)
    assert lumped.sum() == pytest.approx(8.0)
    scale = np.linspace(1.0, 2.0, mesh.n_elements)
    np.testing.assert_allclose(np.asarray(consistent_mass(mesh, scale).sum(axis=1)).ravel(),
                               np.repeat(lumped_mass(mesh, scale), 3), rtol=1e-12)


def test_body_force_vectors(mesh):
    unit = body_force_vectors(mesh)
    b = np.array([0.3, -1.0, 2.0])
    f = np.einsum("dnc,d->nc", unit, b)
    np.testing.assert_allclose(f.ravel(), ref.body_force(mesh.points, mesh.tets, b), rtol=1e-12)


def test_pressure_on_a_face_and_on_the_closed_boundary(mesh):
    # z1 has area 4 and outward normal +z: a unit pressure pushes with -4 in z
    np.testing.assert_allclose(pressure_vector(mesh, "z1").sum(axis=0), [0, 0, -4.0], atol=1e-12)
    np.testing.assert_allclose(pressure_vector(mesh, "x0").sum(axis=0), [2.0, 0, 0], atol=1e-12)
    closed = sum(pressure_vector(mesh, name) for name in mesh.facet_sets)
    np.testing.assert_allclose(closed.sum(axis=0), 0.0, atol=1e-12)
    # nodal loads of a uniform pressure on a P1 triangle: area/3 per node
    tri = mesh.facet_set("z1")
    p = mesh.points[tri]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    expected = np.zeros(mesh.n_nodes)
    np.add.at(expected, tri, np.repeat(area / 3, 3).reshape(-1, 3))
    np.testing.assert_allclose(pressure_vector(mesh, "z1")[:, 2], -expected, atol=1e-12)


def test_pressure_rejects_interior_faces():
    mesh = jaxsync.box_beam(2.0, 1.0, 1.0, (2, 1, 1))
    faces = mesh.tets[:, [0, 1, 2]]
    interior = jaxsync.Mesh(mesh.points, mesh.tets, {"inside": faces})
    with pytest.raises(jaxsync.ProblemError, match="interior"):
        pressure_vector(interior, "inside")


def test_block_ell_matvec_equals_csr(mesh):
    import jax.numpy as jnp

    K = ref.stiffness(mesh.points, mesh.tets, 1.0e3, 0.3)
    adjacency = node_adjacency(mesh.tets, mesh.n_nodes)
    ell = BlockEll(jnp.asarray(adjacency), jnp.asarray(block_ell_values(K, adjacency)))
    u = np.random.default_rng(0).standard_normal((mesh.n_nodes, 3))
    np.testing.assert_allclose(ell.matvec(u), (K @ u.ravel()).reshape(-1, 3), rtol=1e-12,
                               atol=1e-12 * abs(K).max())
    # every slot is a real neighbour or padding pointing at the row itself
    assert np.all(adjacency[:, 0] == np.arange(mesh.n_nodes))


def test_symmetric_block_ell_reverse_pass_equals_the_transpose_product(mesh):
    """The symmetric product's own reverse pass against SciPy: the cotangent of u is
    K^T y_bar, that of the blocks y_bar[r, i] u[columns[r, s], j]; a general BlockEll
    (autodiff of the gather) gives the same, and for a non-symmetric matrix K^T y_bar."""
    import jax
    import jax.numpy as jnp

    K = ref.stiffness(mesh.points, mesh.tets, 1.0e3, 0.3)
    adjacency = node_adjacency(mesh.tets, mesh.n_nodes)
    blocks = block_ell_values(K, adjacency)
    rng = np.random.default_rng(1)
    u, y_bar = rng.standard_normal((2, mesh.n_nodes, 3))
    grads = {}
    for symmetric in (True, False):
        def product(b, v, symmetric=symmetric):
            return BlockEll(jnp.asarray(adjacency), b, symmetric=symmetric).matvec(v)

        y, vjp = jax.vjp(product, jnp.asarray(blocks), jnp.asarray(u))
        grads[symmetric] = vjp(jnp.asarray(y_bar))
        np.testing.assert_allclose(y, (K @ u.ravel()).reshape(-1, 3), rtol=1e-12, atol=1e-12 * abs(K).max())
    expected_u = (K.T @ y_bar.ravel()).reshape(-1, 3)
    expected_blocks = y_bar[:, :, None, None] * u[adjacency][:, None, :, :]
    for blocks_bar, u_bar in grads.values():
        np.testing.assert_allclose(u_bar, expected_u, rtol=1e-12, atol=1e-12 * abs(expected_u).max())
        np.testing.assert_allclose(blocks_bar, expected_blocks, rtol=1e-12, atol=1e-14)
    # a non-symmetric matrix keeps autodiff's exact transpose
    skew = K + 0.1 * abs(K).max() * scipy.sparse.triu(K != 0, 1).astype(float)
    ell = BlockEll(jnp.asarray(adjacency), jnp.asarray(block_ell_values(skew.tocsr(), adjacency)))
    _, vjp = jax.vjp(ell.matvec, jnp.asarray(u))
    np.testing.assert_allclose(vjp(jnp.asarray(y_bar))[0], (skew.T @ y_bar.ravel()).reshape(-1, 3),
                               rtol=1e-12, atol=1e-12 * abs(skew).max())
    assert abs(skew - skew.T).max() > 0


def test_element_blocks_assemble_to_the_stiffness(mesh):
    import scipy.sparse as sp

    k_lambda, k_mu = element_blocks(mesh)
    assert k_lambda.shape == (mesh.n_elements, 12, 12)
    ops = assemble_unit_operators(mesh)
    dofs = (3 * mesh.tets[:, :, None] + np.arange(3)).reshape(-1, 12)
    rows, cols = np.repeat(dofs, 12, axis=1).ravel(), np.tile(dofs, (1, 12)).ravel()
    for blocks, K in ((k_lambda, ops.K_lambda), (k_mu, ops.K_mu)):
        assembled = sp.coo_matrix((blocks.ravel(), (rows, cols)), shape=K.shape).tocsr()
        assert abs(assembled - K).max() <= 1e-12 * abs(K).max()
