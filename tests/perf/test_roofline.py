"""Bytes and flops per stage (jaxsync.perf.roofline): byte counts against the real arrays,
flop counts against an independent count of the operations in the traced programs
(jaxprs), the surrogate against its parameter shapes, achieved rates by hand."""

import dataclasses
import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsync
from jaxsync import ProblemError
from jaxsync.fem import SolverState, apply_dirichlet, build_system, central_difference
from jaxsync.perf.roofline import (
    ELEMENT_FLOPS,
    StageCost,
    achieved,
    achieved_stages,
    roofline_table,
    step_costs,
    step_costs_for,
    surrogate_costs,
    surrogate_flop_breakdown,
    surrogate_step_cost,
)
from jaxsync.surrogate import refill_predict
from jaxsync.surrogate.models import LSTMArchitecture, init_params

ELEMENTWISE = {"add", "sub", "mul", "div", "neg", "logistic", "tanh", "exp", "max", "min"}


def written_flops(fn, *args) -> int:
    """Floating-point operations in the jaxpr of ``fn(*args)``: one per element of each
    elementwise float op (transcendentals included), 2 k per output of a contraction of
    length k, n_in - n_out for a sum, one per update of a scatter-add; scan bodies times
    their length; scalar (rank-0) ops left out (they are per call, not per entry)."""

    def count(jaxpr, mult):
        total = 0
        for eqn in jaxpr.eqns:
            name = eqn.primitive.name
            if name == "scan":
                total += count(eqn.params["jaxpr"].jaxpr, mult * eqn.params["length"])
                continue
            if name == "scatter-add":  # its update_jaxpr is the scalar add, counted here
                total += mult * math.prod(eqn.invars[2].aval.shape)
                continue
            subs = [getattr(v, "jaxpr", v) for v in eqn.params.values()
                    if hasattr(getattr(v, "jaxpr", v), "eqns")]
            if subs:
                total += sum(count(sub, mult) for sub in subs)
                continue
            out = eqn.outvars[0].aval
            if not jnp.issubdtype(out.dtype, jnp.floating) or out.ndim == 0:
                continue
            size = math.prod(out.shape)
            if name == "dot_general":
                (contract, _), _ = eqn.params["dimension_numbers"]
                total += mult * 2 * size * math.prod(eqn.invars[0].aval.shape[i] for i in contract)
            elif name in ELEMENTWISE:
                total += mult * size
            elif name == "reduce_sum":
                total += mult * (math.prod(eqn.invars[0].aval.shape) - size)
        return total

    return count(jax.make_jaxpr(fn)(*args).jaxpr, 1)


@pytest.fixture(scope="module")
def problem():
    return jaxsync.cantilever(jaxsync.box_beam(25.0, 1.0, 1.0, (8, 1, 1)))


def test_matvec_bytes_are_the_arrays_of_a_real_block_ell(problem):
    # the model counts one block ELL as wide as the largest degree (Preassembled's "ell"
    # layout); the default degree-grouped layout streams fewer slots on unstructured meshes
    from jaxsync.fem.forces import Preassembled

    K = build_system(problem, problem.dt, Preassembled(layout="ell")).stiffness
    n, width = K.columns.shape
    u = np.zeros((n, 3))
    cost = step_costs_for(problem)["t_m"]
    # blocks and column indices streamed once, u read once, y written once
    assert cost.bytes == K.columns.nbytes + K.blocks.nbytes + u.nbytes + K.matvec(u).nbytes
    assert cost.flops == 2 * K.blocks.size  # multiply + add per stored block entry
    # the written operations: 9 n w products, 9 n w - 3 n additions (first term not added)
    assert written_flops(K.matvec, jnp.asarray(u)) == 2 * K.blocks.size - 3 * n
    assert step_costs_for(problem)["t_e"] == StageCost("t_e", 0, 0)


