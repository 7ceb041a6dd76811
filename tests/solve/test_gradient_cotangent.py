"""The material parameters' cotangent through the preassembled stiffness (issue 29, item 4b).

Under a traced Young's modulus E with the Poisson ratio fixed, :class:`Preassembled`
holds the constant blocks of K(E=1, nu) and carries E as the operator's scale
(:attr:`jaxsync.fem.BlockEll.scale`): reverse mode then sums one scalar per step
instead of carrying a cotangent as large as K across the time loop. These tests force
that form on the small cantilever (``scale_min_nodes=0``; by default it starts at 1 500
nodes) and compare it with the previous formulation (traced Lame parameters in the
blocks: the default on the cantilever, or nu traced too), with central finite
differences, single device and two parts, and check the loop carries no array of the
blocks' shape any more.
"""

import jax
import jax.extend as jex
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsync
from jaxsync.errors import ProblemError
from jaxsync.fem.forces import Preassembled

SCALED = Preassembled(scale_min_nodes=0)  # E as the operator's scale whenever E is traced and nu fixed
PARAMS = {"E": 1.0e6, "nu": 0.3, "rho": 1.0, "alpha": 0.5}


@pytest.fixture(scope="module")
def problem():
    return jaxsync.cantilever()


def tip_node(mesh):
    x = mesh.points
    return int(np.argmax(x[:, 0] - 1e-3 * np.abs(x[:, 1]) - 1e-3 * np.abs(x[:, 2])))


def make_loss(problem, names, n_steps=300, save_every=10, fixed=None, **kwargs):
    """The tip's squared vertical history as a function of the parameters ``names`` (the
    others at :data:`PARAMS`, or ``fixed``)."""
    tip, dt = tip_node(problem.mesh), problem.dt
    base = dict(PARAMS, **(fixed or {}))

    def loss(*values):
        v = dict(base, **dict(zip(names, values)))
        p = problem.replace(material=jaxsync.LinearElastic(v["E"], v["nu"], v["rho"]), damping=v["alpha"])
        traj = jaxsync.simulate(p, n_steps, dt=dt, save=save_every, **kwargs)
        return jnp.sum(traj.displacement[:, tip, 2] ** 2) / (1e-4 ** 2)

    return loss


def _extrapolated_difference(f, x0, i, h):
    """Central difference of ``f`` in argument ``i`` with step ``h``, Richardson-extrapolated:
    (4 D(h/2) - D(h)) / 3, error O(h^4) plus round-off ~ eps_f |f| / h."""
    def central(step):
        plus, minus = list(x0), list(x0)
        plus[i] += step
        minus[i] -= step
        return (float(f(*plus)) - float(f(*minus))) / (2 * step)

    return (4 * central(h / 2) - central(h)) / 3


def _check_against_differences(loss, names, grads, rel=1e-6):
    forward = jax.jit(loss)
    x0 = [PARAMS[n] for n in names]
    for i, (name, g) in enumerate(zip(names, grads)):
        fd = _extrapolated_difference(forward, x0, i, 1e-2 * x0[i])
        assert float(g) == pytest.approx(fd, rel=rel), name


# --- the operator -------------------------------------------------------------------------


def _operator(problem, mode, E, nu=0.3):
    return mode.operator(problem.replace(material=jaxsync.LinearElastic(E, nu, 1.0)))


def test_scale_exists_only_for_traced_E_with_fixed_nu(problem):
    seen = {}

    def record(key, E, nu=0.3, mode=SCALED):
        op = _operator(problem, mode, E, nu)
        seen[key] = op.scale
        return jnp.sum(op.matvec(jnp.ones((problem.n_nodes, 3))))

    record("concrete", 1.0e6)
    jax.grad(lambda E: record("traced E", E))(1.0e6)
    jax.grad(lambda E, nu: record("traced E, nu", E, nu), (0, 1))(1.0e6, 0.3)
    jax.grad(lambda E: record("small mesh", E, mode=Preassembled()))(1.0e6)  # 104 nodes < 1 500
    assert seen["concrete"] is None and seen["traced E, nu"] is None and seen["small mesh"] is None
    assert isinstance(seen["traced E"], jax.core.Tracer)
    # a concrete material builds the same operator as before, whatever the threshold
    a, b = _operator(problem, SCALED, 1.0e6), _operator(problem, Preassembled(), 1.0e6)
    assert a.scale is None
    for x, y in zip(a.blocks, b.blocks):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    with pytest.raises(ProblemError, match="scale_min_nodes"):
        Preassembled(scale_min_nodes=-1)


