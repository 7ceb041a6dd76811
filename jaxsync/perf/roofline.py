"""Bytes and flops of each stage of an explicit step, and the achieved rates (roofline).

For a part (or a whole mesh) of n nodes, m elements, ELL width w (slots per node row),
L load vectors, n_sh shared nodes of the part and N_a interface nodes of the partition,
the counts per explicit step are below (float64 = 8 bytes, int32 = 4 bytes, a boolean
mask 1 byte per dof). Bytes are the traffic of the arrays each stage reads and writes
as written in jaxsync; flops are a count of the written floating-point operations (a
division, a negation or a transcendental function counts as one flop; a contraction of
length k as 2 k flops, multiply and add, as for matrix products). Each stage is counted
as if it ran alone, as :mod:`jaxsync.perf.timing` times it: the fused real step reads d(n)
once and never stores K d, so its traffic is the sum below minus 2 * 24 n bytes.

``"t_m"``, preassembled (node-blocked ELL of :mod:`jaxsync.fem`, columns (n, w) int32,
blocks (n, 3, w, 3) float64)::

    bytes = n w (9 * 8 + 4)      the blocks and column indices, streamed once
          + 24 n                 u read once (the gathers of u are assumed to hit cache)
          + 24 n                 y = K u written
    flops = 18 n w               multiply + add per stored block entry (9 n w entries)

``"t_e"`` is 0 in the preassembled mode (K is assembled once, before the run).

``"t_e"``, recompute mode (:func:`jaxsync.fem.forces.element_forces`), per element::

    bytes = 4 * 4 (node ids) + 12 * 8 (coordinates gathered) + 12 * 8 (displacements
            gathered) = 208
    flops = 264, as written (:data:`ELEMENT_FLOPS`): edge vectors 9, three cross
            products 27, det 5, gradients / det 9, grad N_0 9, H = u^T grad 72,
            eps 18, trace 2, sigma 28, volume 1, sigma grad 72, times volume 12

``"t_m"``, recompute mode (the weight and the scatter-add of the element forces into the
nodes, :meth:`jaxsync.fem.forces.ElementStiffness.matvec`), per element::

    bytes = 8 (weight) + 12 * 8 (forces scatter-added) = 104
    flops = 12 (times weight) + 12 (scatter-add) = 24

The per-element gathers and scatters are counted every time an element touches a node
(each node has about 20 elements): an upper bound on the memory traffic when they hit
cache, so a recompute "fraction of bandwidth" above 1 means cache reuse.

``"t_e"``, total-Lagrangian mode (:meth:`jaxsync.fem.forces.HyperelasticForce.element_forces`,
a hyperelastic law), per element of k nodes and n_q quadrature points (P1: k = 4, n_q = 1;
P2: k = 10, n_q = 4)::

    bytes = 4 k (node ids) + 8 n_q (3 k + 1) (reference gradients and weights)
            + 48 (the two fibre directions, Holzapfel-Gasser-Ogden only)
            + 8 * 3 k (displacements gathered)
    flops = n_q (9 (2 k - 1) + 3        F = I + sum_a u_a (x) grad N_a
                 + P(law)               the first Piola stress (:data:`HYPERELASTIC_POINT_FLOPS`)
                 + 9 + 15 k)            w P, then f_a = (w P) grad N_a (3 products, 2 sums each)
            + 3 k (n_q - 1)             the quadrature points' forces summed

``"t_m"``, total-Lagrangian mode (the scatter-add of the element forces into the nodes)::

    bytes = 8 * 3 k,  flops = 3 k

As for the recompute mode, the gathers and scatters are counted per element; the
compulsory traffic of the whole force (:func:`hyperelastic_element_cost`) reads u and
writes f once per node instead.

``"t_o"``, the update (:func:`jaxsync.fem._stepper.external_force`, ``central_difference``,
``apply_dirichlet``), per dof (3 per node)::

    bytes = 8 * (3 + L + 1 + 1) + 1   read d(n), d(n-1), lumped mass, L load vectors,
                                      fixed values; write d(n+1); read the fixed mask
    flops = 8 + 2 L                   f = sum_l g_l(t) F_l (multiply + add per load);
                                      (f - Kd), * dt^2, / m, 2 d, +, (1 - a) d_prev, -,
                                      / (1 + a); the Dirichlet select is no flop

``"t_s"``, synchronization (:func:`jaxsync.parallel.exchange.synchronize_forces`, as written;
the bytes on the network are :mod:`jaxsync.perf.costmodel`'s)::

    bytes = 2 * 4 n_sh                index arrays shared_local, shared_interface
          + 24 N_a                    the zeroed interface vector written
          + 24 n_sh + 24 n_sh         partial forces read, added into the interface
          + 24 N_a + 24 N_a           the interface vector reduced: read, result written
          + 24 n_sh + 24 n_sh         the summed values gathered and written back
    flops = 3 n_sh + 3 N_a            scatter-adds; one reduction add per interface dof

``"t_d"``, the surrogate: one refill prediction of n_s windows
(:func:`jaxsync.surrogate.refill_predict`; :func:`surrogate_costs`), with
H = n_H, H_d = 2 n_H, D = n_dof, q = n_cond_repeat, T = n_p, F = n_f, n_in of encoder
layer l (D for the first, 2 H after). A cell step given its input projection costs
8 H^2 (w_h h) + 4 H (add the projection) + 4 H (gate products and sum) + 5 H (3 sigmoid,
2 tanh) = 8 H^2 + 13 H flops. Per window::

    encoder, per layer and direction (both directions run: the layers are bidirectional):
        input projection of all T steps at once: 8 H n_in T + 4 H T (bias)
        T cell steps: T (8 H^2 + 13 H)
    decoder, F steps, input y_prev (+ q copies of the load parameter):
        8 H_d (D + q) + 4 H_d (projection and bias) + 8 H_d^2 + 13 H_d (cell)
        + 2 D H_d + D (dense) + D (padding mask, when given)
    normalization: 2 D T (input), 2 D F (output)

all times n_s windows (one batched program: ``jax.vmap`` over the windows). Bytes: the
parameters (itemsize of ``arch.dtype``) are read once per sequential matrix product, for
all n_s windows together: per encoder layer and direction w_d and b once (one projection
for all steps) and w_h T times; the decoder's w_d, w_h, b and the dense w, b F times;
plus the input buffer n_s T D, mean and std 2 D, mask D and output n_s F D values in the
solver's float64. Intermediate activations (projections, hidden sequences, states) are
not counted: they are small and stay in cache for the paper's sizes. Per solver step:
divide by the n_s n_f steps one prediction serves (:func:`surrogate_step_cost`). The
smooth refill that :class:`jaxsync.surrogate.Surrogate` runs by default evaluates 16 of
the n_s windows (:func:`jaxsync.surrogate.refill_block_means`): count it with
``calls=16``.

Achieved rates (:func:`achieved`), computed from given times and peaks (this module
only counts; the machine's rates are measured by :func:`jaxsync.perf.measure.copy_bandwidth`
and :func:`jaxsync.perf.measure.matmul_flop_rate`): bytes / t, flops / t, arithmetic
intensity flops / bytes, fraction of the machine's memory bandwidth, and the time
the roofline predicts, max(bytes / bandwidth, flops / peak flops), with the ratio
measured / predicted (the distance to the roofline, >= 1 when the model holds).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Mapping

import numpy as np

from ..errors import ProblemError
from ..fem.materials._hyperelastic import HYPERELASTIC
from ..options import Mode, check_option

__all__ = ["StageCost", "STEP_STAGES", "ELEMENT_FLOPS", "HYPERELASTIC_POINT_FLOPS", "hyperelastic_element_cost",
           "step_costs", "step_costs_for",
           "surrogate_flop_breakdown", "surrogate_costs", "surrogate_step_cost",
           "RooflinePoint", "achieved", "achieved_stages", "roofline_table"]

STEP_STAGES = ("t_e", "t_m", "t_s", "t_o")  # the stages of a step that step_costs counts

F64, I32, MASK = 8, 4, 1  # bytes per float64, int32, boolean

# Flops per element of jaxsync.fem.forces.element_forces, operation by operation as
# written (the t_e of the recompute mode).
ELEMENT_FLOPS = {
    "edge vectors r1, r2, r3": 9,
    "cross products c1, c2, c3": 27,  # 6 multiplications + 3 subtractions each
    "det = sum(r1 * c1)": 5,  # 3 multiplications + 2 additions
    "gradients c / det": 9,
    "grad N_0 = -(sum of the others)": 9,  # 2 additions + 1 negation per component
    "H = u^T grad": 72,  # 9 entries, contraction over 4 nodes
    "eps = (H + H^T) / 2": 18,
    "trace": 2,
    "sigma = 2 mu eps + lam tr I": 28,  # 9 + 1 + 9 (times eye) + 9
    "volume = det / 6": 1,
    "sigma grad": 72,  # 12 entries, contraction over 3
    "times volume": 12,
}
SCATTER_FLOPS = 24  # recompute t_m per element: 12 times the weight, 12 scatter-adds

HYPERELASTIC_POINT_FLOPS = {law.__name__: dict(law.point_flops) for law in HYPERELASTIC}
"""{law class name: {operation: flops}} per quadrature point (the t_e of the
total-Lagrangian mode with the deformation gradient and the nodal forces): each built-in
law's :attr:`~jaxsync.fem.materials.FiniteStrainLaw.point_flops`, operation by
operation of its formula (a transcendental function, a division, a comparison or a select
counts as one flop, as in XLA's cost analysis)."""


def _law_cost(law):
    """The :class:`~jaxsync.fem.materials.LawCost` of a law, or of a built-in law's class name."""
    if isinstance(law, str):  # a name, as the cost model's callers have given it
        if law not in HYPERELASTIC_POINT_FLOPS:
            raise ProblemError(f"law must be one of {', '.join(HYPERELASTIC_POINT_FLOPS)}, got {law!r}")
        return next(cls for cls in HYPERELASTIC if cls.__name__ == law).cost()
    cost = law.cost()
    if cost is None:
        raise ProblemError(f"the {type(law).__name__} law has no per-point stress cost (its cost is that of its "
                           "force mode): cost it with mode='preassembled' or 'recompute'")
    return cost


def hyperelastic_element_cost(law, nodes_per_element: int = 4, n_points: int = 1) -> dict:
    """Flops and compulsory bytes per element of the total-Lagrangian internal force
    (:meth:`jaxsync.fem.forces.HyperelasticForce.matvec`) of a law.

    Args:
        law: a finite-strain material law (its
            :meth:`~jaxsync.fem.materials.MaterialLaw.cost`), or a built-in law's class
            name (a key of :data:`HYPERELASTIC_POINT_FLOPS`).
        nodes_per_element: k (4: P1, 10: P2).
        n_points: n_q quadrature points per element (1: P1, 4: P2).

    Returns:
        ``{"flops": per element, "flops_by_part": {"deformation gradient", "stress",
        "nodal forces", "scatter-add"}, "element_bytes": the arrays read once per element
        (node ids, gradients, weights, fibres, internal variables read and written),
        "node_bytes": per node (u read, f written
        once), "gather_bytes": the displacements gathered and the forces scattered when
        each element's touch is counted}``. The compulsory traffic of a mesh of m elements
        and n nodes is ``m element_bytes + n node_bytes``.

    Raises:
        ProblemError: an unknown law name, a law without a stress cost, or counts below 1.
    """
    cost = _law_cost(law)
    k = _count(nodes_per_element, "nodes_per_element", 1)
    q = _count(n_points, "n_points", 1)
    parts = {"deformation gradient": q * (9 * (2 * k - 1) + 3),
             "stress": q * sum(cost.point_flops.values()),
             "nodal forces": q * (9 + 15 * k) + 3 * k * (q - 1),
             "scatter-add": 3 * k}
    return {"flops": sum(parts.values()), "flops_by_part": parts,
            "element_bytes": I32 * k + F64 * q * (3 * k + 1) + cost.element_bytes + q * cost.point_bytes,
            "node_bytes": 2 * 3 * F64, "gather_bytes": 2 * 3 * k * F64}


@dataclasses.dataclass(frozen=True)
class StageCost:
    """Memory traffic and floating-point work of one stage.

    Attributes:
        stage: the stage (``"t_e"``, ``"t_m"``, ``"t_s"``, ``"t_o"``, ``"t_d"``).
        bytes: bytes read + written [bytes].
        flops: floating-point operations [flop].
    """

    stage: str
    bytes: float
    flops: float

    def __post_init__(self):
        for name in ("bytes", "flops"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
                    or not (math.isfinite(value) and value >= 0):
                raise ProblemError(f"StageCost.{name} of {self.stage!r} must be a finite number >= 0, "
                                   f"got {value!r}")
            object.__setattr__(self, name, float(value))

    @property
    def intensity(self) -> float:
        """Arithmetic intensity flops / bytes [flop/byte] (inf when no bytes move but
        flops are done, 0 when nothing is done)."""
        if self.bytes == 0:
            return math.inf if self.flops > 0 else 0.0
        return self.flops / self.bytes

    def scaled(self, factor: float) -> "StageCost":
        """The cost times ``factor`` (e.g. 1 / (n_s n_f) to spread a prediction over steps)."""
        return StageCost(self.stage, self.bytes * factor, self.flops * factor)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def _count(value, name: str, minimum: int = 0) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ProblemError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def step_costs(n_nodes: int, width: int | None = None, n_elements: int | None = None,
               n_load_vectors: int = 1, mode: Mode = "preassembled", n_shared: int = 0,
               n_interface: int = 0, *, law="NeoHookean", nodes_per_element: int = 4,
               n_points: int = 1) -> dict:
    """Bytes and flops of each stage of one explicit step (formulas: module docstring).

    Args:
        n_nodes: n, nodes of the part (or mesh).
        width: w, ELL slots per node row (``"preassembled"``; the second dimension of
            :func:`jaxsync.fem.node_adjacency`).
        n_elements: m, elements of the part (``"recompute"``, ``"total-lagrangian"``).
        n_load_vectors: L, load vectors of the problem.
        mode: ``"preassembled"``, ``"recompute"`` or ``"total-lagrangian"``.
        n_shared: n_sh, shared nodes of the part (0: no synchronization).
        n_interface: N_a, shared nodes of the whole partition.
        law, nodes_per_element, n_points: the finite-strain law (or a built-in law's
            class name), nodes and quadrature points per element (``"total-lagrangian"`` only;
            :func:`hyperelastic_element_cost`).

    Returns:
        ``{"t_e": StageCost, "t_m": ..., "t_s": ..., "t_o": ...}``.

    Raises:
        ProblemError: unknown mode, a missing ``width`` / ``n_elements``, negative counts,
            n_shared > n_interface or n_shared > n_nodes.
    """
    check_option("mode", mode, Mode, error=ProblemError)
    n = _count(n_nodes, "n_nodes", 1)
    loads = _count(n_load_vectors, "n_load_vectors")
    n_sh = _count(n_shared, "n_shared")
    n_a = _count(n_interface, "n_interface")
    if n_sh > n_a or n_sh > n:
        raise ProblemError(f"n_shared={n_sh} cannot exceed n_interface={n_a} or n_nodes={n}")
    if mode == "preassembled":
        if width is None:
            raise ProblemError("the preassembled mode needs the ELL width (slots per row): pass width=")
        w = _count(width, "width", 1)
        t_e = StageCost("t_e", 0, 0)
        t_m = StageCost("t_m", n * w * (9 * F64 + I32) + 2 * 3 * F64 * n, 18 * n * w)
    elif mode == "total-lagrangian":
        if n_elements is None:
            raise ProblemError("the total-Lagrangian mode needs the number of elements: pass n_elements=")
        m = _count(n_elements, "n_elements", 1)
        cost = hyperelastic_element_cost(law, nodes_per_element, n_points)
        scatter = cost["flops_by_part"]["scatter-add"]
        t_e = StageCost("t_e", m * (cost["element_bytes"] + cost["gather_bytes"] // 2), m * (cost["flops"] - scatter))
        t_m = StageCost("t_m", m * cost["gather_bytes"] // 2, m * scatter)
    else:
        if n_elements is None:
            raise ProblemError("the recompute mode needs the number of elements: pass n_elements=")
        m = _count(n_elements, "n_elements", 1)
        t_e = StageCost("t_e", m * (4 * I32 + 12 * F64 + 12 * F64), m * sum(ELEMENT_FLOPS.values()))
        t_m = StageCost("t_m", m * (F64 + 12 * F64), m * SCATTER_FLOPS)
    dofs = 3 * n
    t_o = StageCost("t_o", dofs * (F64 * (3 + loads + 1 + 1) + MASK), dofs * (8 + 2 * loads))
    vec = 3 * F64  # bytes of one node's 3 components
    t_s = StageCost("t_s", 2 * I32 * n_sh + vec * n_a + 2 * vec * n_sh + 2 * vec * n_a + 2 * vec * n_sh,
                    3 * n_sh + 3 * n_a)
    return {"t_e": t_e, "t_m": t_m, "t_s": t_s, "t_o": t_o}


def step_costs_for(problem, partition=None, mode: Mode = "preassembled"):
    """:func:`step_costs` of a :class:`jaxsync.Problem`, whole or per part.

    The preassembled product's slots per row are those of the default layout
    (:class:`jaxsync.fem.GroupedEll`: rows grouped by degree, each group padded to
    its own width), averaged over the rows and rounded up.

    Args:
        problem: the problem (nodes of its element, ELL slots, load vectors).
        partition: None for the whole mesh on one device (no synchronization), or a
            :class:`jaxsync.Partition` of ``problem.mesh``: then each part at its own
            (unpadded) size, as :func:`jaxsync.perf.timing.timing_breakdown` measures it (the
            SPMD program pads every part to the largest).
        mode: ``"preassembled"``, ``"recompute"`` or ``"total-lagrangian"`` (the law, nodes
            and quadrature points per element from the problem's material and element;
            a hyperelastic problem is costed so in any mode, as it runs so).

    Returns:
        One dict of stage costs, or for a partition a tuple of them (one per part).
    """
    from ..fem.forces._internal_force import force_model

    n_loads = len(problem.load_vectors()[0])
    mesh = problem.mesh
    law = {}
    mode = problem.material.force_model(force_model(mode)).name  # the model the law runs on
    if mode == "total-lagrangian":
        from ..fem._reference_element import n_quadrature_points

        space = problem.space
        law = {"law": problem.material, "nodes_per_element": space.nodes_per_cell,
               "n_points": n_quadrature_points(space)}
    if partition is None:
        width = _slots_per_row(problem.space.cells, problem.n_nodes) if mode == "preassembled" else None
        return step_costs(problem.n_nodes, width, mesh.n_elements, n_loads, mode, **law)
    if partition.mesh.n_nodes != mesh.n_nodes or partition.mesh.n_elements != mesh.n_elements:
        raise ProblemError("the partition was made for another mesh: partition problem.mesh")
    out = []
    for part in partition.parts:
        width = _slots_per_row(part.local_tets, part.n_local) if mode == "preassembled" else None
        out.append(step_costs(part.n_local, width, len(part.elements), n_loads, mode,
                              part.n_shared, partition.n_interface, **law))
    return tuple(out)


def _slots_per_row(cells, n_nodes: int) -> int:
    """Stored block slots per row of the default grouped layout, rounded up."""
    from ..fem._sparse import degree_widths, node_adjacency, row_degrees

    degree = row_degrees(node_adjacency(cells, n_nodes))
    low, slots = 0, 0
    for width in degree_widths(degree):
        slots += width * int(((degree > low) & (degree <= width)).sum())
        low = width
    return -(-slots // n_nodes)


# ----------------------------------------------------------------------------- surrogate


def _check_arch(arch, n_s, lstm_only: bool = False):
    from ..surrogate.models._lstm import LSTMArchitecture
    from ..surrogate.models._protocol import SurrogateArchitecture

    if lstm_only and not isinstance(arch, LSTMArchitecture):
        raise ProblemError(f"expected a jaxsync.surrogate.models.LSTMArchitecture, got {arch!r}")
    if not isinstance(arch, SurrogateArchitecture):
        raise ProblemError(f"expected a surrogate model (jaxsync.surrogate.SurrogateArchitecture), got {arch!r}")
    return _count(n_s, "n_s", 1)


def surrogate_flop_breakdown(arch, n_s: int, masked: bool = True) -> dict:
    """Flops of one LSTM refill prediction (n_s windows), by kind (formulas: module
    docstring; :func:`jaxsync.surrogate.models.count_flops`).

    Returns:
        ``{"matmul": ..., "bias": ..., "cell": ..., "normalize": ..., "mask": ...}``:
        ``"matmul"`` the matrix products (2 flops per weight entry per use), ``"bias"``
        the bias additions, ``"cell"`` the gate arithmetic (13 per hidden unit per
        step), ``"normalize"`` the input and output scaling, ``"mask"`` the padding mask.
    """
    from ..surrogate.models._lstm import count_flops

    return count_flops(arch, _check_arch(arch, n_s, lstm_only=True), masked)


def surrogate_costs(arch, n_s: int, masked: bool = True, io_bytes_per_value: int = 8) -> StageCost:
    """Bytes and flops of one refill prediction (n_s windows of one part), stage ``"t_d"``:
    the model's own count (:meth:`~jaxsync.surrogate.SurrogateArchitecture.prediction_cost`;
    the LSTM's formulas are in the module docstring).

    Args:
        arch: the surrogate model (e.g. a :class:`jaxsync.surrogate.models.LSTMArchitecture`).
        n_s: sampling stride: windows per prediction.
        masked: the padding mask is applied (the synchronization-avoiding solver does).
        io_bytes_per_value: bytes per value of the solver-side buffer, mean, std, mask
            and output (8: float64).
    """
    cost = arch.prediction_cost(_check_arch(arch, n_s), masked, io_bytes_per_value)
    return StageCost("t_d", cost.bytes, cost.flops)


def surrogate_step_cost(arch, n_s: int, masked: bool = True, io_bytes_per_value: int = 8,
                        calls: int | None = None) -> StageCost:
    """:func:`surrogate_costs` of one refill spread over the n_s n_f solver steps it serves.

    Args:
        calls: the network applications (windows) one refill evaluates: n_s (None, the
            default: the paper's raw refill) or a smooth refill's
            :attr:`jaxsync.surrogate.Surrogate.refill_calls` (16 by default,
            :data:`jaxsync.surrogate.DEFAULT_REFILL_SAMPLES`).
    """
    windows = n_s if calls is None else _count(calls, "calls", 1)
    return surrogate_costs(arch, windows, masked, io_bytes_per_value).scaled(1.0 / (_count(n_s, "n_s", 1)
                                                                                    * arch.n_future))


# ----------------------------------------------------------------------------- roofline


@dataclasses.dataclass(frozen=True)
class RooflinePoint:
    """A stage's measured time against its counted cost and the machine's peaks.

    Attributes:
        stage: the stage.
        bytes, flops: counted cost [bytes], [flop].
        seconds: measured time [s].
        peak_bandwidth_Bps: memory bandwidth of the machine [bytes/s].
        peak_flops: peak floating-point rate [flop/s], or None (bandwidth roof only).
    """

    stage: str
    bytes: float
    flops: float
    seconds: float
    peak_bandwidth_Bps: float
    peak_flops: float | None = None

    @property
    def achieved_Bps(self) -> float:
        """bytes / seconds [bytes/s]."""
        return self.bytes / self.seconds

    @property
    def achieved_flops(self) -> float:
        """flops / seconds [flop/s]."""
        return self.flops / self.seconds

    @property
    def intensity(self) -> float:
        """flops / bytes [flop/byte]."""
        return StageCost(self.stage, self.bytes, self.flops).intensity

    @property
    def bandwidth_fraction(self) -> float:
        """achieved_Bps / peak_bandwidth_Bps."""
        return self.achieved_Bps / self.peak_bandwidth_Bps

    @property
    def roofline_s(self) -> float:
        """The time the roofline predicts [s]: max(bytes / bandwidth, flops / peak_flops)."""
        t = self.bytes / self.peak_bandwidth_Bps
        return max(t, self.flops / self.peak_flops) if self.peak_flops else t

    @property
    def distance(self) -> float:
        """seconds / roofline_s: how many times slower than the roofline (>= 1 expected)."""
        return self.seconds / self.roofline_s

    def to_dict(self) -> dict:
        """JSON-ready: the fields and the derived rates (GB/s, GFlop/s)."""
        return dict(dataclasses.asdict(self), GB_per_s=self.achieved_Bps / 1e9,
                    GFlop_per_s=self.achieved_flops / 1e9, intensity=self.intensity,
                    bandwidth_fraction=self.bandwidth_fraction, roofline_s=self.roofline_s,
                    distance=self.distance)


def achieved(cost: StageCost, seconds: float, peak_bandwidth_Bps: float,
             peak_flops: float | None = None) -> RooflinePoint:
    """The achieved rates of a stage of cost ``cost`` measured at ``seconds``.

    Raises:
        ProblemError: a time or peak that is not finite and > 0, or a stage with no cost
            (nothing to compare: e.g. t_e of the preassembled mode).
    """
    if not isinstance(cost, StageCost):
        raise ProblemError(f"expected a StageCost, got {cost!r}")
    values = {"seconds": seconds, "peak_bandwidth_Bps": peak_bandwidth_Bps}
    if peak_flops is not None:
        values["peak_flops"] = peak_flops
    for name, value in values.items():
        try:
            ok = math.isfinite(float(value)) and float(value) > 0
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ProblemError(f"{name} of stage {cost.stage!r} must be a finite number > 0, got "
                               f"{value!r} (a stage time clipped to 0 has no rate: leave it out)")
    point = RooflinePoint(cost.stage, cost.bytes, cost.flops, float(seconds), float(peak_bandwidth_Bps),
                          None if peak_flops is None else float(peak_flops))
    if point.roofline_s == 0:
        raise ProblemError(f"stage {cost.stage!r} moves no bytes"
                           + ("" if peak_flops else " (and no peak_flops was given)")
                           + ": nothing to compare with the roofline")
    return point


def achieved_stages(costs: Mapping, times, peak_bandwidth_Bps: float,
                    peak_flops: float | None = None) -> dict:
    """:func:`achieved` for every stage with a cost > 0 and a time > 0.

    Args:
        costs: ``{stage: StageCost}`` (:func:`step_costs`, maybe with ``"t_d"`` added).
        times: ``{stage: seconds}``, or an object with the stages as attributes (a
            :class:`jaxsync.perf.reports.PartTiming`).
        peak_bandwidth_Bps, peak_flops: as in :func:`achieved`.

    Returns:
        ``{stage: RooflinePoint}`` in the order of ``costs``.
    """
    out = {}
    for stage, cost in costs.items():
        seconds = times.get(stage) if isinstance(times, Mapping) else getattr(times, stage, None)
        if seconds is None or not seconds > 0 or (cost.bytes == 0 and cost.flops == 0):
            continue
        if cost.bytes == 0 and not peak_flops:
            continue
        out[stage] = achieved(cost, seconds, peak_bandwidth_Bps, peak_flops)
    return out


def roofline_table(points) -> str:
    """A printable table of :class:`RooflinePoint` s (a dict or an iterable)."""
    points = list(points.values() if isinstance(points, Mapping) else points)
    lines = [f"{'stage':<6} {'bytes':>12} {'flops':>12} {'flop/B':>7} {'us':>10} {'GB/s':>8} "
             f"{'GFlop/s':>8} {'of bw':>6} {'roof us':>10} {'x roof':>7}"]
    for p in points:
        lines.append(f"{p.stage:<6} {p.bytes:>12.4g} {p.flops:>12.4g} {p.intensity:>7.3f} "
                     f"{1e6 * p.seconds:>10.3f} {p.achieved_Bps / 1e9:>8.2f} {p.achieved_flops / 1e9:>8.2f} "
                     f"{p.bandwidth_fraction:>6.0%} {1e6 * p.roofline_s:>10.3f} {p.distance:>7.2f}")
    return "\n".join(lines)