def test_matvec_slots_are_those_of_the_grouped_operator_on_an_unstructured_mesh():
    """On a vessel the default layout groups rows by degree: the model counts the slots the
    real operator stores (rounded up per row), fewer than one ELL as wide as the largest
    degree."""
    from jaxsync.fem import node_adjacency
    from jaxsync.fem.forces import Preassembled

    mesh = jaxsync.vessel_mesh(None, length=2.0, radius=0.5, wall=0.3, size=0.15)
    problem = jaxsync.Problem(mesh, dirichlet=[jaxsync.Dirichlet("inlet")])
    K = Preassembled().operator(problem)
    slots = sum(int(np.prod(np.shape(c))) for c in K.columns)
    n = problem.n_nodes
    cost = step_costs_for(problem)["t_m"]
    assert cost.flops == 18 * n * -(-slots // n)
    assert -(-slots // n) < node_adjacency(mesh.tets, n).shape[1]


def test_update_counts_against_the_real_arrays(problem):
    system = build_system(problem, problem.dt)
    n = problem.mesh.n_nodes
    d = jnp.zeros((n, 3))
    state = SolverState(d, d, jnp.asarray(3, dtype=jnp.int32))
    cost = step_costs_for(problem)["t_o"]
    n_loads = system.load_vectors.shape[0]
    assert n_loads == 1
    # read d(n), d(n-1), mass, loads, Dirichlet mask and values; write d(n+1)
    assert cost.bytes == (2 * d.nbytes + system.mass.nbytes + system.load_vectors.nbytes
                          + system.fixed.nbytes + system.fixed_values.nbytes + d.nbytes)
    update = lambda s: apply_dirichlet(system, central_difference(system, s, jnp.zeros((n, 3))), 0.0)  # noqa: E731
    assert cost.flops == written_flops(update, state) == 3 * n * (8 + 2 * n_loads)


def test_recompute_counts_against_the_element_force_code(problem):
    system = build_system(problem, problem.dt, "recompute")
    K = system.stiffness
    m, n = problem.mesh.n_elements, problem.mesh.n_nodes
    u = jnp.zeros((n, 3))
    costs = step_costs_for(problem, mode="recompute")
    gathered = np.asarray(K.points)[np.asarray(K.tets)]  # (m, 4, 3) coordinates per element
    assert costs["t_e"].bytes == K.tets.nbytes + gathered.nbytes + np.asarray(u)[np.asarray(K.tets)].nbytes
    assert costs["t_m"].bytes == K.weight.nbytes + np.zeros((m, 4, 3)).nbytes
    from jaxsync.fem.forces import element_forces

    per_element = written_flops(lambda x: element_forces(K.points, K.tets, x, K.lam, K.mu), u) / m
    assert costs["t_e"].flops / m == per_element == sum(ELEMENT_FLOPS.values()) == 264
    assert costs["t_e"].flops + costs["t_m"].flops == written_flops(K.matvec, u)


def test_per_part_costs_match_the_part_systems(problem):
    from jaxsync.fem.forces import Preassembled
    from jaxsync.parallel import PartLayout, part_systems

    part_info = jaxsync.partition(problem.mesh, 2, seed=0)
    system = build_system(problem, problem.dt)
    per_part = step_costs_for(problem, part_info)
    assert len(per_part) == 2
    for part, costs in zip(part_info.parts, per_part):
        # the part's own system at its own size, as jaxsync.perf.timing times it
        alone = part_systems(problem, system, PartLayout.of(dataclasses.replace(part_info, parts=(part,))),
                             Preassembled(layout="ell")).system.stiffness
        assert costs["t_m"].bytes == alone.columns.nbytes + alone.blocks.nbytes + 2 * 24 * part.n_local
        n_sh, n_a = part.n_shared, part_info.n_interface
        assert n_sh > 0
        assert costs["t_s"].bytes == 8 * n_sh + 4 * 24 * n_sh + 3 * 24 * n_a
        assert costs["t_s"].flops == 3 * n_sh + 3 * n_a


def test_step_costs_by_hand():
    costs = step_costs(10, width=5, n_load_vectors=2, n_shared=2, n_interface=3)
    assert costs["t_m"] == StageCost("t_m", 10 * 5 * 76 + 480, 10 * 5 * 18)
    assert costs["t_o"] == StageCost("t_o", 30 * (8 * 7 + 1), 30 * 12)
    # indices 16, zeroed interface 72, scatter 48 + 48, reduce 72 + 72, gather 48 + 48
    assert costs["t_s"] == StageCost("t_s", 424, 15)
    nosync = step_costs(10, width=5)
    assert nosync["t_s"] == StageCost("t_s", 0, 0)
    recompute = step_costs(10, n_elements=7, mode="recompute")
    assert recompute["t_e"] == StageCost("t_e", 7 * 208, 7 * 264)
    assert recompute["t_m"] == StageCost("t_m", 7 * 104, 7 * 24)


def shape_count(params, arch, n_s, masked):
    """Flops and bytes of one refill prediction from the parameter shapes."""
    T, F, D = arch.n_past, arch.n_future, arch.n_dof
    matmul = bias = cell = 0
    reads = 0  # parameter entries read
    for layer in params["encoder"]:
        for cell_params in (layer["forward"], layer["backward"]):
            H = cell_params["w_h"].shape[1]
            matmul += T * 2 * (cell_params["w_d"].size + cell_params["w_h"].size)
            bias += T * cell_params["b"].size
            cell += T * 13 * H  # add w_h h to the projection 4 H, gates 4 H, 3 sigmoid + 2 tanh
            reads += cell_params["w_d"].size + cell_params["b"].size + T * cell_params["w_h"].size
    dec, dense = params["decoder"], params["dense"]
    matmul += F * 2 * (dec["w_d"].size + dec["w_h"].size + dense["w"].size)
    bias += F * (dec["b"].size + dense["b"].size)
    cell += F * 13 * dec["w_h"].shape[1]
    reads += F * (dec["w_d"].size + dec["w_h"].size + dec["b"].size + dense["w"].size + dense["b"].size)
    flops = n_s * (matmul + bias + cell + 2 * D * (T + F) + (F * D if masked else 0))
    io = n_s * T * D + 2 * D + n_s * F * D + (D if masked else 0)
    item = np.dtype(arch.dtype).itemsize
    return n_s * matmul, flops, item * reads + 8 * io


@pytest.mark.parametrize("layers, q, masked, dtype", [(1, 0, True, "float32"), (2, 0, False, "float64"),
                                                      (2, 1, True, "float64")])
def test_surrogate_counts_from_the_parameter_shapes(layers, q, masked, dtype):
    arch = LSTMArchitecture(n_dof=3, n_hidden=2, n_layers=layers, n_past=2, n_future=2,
                            n_cond_repeat=q, dtype=dtype)
    n_s = 3
    params = init_params(jax.random.PRNGKey(0), arch)
    matmul, flops, nbytes = shape_count(params, arch, n_s, masked)
    assert surrogate_flop_breakdown(arch, n_s, masked)["matmul"] == matmul
    cost = surrogate_costs(arch, n_s, masked)
    assert cost.stage == "t_d" and cost.flops == flops and cost.bytes == nbytes
    # and the operations of the traced refill prediction
    mean, std = jnp.zeros(3), jnp.ones(3)
    mask = jnp.ones(3) if masked else None
    cond = 0.5 if q else None
    traced = written_flops(lambda b: refill_predict(params, arch, mean, std, b, n_s, cond, mask),
                           jnp.zeros((n_s * arch.n_past, 3)))
    assert traced == flops
    step = surrogate_step_cost(arch, n_s, masked)
    assert step.flops == pytest.approx(flops / (n_s * arch.n_future))
    assert step.bytes == pytest.approx(nbytes / (n_s * arch.n_future))
    # a smooth refill of 2 network calls: 2 windows' cost over the same n_s n_f steps
    _, flops_2, nbytes_2 = shape_count(params, arch, 2, masked)
    sampled = surrogate_step_cost(arch, n_s, masked, calls=2)
    assert sampled.flops == pytest.approx(flops_2 / (n_s * arch.n_future)) and sampled.flops < step.flops
    assert sampled.bytes == pytest.approx(nbytes_2 / (n_s * arch.n_future))
    with pytest.raises(ProblemError, match="calls must be an integer >= 1"):
        surrogate_step_cost(arch, n_s, masked, calls=0)


def test_surrogate_matmul_flops_by_hand():
    # n_dof 3, n_H 2, one layer, n_p = n_f = 2, one window:
    # encoder 2 directions x 2 steps x 2 (w_d 8x3 + w_h 8x2) = 160 per direction;
    # decoder (H 4) 2 steps x 2 (w_d 16x3 + w_h 16x4 + dense 3x4) = 496
    arch = LSTMArchitecture(n_dof=3, n_hidden=2, n_layers=1, n_past=2, n_future=2)
    assert surrogate_flop_breakdown(arch, 1)["matmul"] == 2 * 160 + 496


def test_achieved_rates_by_hand():
    cost = StageCost("t_m", 1e9, 2e9)
    point = achieved(cost, 0.5, 10e9, 100e9)
    assert point.achieved_Bps == pytest.approx(2e9)
    assert point.achieved_flops == pytest.approx(4e9)
    assert point.intensity == pytest.approx(2.0)
    assert point.bandwidth_fraction == pytest.approx(0.2)
    assert point.roofline_s == pytest.approx(0.1)  # max(1e9 / 10e9, 2e9 / 100e9)
    assert point.distance == pytest.approx(5.0)
    compute_bound = achieved(StageCost("t_d", 1e6, 1e10), 0.5, 10e9, 100e9)
    assert compute_bound.roofline_s == pytest.approx(0.1) and compute_bound.distance == pytest.approx(5.0)
    assert achieved(cost, 0.5, 10e9).roofline_s == pytest.approx(0.1)  # bandwidth roof only
    data = json.loads(json.dumps(point.to_dict()))
    assert data["GB_per_s"] == pytest.approx(2.0) and data["GFlop_per_s"] == pytest.approx(4.0)


def test_achieved_stages_skips_empty_stages():
    costs = step_costs(10, width=5)  # preassembled, one part: t_e and t_s cost nothing
    times = {"t_e": 0.0, "t_m": 1e-6, "t_s": 0.0, "t_o": 2e-6}
    points = achieved_stages(costs, times, 10e9)
    assert list(points) == ["t_m", "t_o"]
    assert points["t_o"].achieved_Bps == pytest.approx(costs["t_o"].bytes / 2e-6)
    assert "t_m" in roofline_table(points)


def test_bad_inputs_are_refused():
    cost = StageCost("t_m", 1e3, 1e3)
    with pytest.raises(ProblemError, match="seconds"):
        achieved(cost, 0.0, 10e9)
    with pytest.raises(ProblemError, match="peak_bandwidth_Bps"):
        achieved(cost, 1.0, -1.0)
    with pytest.raises(ProblemError, match="no bytes"):
        achieved(StageCost("t_e", 0, 0), 1.0, 10e9)
    with pytest.raises(ProblemError, match="bytes"):
        StageCost("t_m", -1, 0)
    with pytest.raises(ProblemError, match="mode"):
        step_costs(10, width=5, mode="implicit")
    with pytest.raises(ProblemError, match="width"):
        step_costs(10)
    with pytest.raises(ProblemError, match="n_elements"):
        step_costs(10, mode="recompute")
    with pytest.raises(ProblemError, match="n_shared"):
        step_costs(10, width=5, n_shared=4, n_interface=3)
    with pytest.raises(ProblemError, match="n_s"):
        surrogate_costs(LSTMArchitecture(n_dof=3), 0)
