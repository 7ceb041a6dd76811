"""Cost of one synchronization per step between processes: XLA psum (gloo, or MPI through
MPItrampoline) against an MPI Allreduce called from inside the compiled step (mpi4jax,
jaxsync's ctypes FFI handler, an mpi4py callback).

Run under MPI, one CPU device per process (loopback on one machine, or across nodes):

    mpiexec -n 2 python benchmarks/bench_sync.py [--sizes 12 1002] [--steps 2000]
                                                 [--repeats 5] [--json PATH]
                                                 [--cpu-collectives gloo|mpi]
                                                 [--case cantilever|vessel]

Every method runs a compiled ``lax.scan`` of ``--steps`` steps whose body sums an
interface vector of n doubles over the processes and feeds it back (x <- sum / n_processes,
so the values stay bounded and no step can be skipped; the result is checked); the time per
step is the wall time of the whole scan divided by the steps (best and median of
``--repeats`` runs after one compiling run). Methods:

* ``none``: the same scan without any communication (the floor of a scan step);
* ``psum-gloo``: ``jax.lax.psum`` inside ``jax.shard_map`` over the global mesh of all
  processes' devices: JAX's own CPU collectives, gloo over TCP;
* ``mpi4jax``: ``mpi4jax.allreduce`` (XLA FFI custom call into MPI, compiled C++, no host
  round trip), if mpi4jax is installed (the ``mpi`` extra);
* ``mpi-ctypes``: jaxsync's own XLA FFI custom call whose handler is a ``ctypes`` function
  calling the MPI library's ``MPI_Allreduce`` on XLA's buffers (every install, no compiler);
* ``mpi-callback``: ``jax.pure_callback`` into mpi4py ``Comm.Allreduce`` (a host round trip);
* ``mpi4py-host``: a plain Python loop of ``Comm.Allreduce`` on numpy buffers (the lower
  bound of an MPI exchange, outside JAX).

Then the real thing: the coarse cantilever (paper Table 1, 2 METIS parts, one per
process, interface of 4 nodes = 12 doubles) advanced by the distributed solver with each
synchronization (``jaxsync.solve.executors.DistributedRunner(sync=...)``), time per step of a
compiled chunk of ``--solver-steps`` steps, and the cost of one exchange: that step minus
the same chunk without synchronization (``nosync`` below). The interface sizes: 12 doubles
is that cantilever's interface; 1002 doubles (334 nodes) stands for a refined mesh. The
result also names the default of this install (``default_allreduce``, ``transport``:
:func:`jaxsync.solve.transport`).

Then the speed-up with real processes (``kind: speedup``): on the same cantilever, one part
per process, the same compiled chunks without synchronization (``nosync``), with deep
halos (``halo-k``: parts grown by k layers exchange both displacement levels every k
steps, through MPI as ``sync="mpi"`` does; :mod:`jaxsync.parallel.exchange`) and the
synchronization-avoiding program (``avoid-*``: n_s n_f unsynchronized steps and one batched
refill prediction per cycle, no collective; untrained surrogates of the paper's LSTM,
n_H = 100 at n_s = 80, of ``jaxsync train``'s default, n_H = 50 at n_s = 150, and of the
linear model at n_s = 150: the cost of a network does not depend on its weights). zeta is
the best synchronized solver row (the fastest transport) over each row. Every rank times
its own calls after a barrier; the slowest rank's time is kept.

``--case vessel``: the solver and speed-up rows on the vessel of ``jaxsync demo --case
vessel`` instead (:func:`jaxsync.app.demo.vessel_problem`, the small generated coronary
tree, mass-scaled; one METIS part per process), with the demo's surrogates at its
n_s = 1 000: the LSTM (n_H 32, 2 layers) with a linear highway of 108 directions (what the
demo's fit keeps) and the linear map of 108 directions, both with the default smooth
refill (:data:`jaxsync.surrogate.DEFAULT_REFILL_SAMPLES` network calls per refill), and
the LSTM evaluating every application (``avoid-lstm-all``); ``--solver-steps`` defaults
to one refill cycle, 20 000 steps, and the halo depths to 1, 2, 4, 8. Default output
``benchmarks/results/sync_vessel.json``.

Cost model check (``model_check``): latency and bandwidth of each transport fitted to its
``collective`` rows (``jaxsync.perf.costmodel.fit_interconnect``), the solver's t_s predicted
from the partition's interface (``sync_time``, one message of the interface for 2
processes) against the measured t_s = synchronized step - ``nosync`` step.

Rank 0 prints a table and writes JSON (default ``benchmarks/results/sync.json``).

``--cpu-collectives mpi`` measures the other candidate on its own: JAX's CPU collectives
through MPI (``jax_cpu_collectives_implementation="mpi"``, MPItrampoline), rows ``none`` and
``psum-mpi`` of the same sizes and the cantilever's ``psum-mpi`` and ``nosync`` steps. It
needs ``MPITRAMPOLINE_LIB`` naming an MPIwrapper library (compiled with C, C++ and Fortran
compilers against an MPI with Fortran bindings, which the pip ``mpich`` wheel lacks) and
runs without mpi4py, since JAX then initializes MPI itself (ranks from the launcher's
environment); default output ``benchmarks/results/sync_cpu_mpi.json``:

    MPITRAMPOLINE_LIB=/path/to/libmpiwrapper.so mpiexec -n 2 python benchmarks/bench_sync.py --cpu-collectives mpi
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

import jaxsync
from jaxsync.parallel import multiprocess  # noqa: E402  (imports no JAX state)
from jaxsync.solve import transport  # noqa: E402


def _timed(fn, repeats: int) -> list[float]:
    """Wall times [s] of ``repeats`` calls of ``fn()`` after an untimed first one (the
    harness of every jaxsync timing, :func:`jaxsync.perf.measure.sample_times`)."""
    from jaxsync.perf.measure import sample_times

    return sample_times({"fn": (fn, ())}, repeats)["fn"].tolist()


def allreduce_methods() -> list[tuple[str, str]]:
    """(row name, make_allreduce backend) of every MPI sum that runs in this install, fastest
    kind first."""
    methods = [("mpi4jax", "mpi4jax")] if multiprocess.mpi4jax_available() else []
    if multiprocess.ctypes_available():
        methods.append(("mpi-ctypes", "ctypes"))
    return methods + [("mpi-callback", "callback")]


def psum_name() -> str:
    """``psum-gloo`` or ``psum-mpi``: JAX's CPU collectives of this run."""
    import jax

    return f"psum-{jax.config.jax_cpu_collectives_implementation}"


