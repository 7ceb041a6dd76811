"""Cost of one synchronization per step between processes: XLA psum (gloo) against an MPI
Allreduce called from inside the compiled step.

Run under MPI, one CPU device per process (loopback on one machine, or across nodes):

    mpiexec -n 2 python benchmarks/bench_sync.py [--sizes 12 1002] [--steps 2000]
                                                 [--repeats 5] [--json PATH]

Every method runs a compiled ``lax.scan`` of ``--steps`` steps whose body sums an
interface vector of n doubles over the processes and feeds it back (x <- sum / n_processes,
so the values stay bounded and no step can be skipped; the result is checked); the time per step is the wall
time of the whole scan divided by the steps (best and median of ``--repeats`` runs after
one compiling run). Methods:

* ``none``: the same scan without any communication (the floor of a scan step);
* ``psum-gloo``: ``jax.lax.psum`` inside ``jax.shard_map`` over the global mesh of all
  processes' devices (JAX's CPU collectives: gloo over TCP);
* ``mpi4jax``: ``mpi4jax.allreduce`` (XLA FFI custom call into MPI, no host round trip),
  if mpi4jax is installed;
* ``mpi-callback``: ``jax.pure_callback`` into mpi4py ``Comm.Allreduce``;
* ``mpi4py-host``: a plain Python loop of ``Comm.Allreduce`` on numpy buffers (the lower
  bound of an MPI exchange, outside JAX).

Then the real thing: the coarse cantilever (paper Table 1, 2 METIS parts, one per
process, interface of 4 nodes = 12 doubles) advanced by the distributed solver with each
synchronization (``jaxsync.solve.distributed.DistributedRunner(sync=...)``), time per step of a
compiled chunk of ``--solver-steps`` steps. The interface sizes: 12 doubles is that
cantilever's interface; 1002 doubles (334 nodes) stands for a refined mesh.

Rank 0 prints a table and writes JSON (default ``benchmarks/results/sync.json``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import socket
import statistics
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from jaxsync.parallel import multiprocess  # noqa: E402  (imports no JAX state)


def _timed(fn, repeats: int) -> list[float]:
    """Wall times [s] of ``repeats`` calls of ``fn()`` after an untimed first one (the
    harness of every jaxsync timing, :func:`jaxsync.perf.measure.sample_times`)."""
    from jaxsync.perf.measure import sample_times

    return sample_times({"fn": (fn, ())}, repeats)["fn"].tolist()


def bench_collectives(sizes, steps: int, repeats: int, comm) -> list[dict]:
    import jax
    import numpy as np
    from jax.sharding import Mesh, NamedSharding

    from jaxsync.parallel.spmd import AXIS, part_spec, spmd_program

    n_proc = jax.process_count()
    global_mesh = Mesh(np.array(jax.devices()), (AXIS,))
    local_device = jax.local_devices()[0]

    def scan_of(body):
        def run(x0):
            def step(x, _):
                return body(x) * (1.0 / n_proc), None

            return jax.lax.scan(step, x0, None, length=steps)[0]

        return run

    rows = []
    for n in sizes:
        x_local = np.full(n, 1.0 + comm.Get_rank())
        expected = sum(1.0 + r for r in range(n_proc)) / n_proc  # the mean, from step 1 on
        methods = {}

        # no communication: the floor of a scan step
        none = jax.jit(scan_of(lambda x: x[::-1] * n_proc))  # not elided
        methods["none"] = (lambda f=none, x=jax.device_put(x_local, local_device): f(x).block_until_ready(), None)

        # psum over the global mesh (gloo between processes), one part per device
        sharding = NamedSharding(global_mesh, part_spec())
        x_global = jax.make_array_from_callback((n_proc, n), sharding, lambda idx: x_local[None])
        psum = spmd_program(scan_of(lambda x: jax.lax.psum(x, AXIS)), global_mesh, n_in=1, n_out=1)
        methods["psum-gloo"] = (lambda f=psum, x=x_global: f(x).block_until_ready(),
                                lambda f=psum, x=x_global: np.asarray(f(x).addressable_data(0)))

        backends = ["mpi4jax", "callback"] if multiprocess.mpi4jax_available() else ["callback"]
        for backend in backends:
            allreduce = multiprocess.make_allreduce(comm, backend)
            f = jax.jit(scan_of(allreduce))
            x = jax.device_put(x_local, local_device)
            name = "mpi4jax" if backend == "mpi4jax" else "mpi-callback"
            methods[name] = (lambda f=f, x=x: f(x).block_until_ready(), lambda f=f, x=x: np.asarray(f(x)))

        from mpi4py import MPI

        send, recv = x_local.copy(), np.empty_like(x_local)

        def host_loop():
            for _ in range(steps):
                comm.Allreduce(send, recv, op=MPI.SUM)

        methods["mpi4py-host"] = (host_loop, None)

        for name, (run, result) in methods.items():
            if result is not None:  # check the sum before timing it
                value = result()
                if not np.allclose(value, expected, rtol=1e-12):
                    raise RuntimeError(f"{name}: wrong sum {value[:3]} (expected {expected})")
            comm.Barrier()
            times = _timed(run, repeats)
            worst = comm.allreduce(max(times), op=MPI.MAX)  # slowest rank bounds the step
            best = comm.allreduce(min(times), op=MPI.MAX)
            median = comm.allreduce(statistics.median(times), op=MPI.MAX)
            rows.append({"kind": "collective", "method": name, "n_doubles": n, "steps": steps,
                         "us_per_step_best": 1e6 * best / steps,
                         "us_per_step_median": 1e6 * median / steps,
                         "us_per_step_worst": 1e6 * worst / steps})
    return rows


def bench_solver(steps: int, repeats: int, comm) -> list[dict]:
    import jax
    import numpy as np
    from mpi4py import MPI

    import jaxsync
    from jaxsync.fem.stepper import build_system, initial_state
    from jaxsync.solve.distributed import DistributedRunner

    problem = jaxsync.cantilever()
    system = build_system(problem, problem.dt)
    state = initial_state(problem, system)
    n_parts = jax.process_count()
    configs = [("psum", "auto", "psum-gloo")]
    if multiprocess.mpi4jax_available():
        configs.append(("mpi", "mpi4jax", "mpi4jax"))
    configs.append(("mpi", "callback", "mpi-callback"))
    rows, finals = [], {}
    for sync, backend, name in configs:
        runner = DistributedRunner(problem, system, n_parts, save_every=steps, sync=sync,
                                   allreduce=backend)
        start_state = runner.from_global(state)
        compiled = runner.program(1)

        def run(compiled=compiled, start_state=start_state):
            jax.block_until_ready(compiled(runner.parts, start_state))

        comm.Barrier()
        times = _timed(run, repeats)
        best = comm.allreduce(min(times), op=MPI.MAX)
        median = comm.allreduce(statistics.median(times), op=MPI.MAX)
        final, _ = compiled(runner.parts, start_state)
        finals[name] = runner.to_global(final).displacement
        rows.append({"kind": "solver", "method": name, "n_doubles": 3 * runner.partition.n_interface,
                     "steps": steps, "us_per_step_best": 1e6 * best / steps,
                     "us_per_step_median": 1e6 * median / steps})
    reference = finals["psum-gloo"]
    for row in rows:
        d = finals[row["method"]]
        row["max_rel_diff_vs_psum"] = float(np.abs(d - reference).max() / np.abs(reference).max())
    return rows


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[12, 1002],
                        help="interface sizes in doubles (default: %(default)s)")
    parser.add_argument("--steps", type=int, default=2000, help="scan steps per timing (default: %(default)s)")
    parser.add_argument("--solver-steps", type=int, default=4000,
                        help="cantilever steps per timing (default: %(default)s)")
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats (default: %(default)s)")
    parser.add_argument("--json", default=os.path.join(os.path.dirname(os.path.abspath(__file__)),
                                                       "results", "sync.json"))
    args = parser.parse_args(argv)

    with multiprocess.abort_on_error():
        n_proc = multiprocess.initialize()
        import jax

        jax.config.update("jax_enable_x64", True)
        if n_proc < 2:
            raise SystemExit("run under MPI with 2 or more ranks: mpiexec -n 2 python "
                             "benchmarks/bench_sync.py")
        comm = multiprocess.world().Dup()
        rows = bench_collectives(args.sizes, args.steps, args.repeats, comm)
        rows += bench_solver(args.solver_steps, args.repeats, comm)
        from mpi4py import MPI

        hosts = sorted(set(comm.allgather(socket.gethostname())))
        result = {
            "benchmark": "per-step synchronization between processes",
            "processes": n_proc, "hosts": hosts, "devices_per_process": len(jax.local_devices()),
            "jax": jax.__version__, "mpi4py": __import__("mpi4py").__version__,
            "mpi4jax": (__import__("mpi4jax").__version__ if multiprocess.mpi4jax_available() else None),
            "mpi_library": MPI.Get_library_version().splitlines()[0].strip(),
            "cpu_count": os.cpu_count(), "load_average": list(os.getloadavg()),
            "python": platform.python_version(),
            "command": "mpiexec -n %d python %s" % (
                n_proc, " ".join([os.path.relpath(__file__)] + (argv or sys.argv[1:]))),
            "rows": rows,
        }
        if multiprocess.is_main_process():
            _print_table(result)
            os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
            with open(args.json, "w") as f:
                json.dump(result, f, indent=2)
            print(f"wrote {args.json}")
        return result


def _print_table(result: dict) -> None:
    print(f"per-step synchronization, {result['processes']} processes on {', '.join(result['hosts'])} "
          f"(jax {result['jax']}, mpi4jax {result['mpi4jax']}, {result['mpi_library']})")
    print(f"{'what':<11} {'method':<13} {'doubles':>7} {'best us/step':>13} {'median us/step':>15}")
    for row in result["rows"]:
        print(f"{row['kind']:<11} {row['method']:<13} {row['n_doubles']:>7} "
              f"{row['us_per_step_best']:>13.2f} {row['us_per_step_median']:>15.2f}")


if __name__ == "__main__":
    main()