@pytest.mark.parametrize("layout, blocks_dtype", [("grouped", "float64"), ("ell", "float64"),
                                                  ("grouped", "float32")])
def test_scaled_product_and_reverse_pass_equal_the_lame_blocks(problem, layout, blocks_dtype):
    # y = E (K_1 u) and its vjp in (E, u) against the blocks lam K_lambda + mu K_mu with E
    # traced through lam and mu (the previous formulation: nu traced too)
    u = jnp.asarray(np.random.default_rng(0).standard_normal((problem.n_nodes, 3)))
    y_bar = jnp.asarray(np.random.default_rng(1).standard_normal((problem.n_nodes, 3)))
    mode = Preassembled(layout=layout, blocks_dtype=blocks_dtype, scale_min_nodes=0)

    def scaled(E, u):
        return _operator(problem, mode, E).matvec(u)

    def lame(E, nu, u):
        return _operator(problem, mode, E, nu).matvec(u)

    y, vjp = jax.vjp(scaled, 1.0e6, u)
    y_ref, vjp_ref = jax.vjp(lame, 1.0e6, 0.3, u)
    (E_bar, u_bar), (E_ref, _, u_ref) = vjp(y_bar), vjp_ref(y_bar)
    # float32: K_1 rounded instead of K (both about 6e-8 relative), the diagonals are
    # minus the float64 sums of the rounded rows either way
    rel = 1e-12 if blocks_dtype == "float64" else 1e-6
    scale = float(jnp.max(jnp.abs(y_ref)))
    np.testing.assert_allclose(y, y_ref, rtol=0, atol=rel * scale)
    np.testing.assert_allclose(u_bar, u_ref, rtol=0, atol=rel * float(jnp.max(jnp.abs(u_ref))))
    assert float(E_bar) == pytest.approx(float(E_ref), rel=rel)
    # and E's cotangent is <K_1 y_bar, u> = <y_bar, K u> / E
    assert float(E_bar) == pytest.approx(float(jnp.sum(y_bar * y_ref)) / 1.0e6, rel=rel)


# --- gradients of runs --------------------------------------------------------------------


@pytest.mark.parametrize("partitions", [None, pytest.param(2, marks=pytest.mark.slow)])
def test_gradient_in_E_equals_previous_formulation_and_differences(problem, partitions):
    kwargs = {} if partitions is None else {"partitions": partitions}
    names = ("E", "alpha")
    loss = make_loss(problem, names, mode=SCALED, **kwargs)
    grads = jax.jit(jax.grad(loss, (0, 1)))(PARAMS["E"], PARAMS["alpha"])
    # the previous formulation: the Lame blocks, E traced through them (the default on
    # this small mesh), and nu traced as well
    before = jax.jit(jax.grad(make_loss(problem, names, **kwargs), (0, 1)))(PARAMS["E"], PARAMS["alpha"])
    with_nu = jax.jit(jax.grad(make_loss(problem, ("E", "nu", "alpha"), mode=SCALED, **kwargs), (0, 2)))(
        PARAMS["E"], PARAMS["nu"], PARAMS["alpha"])
    for g, b, c in zip(grads, before, with_nu):
        assert float(g) == pytest.approx(float(b), rel=1e-11)
        assert float(g) == pytest.approx(float(c), rel=1e-11)
    _check_against_differences(loss, names, grads)