def bench_collectives(sizes, steps: int, repeats: int, comm) -> list[dict]:
    import jax
    import numpy as np
    from jax.sharding import Mesh, NamedSharding

    from jaxsync.parallel import AXIS, part_spec, spmd_program

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
        methods[psum_name()] = (lambda f=psum, x=x_global: f(x).block_until_ready(),
                                lambda f=psum, x=x_global: np.asarray(f(x).addressable_data(0)))

        for name, backend in allreduce_methods():
            allreduce = multiprocess.make_allreduce(comm, backend)
            f = jax.jit(scan_of(allreduce))
            x = jax.device_put(x_local, local_device)
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


def case_problem(case: str):
    """The problem of ``--case``: the coarse cantilever or the vessel demo's tree."""
    if case == "vessel":
        from jaxsync.app.demo import vessel_problem

        return vessel_problem("small")[1]
    return jaxsync.cantilever()


def case_surrogates(case: str, partition) -> dict:
    """The untrained surrogates timed on ``case`` (module docstring), by row name."""
    from jaxsync.surrogate import Surrogate

    if case == "vessel":
        lstm = Surrogate.initialized(partition, 1000, n_hidden=32, n_layers=2, highway_rank=108)
        return {"avoid-lstm-vessel-demo": lstm, "avoid-lstm-all": lstm.with_refill_samples(None),
                "avoid-linear": Surrogate.initialized(partition, 1000, model="linear", rank=108)}
    return {"avoid-lstm-paper": Surrogate.initialized(partition, 80, n_hidden=100),
            "avoid-lstm-default": Surrogate.initialized(partition, 150, n_hidden=50),
            "avoid-linear": Surrogate.initialized(partition, 150, model="linear")}


def bench_solver(steps: int, repeats: int, comm, problem) -> list[dict]:
    import jax
    import numpy as np
    from mpi4py import MPI

    from jaxsync.fem import build_system, initial_state
    from jaxsync.solve.executors import DistributedRunner

    system = build_system(problem, problem.dt)
    state = initial_state(problem, system)
    n_parts = jax.process_count()
    configs = [(psum_name(), jaxsync.Psum())] + [(name, jaxsync.Mpi(allreduce=backend))
                                                for name, backend in allreduce_methods()]
    rows, finals = [], {}
    for name, sync in configs:
        runner = DistributedRunner(problem, system, n_parts, save_every=steps, sync=sync)
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
        rows_final = finals[name]
        rows.append({"kind": "solver", "method": name, "n_doubles": 3 * runner.partition.n_interface,
                     "steps": steps, "us_per_step_best": 1e6 * best / steps,
                     "us_per_step_median": 1e6 * median / steps, "final": rows_final})
    reference = finals[psum_name()]
    for row in rows:
        d = finals[row["method"]]
        row["max_rel_diff_vs_psum"] = float(np.abs(d - reference).max() / np.abs(reference).max())
    return rows


