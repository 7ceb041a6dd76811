"""Reverse mode through long runs: time and memory of checkpointed gradients, and their
agreement with central finite differences.

**Timing and memory, coarse cantilever** (104 nodes, 312 dofs): the gradient of a scalar
loss (the tip's vertical displacement at the end) with respect to E and the damping alpha
through 1e3, 1e4 and 1e5 steps (``--quick``: 1e3 and 1e4), by
``jax.grad(jaxsync.simulate)`` with ``gradient_checkpoints=True`` (recomputation,
:mod:`jaxsync.solve.gradients`) and, for comparison, ``False`` (plain reverse mode through
``lax.scan``: every step stored; left out at 1e5 steps, where its buffers exceed 7 GB).
Per case:

- ``forward_s``: the jitted forward run (the loss alone), best of a few calls;
- ``grad_s``: the jitted value-and-gradient, best of a few calls; ``ratio`` = grad / forward;
- ``temp_bytes``: the compiled program's temporary memory (XLA buffer assignment,
  ``compiled.memory_analysis().temp_size_in_bytes``: the peak of the reverse pass's
  stored residuals and work buffers);
- ``vs_all_states``: temp_bytes relative to storing every state, n_steps * 2 * n_dofs * 8
  bytes (the two displacement levels of every step).

**Finite differences at 1e4 steps** (``fd_checks``; the target: gradients equal
central finite differences to 1e-6 relative on the coarse cantilever through 1e4 steps,
single device and partitioned): the objective is the mean squared free-end (tip)
displacement over the saves (every 10th step, in units of 1e-4 cm squared); its gradient
in E and alpha by ``jax.grad`` (checkpointed) on one device and with ``partitions=2``
(psum over 2 emulated devices), against central differences of the same (jitted, float64)
forward run with relative steps h = 1e-2 ... 1e-6 and the Richardson extrapolation
(4 D(h/2) - D(h)) / 3 of the largest (h = 1e-2: its error is O(h^4)). Recorded: every
relative difference, the best, and met / missed against 1e-6. The forward run's round-off
(about 5e-11 relative after 1e4 steps) makes small steps worse: the error of D(h) is
about 5e-11 / (h * relative sensitivity), and the objective's relative sensitivity to
alpha is only 0.07, so plain differences in alpha reach at best 7e-7 (h = 1e-3), the
extrapolated one about 1e-8.

**A 109k-dof mesh** (``--large``): the refined cantilever
``box_beam(25, 1, 1, (160, 14, 14))`` (36 225 nodes, 108 675 dofs), forward and
checkpointed gradient through 1e4 steps, each compiled first and then timed once (the
gradient takes minutes on 2 cores). Plain reverse mode is not run there: its residuals
(measured 3.0 MB per step at 500 steps) would take about 30 GB at 1e4 steps, more than the
machine's 24 GiB. Beside it, a breakdown at 500 steps: forward, checkpointed
and plain gradients in (E, alpha), the checkpointed gradient in alpha alone (E
constant: the stiffness gets no cotangent), and the checkpointed gradient in (E, nu,
alpha), to show where the reverse pass's time goes (one warm-up call, then the best of
two timed calls each).

**E's cotangent.** With nu fixed (every row but the last), the preassembled stiffness
of a mesh of 1 500 nodes or more is E K(E=1, nu), its blocks constants and E a traced
scale (:class:`jaxsync.fem.forces.Preassembled`): the reverse pass sums one
scalar per step, <K_1 y_bar, u>. With nu traced too (the (E, nu, alpha) row), the blocks
are lambda K_lambda + mu K_mu, traced, and the reverse pass carries their cotangent, an
array as large as K, across the time loop, as every row did before (issue 29). The
coarse cantilever (104 nodes) keeps the Lame blocks: there the per-step dot product
measured slower than the blocks' cotangent (``Preassembled.scale_min_nodes``).

**E's cotangent against the Lame blocks** (``--cotangent``, added to the existing result
file as ``cotangent``): on the beams ``box_beam(25, 1, 1, d)`` of 8 967, 36 663 and
108 675 dofs, the checkpointed gradient in (E, alpha) (E the stiffness's scale) and in
(E, nu, alpha) (the Lame blocks, as before), both compiled first, then their forward and
gradient calls alternated three times in one process and the best of each kept (the
machine is shared: alternating puts both under the same load).

Usage: python benchmarks/bench_gradients.py [--quick] [--large] [--no-fd] [--cotangent]
                                            [--out benchmarks/results/gradients.json]
"""

