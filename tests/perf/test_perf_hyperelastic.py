"""The roofline's counts of the total-Lagrangian (hyperelastic) internal force against
independent numbers: XLA's cost analysis of the formulas written entry by entry, and the
bytes of the operator's arrays."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsync
from jaxsync.errors import ProblemError
from jaxsync.fem.forces import TotalLagrangian
from jaxsync.perf.roofline import (
    ELEMENT_FLOPS,
    HYPERELASTIC_POINT_FLOPS,
    hyperelastic_element_cost,
    step_costs,
    step_costs_for,
)

N = 64  # points of the batches whose cost XLA counts


def xla_flops_per_entry(fn, *args) -> float:
    """(flops + transcendentals) / N of XLA's cost analysis of ``fn`` as written (the
    lowered, not yet optimized module: fusion may duplicate work, this count does not)."""
    cost = jax.jit(fn).lower(*args).cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    return (cost.get("flops", 0.0) + cost.get("transcendentals", 0.0)) / N


def components(F):
    return [[F[:, i, j] for j in range(3)] for i in range(3)]


def cofactor_and_j(F):
    c = [[F[(i + 1) % 3][(j + 1) % 3] * F[(i + 2) % 3][(j + 2) % 3]
          - F[(i + 1) % 3][(j + 2) % 3] * F[(i + 2) % 3][(j + 1) % 3] for j in range(3)] for i in range(3)]
    return c, F[0][0] * c[0][0] + F[0][1] * c[0][1] + F[0][2] * c[0][2]


def combine(a, F, b, c):
    return [[a * F[i][j] + b * c[i][j] for j in range(3)] for i in range(3)]


def neo_hookean(law, F, _):
    F = components(F)
    c, J = cofactor_and_j(F)
    s = (law.lam * jnp.log(J) - law.mu) / J
    return [[law.mu * F[i][j] + s * c[i][j] for j in range(3)] for i in range(3)]


def isochoric_volumetric(law, F):
    c, J = cofactor_and_j(F)
    j23 = jnp.exp(-2.0 / 3.0 * jnp.log(J))
    i1 = F[0][0] * F[0][0]
    for i, j in [(i, j) for i in range(3) for j in range(3)][1:]:
        i1 = i1 + F[i][j] * F[i][j]
    a = law.mu * j23
    b = (0.5 * law.bulk * (J * J - 1.0) - a * i1 / 3.0) / J
    return combine(a, F, b, c), i1


def nearly_incompressible(law, F, _):
    return isochoric_volumetric(law, components(F))[0]


def holzapfel_gasser_ogden(law, F, fibres):
    F = components(F)
    P, i1 = isochoric_volumetric(law, F)
    kappa = law.dispersion
    base = kappa * (i1 - 3.0)
    outer, slopes = None, []
    for f in range(2):
        a = [fibres[:, f, j] for j in range(3)]
        Fa = [F[i][0] * a[0] + F[i][1] * a[1] + F[i][2] * a[2] for i in range(3)]
        i4 = Fa[0] * Fa[0] + Fa[1] * Fa[1] + Fa[2] * Fa[2]
        strain = base + (1.0 - 3.0 * kappa) * (i4 - 1.0)
        slope = jnp.where(i4 >= 1.0 - 1e-12, law.k1 * strain * jnp.exp(law.k2 * (strain * strain)), 0.0)
        slopes.append(slope)
        sFa = [slope * Fa[i] for i in range(3)]
        term = [[sFa[i] * a[j] for j in range(3)] for i in range(3)]
        outer = term if outer is None else [[outer[i][j] + term[i][j] for j in range(3)] for i in range(3)]
    iso = 2.0 * kappa * (slopes[0] + slopes[1])
    P = [[P[i][j] + iso * F[i][j] for j in range(3)] for i in range(3)]
    return [[P[i][j] + 2.0 * (1.0 - 3.0 * kappa) * outer[i][j] for j in range(3)] for i in range(3)]


LAWS = {"NeoHookean": (jaxsync.NeoHookean(1.0e6, 0.3, 1.0), neo_hookean),
        "NearlyIncompressibleNeoHookean": (jaxsync.NearlyIncompressibleNeoHookean(1.0e6, 0.45, 1.0),
                                           nearly_incompressible),
        "HolzapfelGasserOgden": (jaxsync.HolzapfelGasserOgden(mu=3.0e5, k1=2.0e5, k2=0.8, kappa_bulk=1.0e7,
                                                               dispersion=0.1), holzapfel_gasser_ogden)}


@pytest.fixture(scope="module")
def points():
    rng = np.random.default_rng(0)
    F = jnp.asarray(np.eye(3) + 0.1 * rng.standard_normal((N, 3, 3)))
    fibres = jnp.asarray(jaxsync.helical_fibres(rng.standard_normal((N, 3)), angle=35.0))
    return F, fibres


@pytest.mark.parametrize("name", list(LAWS))
def test_stress_flops_are_xla_count_of_the_law_written_entry_by_entry(name, points):
    F, fibres = points
    law, written = LAWS[name]
    P = jnp.stack([jnp.stack(row, axis=-1) for row in written(law, F, fibres)], axis=-2)
    reference = law.first_piola(F, fibres if name == "HolzapfelGasserOgden" else None)
    np.testing.assert_allclose(P, reference, rtol=1e-12, atol=1e-12 * float(jnp.max(jnp.abs(reference))))
    # the fibres' tension test must be exercised both ways
    if name == "HolzapfelGasserOgden":
        i4 = jnp.sum(jnp.einsum("nij,nfj->nfi", F, fibres) ** 2, axis=-1)
        assert bool(jnp.any(i4 >= 1.0)) and bool(jnp.any(i4 < 1.0))
    counted = xla_flops_per_entry(lambda F, a: written(law, F, a), F, fibres)
    assert counted == pytest.approx(sum(HYPERELASTIC_POINT_FLOPS[name].values()), abs=0.1)


def test_deformation_gradient_and_force_flops_are_xla_count_of_a_p1_element():
    """F, w P, f_a = (w P) grad N_a and the scatter-add of one P1 element per point,
    written entry by entry (P = F stands for the law)."""
    rng = np.random.default_rng(1)
    ue, g = jnp.asarray(rng.standard_normal((N, 4, 3))), jnp.asarray(rng.standard_normal((N, 4, 3)))
    w, cells = jnp.asarray(rng.random(N)), jnp.asarray(rng.integers(0, 10, (N, 4)), dtype=jnp.int32)

    def element(ue, g, w, cells):
        F = [[sum(ue[:, a, i] * g[:, a, j] for a in range(4)) + (1.0 if i == j else 0.0) for j in range(3)]
             for i in range(3)]
        Pw = [[w * F[i][j] for j in range(3)] for i in range(3)]
        f = jnp.stack([jnp.stack([Pw[i][0] * g[:, a, 0] + Pw[i][1] * g[:, a, 1] + Pw[i][2] * g[:, a, 2]
                                  for i in range(3)], -1) for a in range(4)], 1)
        return jax.ops.segment_sum(f.reshape(-1, 3), cells.reshape(-1), num_segments=10)

    cost = hyperelastic_element_cost("NeoHookean")["flops_by_part"]
    counted = xla_flops_per_entry(element, ue, g, w, cells)
    # the identity's diagonal: XLA counts one add per diagonal entry (3), as the formula
    assert counted == pytest.approx(cost["deformation gradient"] + cost["nodal forces"] + cost["scatter-add"],
                                    abs=0.1)


def test_p2_counts_scale_with_nodes_and_points():
    p1, p2 = hyperelastic_element_cost("NeoHookean"), hyperelastic_element_cost("NeoHookean", 10, 4)
    stress = sum(HYPERELASTIC_POINT_FLOPS["NeoHookean"].values())
    assert p1["flops_by_part"] == {"deformation gradient": 66, "stress": stress, "nodal forces": 69,
                                   "scatter-add": 12}
    assert p2["flops_by_part"] == {"deformation gradient": 4 * 174, "stress": 4 * stress,
                                   "nodal forces": 4 * 159 + 90, "scatter-add": 30}
    assert p2["element_bytes"] == 40 + 8 * 4 * 31


@pytest.mark.parametrize("element", ["P1", "P2"])
def test_total_lagrangian_bytes_are_the_operator_arrays(element):
    beam = jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1))
    rng = np.random.default_rng(2)
    fibres = jaxsync.helical_fibres(rng.standard_normal((beam.n_elements, 3)), angle=30.0)
    for material in (jaxsync.NeoHookean(1.0e6, 0.3, 1.0),
                     jaxsync.HolzapfelGasserOgden(mu=3.0e5, k1=2.0e5, k2=0.8, kappa_bulk=1.0e6, fibres=fibres)):
        problem = jaxsync.cantilever(beam, material=material).replace(element=element)
        op = TotalLagrangian().operator(problem)
        m, n = problem.mesh.n_elements, problem.n_nodes
        arrays = [op.cells, op.gradients, op.weights] + ([op.fibres] if op.fibres is not None else [])
        cost = hyperelastic_element_cost(type(material).__name__, op.cells.shape[1], op.weights.shape[1])
        assert cost["element_bytes"] * m == sum(np.asarray(a).nbytes for a in arrays)
        assert cost["gather_bytes"] * m == 2 * np.asarray(jnp.zeros((n, 3))[op.cells]).nbytes
        costs = step_costs_for(problem)  # a hyperelastic problem is costed as it runs, in any mode
        assert costs == step_costs_for(problem, mode="total-lagrangian")
        assert costs["t_e"].flops + costs["t_m"].flops == m * cost["flops"]
        assert costs["t_e"].bytes + costs["t_m"].bytes == m * (cost["element_bytes"] + cost["gather_bytes"])


def test_total_lagrangian_is_not_costed_as_the_linear_recompute():
    linear = step_costs(10, n_elements=7, mode="recompute")
    hyper = step_costs(10, n_elements=7, mode="total-lagrangian")
    assert linear["t_e"].flops == 7 * sum(ELEMENT_FLOPS.values())
    assert hyper["t_e"].flops == 7 * (hyperelastic_element_cost("NeoHookean")["flops"] - 12)
    assert hyper["t_e"] != linear["t_e"]
    hgo = step_costs(10, n_elements=7, mode="total-lagrangian", law="HolzapfelGasserOgden")
    assert hgo["t_e"].flops > hyper["t_e"].flops and hgo["t_e"].bytes == hyper["t_e"].bytes + 7 * 48
    with pytest.raises(ProblemError):
        step_costs(10, n_elements=7, mode="total-lagrangian", law="Ogden")
    with pytest.raises(ProblemError):
        step_costs(10, mode="total-lagrangian")