def bench_speedup(steps: int, repeats: int, comm, halo_depths, solver_rows, case: str, problem) -> list[dict]:
    """The ``nosync``, ``halo-k`` and ``avoid-*`` rows (module docstring), each with zeta
    against the best synchronized solver row of ``solver_rows``."""
    import jax
    import numpy as np
    from mpi4py import MPI

    from jaxsync.errors import PartitionError
    from jaxsync.fem import build_system, initial_state
    from jaxsync.solve.executors import DistributedRunner, PredictedPhase
    from jaxsync.surrogate.models import architecture_to_dict
    from jaxsync.surrogate.training import shared_dof_layout

    system = build_system(problem, problem.dt)
    state = initial_state(problem, system)
    n_parts = jax.process_count()
    backend = multiprocess.default_allreduce()

    def time_per_step(run, n_steps):
        comm.Barrier()
        times = _timed(run, repeats)
        return (1e6 * comm.allreduce(min(times), op=MPI.MAX) / n_steps,
                1e6 * comm.allreduce(statistics.median(times), op=MPI.MAX) / n_steps)

    rows, finals = [], {}
    local = DistributedRunner(problem, system, n_parts, save_every=steps, sync=jaxsync.Mpi(allreduce=backend))
    start = local.from_global(state)
    programs = {"nosync": (local, local.program(1, synchronize=False), start)}
    for k in halo_depths:
        try:
            halo = DistributedRunner(problem, system, local.partition, save_every=steps, sync=jaxsync.Halo(k))
        except PartitionError as exc:  # a halo that would hold a whole part: left out, and said
            if multiprocess.is_main_process():
                print(f"halo-{k} left out: {exc}")
            continue
        programs[f"halo-{k}"] = (halo, halo.program(1), halo.from_global(state))
    for name, (runner, program, begin) in programs.items():
        best, median = time_per_step(lambda p=program, b=begin, r=runner: jax.block_until_ready(p(r.parts, b)),
                                     steps)
        finals[name] = runner.to_global(program(runner.parts, begin)[0]).displacement
        rows.append({"kind": "speedup", "method": name, "steps": steps, "us_per_step_best": best,
                     "us_per_step_median": median, "transport": runner.transport})
    n_dof, _ = shared_dof_layout(local.partition)
    for name, predictor in case_surrogates(case, local.partition).items():
        cycle = predictor.n_s * predictor.n_future
        n_cycles = max(1, round(steps / cycle))
        online = PredictedPhase(local, predictor, save_every=cycle)
        buffer = local.put(np.zeros((n_parts, predictor.n_s * predictor.n_past, n_dof)))
        program = online.prepare(start, buffer, n_cycles, cycle)
        args = (local.parts, online.predictor, start, buffer, online.step_counter(0))
        best, median = time_per_step(lambda p=program, a=args: jax.block_until_ready(p(*a)), n_cycles * cycle)
        rows.append({"kind": "speedup", "method": name, "steps": n_cycles * cycle, "us_per_step_best": best,
                     "us_per_step_median": median, "n_s": predictor.n_s, "refill_calls": predictor.refill_calls,
                     "architecture": architecture_to_dict(predictor.arch)})
    synchronized = min(solver_rows, key=lambda r: r["us_per_step_best"])
    for row in rows:
        row["baseline"] = synchronized["method"]
        row["zeta"] = synchronized["us_per_step_best"] / row["us_per_step_best"]
    exact = {r["method"]: r for r in solver_rows}
    for row in rows:
        if row["method"].startswith("halo-"):
            # deep halos are exact: their final field equals the synchronized solver's
            reference = exact[psum_name()]["final"]
            row["max_rel_diff_vs_psum"] = float(np.abs(finals[row["method"]] - reference).max()
                                                / np.abs(reference).max())
    return rows