from __future__ import annotations

import argparse
import os
import platform
import time

os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                           + " --xla_force_host_platform_device_count=2").strip()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxsync  # noqa: E402
from jaxsync.perf.measure import best_time  # noqa: E402

FD_TARGET = 1e-6  # relative agreement with central finite differences
LARGE_DIVISIONS = (160, 14, 14)  # 36 225 nodes, 108 675 dofs
COTANGENT_CASES = (((60, 6, 6), 2000), ((100, 10, 10), 1000), (LARGE_DIVISIONS, 500))  # (divisions, steps)


def tip_node(mesh):
    x = mesh.points
    return int(np.argmax(x[:, 0] - 1e-3 * np.abs(x[:, 1]) - 1e-3 * np.abs(x[:, 2])))


def make_loss(problem, n_steps, checkpoints, names=("E", "alpha")):
    """The tip's vertical displacement at the end as a function of ``names`` (of E, alpha,
    nu; the others fixed at 1e6, 0.5, 0.3)."""
    tip = tip_node(problem.mesh)
    dt = problem.dt

    def loss(*values):
        v = dict({"E": 1.0e6, "alpha": 0.5, "nu": 0.3}, **dict(zip(names, values)))
        p = problem.replace(material=jaxsync.LinearElastic(v["E"], v["nu"], 1.0), damping=v["alpha"])
        adjoint = jaxsync.Recompute() if checkpoints else jaxsync.StoreAll()
        traj = jaxsync.simulate(p, n_steps, dt=dt, save=n_steps, executor=jaxsync.TracedExecutor(adjoint))
        return traj.displacement[-1, tip, 2]

    return loss


def make_objective(problem, n_steps, save_every, **kwargs):
    """The mean squared tip displacement over the saves [(1e-4 cm)^2]: smooth in E and alpha."""
    tip, dt = tip_node(problem.mesh), problem.dt

    def objective(E, alpha):
        p = problem.replace(material=jaxsync.LinearElastic(E, 0.3, 1.0), damping=alpha)
        traj = jaxsync.simulate(p, n_steps, dt=dt, save=save_every, **kwargs)
        return jnp.mean(jnp.sum(traj.displacement[:, tip, :] ** 2, axis=-1)) / (1e-4 ** 2)

    return objective


def best_of(f, args, repeats):
    return best_time(f, repeats, *args)  # one untimed call, then the best of `repeats`


def once(f, args):
    start = time.perf_counter()
    jax.block_until_ready(f(*args))
    return time.perf_counter() - start


START = {"E": 1.0e6, "alpha": 0.5, "nu": 0.3}


def measure(problem, n_steps, checkpoints, repeats, *, wrt=("E", "alpha"), single_call=False):
    args = tuple(jnp.asarray(START[n]) for n in wrt)
    loss = make_loss(problem, n_steps, checkpoints, wrt)
    start = time.perf_counter()
    forward = jax.jit(loss).lower(*args).compile()
    grad = jax.jit(jax.value_and_grad(loss, tuple(range(len(wrt))))).lower(*args).compile()
    compile_s = time.perf_counter() - start
    temp = int(grad.memory_analysis().temp_size_in_bytes)
    forward_temp = int(forward.memory_analysis().temp_size_in_bytes)
    timer = once if single_call else (lambda f, a: best_of(f, a, repeats))
    forward_s = timer(forward, args)
    grad_s = timer(grad, args)
    all_states = n_steps * 2 * problem.mesh.n_dofs * 8
    return {"n_steps": n_steps, "n_dofs": problem.mesh.n_dofs, "checkpoints": checkpoints,
            "wrt": list(wrt),
            "forward_s": forward_s, "grad_s": grad_s, "ratio": grad_s / forward_s,
            "timing": "one call after compiling" if single_call else f"best of {repeats} after a warm-up",
            "compile_s": compile_s, "temp_bytes": temp, "forward_temp_bytes": forward_temp,
            "all_states_bytes": all_states, "vs_all_states": temp / all_states}


