"""Hyperelastic element kernel: throughput, flops and bytes per element, roofline, and its
cost against the pre-assembled linear step.

On the generated coronary tree (:func:`jaxsync.coronary`, the paper's vessel) at about 5 000
and 40 000 tetrahedra, P1, and P2 on the smaller mesh, for the three hyperelastic laws
(:class:`jaxsync.NeoHookean` and :class:`jaxsync.NearlyIncompressibleNeoHookean` of the
vessel's E, nu; :class:`jaxsync.HolzapfelGasserOgden` with the same ground matrix and two
helical fibre families, :func:`jaxsync.helical_fibres` at +/- 40 degrees):

- ``matvec``: the internal force f_int(u)
  (:meth:`jaxsync.fem.forces.HyperelasticForce.matvec`) at a deformed state
  (a homogeneous 1-2 % stretch and compression plus a small random field, so that both
  fibre families are partly in tension), and elements per second; timed as a chain of
  products in one compiled call (the cost of a call left out, as in a time loop);
- ``step``: one full explicit step through :func:`jaxsync.fem.advance`
  (``mode=TotalLagrangian()``), per step of a call of several steps;
- the same two for the linear law of the same E, nu pre-assembled
  (``Preassembled()``, :class:`jaxsync.LinearElastic`): ``x lin`` is the hyperelastic time
  over the linear one.

Counts per element. Flops: XLA's cost analysis of the compiled matvec (``flops`` plus
``transcendentals``, each counted as one) and the analytic count of the formulas as written
(:func:`jaxsync.perf.roofline.hyperelastic_element_cost`: F, the law's P, the nodal forces,
the scatter-add); XLA's count is higher where fusion recomputes shared terms or automatic
differentiation does more than the formula. Bytes: the compulsory traffic, node ids,
reference gradients, weights (and fibres) read once per element, u read and f written
once per node (the gathers and the scatter assumed to hit cache). Intensity = formula
flops / compulsory bytes.

Roofline. The machine's rates are measured in the same run on the same single core:
the float64 flop rate of a jitted 1024 x 1024 matrix product
(:func:`jaxsync.perf.measure.matmul_flop_rate`, the attainable peak with FMA and SIMD) and
the memory bandwidth of a 400 MB ``numpy.copyto`` (:func:`jaxsync.perf.measure.copy_bandwidth`,
read + write bytes), each measured before every case and at the end, the best kept. The
bound is the roofline time max(formula flops / peak, bytes / bandwidth):
the compute bound when the intensity is above the machine balance peak / bandwidth, else
the bandwidth bound; ``x roof`` is the measured time over it (1 = on the roofline; the
JSON also has it at XLA's flops, ``times_roofline_at_xla_flops``).

Per core: the process pins itself to one core (``os.sched_setaffinity``) before JAX
starts, so that every rate (kernel, peak, bandwidth) is that of one core; XLA's threads
share it. All calls of a case are timed in rounds, round-robin, after an untimed first
call, and the best round kept (:func:`jaxsync.perf.measure.sample_times`); the median is
recorded too.

Usage: python benchmarks/bench_hyperelastic.py [--quick] [--out benchmarks/results/hyperelastic.json]
"""

from __future__ import annotations

import argparse
import functools
import os
import platform
import sys

if hasattr(os, "sched_setaffinity"):  # one core: the rates are per core
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[-1]})

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxsync  # noqa: E402
from jaxsync.fem import advance, build_system, initial_state  # noqa: E402
from jaxsync.fem.forces import Preassembled, TotalLagrangian  # noqa: E402
from jaxsync.perf.measure import copy_bandwidth, matmul_flop_rate, sample_times  # noqa: E402
from jaxsync.perf.roofline import hyperelastic_element_cost  # noqa: E402

advance_jit = jax.jit(advance, static_argnums=(2, 3))
matvec_jit = jax.jit(lambda op, u: op.matvec(u))


@functools.partial(jax.jit, static_argnums=3)
def repeated_matvec(op, u, scale, reps):
    """``reps`` dependent products x <- u + scale f(x) in one call (scale = 0 passed at run
    time, which XLA cannot fold away): the time of a product without the cost of a call."""
    return jax.lax.fori_loop(0, reps, lambda i, x: u + scale * op.matvec(x), u)

LAWS = ("NeoHookean", "NearlyIncompressibleNeoHookean", "HolzapfelGasserOgden")
SHORT = {"NeoHookean": "neo-Hookean", "NearlyIncompressibleNeoHookean": "nearly-incompr.",
         "HolzapfelGasserOgden": "HGO", "LinearElastic": "linear (pre-assembled)"}