def model_check(rows, partition) -> list[dict]:
    """Cost model against the measured multi-process t_s (module docstring)."""
    import numpy as np

    from jaxsync.errors import JaxsyncError
    from jaxsync.perf import costmodel

    pattern = costmodel.communication_pattern(partition)
    nosync = next(r for r in rows if r["method"] == "nosync")["us_per_step_best"]
    checks = []
    for method in [psum_name()] + [name for name, _ in allreduce_methods()]:
        calib = [r for r in rows if r["kind"] == "collective" and r["method"] == method]
        solver = [r for r in rows if r["kind"] == "solver" and r["method"] == method]
        if not calib or not solver:
            continue
        sizes = np.array([8 * r["n_doubles"] for r in calib])
        seconds = np.array([1e-6 * r["us_per_step_best"] for r in calib])
        try:
            link = costmodel.fit_interconnect(sizes, seconds, name=method,
                                              source="fitted to this run's collective rows")
        except JaxsyncError as exc:  # too noisy to fit: the smallest message's time as latency
            if multiprocess.is_main_process():
                print(f"cost model fit ({method}): {exc}; latency = the smallest message's time")
            link = costmodel.Interconnect(method, float(seconds[np.argmin(sizes)]), 1e12,
                                          "smallest collective of this run")
        predicted = costmodel.sync_time(pattern, link, "collective")
        measured = max(solver[0]["us_per_step_best"] - nosync, 1e-3) * 1e-6
        checks.append({"method": method, "latency_us": 1e6 * link.latency_s,
                       "bandwidth_GBps": link.bandwidth_Bps / 1e9, "interface_bytes": pattern.interface_bytes,
                       "predicted_us": 1e6 * predicted, "measured_us": 1e6 * measured,
                       "relative_error": float(costmodel.relative_error(predicted, measured))})
    return checks


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[12, 120, 1002, 12000],
                        help="interface sizes in doubles (default: %(default)s)")
    parser.add_argument("--steps", type=int, default=2000, help="scan steps per timing (default: %(default)s)")
    parser.add_argument("--case", choices=("cantilever", "vessel"), default="cantilever",
                        help="the mesh of the solver and speed-up rows (default: %(default)s)")
    parser.add_argument("--solver-steps", type=int, default=None,
                        help="solver steps per timing (default: 3200 on the cantilever, one refill cycle of "
                             "20 000 on the vessel; a multiple of every --halo-depths)")
    parser.add_argument("--halo-depths", type=int, nargs="*", default=None,
                        help="deep-halo depths to time (default: 1 4 16 64 on the cantilever, 1 2 4 8 on the "
                             "vessel)")
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats (default: %(default)s)")
    parser.add_argument("--cpu-collectives", choices=("gloo", "mpi"), default="gloo",
                        help="JAX's own collectives between the CPU processes: gloo (the full comparison), or "
                             "mpi: only psum through MPItrampoline, without mpi4py (needs MPITRAMPOLINE_LIB; "
                             "default: %(default)s)")
    parser.add_argument("--json", default=None, help="output (default: benchmarks/results/sync.json, with "
                        "--cpu-collectives mpi sync_cpu_mpi.json)")
    args = parser.parse_args(argv)
    vessel = args.case == "vessel"
    if args.solver_steps is None:
        args.solver_steps = 20000 if vessel else 3200
    if args.halo_depths is None:
        args.halo_depths = [1, 2, 4, 8] if vessel else [1, 4, 16, 64]
    if args.json is None:
        name = "sync_vessel.json" if vessel else ("sync.json" if args.cpu_collectives == "gloo"
                                                  else "sync_cpu_mpi.json")
        args.json = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", name)

    if args.cpu_collectives == "mpi":
        return bench_cpu_mpi(args, argv)
    with multiprocess.abort_on_error():
        n_proc = multiprocess.initialize()
        import jax

        jax.config.update("jax_enable_x64", True)
        if n_proc < 2:
            raise SystemExit("run under MPI with 2 or more ranks: mpiexec -n 2 python "
                             "benchmarks/bench_sync.py")
        comm = multiprocess.world().Dup()
        problem = case_problem(args.case)
        rows = bench_collectives(args.sizes, args.steps, args.repeats, comm)
        solver_rows = bench_solver(args.solver_steps, args.repeats, comm, problem)
        rows += solver_rows
        rows += bench_speedup(args.solver_steps, args.repeats, comm, args.halo_depths, solver_rows, args.case,
                              problem)
        nosync = next(r for r in rows if r["method"] == "nosync")
        for row in solver_rows:
            del row["final"]
            # the cost of one exchange: the synchronized step less the same step without it
            row["us_per_exchange_best"] = row["us_per_step_best"] - nosync["us_per_step_best"]
            row["us_per_exchange_median"] = row["us_per_step_median"] - nosync["us_per_step_median"]
        import jaxsync

        checks = model_check(rows, jaxsync.partition(problem.mesh, n_proc))
        from mpi4py import MPI

        hosts = sorted(set(comm.allgather(socket.gethostname())))
        result = {
            "benchmark": "per-step synchronization between processes",
            "case": args.case, "n_dofs": int(problem.n_dofs),
            "processes": n_proc, "hosts": hosts, "devices_per_process": len(jax.local_devices()),
            "jax": jax.__version__, "mpi4py": __import__("mpi4py").__version__,
            "mpi4jax": (__import__("mpi4jax").__version__ if multiprocess.mpi4jax_available() else None),
            "cpu_collectives": args.cpu_collectives,
            "default_allreduce": multiprocess.default_allreduce(),
            "transport": transport(None, n_proc),
            "mpi_library": MPI.Get_library_version().splitlines()[0].strip(),
            "cpu_count": os.cpu_count(), "load_average": list(os.getloadavg()),
            "python": platform.python_version(),
            "command": "mpiexec -n %d python %s" % (
                n_proc, " ".join([os.path.relpath(__file__)] + (argv or sys.argv[1:]))),
            "rows": rows, "model_check": checks,
        }
        if multiprocess.is_main_process():
            _print_table(result)
            os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
            with open(args.json, "w") as f:
                json.dump(result, f, indent=2)
            print(f"wrote {args.json}")
        return result