def fd_check(problem, n_steps, save_every, partitions=None, steps=(1e-2, 1e-3, 1e-4, 1e-5, 1e-6)):
    """jax.grad (checkpointed) of :func:`make_objective` in (E, alpha) against central
    differences with relative steps ``steps`` and a Richardson extrapolation."""
    kwargs = {} if partitions is None else {"partitions": partitions}
    objective = make_objective(problem, n_steps, save_every, **kwargs)
    x0 = (1.0e6, 0.5)
    start = time.perf_counter()
    value, grads = jax.jit(jax.value_and_grad(objective, (0, 1)))(*map(jnp.asarray, x0))
    grad_s = time.perf_counter() - start
    f = jax.jit(objective)

    def central(i, h):
        plus, minus = list(x0), list(x0)
        plus[i] += h
        minus[i] -= h
        return (float(f(*plus)) - float(f(*minus))) / (2 * h)

    result = {"partitions": partitions or 1, "n_steps": n_steps, "save_every": save_every,
              "objective": float(value), "grad_s_incl_compile": grad_s, "target": FD_TARGET}
    for i, name in enumerate(("E", "alpha")):
        ad = float(grads[i])
        fd = {h: central(i, h * x0[i]) for h in steps}
        half = central(i, 0.5 * steps[0] * x0[i])
        richardson = (4 * half - fd[steps[0]]) / 3
        rel = {f"{h:g}": abs(fd[h] - ad) / abs(ad) for h in steps}
        best_h = min(rel, key=rel.get)
        rel_r = abs(richardson - ad) / abs(ad)
        best = min(rel[best_h], rel_r)
        result[name] = {"ad": ad, "fd": {f"{h:g}": fd[h] for h in steps}, "rel_diff": rel,
                        "best_h": best_h, "richardson": richardson, "rel_diff_richardson": rel_r,
                        "best_rel_diff": best, "met": bool(best <= FD_TARGET)}
    return result


def compare_cotangents(divisions, n_steps, rounds=3):
    """Checkpointed gradients in (E, alpha) and (E, nu, alpha) on ``box_beam(25, 1, 1,
    divisions)``: forward and gradient calls alternated ``rounds`` times, best of each."""
    problem = jaxsync.cantilever(jaxsync.box_beam(25.0, 1.0, 1.0, divisions))
    programs = {}
    for names in (("E", "alpha"), ("E", "nu", "alpha")):
        args = tuple(jnp.asarray(START[n]) for n in names)
        loss = make_loss(problem, n_steps, True, names)
        grad = jax.jit(jax.value_and_grad(loss, tuple(range(len(names))))).lower(*args).compile()
        forward = jax.jit(loss).lower(*args).compile()
        once(forward, args), once(grad, args)  # warm-up
        programs[names] = (forward, grad, args)
    best = {names: [np.inf, np.inf] for names in programs}
    for _ in range(rounds):
        for names, (forward, grad, args) in programs.items():
            best[names] = [min(best[names][0], once(forward, args)), min(best[names][1], once(grad, args))]
    rows = [{"mesh": f"box_beam(25, 1, 1, {tuple(divisions)})", "n_dofs": problem.mesh.n_dofs,
             "n_steps": n_steps, "checkpoints": True, "wrt": list(names), "forward_s": f, "grad_s": g,
             "ratio": g / f, "timing": f"best of {rounds} alternated calls after a warm-up"}
            for names, (f, g) in best.items()]
    rows[0]["speedup_vs_lame"] = rows[1]["grad_s"] / rows[0]["grad_s"]
    return rows


def write(path, result):
    from jaxsync.io import atomic_json

    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    result["machine"] = {"platform": platform.platform(), "cpus": os.cpu_count(),
                         "load_average": os.getloadavg()[0], "jax": jax.__version__}
    atomic_json(path, result)


