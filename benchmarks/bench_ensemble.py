"""Ensembles whose members differ in material: set-up time per member and batched speed.

``jaxsync.ensemble(problem, n_steps, members=jaxsync.Members(...))`` sets up n_runs
cantilevers (the paper's coarse beam, 312 dofs) that differ in Young's modulus E (and, in
the ``E,nu,rho`` case, Poisson ratio and density), damping alpha and load magnitude in one
vectorised pass; ``jaxsync.ensemble(problems, n_steps)`` takes one
:class:`jaxsync.Problem` per member. Per case and size:

- ``setup_ms_per_member``: the vectorised call's wall time less the compilation of the
  stepping program and the steps themselves (``stats``), per member: everything else
  (checks, stability bounds, the batched system, the initial states, the trajectories).
  ``cold`` is the first call at that size in the process (it compiles the vmapped start,
  the consistent-mass solve of every member, once per shape; the process's own first-use
  costs are spent before, on an ensemble of 2 members, except with ``--quick``); ``warm``
  a second call;
- ``problems_ms_per_member``: the same with the members given as problems
  (``jaxsync.cantilever(mesh, material=..., body_force=...)`` each, their construction
  included: each assembles its mesh's unit operators);
- ``own_systems_ms_per_member``: each member set up on its own (its Problem, its full
  system ``build_system``, its start ``initial_state`` and its stability check
  ``check_dt``), on up to ``--own-systems-members`` members;
- ``run_steps_per_s``: members times batched steps per second (``stats.us_per_step`` of the
  warm call, ``--steps`` steps; every call runs them).

Vessels (rows with ``"problem": "vessel"``): the demo's coronary tree
(``jaxsync.app.demo.vessel_problem``: the generated tree of about ``--vessel-size``
tetrahedra under the paper's pulsatile lumen pressure, mass-scaled to 2.5 times its CFL
step), ``--vessel-members`` members whose E (and in the ``E,nu,rho`` case nu and rho)
differ, ``--vessel-steps`` batched steps: the set-up per member (first call and compiled,
as above), the batched step and run-steps per second, and ``max_rel_diff_member_vs_simulate``:
the largest |difference| of the last member's trajectory from ``jaxsync.simulate`` of its
own problem (``members.problem(problem, r)``) at the ensemble's step, over its largest
|displacement|.

Usage: python benchmarks/bench_ensemble.py [--members 64 512] [--steps 2000]
    [--vessel-members 32] [--vessel-steps 500] [--vessel-size 3500] [--quick]
    [--out benchmarks/results/ensemble/ensemble.json]

``--quick``: 8 members, 100 steps; vessels: 2 members, 20 steps (the test's settings).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import experiments  # noqa: E402  (machine())
import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxsync  # noqa: E402
from jaxsync.io import atomic_json  # noqa: E402

DEFAULT_OUT = os.path.join(HERE, "results", "ensemble", "ensemble.json")
CASES = ("E", "E,nu,rho")


def draw(case: str, n: int, seed: int = 0) -> dict:
    """The members' parameters: E ~ U(0.8, 1.2) 1e6 dyn/cm^2, alpha ~ U(0.1, 1) 1/s, load
    factor ~ U(0.6, 1.4); with ``E,nu,rho`` also nu ~ U(0.2, 0.35), rho ~ U(0.9, 1.1) g/cm^3."""
    rng = np.random.default_rng(seed)
    material = {"E": rng.uniform(0.8e6, 1.2e6, n)}
    if case == "E,nu,rho":
        material.update(nu=rng.uniform(0.2, 0.35, n), rho=rng.uniform(0.9, 1.1, n))
    return {"material": material, "damping": rng.uniform(0.1, 1.0, n), "load_scale": rng.uniform(0.6, 1.4, n)}


def setup_seconds(call, n_steps: int) -> tuple[float, tuple]:
    """(wall time of ``call()`` less its stepping program's compilation and steps [s], its trajectories)."""
    start = time.perf_counter()
    trajectories = call()
    wall = time.perf_counter() - start
    stats = trajectories[0].stats
    return wall - stats.compile_seconds - stats.us_per_step * 1e-6 * n_steps, trajectories


def own_systems_per_member(mesh, params: dict, n: int, dt: float) -> float:
    """Seconds per member of setting each member up on its own (module docstring), over n members."""
    from jaxsync.fem import build_system, check_dt, initial_state

    start = time.perf_counter()
    for r in range(n):
        material = jaxsync.LinearElastic(*(float(params["material"].get(k, d)[r]) if k in params["material"] else d
                                           for k, d in (("E", 1e6), ("nu", 0.3), ("rho", 1.0))))
        problem = jaxsync.cantilever(mesh, material=material, damping=float(params["damping"][r]),
                                     body_force=(0.0, 0.0, -0.5 * float(params["load_scale"][r])))
        check_dt(problem, dt)
        initial_state(problem, build_system(problem, dt))
    return (time.perf_counter() - start) / n


def measure(case: str, n: int, n_steps: int, own_systems_members: int) -> dict:
    mesh = jaxsync.box_beam()
    base = jaxsync.cantilever(mesh)
    params = draw(case, n)
    members = jaxsync.Members(**params)
    quiet = jaxsync.HostExecutor(progress=False)

    def vectorised():
        return jaxsync.ensemble(base, n_steps, members=members, save=n_steps, executor=quiet)

    cold, runs = setup_seconds(vectorised, n_steps)
    warm, again = setup_seconds(vectorised, n_steps)  # its steps timed for the batched speed too
    dt = float(runs[0].dt)
    problems_start = time.perf_counter()
    problems = []
    for r in range(n):  # as a user writes them: one cantilever per member
        material = jaxsync.LinearElastic(*(float(params["material"][k][r]) if k in params["material"] else d
                                           for k, d in (("E", 1e6), ("nu", 0.3), ("rho", 1.0))))
        problems.append(jaxsync.cantilever(mesh, material=material, damping=float(params["damping"][r]),
                                           body_force=(0.0, 0.0, -0.5 * float(params["load_scale"][r]))))
    built = time.perf_counter() - problems_start
    per_problem, together = setup_seconds(
        lambda: jaxsync.ensemble(problems, n_steps, dt=dt, save=n_steps, executor=quiet), n_steps)
    difference = max(float(np.abs(a.displacement - b.displacement).max() / max(np.abs(b.displacement).max(), 1e-300))
                     for a, b in zip(runs, together))
    own = own_systems_per_member(mesh, params, min(n, own_systems_members), dt)
    us = again[0].stats.us_per_step
    return {"problem": "cantilever", "case": case, "members": n, "dofs": base.n_dofs, "dt": dt,
            "setup_ms_per_member": {"cold": 1e3 * cold / n, "warm": 1e3 * warm / n},
            "problems_ms_per_member": 1e3 * (built + per_problem) / n,
            "problems_construction_ms_per_member": 1e3 * built / n,
            "own_systems_ms_per_member": 1e3 * own, "own_systems_members": min(n, own_systems_members),
            "max_rel_diff_members_vs_problems": difference,
            "steps": n_steps, "us_per_batched_step": us, "run_steps_per_s": n * 1e6 / us,
            "compile_s": runs[0].stats.compile_seconds}


def draw_vessel(case: str, n: int, material, seed: int = 0) -> dict:
    """The vessel members' material: E ~ U(0.8, 1.2) times the problem's; with ``E,nu,rho``
    also nu ~ U(0.35, 0.45) and rho ~ U(0.9, 1.1) times the problem's (the wall's 0.4 and 1)."""
    rng = np.random.default_rng(seed)
    out = {"E": material.E * rng.uniform(0.8, 1.2, n)}
    if case == "E,nu,rho":
        out.update(nu=rng.uniform(0.35, 0.45, n), rho=material.rho * rng.uniform(0.9, 1.1, n))
    return out


def vessel_case(size: int):
    """The demo's vessel, mass-scaled (module docstring)."""
    from jaxsync.app.demo import vessel_problem

    return vessel_problem(size)[1]


def measure_vessel(problem, case: str, n: int, n_steps: int) -> dict:
    """One vessel row (module docstring)."""
    members = jaxsync.Members(material=draw_vessel(case, n, problem.material))
    quiet = jaxsync.HostExecutor(progress=False)

    def vectorised():
        return jaxsync.ensemble(problem, n_steps, members=members, save=n_steps, executor=quiet)

    cold, runs = setup_seconds(vectorised, n_steps)
    warm, again = setup_seconds(vectorised, n_steps)
    dt = float(runs[0].dt)
    last = n - 1  # the member checked against its own run
    alone = jaxsync.simulate(members.problem(problem, last), n_steps, dt=dt, save=n_steps, executor=quiet)
    reference = np.asarray(alone.displacement)
    difference = float(np.abs(np.asarray(runs[last].displacement) - reference).max()
                       / max(np.abs(reference).max(), 1e-300))
    us = again[0].stats.us_per_step
    return {"problem": "vessel", "case": case, "members": n, "dofs": problem.n_dofs,
            "elements": int(problem.mesh.n_elements), "dt": dt,
            "setup_ms_per_member": {"cold": 1e3 * cold / n, "warm": 1e3 * warm / n},
            "max_rel_diff_member_vs_simulate": difference, "member_checked": last,
            "us_per_step_member_alone": alone.stats.us_per_step,
            "steps": n_steps, "us_per_batched_step": us, "run_steps_per_s": n * 1e6 / us,
            "compile_s": runs[0].stats.compile_seconds}


def table(rows: list[dict]) -> str:
    lines = ["| problem | varying | members | setup ms/member cold / warm | as problems ms/member "
             "| own systems ms/member | us / batched step | run-steps/s |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        s = r["setup_ms_per_member"]
        if r.get("problem") == "vessel":
            lines.append(f"| vessel ({r['dofs']} dofs) | {r['case']} | {r['members']} | {s['cold']:.2f} / "
                         f"{s['warm']:.2f} | - | - | {r['us_per_batched_step']:.0f} | {r['run_steps_per_s']:.3g} |")
            continue
        lines.append(f"| cantilever ({r['dofs']} dofs) | {r['case']} | {r['members']} | {s['cold']:.2f} / "
                     f"{s['warm']:.2f} | "
                     f"{r['problems_ms_per_member']:.1f} | {r['own_systems_ms_per_member']:.1f} | "
                     f"{r['us_per_batched_step']:.0f} | {r['run_steps_per_s']:.3g} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--members", type=int, nargs="+", default=None, help="ensemble sizes (default 64 512)")
    parser.add_argument("--steps", type=int, default=None, help="batched steps timed (default 2000; --quick 100)")
    parser.add_argument("--case", nargs="+", choices=CASES, default=None, help="what varies (default: both)")
    parser.add_argument("--own-systems-members", type=int, default=64,
                        help="members set up on their own, timed (default 64)")
    parser.add_argument("--vessel-members", type=int, nargs="*", default=None,
                        help="vessel ensemble sizes (default 32; --quick 2; none: no vessel rows)")
    parser.add_argument("--vessel-steps", type=int, default=None,
                        help="batched vessel steps timed (default 500; --quick 20)")
    parser.add_argument("--vessel-size", type=int, default=3500,
                        help="target tetrahedra of the vessel (default %(default)s)")
    parser.add_argument("--quick", action="store_true", help="8 members, 100 steps; vessels 2 members, 20 steps")
    parser.add_argument("--out", default=DEFAULT_OUT, help="result JSON (default %(default)s)")
    args = parser.parse_args(argv)
    sizes = args.members or ([8] if args.quick else [64, 512])
    n_steps = args.steps or (100 if args.quick else 2000)
    if not args.quick:  # the process's first-use costs (imports, first compilations), outside the rows
        jaxsync.ensemble(jaxsync.cantilever(), 10, members=jaxsync.Members(damping=np.array([0.5, 0.6])),
                         executor=jaxsync.HostExecutor(progress=False))
    rows = []
    for case in args.case or CASES:
        for n in sizes:
            rows.append(measure(case, n, n_steps, 8 if args.quick else args.own_systems_members))
            r = rows[-1]
            print(f"{case} x {n}: setup {r['setup_ms_per_member']['cold']:.2f} ms/member (cold), "
                  f"{r['setup_ms_per_member']['warm']:.2f} (warm); as problems {r['problems_ms_per_member']:.1f}; "
                  f"own systems {r['own_systems_ms_per_member']:.1f}", flush=True)
    vessel_sizes = [2] if args.quick and args.vessel_members is None else (
        [32] if args.vessel_members is None else args.vessel_members)
    vessel_steps = args.vessel_steps or (20 if args.quick else 500)
    vessel = vessel_case(args.vessel_size) if vessel_sizes else None
    for case in (args.case or CASES) if vessel_sizes else ():
        for n in vessel_sizes:
            rows.append(measure_vessel(vessel, case, n, vessel_steps))
            r = rows[-1]
            print(f"vessel ({r['elements']} tets, {r['dofs']} dofs) {case} x {n}: setup "
                  f"{r['setup_ms_per_member']['cold']:.2f} ms/member (cold), {r['setup_ms_per_member']['warm']:.2f} "
                  f"(warm); {r['us_per_batched_step']:.0f} us per batched step, {r['run_steps_per_s']:.3g} "
                  f"run-steps/s; member {r['member_checked']} vs simulate {r['max_rel_diff_member_vs_simulate']:.1e}",
                  flush=True)
    text = table(rows)
    print(text)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    atomic_json(args.out, {"rows": rows, "quick": args.quick, "table": text, "machine": experiments.machine(),
                           "command": " ".join(["python benchmarks/bench_ensemble.py",
                                                   *(sys.argv[1:] if argv is None else map(str, argv))])})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