def bench_cpu_mpi(args, argv) -> dict:
    """``--cpu-collectives mpi``: psum through JAX's MPI collectives, without mpi4py (module
    docstring)."""
    if not os.environ.get("MPITRAMPOLINE_LIB"):
        raise SystemExit("--cpu-collectives mpi needs MPITRAMPOLINE_LIB=/path/to/libmpiwrapper.so "
                         "(docs/guides/clusters.md)")
    n_proc = multiprocess.launched_size()
    if n_proc < 2:
        raise SystemExit("run under MPI with 2 or more ranks")
    import jax
    import numpy as np
    from jax.experimental import multihost_utils
    from jax.sharding import Mesh, NamedSharding

    from jaxsync.fem import build_system, initial_state
    from jaxsync.parallel import AXIS, part_spec, spmd_program
    from jaxsync.solve.executors import DistributedRunner

    jax.config.update("jax_cpu_collectives_implementation", "mpi")
    jax.config.update("jax_num_cpu_devices", 1)
    jax.config.update("jax_enable_x64", True)
    jax.distributed.initialize(coordinator_address=os.environ.get("JAX_COORDINATOR_ADDRESS", "127.0.0.1:23457"),
                               num_processes=n_proc, process_id=multiprocess.launched_rank())
    rank = jax.process_index()
    mesh = Mesh(np.array(jax.devices()), (AXIS,))

    def slowest(times) -> tuple[float, float]:  # (best, median) of the slowest rank [s]
        gathered = np.asarray(multihost_utils.process_allgather(np.array([min(times), statistics.median(times)])))
        return float(gathered[:, 0].max()), float(gathered[:, 1].max())

    rows = []
    for n in args.sizes:
        x_local = np.full(n, 1.0 + rank)

        def scan_of(body):
            def run(x0):
                return jax.lax.scan(lambda x, _: (body(x) * (1.0 / n_proc), None), x0, None, length=args.steps)[0]
            return run

        none = jax.jit(scan_of(lambda x: x[::-1] * n_proc))
        x_one = jax.device_put(x_local, jax.local_devices()[0])
        x_global = jax.make_array_from_callback((n_proc, n), NamedSharding(mesh, part_spec()), lambda i: x_local[None])
        psum = spmd_program(scan_of(lambda x: jax.lax.psum(x, AXIS)), mesh, n_in=1, n_out=1)
        value = np.asarray(psum(x_global).addressable_data(0))
        if not np.allclose(value, (n_proc + 1) / 2, rtol=1e-12):
            raise RuntimeError(f"psum-mpi: wrong sum {value[:3]}")
        for name, run in (("none", lambda: none(x_one).block_until_ready()),
                          ("psum-mpi", lambda: psum(x_global).block_until_ready())):
            best, median = slowest(_timed(run, args.repeats))
            rows.append({"kind": "collective", "method": name, "n_doubles": n, "steps": args.steps,
                         "us_per_step_best": 1e6 * best / args.steps, "us_per_step_median": 1e6 * median / args.steps})
    problem = jaxsync.cantilever()
    system = build_system(problem, problem.dt)
    runner = DistributedRunner(problem, system, n_proc, save_every=args.solver_steps, sync=jaxsync.Psum())
    start = runner.from_global(initial_state(problem, system))
    solver = {}
    for name, synchronize in (("nosync", False), ("psum-mpi", True)):
        program = runner.program(1, synchronize=synchronize)
        best, median = slowest(_timed(lambda p=program: jax.block_until_ready(p(runner.parts, start)), args.repeats))
        solver[name] = (1e6 * best / args.solver_steps, 1e6 * median / args.solver_steps)
    rows.append({"kind": "solver", "method": "psum-mpi", "n_doubles": 3 * runner.partition.n_interface,
                 "steps": args.solver_steps, "us_per_step_best": solver["psum-mpi"][0],
                 "us_per_step_median": solver["psum-mpi"][1],
                 "us_per_exchange_best": solver["psum-mpi"][0] - solver["nosync"][0],
                 "us_per_exchange_median": solver["psum-mpi"][1] - solver["nosync"][1]})
    rows.append({"kind": "speedup", "method": "nosync", "steps": args.solver_steps,
                 "us_per_step_best": solver["nosync"][0], "us_per_step_median": solver["nosync"][1]})
    result = {"benchmark": "per-step psum between processes through JAX's MPI collectives",
              "processes": n_proc, "devices_per_process": len(jax.local_devices()), "jax": jax.__version__,
              "cpu_collectives": "mpi", "mpitrampoline_lib": os.environ["MPITRAMPOLINE_LIB"],
              "cpu_count": os.cpu_count(), "load_average": list(os.getloadavg()),
              "python": platform.python_version(),
              "command": "MPITRAMPOLINE_LIB=... mpiexec -n %d python %s" % (
                  n_proc, " ".join([os.path.relpath(__file__)] + (argv or sys.argv[1:]))),
              "rows": rows}
    if rank == 0:
        print(f"psum through JAX's MPI collectives, {n_proc} processes (jax {jax.__version__})")
        print(f"{'what':<11} {'method':<10} {'doubles':>7} {'best us/step':>13} {'median us/step':>15} "
              f"{'us/exchange':>12}")
        for row in rows:
            exchange = f"{row['us_per_exchange_best']:12.2f}" if "us_per_exchange_best" in row else ""
            print(f"{row['kind']:<11} {row['method']:<10} {row.get('n_doubles', ''):>7} "
                  f"{row['us_per_step_best']:>13.2f} {row['us_per_step_median']:>15.2f} {exchange}")
        os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
        with open(args.json, "w") as f:
            json.dump(result, f, indent=2)
        print(f"wrote {args.json}")
    jax.distributed.shutdown()
    return result