def test_gradient_in_E_and_nu_equals_differences(problem):
    names = ("E", "nu")
    loss = make_loss(problem, names, mode=SCALED)
    _check_against_differences(loss, names, jax.jit(jax.grad(loss, (0, 1)))(PARAMS["E"], PARAMS["nu"]))


@pytest.mark.parametrize("partitions", [None, pytest.param(2, marks=pytest.mark.slow)])
def test_gradient_in_rho_and_damping_equals_differences(problem, partitions):
    kwargs = {} if partitions is None else {"partitions": partitions}
    names = ("rho", "alpha")
    loss = make_loss(problem, names, mode=SCALED, **kwargs)
    _check_against_differences(loss, names, jax.jit(jax.grad(loss, (0, 1)))(PARAMS["rho"], PARAMS["alpha"]))


def test_float32_blocks_give_E_a_float64_cotangent(problem):
    # the previous formulation sums the blocks' float32 cotangents over the time loop
    # (measured 1.0e-4 relative off the float64 gradient here); under the scale E's
    # cotangent is a float64 sum, off only through the rounded blocks' effect on the run
    # (measured 4.7e-6)
    names = ("E",)
    exact = jax.jit(jax.grad(make_loss(problem, names, n_steps=2000, mode=SCALED)))(PARAMS["E"])
    f32 = Preassembled(blocks_dtype="float32", scale_min_nodes=0)
    scaled = jax.jit(jax.grad(make_loss(problem, names, n_steps=2000, mode=f32)))(PARAMS["E"])
    lame = jax.jit(jax.grad(make_loss(problem, names, n_steps=2000,
                                      mode=Preassembled(blocks_dtype="float32"))))(PARAMS["E"])
    error_scaled = abs(float(scaled) / float(exact) - 1)
    error_lame = abs(float(lame) / float(exact) - 1)
    assert error_scaled < 1e-5
    assert error_scaled < error_lame / 10


# --- what the time loop carries ------------------------------------------------------------


def _loop_carries(jaxpr, out):
    """Shapes of the loop-carried values of every scan and while loop in ``jaxpr``."""
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "scan":
            first = eqn.params["num_consts"]
            carried = eqn.params["jaxpr"].jaxpr.invars[first:first + eqn.params["num_carry"]]
            out.extend(tuple(v.aval.shape) for v in carried)
        elif eqn.primitive.name == "while":
            out.extend(tuple(v.aval.shape) for v in eqn.params["body_jaxpr"].jaxpr.invars[eqn.params["body_nconsts"]:])
        for sub in jex.core.jaxprs_in_params(eqn.params):
            _loop_carries(sub, out)
    return out


@pytest.mark.parametrize("partitions", [None, 2])
def test_loop_carries_no_cotangent_of_the_blocks(problem, partitions):
    kwargs = {} if partitions is None else {"partitions": partitions}
    if partitions is None:
        blocks = _operator(problem, SCALED, 1.0e6).blocks
    else:
        from jaxsync.solve.executors import DistributedParts

        layout = DistributedParts(problem, partitions).layout
        blocks = SCALED.part_operators(problem, layout.parts, layout.n_local).blocks
    # the blocks' shapes (of one part: under shard_map a device holds (1, ...) of them)
    shapes = {tuple(np.shape(b))[-4:] for b in blocks}

    def blocks_carried(names):
        loss = make_loss(problem, names, n_steps=100, mode=SCALED, **kwargs)
        jaxpr = jax.make_jaxpr(jax.grad(loss, tuple(range(len(names)))))(*[PARAMS[n] for n in names]).jaxpr
        return {c for c in _loop_carries(jaxpr, []) if c[-4:] in shapes}

    assert not blocks_carried(("E", "alpha"))
    assert not blocks_carried(("E", "rho", "alpha"))
    # the previous formulation (nu traced: E and nu in the Lame blocks) carries the blocks'
    # cotangent across the loop, which this test exists to catch
    assert blocks_carried(("E", "nu", "alpha"))
