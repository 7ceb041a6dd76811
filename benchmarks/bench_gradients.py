"""Reverse mode through long runs: time and memory of checkpointed gradients.

On the coarse cantilever (104 nodes, 312 dofs), the gradient of a scalar loss (the tip's
vertical displacement at the end) with respect to E and the damping alpha through 1e3, 1e4
and 1e5 steps (``--quick``: 1e3 and 1e4), by ``jax.grad(jaxsync.simulate)`` with
``gradient_checkpoints=True`` (recomputation, :mod:`jaxsync.solve.gradients`) and, for
comparison, ``False`` (plain reverse mode through ``lax.scan``: every step stored; left
out at 1e5 steps, where its buffers exceed 7 GB). Per case:

- ``forward_s``: the jitted forward run (the loss alone), best of a few calls;
- ``grad_s``: the jitted value-and-gradient, best of a few calls; ``ratio`` = grad / forward;
- ``temp_bytes``: the compiled program's temporary memory (XLA buffer assignment,
  ``compiled.memory_analysis().temp_size_in_bytes``: the peak of the reverse pass's
  stored residuals and work buffers);
- ``vs_all_states``: temp_bytes relative to storing every state, n_steps * 2 * n_dofs * 8
  bytes (the two displacement levels of every step).

Usage: python benchmarks/bench_gradients.py [--quick] [--out benchmarks/results/gradients.json]
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

import numpy as np  # noqa: E402

import jaxsync  # noqa: E402


def make_loss(problem, n_steps, checkpoints):
    x = problem.mesh.points
    tip = int(np.argmax(x[:, 0] - 1e-3 * np.abs(x[:, 1]) - 1e-3 * np.abs(x[:, 2])))
    dt = problem.dt

    def loss(E, alpha):
        p = problem.replace(material=jaxsync.LinearElastic(E, 0.3, 1.0), damping=alpha)
        traj = jaxsync.simulate(p, n_steps, dt=dt, save_every=n_steps, gradient_checkpoints=checkpoints)
        return traj.displacement[-1, tip, 2]

    return loss


def best_of(f, args, repeats):
    jax.block_until_ready(f(*args))  # compiled and warm
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(f(*args))
        times.append(time.perf_counter() - start)
    return min(times)


def measure(problem, n_steps, checkpoints, repeats):
    args = (jax.numpy.asarray(1.0e6), jax.numpy.asarray(0.5))
    loss = make_loss(problem, n_steps, checkpoints)
    forward = jax.jit(loss)
    grad = jax.jit(jax.value_and_grad(loss, (0, 1)))
    start = time.perf_counter()
    compiled = grad.lower(*args).compile()
    compile_s = time.perf_counter() - start
    temp = int(compiled.memory_analysis().temp_size_in_bytes)
    forward_s = best_of(forward, args, repeats)
    grad_s = best_of(compiled, args, repeats)
    all_states = n_steps * 2 * problem.mesh.n_dofs * 8
    return {"n_steps": n_steps, "checkpoints": checkpoints, "forward_s": forward_s, "grad_s": grad_s,
            "ratio": grad_s / forward_s, "compile_s": compile_s, "temp_bytes": temp,
            "all_states_bytes": all_states, "vs_all_states": temp / all_states}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1e3 and 1e4 steps only")
    parser.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "gradients.json"))
    args = parser.parse_args(argv)
    problem = jaxsync.cantilever()
    cases = [(1000, True), (1000, False), (10000, True), (10000, False)]
    if not args.quick:
        cases.append((100000, True))
    rows = []
    print(f"{'steps':>7} {'ckpt':>5} {'fwd [s]':>9} {'grad [s]':>9} {'ratio':>6} "
          f"{'temp [MB]':>10} {'all states [MB]':>16} {'temp/all':>9}")
    for n_steps, checkpoints in cases:
        row = measure(problem, n_steps, checkpoints, repeats=3 if n_steps <= 10000 else 1)
        rows.append(row)
        print(f"{n_steps:>7} {str(checkpoints):>5} {row['forward_s']:9.4f} {row['grad_s']:9.4f} "
              f"{row['ratio']:6.2f} {row['temp_bytes'] / 1e6:10.3f} {row['all_states_bytes'] / 1e6:16.3f} "
              f"{row['vs_all_states']:9.4f}", flush=True)
    result = {"problem": "coarse cantilever", "n_dofs": problem.mesh.n_dofs, "rows": rows,
              "machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                          "load_average": os.getloadavg()[0], "jax": jax.__version__}}
    from jaxsync.io import atomic_json

    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    atomic_json(args.out, result)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