def law(name, linear, mesh):
    """The hyperelastic law ``name`` that linearises to ``linear`` (HGO: its ground matrix)."""
    if name == "HolzapfelGasserOgden":
        centres = mesh.points[mesh.tets].mean(axis=1)
        fibres = jaxsync.helical_fibres(centres, axis=(0.0, 0.0, 1.0), angle=40.0,
                                        origin=centres.mean(axis=0))
        return jaxsync.HolzapfelGasserOgden(mu=linear.mu, k1=linear.mu, k2=0.8393,
                                            kappa_bulk=linear.lam + 2.0 * linear.mu / 3.0,
                                            rho=linear.rho, fibres=fibres)
    return getattr(jaxsync, name)(linear.E, linear.nu, linear.rho)


def deformed_state(points, seed=0):
    """(n_nodes, 3) a homogeneous stretch (+2 %, -1 %, +1 %) plus a random field of 1e-4 of
    the body's size [cm]."""
    x = np.asarray(points) - np.asarray(points).mean(axis=0)
    size = float(np.ptp(x, axis=0).max())
    noise = np.random.default_rng(seed).standard_normal(x.shape)
    return jnp.asarray(x * np.array([0.02, -0.01, 0.01]) + 1e-4 * size * noise)


def xla_cost(op, u):
    """(flops, transcendentals) of the compiled matvec, XLA's cost analysis."""
    cost = matvec_jit.lower(op, u).compile().cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    return float(cost.get("flops", 0.0)), float(cost.get("transcendentals", 0.0))