def _print_table(result: dict) -> None:
    print(f"per-step synchronization, {result['processes']} processes on {', '.join(result['hosts'])} "
          f"(jax {result['jax']}, mpi4jax {result['mpi4jax']}, {result['mpi_library']})")
    print(f"the default of this install: {result['transport']}")
    print(f"{'what':<11} {'method':<19} {'doubles':>7} {'best us/step':>13} {'median us/step':>15} "
          f"{'us/exchange':>12} {'zeta':>6}")
    for row in result["rows"]:
        zeta = f"{row['zeta']:6.2f}" if "zeta" in row else ""
        exchange = f"{row['us_per_exchange_best']:12.2f}" if "us_per_exchange_best" in row else " " * 12
        print(f"{row['kind']:<11} {row['method']:<19} {row.get('n_doubles', ''):>7} "
              f"{row['us_per_step_best']:>13.2f} {row['us_per_step_median']:>15.2f} {exchange} {zeta}")
    print("us/exchange: the synchronized solver step less the nosync step (best times); "
          "zeta: the best synchronized solver row over the row")
    for c in result["model_check"]:
        print(f"cost model, {c['method']}: fitted latency {c['latency_us']:.1f} us, bandwidth "
              f"{c['bandwidth_GBps']:.2f} GB/s; t_s of the solver predicted {c['predicted_us']:.1f} us, "
              f"measured {c['measured_us']:.1f} us ({100 * c['relative_error']:+.0f} %)")


if __name__ == "__main__":
    main()