def print_row(row):
    print(f"{row['n_dofs']:>7} {row['n_steps']:>7} {str(row['checkpoints']):>5} {','.join(row['wrt']):>7} "
          f"{row['forward_s']:9.3f} {row['grad_s']:9.3f} {row['ratio']:6.2f} {row['temp_bytes'] / 1e6:10.3f} "
          f"{row['all_states_bytes'] / 1e6:16.3f} {row['vs_all_states']:9.4f}", flush=True)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1e3 and 1e4 steps only")
    parser.add_argument("--large", action="store_true",
                        help="also the 109k-dof mesh through 1e4 steps (about 10 minutes on 2 cores)")
    parser.add_argument("--no-fd", action="store_true", help="leave out the finite-difference checks")
    parser.add_argument("--cotangent", action="store_true",
                        help="only compare E's cotangent with the Lame blocks' on three beams, added to --out")
    parser.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "gradients.json"))
    args = parser.parse_args(argv)
    if args.cotangent:
        import json

        with open(args.out) as f:
            result = json.load(f)
        result["cotangent"] = []
        for divisions, n_steps in COTANGENT_CASES:
            for row in compare_cotangents(divisions, n_steps):
                result["cotangent"].append(row)
                print(f"{row['n_dofs']:>7} {row['n_steps']:>6} {','.join(row['wrt']):>12} forward "
                      f"{row['forward_s']:.3f} s  gradient {row['grad_s']:.3f} s  ratio {row['ratio']:.2f}"
                      + (f"  ({row['speedup_vs_lame']:.2f}x faster)" if "speedup_vs_lame" in row else ""),
                      flush=True)
        from jaxsync.io import atomic_json

        # the other sections' machine record stays theirs
        result["cotangent_machine"] = {"platform": platform.platform(), "cpus": os.cpu_count(),
                                       "load_average": os.getloadavg()[0], "jax": jax.__version__}
        atomic_json(args.out, result)
        print(f"wrote {args.out}")
        return
    problem = jaxsync.cantilever()
    cases = [(1000, True), (1000, False), (10000, True), (10000, False)]
    if not args.quick:
        cases.append((100000, True))
    result = {"problem": "coarse cantilever", "n_dofs": problem.mesh.n_dofs, "rows": []}
    print(f"{'dofs':>7} {'steps':>7} {'ckpt':>5} {'wrt':>7} {'fwd [s]':>9} {'grad [s]':>9} {'ratio':>6} "
          f"{'temp [MB]':>10} {'all states [MB]':>16} {'temp/all':>9}")
    for n_steps, checkpoints in cases:
        row = measure(problem, n_steps, checkpoints, repeats=3 if n_steps <= 10000 else 1)
        result["rows"].append(row)
        print_row(row)
    write(args.out, result)

    if not args.no_fd:
        result["fd_checks"] = []
        print(f"\ncentral differences, {10000} steps, objective mean |u_tip|^2 over every 10th step:")
        for partitions in (None, 2):
            check = fd_check(problem, 10000, 10, partitions)
            result["fd_checks"].append(check)
            for name in ("E", "alpha"):
                c = check[name]
                rel = " ".join(f"h={h}: {r:.1e}" for h, r in c["rel_diff"].items())
                print(f"  parts={check['partitions']} d/d{name:<5} ad={c['ad']:+.10e}  {rel}  "
                      f"richardson: {c['rel_diff_richardson']:.1e}  best {c['best_rel_diff']:.1e} "
                      f"({'met' if c['met'] else 'MISSED'} vs {FD_TARGET:g})", flush=True)
            write(args.out, result)

    if args.large:
        mesh = jaxsync.box_beam(25.0, 1.0, 1.0, LARGE_DIVISIONS)
        large = jaxsync.cantilever(mesh)
        per_step = 3 * 3 * mesh.n_nodes * 8  # plain reverse mode: 3 fields per step (step_residual_bytes)
        result["large"] = {"mesh": f"box_beam(25, 1, 1, {LARGE_DIVISIONS})", "n_dofs": mesh.n_dofs,
                           "dt": large.dt, "rows": [], "breakdown": [],
                           "plain_1e4_estimate_bytes": 10000 * per_step,
                           "plain_1e4_note": "not run: more than the machine's 24 GiB"}
        print(f"\nlarge mesh: {mesh.n_dofs} dofs; plain reverse mode through 1e4 steps would store about "
              f"{10000 * per_step / 2**30:.1f} GiB (not run)")
        for n_steps, checkpoints, wrt in ((500, True, ("E", "alpha")), (500, False, ("E", "alpha")),
                                          (500, True, ("alpha",)), (500, True, ("E", "nu", "alpha"))):
            row = measure(large, n_steps, checkpoints, 2, wrt=wrt)
            result["large"]["breakdown"].append(row)
            print_row(row)
            write(args.out, result)
        row = measure(large, 10000, True, 1, single_call=True)
        result["large"]["rows"].append(row)
        print_row(row)
        write(args.out, result)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