def run_case(name, target, element, n_steps, repeats, peak, bandwidth):
    mesh = jaxsync.coronary_mesh(target_elements=target)
    linear = jaxsync.coronary(mesh).replace(element=element)
    dt = linear.dt
    m, n = mesh.n_elements, linear.n_nodes
    u = deformed_state(linear.space.points)
    calls, ops, systems = {}, {}, {}
    for key in LAWS:
        problem = linear.replace(material=law(key, linear.material, mesh))
        ops[key] = TotalLagrangian().operator(problem)
        systems[key] = build_system(problem, dt, TotalLagrangian())
    systems["LinearElastic"] = build_system(linear, dt, Preassembled())
    ops["LinearElastic"] = systems["LinearElastic"].stiffness
    for key, system in systems.items():
        state = initial_state(linear, system) if key == "LinearElastic" else initial_state(
            linear.replace(material=law(key, linear.material, mesh)), system)
        calls[f"{key} matvec"] = (repeated_matvec, (ops[key], u, jnp.zeros(()), n_steps))
        calls[f"{key} step"] = (advance_jit, (system, state, 1, n_steps))
    samples = sample_times(calls, repeats)
    best = {k: float(v.min()) for k, v in samples.items()}
    median = {k: float(np.median(v)) for k, v in samples.items()}
    k_nodes = int(linear.space.nodes_per_cell)
    n_q = int(ops["NeoHookean"].weights.shape[1])
    rows = []
    for key in LAWS + ("LinearElastic",):
        t_mv, t_step = best[f"{key} matvec"] / n_steps, best[f"{key} step"] / n_steps
        row = {"case": name, "element": element, "elements": m, "nodes": n, "dofs": 3 * n, "law": key,
               "nodes_per_element": k_nodes, "quadrature_points": n_q,
               "matvec_us": 1e6 * t_mv, "matvec_us_median": 1e6 * median[f"{key} matvec"] / n_steps,
               "step_us": 1e6 * t_step, "step_us_median": 1e6 * median[f"{key} step"] / n_steps,
               "steps_per_call": n_steps}
        if key != "LinearElastic":
            op = ops[key]
            flops, trans = xla_cost(op, u)
            cost = hyperelastic_element_cost(key, k_nodes, n_q)
            arrays = [op.cells, op.gradients, op.weights] + ([op.fibres] if op.fibres is not None else [])
            element_bytes = sum(int(np.asarray(a).nbytes) for a in arrays) / m
            assert element_bytes == cost["element_bytes"], (element_bytes, cost)
            bytes_per_element = element_bytes + cost["node_bytes"] * n / m
            xla_flops = (flops + trans) / m
            t_compute, t_memory = cost["flops"] * m / peak, bytes_per_element * m / bandwidth
            bound = max(t_compute, t_memory)
            bound_xla = max(xla_flops * m / peak, t_memory)
            row.update({
                "elements_per_s_per_core": m / t_mv,
                "ns_per_element": 1e9 * t_mv / m,
                "xla_flops_per_element": xla_flops, "xla_transcendentals_per_element": trans / m,
                "analytic_flops_per_element": float(cost["flops"]),
                "analytic_flops_by_part": cost["flops_by_part"],
                "bytes_per_element": bytes_per_element,
                "intensity_flop_per_byte": cost["flops"] / bytes_per_element,
                "GFlop_per_s": cost["flops"] * m / t_mv / 1e9, "GB_per_s": bytes_per_element * m / t_mv / 1e9,
                "bound": "compute" if t_compute >= t_memory else "bandwidth",
                "roofline_us": 1e6 * bound, "times_roofline": t_mv / bound,
                "times_roofline_at_xla_flops": t_mv / bound_xla,
                "within_2x_of_roofline": bool(t_mv <= 2.0 * bound),
                "matvec_vs_linear": t_mv / (best["LinearElastic matvec"] / n_steps),
                "step_vs_linear": t_step / (best["LinearElastic step"] / n_steps)})
        rows.append(row)
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="only the ~5 000-tet vessel, P1 and P2")
    parser.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "hyperelastic.json"))
    args = parser.parse_args(argv)

    # (name, target tetrahedra, element, steps per call, repeats)
    # (many rounds: a round costs well under a second, compiling a case tens of seconds)
    cases = [("vessel-5k", 5_000, "P1", 20, 60), ("vessel-5k-p2", 5_000, "P2", 5, 30),
             ("vessel-40k", 40_000, "P1", 5, 40)]
    if args.quick:
        cases = cases[:2]
    rates = []  # (flop rate, bandwidth), measured before every case and at the end: the best of each

    def measure_machine():
        rates.append((matmul_flop_rate(1024, "float64"), copy_bandwidth()))
        return max(r[0] for r in rates), max(r[1] for r in rates)

    measure_machine()
    results = []
    for name, target, element, n_steps, repeats in cases:
        peak, bandwidth = measure_machine()
        results.append(run_case(name, target, element, n_steps, repeats, peak, bandwidth))
        print(f"{name}: done (load {os.getloadavg()[0]:.2f})", flush=True)
    peak, bandwidth = measure_machine()
    rows = []
    for case_rows in results:  # the roofline of every case at the best rates of the run
        for r in case_rows:
            if "times_roofline" in r:
                m = r["elements"]
                t = r["matvec_us"] * 1e-6
                t_memory = r["bytes_per_element"] * m / bandwidth
                bound = max(r["analytic_flops_per_element"] * m / peak, t_memory)
                r.update(bound="compute" if bound > t_memory else "bandwidth", roofline_us=1e6 * bound,
                         times_roofline=t / bound, within_2x_of_roofline=bool(t <= 2.0 * bound),
                         times_roofline_at_xla_flops=t / max(r["xla_flops_per_element"] * m / peak, t_memory))
            rows.append(r)
    balance = peak / bandwidth
    print(f"one core: float64 matmul {peak / 1e9:.1f} GFlop/s, copy bandwidth (read + write) "
          f"{bandwidth / 1e9:.1f} GB/s, balance {balance:.2f} flop/B; load {os.getloadavg()[0]:.2f}")
    print(f"{'case':<13} {'law':<23} {'elems':>6} {'matvec us':>10} {'Melem/s':>8} {'flop/el':>8} "
          f"{'XLA':>6} {'B/el':>6} {'flop/B':>6} {'bound':>9} {'x roof':>7} {'step us':>9} {'x lin':>6}")
    for r in rows:
        if r["law"] == "LinearElastic":
            print(f"{r['case']:<13} {SHORT[r['law']]:<23} {r['elements']:>6} {r['matvec_us']:>10.1f} "
                  f"{'':>8} {'':>8} {'':>6} {'':>6} {'':>6} {'':>9} {'':>7} {r['step_us']:>9.1f} {1.0:>6.2f}")
            continue
        print(f"{r['case']:<13} {SHORT[r['law']]:<23} {r['elements']:>6} {r['matvec_us']:>10.1f} "
              f"{r['elements_per_s_per_core'] / 1e6:>8.2f} {r['analytic_flops_per_element']:>8.0f} "
              f"{r['xla_flops_per_element']:>6.0f} {r['bytes_per_element']:>6.0f} "
              f"{r['intensity_flop_per_byte']:>6.2f} {r['bound']:>9} {r['times_roofline']:>7.1f} "
              f"{r['step_us']:>9.1f} {r['step_vs_linear']:>6.2f}")
    worst = max(r["times_roofline"] for r in rows if "times_roofline" in r)
    best = min(r["times_roofline"] for r in rows if "times_roofline" in r)
    print(f"distance to the roofline: {best:.1f}x to {worst:.1f}x (target: within 2x) -> "
          f"{'met' if worst <= 2.0 else 'not met'}")
    result = {"benchmark": "hyperelastic", "peak_flops_per_core": peak, "bandwidth_Bps": bandwidth,
              "rates_measured": [{"flops_per_s": f, "Bps": b} for f, b in rates],
              "machine_balance_flop_per_byte": balance, "target_times_roofline": 2.0,
              "target_met": bool(worst <= 2.0), "rows": rows,
              "machine": {"platform": platform.platform(), "cores_used": 1, "cores": os.cpu_count(),
                          "python": sys.version.split()[0], "jax": jax.__version__,
                          "xla_flags": os.environ.get("XLA_FLAGS", ""), "load_average": os.getloadavg()[0]}}
    from jaxsync.io import atomic_json

    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    atomic_json(args.out, result)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
