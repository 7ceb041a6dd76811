"""The degree-grouped stiffness layout (jaxsync.fem.GroupedEll), the parts' reverse
Cuthill-McKee local order (jaxsync.parallel.local_order) and the float32 blocks option of
Preassembled: products against SciPy's CSR product on a mesh whose node degree varies (a
small generated coronary tree), reverse passes against SciPy's transpose product and
autodiff, trajectories (one device, 2 parts with psum and with deep halos) against a
SciPy reference written in the test, and the float32 trajectories within their bound."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse.linalg as spla

import fem_reference as ref
import jaxsync
from jaxsync import ProblemError
from jaxsync.fem import (
    BlockEll,
    GroupedEll,
    block_ell_values,
    degree_widths,
    grouped_layout,
    in_compact_form,
    node_adjacency,
    row_degrees,
    split_diagonal,
)
from jaxsync.fem.forces import Preassembled
from jaxsync.parallel import PartLayout, local_order, ordered_parts

MATERIAL = jaxsync.LinearElastic(6.26e6, 0.4, 1.0)
BODY_FORCE = np.array([2.0e3, -1.0e3, 5.0e2])


@pytest.fixture(scope="module")
def tree():
    """A small coronary tree: node degrees 7 to 18 (mean 11), three degree groups."""
    return jaxsync.coronary_mesh(target_elements=3500)


@pytest.fixture(scope="module")
def stiffness(tree):
    return ref.stiffness(tree.points, tree.tets, MATERIAL.E, MATERIAL.nu)


def grouped(K, adjacency, dtype=jnp.float64, compact=False):
    """GroupedEll of the SciPy matrix K on ``adjacency`` (float32: split diagonal;
    ``compact``: the one-gather product)."""
    rows, columns, (blocks,) = grouped_layout(adjacency, block_ell_values(K, adjacency))
    blocks, diagonal = tuple(jnp.asarray(b) for b in blocks), None
    if dtype == jnp.float32:
        blocks, diagonal = zip(*(split_diagonal(b, jnp.float32) for b in blocks))
    return GroupedEll(columns=tuple(jnp.asarray(c) for c in columns), blocks=tuple(blocks), symmetric=True,
                      rows=tuple(None if r is None else jnp.asarray(r) for r in rows), n_rows=adjacency.shape[0],
                      diagonal=None if diagonal is None else tuple(diagonal), compact=compact)


def test_degree_groups_follow_the_mean_degree(tree):
    adjacency = node_adjacency(tree.tets, tree.n_nodes)
    degree = row_degrees(adjacency)
    assert degree.max() == adjacency.shape[1] and degree.min() >= 4 and degree.max() >= 1.4 * degree.mean()
    widths = degree_widths(degree)
    assert len(widths) >= 2 and widths[-1] == degree.max()
    # the stored slots follow the mean degree: within 25 % of the real blocks (one ELL: 1.6x)
    slots = sum(int(((degree > lo) & (degree <= w)).sum()) * w for lo, w in zip((0,) + widths[:-1], widths))
    assert slots <= 1.25 * degree.sum() < 0.8 * adjacency.size
    # a structured beam keeps one group, as wide as its largest degree: a second would
    # save too few slots (7-11 %) to pay for scattering the rows
    beam = jaxsync.box_beam(25.0, 1.0, 1.0, (60, 8, 8))
    beam_adjacency = node_adjacency(beam.tets, beam.n_nodes)
    assert degree_widths(row_degrees(beam_adjacency)) == (beam_adjacency.shape[1],)
    coarse = jaxsync.cantilever().mesh  # 104 nodes: a second group would cost more than it saves
    assert len(degree_widths(row_degrees(node_adjacency(coarse.tets, coarse.n_nodes)))) == 1


def test_degree_widths_minimize_slots_plus_a_cost_per_group():
    """Against a brute force over every set of widths of a small histogram."""
    import itertools

    rng = np.random.default_rng(0)
    degrees = rng.choice([4, 7, 8, 11, 12, 13, 18, 19, 25], size=500, p=[.05, .1, .1, .3, .1, .1, .1, .1, .05])
    values = np.unique(degrees)

    def cost(widths):
        lows = (0,) + widths[:-1]
        slots = sum(int(((degrees > lo) & (degrees <= w)).sum()) * w for lo, w in zip(lows, widths))
        return slots + (3.0 * len(degrees) if len(widths) > 1 else 0.0) + 500.0 * (len(widths) - 1)

    best = min((c + (values[-1],) for k in range(4) for c in itertools.combinations(values[:-1], k)), key=cost)
    assert cost(degree_widths(degrees)) == cost(tuple(int(v) for v in best))


@pytest.mark.parametrize("compact", [False, True], ids=["fused", "compact"])
@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_grouped_product_equals_scipy_csr(tree, stiffness, dtype, compact):
    K = stiffness
    adjacency = node_adjacency(tree.tets, tree.n_nodes)
    op = grouped(K, adjacency, dtype, compact)
    assert len(op.columns) >= 2 and op.rows[0] is not None
    u = np.random.default_rng(0).standard_normal((tree.n_nodes, 3))
    expected = (K @ u.ravel()).reshape(-1, 3)
    y = jax.jit(lambda o, v: o.matvec(v))(op, jnp.asarray(u))
    assert y.dtype == jnp.float64
    # float32 off-diagonal blocks: rounded to 6e-8 relative, summed in float64
    tol = 1e-13 if dtype == jnp.float64 else 2e-7
    np.testing.assert_allclose(y, expected, rtol=0, atol=tol * abs(expected).max())
    # and a rigid translation gives no force, as K's own rows (they sum to zero)
    shift = np.broadcast_to([1.0, -2.0, 0.5], (tree.n_nodes, 3))
    assert abs(np.asarray(op.matvec(jnp.asarray(shift)))).max() < 1e-12 * abs(K).max()


@pytest.mark.parametrize("compact", [False, True], ids=["fused", "compact"])
def test_grouped_reverse_pass_equals_the_transpose_product_and_autodiff(tree, stiffness, compact):
    """The symmetric product's own reverse pass: u's cotangent K^T y_bar (SciPy), the
    blocks' the outer product y_bar[rows, i] u[columns, j]; autodiff of the same product
    (symmetric=False) gives the same. In both forms of the product."""
    K = stiffness
    adjacency = node_adjacency(tree.tets, tree.n_nodes)
    op = grouped(K, adjacency, compact=compact)
    rng = np.random.default_rng(1)
    u, y_bar = rng.standard_normal((2, tree.n_nodes, 3))
    grads = {}
    for symmetric in (True, False):
        def product(blocks, v, symmetric=symmetric):
            return dataclasses.replace(op, blocks=blocks, symmetric=symmetric).matvec(v)

        # one compiled program (op by op, the reverse pass is slow to dispatch)
        grads[symmetric] = jax.jit(lambda blocks, v, w, product=product: jax.vjp(product, blocks, v)[1](w))(
            op.blocks, jnp.asarray(u), jnp.asarray(y_bar))
    expected_u = (K.T @ y_bar.ravel()).reshape(-1, 3)
    for blocks_bar, u_bar in grads.values():
        np.testing.assert_allclose(u_bar, expected_u, rtol=0, atol=1e-12 * abs(expected_u).max())
        for r, c, b in zip(op.rows, op.columns, blocks_bar):
            rows = np.asarray(r)
            real = rows < tree.n_nodes
            outer = y_bar[rows[real]][:, :, None, None] * u[np.asarray(c)[real]][:, None, :, :]
            np.testing.assert_allclose(np.asarray(b)[real], outer, rtol=1e-12, atol=1e-14)
    for a, b in zip(jax.tree_util.tree_leaves(grads[True]), jax.tree_util.tree_leaves(grads[False])):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * float(abs(b).max()))


def test_float32_blocks_reverse_pass_against_autodiff(tree, stiffness):
    """The split storage (float32 off-diagonal blocks, float64 diagonal = minus their sum):
    gradients with respect to a stiffness scale through the blocks, the cast and the
    diagonal agree with autodiff of the same product to float32 rounding."""
    adjacency = node_adjacency(tree.tets, tree.n_nodes)
    rows, columns, (blocks,) = grouped_layout(adjacency, block_ell_values(stiffness, adjacency))
    u = jnp.asarray(np.random.default_rng(2).standard_normal((tree.n_nodes, 3)))
    weights = jnp.asarray(np.random.default_rng(3).standard_normal((tree.n_nodes, 3)))

    def energy(scale, symmetric):
        parts = [split_diagonal(scale * jnp.asarray(b), jnp.float32) for b in blocks]
        op = GroupedEll(columns=tuple(jnp.asarray(c) for c in columns), blocks=tuple(p[0] for p in parts),
                        symmetric=symmetric, rows=tuple(None if r is None else jnp.asarray(r) for r in rows),
                        n_rows=tree.n_nodes, diagonal=tuple(p[1] for p in parts))
        return jnp.sum(weights * op.matvec(u))

    own, auto = (jax.jit(jax.grad(energy), static_argnums=1)(1.5, s) for s in (True, False))
    exact = float(jnp.sum(weights * jnp.asarray((stiffness @ np.asarray(u).ravel()).reshape(-1, 3))))
    assert abs(float(own) - float(auto)) <= 1e-6 * abs(exact)
    assert abs(float(own) - exact) <= 1e-6 * abs(exact)


def test_stacked_parts_share_the_groups_under_vmap(tree):
    """Parts of different degree mixes padded to the same groups: each part's product
    under vmap equals its own SciPy product; padding rows get zero force."""
    part_info = jaxsync.partition(tree, 3, seed=0)
    problem = jaxsync.Problem(tree, MATERIAL)
    layout = PartLayout.of(part_info)
    op = Preassembled().part_operators(problem, layout.parts, layout.n_local)
    assert isinstance(op, GroupedEll) and op.n_rows == layout.n_local
    assert all(np.shape(c)[0] == 3 for c in op.columns)
    rng = np.random.default_rng(4)
    u = rng.standard_normal((3, layout.n_local, 3))
    y = np.asarray(jax.vmap(lambda o, v: o.matvec(v))(op, jnp.asarray(u)))
    for p, part in enumerate(layout.parts):
        K = ref.stiffness(tree.points, tree.tets[part_info.parts[p].elements], MATERIAL.E, MATERIAL.nu)
        n = part.n_local
        full = np.zeros((tree.n_nodes, 3))
        full[part.nodes] = u[p, :n]
        expected = (K @ full.ravel()).reshape(-1, 3)[part.nodes]
        np.testing.assert_allclose(y[p, :n], expected, rtol=0, atol=1e-12 * abs(expected).max())
        assert np.all(y[p, n:] == 0.0)


def test_parts_local_nodes_in_reverse_cuthill_mckee_order(tree):
    part_info = jaxsync.partition(tree, 2, seed=0)
    layout = PartLayout.of(part_info)
    for before, after in zip(part_info.parts, layout.parts):
        # the same nodes, elements and shared nodes (in the same order: records unchanged)
        assert sorted(after.nodes) == sorted(before.nodes)
        np.testing.assert_array_equal(after.nodes[after.local_tets], before.nodes[before.local_tets])
        np.testing.assert_array_equal(after.shared_nodes, before.shared_nodes)
        np.testing.assert_array_equal(after.shared_interface, before.shared_interface)

        def spread(part):
            tets = part.local_tets
            return np.abs(tets[:, :, None] - tets[:, None, :]).mean()

        assert spread(after) < 0.2 * spread(before)
        np.testing.assert_array_equal(local_order(after), np.arange(after.n_local))  # idempotent
    assert ordered_parts(layout.partition) is layout.partition
    # split and merge still map the global numbering
    field = np.random.default_rng(5).standard_normal((tree.n_nodes, 3))
    local = np.asarray(layout.split(field))
    for p, part in enumerate(layout.parts):
        np.testing.assert_array_equal(local[p, :part.n_local], field[part.nodes])
    np.testing.assert_array_equal(np.asarray(layout.merge(local)), field)
    halo = jaxsync.parallel.exchange.halo_partition(part_info, 2)
    halo_layout = PartLayout.of(halo)
    for p, part in enumerate(halo_layout.parts):
        owned = part.nodes[halo_layout.partition.owned_local[p]]
        np.testing.assert_array_equal(np.sort(owned), np.sort(halo.parts[p].nodes[halo.owned_local[p]]))


def reference_run(mesh, problem, n_steps):
    """The explicit run of ``problem`` (body force, clamped inlet and outlets, initial
    displacement and velocity) written out with SciPy (tests/fem_reference.py)."""
    K = ref.stiffness(mesh.points, mesh.tets, MATERIAL.E, MATERIAL.nu)
    M = ref.consistent_mass(mesh.points, mesh.tets, MATERIAL.rho)
    m = ref.lumped_mass(mesh.points, mesh.tets, MATERIAL.rho)
    f = ref.body_force(mesh.points, mesh.tets, BODY_FORCE)
    fixed, _ = problem.dirichlet_dofs()
    free = np.setdiff1d(np.arange(mesh.n_dofs), fixed)
    dt, alpha = problem.dt, problem.damping
    d0 = problem.initial_displacement.ravel().copy()
    v0 = problem.initial_velocity.ravel().copy()
    d0[fixed] = 0.0
    rhs = f - alpha * (M @ v0) - K @ d0
    a0 = np.zeros_like(d0)
    a0[free] = spla.spsolve(M[free][:, free].tocsc(), rhs[free])
    dm1 = d0 - dt * v0 + 0.5 * dt**2 * a0
    dm1[fixed] = 0.0
    return ref.central_difference(K, m, lambda t: f, alpha, dt, d0, dm1, fixed, np.zeros(len(fixed)), n_steps)


@pytest.fixture(scope="module")
def vessel_problem(tree):
    rng = np.random.default_rng(6)
    return jaxsync.Problem(
        tree, MATERIAL, dirichlet=(jaxsync.Dirichlet("inlet"), jaxsync.Dirichlet("outlet")),
        loads=(jaxsync.BodyForce(BODY_FORCE, jaxsync.Constant()),), damping=0.5,
        initial_displacement=1e-4 * rng.standard_normal((tree.n_nodes, 3)),
        initial_velocity=1e-2 * rng.standard_normal((tree.n_nodes, 3)))


@pytest.fixture(scope="module")
def vessel_reference(tree, vessel_problem):
    return reference_run(tree, vessel_problem, 300)


@pytest.mark.parametrize("product", ["fused", "compact"])
@pytest.mark.parametrize("layout", ["grouped", "ell"])
def test_one_device_trajectory_equals_scipy_reference(vessel_problem, vessel_reference, layout, product):
    run = jaxsync.simulate(vessel_problem, 300, save=100, mode=Preassembled(layout=layout, product=product))
    expected = vessel_reference[::100]
    got = np.asarray(run.displacement).reshape(len(expected), -1)
    assert abs(got - expected).max() <= 1e-11 * abs(expected).max()


@pytest.mark.parametrize("sync", ["psum", "halo"])
def test_two_parts_trajectory_equals_scipy_reference(vessel_problem, vessel_reference, sync):
    """Parts in RCM local order with the grouped layout, synchronized by psum or by deep
    halos (depth 2): the merged field equals the global SciPy run to round-off."""
    kwargs = {"sync": jaxsync.Halo(2)} if sync == "halo" else {"sync": "psum"}
    run = jaxsync.simulate(vessel_problem, 300, save=100, partitions=2, **kwargs)
    expected = vessel_reference[::100]
    got = np.asarray(run.displacement).reshape(len(expected), -1)
    assert abs(got - expected).max() <= 1e-11 * abs(expected).max()


FLOAT32_BOUND = 1e-6
"""The bounds of Preassembled(blocks_dtype="float32") documented in
docs/guides/performance.md, as the largest displacement error over the largest
displacement: 1e-6 for a run loaded from rest (measured over 1e5 steps: 4e-8 on the
cantilever, 4e-7 on the vessel); and where the initial fields excite every mode (rough
initial displacement and velocity, little damping), 1e-6 per 1 000 steps (the error grows
with the steps: measured 5e-7 after 1 000 steps, 5e-5 after 1e5)."""


@pytest.mark.parametrize("which", ["cantilever", "rough vessel"])
def test_float32_blocks_trajectory_within_the_documented_bound(vessel_problem, which):
    problem = jaxsync.cantilever() if which == "cantilever" else vessel_problem
    n_steps = 4000 if which == "cantilever" else 1000
    exact = np.asarray(jaxsync.simulate(problem, n_steps, save=n_steps // 4).displacement)
    single = np.asarray(jaxsync.simulate(problem, n_steps, save=n_steps // 4,
                                         mode=Preassembled(blocks_dtype="float32")).displacement)
    error = abs(single - exact).max() / abs(exact).max()
    bound = FLOAT32_BOUND if which == "cantilever" else FLOAT32_BOUND * n_steps / 1000
    assert 0.0 < error <= bound


@pytest.mark.parametrize("which", [pytest.param("rough vessel", marks=pytest.mark.slow), "cantilever"])
def test_float32_blocks_gradient_follows_float64(vessel_problem, which):
    """A loss of the displacement after n steps differentiated with respect to E with
    float32 blocks and with float64 ones: within the documented accuracy (the blocks'
    cotangents are float32 and summed over the steps in float32: measured 2e-6 on the
    vessel, 6.5e-4 on the cantilever's smooth bending over 2 000 steps)."""
    from jaxsync.fem import advance, build_system, initial_state

    problem = vessel_problem if which == "rough vessel" else jaxsync.cantilever()
    n_steps, bound = (200, 1e-5) if which == "rough vessel" else (2000, 2e-3)

    def loss(E, mode):
        changed = dataclasses.replace(problem, material=dataclasses.replace(problem.material, E=E))
        system = build_system(changed, problem.dt, mode)
        state, _ = advance(system, initial_state(changed, system), 1, n_steps)
        return jnp.sum(state.displacement ** 2)

    g64 = jax.grad(loss)(problem.material.E, Preassembled())
    g32 = jax.grad(loss)(problem.material.E, Preassembled(blocks_dtype="float32"))
    assert np.isfinite(float(g32)) and abs(float(g32) - float(g64)) <= bound * abs(float(g64))


def test_block_ell_compact_product_and_its_reverse_pass_equal_scipy(tree, stiffness):
    """One block ELL as wide as the largest degree (padding slots included), with a
    scale: the compact product equals SciPy's, and its reverse pass SciPy's transpose
    product (u) and <K_1 y_bar, u> (the scale)."""
    adjacency = node_adjacency(tree.tets, tree.n_nodes)
    rng = np.random.default_rng(4)
    u, y_bar = rng.standard_normal((2, tree.n_nodes, 3))
    op = BlockEll(jnp.asarray(adjacency), jnp.asarray(block_ell_values(stiffness, adjacency)), symmetric=True,
                  scale=jnp.asarray(2.5), compact=True)
    y, pullback = jax.jit(lambda o, v: jax.vjp(lambda s, w: dataclasses.replace(o, scale=s).matvec(w),
                                               o.scale, v))(op, jnp.asarray(u))
    expected = 2.5 * (stiffness @ u.ravel()).reshape(-1, 3)
    np.testing.assert_allclose(y, expected, rtol=0, atol=1e-13 * abs(expected).max())
    scale_bar, u_bar = pullback(jnp.asarray(y_bar))
    K_y_bar = (stiffness @ y_bar.ravel()).reshape(-1, 3)
    np.testing.assert_allclose(u_bar, 2.5 * K_y_bar, rtol=0, atol=1e-13 * abs(K_y_bar).max() * 2.5)
    assert abs(float(scale_bar) - float(np.sum(K_y_bar * u))) <= 1e-12 * float(np.sum(abs(K_y_bar * u)))


def test_in_compact_form_keeps_the_product_and_leaves_other_operators(tree, stiffness):
    """The start's operators (jaxsync.fem.start_levels): a fused BlockEll and
    GroupedEll turned compact still compute SciPy's K u; an operator without stored blocks
    is returned as it is."""
    adjacency = node_adjacency(tree.tets, tree.n_nodes)
    u = np.random.default_rng(5).standard_normal((tree.n_nodes, 3))
    expected = (stiffness @ u.ravel()).reshape(-1, 3)
    for op in (BlockEll(jnp.asarray(adjacency), jnp.asarray(block_ell_values(stiffness, adjacency)), symmetric=True),
               grouped(stiffness, adjacency)):
        compact = in_compact_form(op)
        assert not op.compact and compact.compact and type(compact) is type(op)
        np.testing.assert_allclose(jax.jit(lambda o: o.matvec(jnp.asarray(u)))(compact), expected,
                                   rtol=0, atol=1e-13 * abs(expected).max())
        assert in_compact_form(compact) is compact
    other = object()
    assert in_compact_form(other) is other


def test_auto_product_is_chosen_by_the_run_length():
    """Preassembled(product="auto"): compact for runs of fewer slot-steps than
    COMPACT_SLOT_STEPS, fused for longer ones and where the run length is not known;
    a product given explicitly, and a finite-strain problem, stay as they are."""
    from jaxsync.fem.forces import COMPACT_SLOT_STEPS, run_force_model

    problem = jaxsync.cantilever()
    slots = int(np.prod(problem.operators.block_ell[0].shape))
    below, above = int(COMPACT_SLOT_STEPS // slots) - 1, int(COMPACT_SLOT_STEPS // slots) + 1
    assert run_force_model("preassembled", problem, below).product == "compact"
    assert run_force_model("preassembled", problem, above).product == "fused"
    assert run_force_model(Preassembled(product="fused"), problem, 10).product == "fused"
    assert run_force_model(Preassembled(product="compact"), problem, 10 ** 9).product == "compact"
    assert run_force_model("recompute", problem, 10) == "recompute"
    assert not Preassembled().operator(problem).compact  # no run length: the fast step
    assert Preassembled(product="compact").operator(problem).compact
    neo = dataclasses.replace(problem, material=jaxsync.NeoHookean(1e6, 0.45, 1.0))
    assert run_force_model("preassembled", neo, 10) == Preassembled()
    with pytest.raises(ProblemError, match="product"):
        Preassembled(product="einsum")


def test_preassembled_options_are_checked():
    with pytest.raises(ProblemError, match="layout='grouped'"):
        Preassembled(layout="ell", blocks_dtype="float32")
    with pytest.raises(ProblemError, match="blocks_dtype"):
        Preassembled(blocks_dtype="float16")
    with pytest.raises(ProblemError, match="layout"):
        Preassembled(layout="csr")
    problem = jaxsync.cantilever()
    assert type(Preassembled(layout="ell").operator(problem)) is BlockEll
    op = Preassembled(blocks_dtype="float32").operator(problem)
    assert all(b.dtype == jnp.float32 for b in op.blocks) and all(d.dtype == jnp.float64 for d in op.diagonal)
