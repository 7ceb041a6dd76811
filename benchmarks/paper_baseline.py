"""Baseline: one synchronized explicit step per loop iteration the way the paper's
published code does it (NumPy/SciPy on each MPI rank, force synchronization through
rank 0), for comparison with jaxsync in ``bench_distributed.py``.

Run under MPI, one rank per part:

    mpiexec -n 2 python benchmarks/paper_baseline.py INPUT.npz OUTPUT.json [--steps N]
                                                     [--comm pickle|buffers]

Per step, on every rank (the structure of the published distributed solver):

1. F_int = K_r d, the part's own stiffness (SciPy CSR) times its local displacements;
2. F_ext = F_r R(t_n), the ramped external load at the local nodes;
3. the *unsynchronized* update d(n+1) from F_int (the published code forms it every step
   as training data for the surrogates) and its Dirichlet values;
4. synchronization: every rank's partial F_int is gathered on rank 0 together with the
   rank's global node numbers, rank 0 adds them into a global force vector and
   broadcasts the whole vector back, and each rank takes its local entries
   (``--comm pickle``, the default: ``comm.gather`` / ``comm.bcast`` of Python objects as
   in the published code; ``--comm buffers``: ``Gatherv`` / ``Bcast`` of NumPy buffers,
   the same pattern without pickling);
5. the synchronized update d(n+1) = [dt^2 (F_ext - F_int)/m + 2 d(n)
   - (1 - alpha dt/2) d(n-1)] / (1 + alpha dt/2), then the Dirichlet values (zero).

INPUT.npz (written by ``bench_distributed.py``) holds, for each part r: ``K{r}_data``,
``K{r}_indices``, ``K{r}_indptr`` (local stiffness, node-interleaved dofs), ``nodes{r}``
(global node ids), ``mass{r}``, ``load{r}`` (per local dof), ``fixed{r}`` (local dof
ids); and ``n_nodes``, ``dt``, ``alpha``, ``t_ramp``, ``d0``, ``dm1`` (global initial
d(0), d(-1), (n_nodes * 3,)). Rank 0 writes OUTPUT.json: per-step times averaged over the
run for each rank (product t_m, synchronization t_s, total t_t), the max-average (the
rank with the largest t_t), and the final global displacement for checking.
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np
import scipy.sparse as sp
from mpi4py import MPI


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("input", help="npz file with the parts (see the module docstring)")
    parser.add_argument("output", help="JSON file written by rank 0")
    parser.add_argument("--steps", type=int, default=1000, help="time steps (default: %(default)s)")
    parser.add_argument("--comm", choices=("pickle", "buffers"), default="pickle",
                        help="gather/bcast of Python objects (as published) or of NumPy buffers")
    args = parser.parse_args(argv)

    comm = MPI.COMM_WORLD
    rank, size = comm.Get_rank(), comm.Get_size()
    data = np.load(args.input)
    n_parts = int(data["n_parts"])
    if size != n_parts:
        if rank == 0:
            print(f"error: {args.input} has {n_parts} parts; run with mpiexec -n {n_parts}", flush=True)
        comm.Abort(2)
    n_dofs = 3 * int(data["n_nodes"])
    nodes = data[f"nodes{rank}"]
    dofs = (3 * nodes[:, None] + np.arange(3)).ravel()
    n_local = len(dofs)
    K = sp.csr_matrix((data[f"K{rank}_data"], data[f"K{rank}_indices"], data[f"K{rank}_indptr"]),
                      shape=(n_local, n_local))
    mass, load, fixed = data[f"mass{rank}"], data[f"load{rank}"], data[f"fixed{rank}"]
    dt, alpha, t_ramp = float(data["dt"]), float(data["alpha"]), float(data["t_ramp"])
    d, d_prev = data["d0"][dofs].copy(), data["dm1"][dofs].copy()
    half = 0.5 * alpha * dt
    counts = comm.allgather(n_local)
    all_dofs = comm.gather(dofs, root=0)
    if rank == 0:
        displs = np.concatenate([[0], np.cumsum(counts)[:-1]])
        gathered = np.empty(sum(counts))
        gathered_dofs = np.concatenate(all_dofs)
    global_force = np.empty(n_dofs)

    def synchronize_pickle(f_int):
        forces = comm.gather(f_int, root=0)
        local_dofs = comm.gather(dofs, root=0)
        if rank == 0:
            total = np.zeros(n_dofs)
            for f, ids in zip(forces, local_dofs):
                total[ids] += f
        else:
            total = None
        total = comm.bcast(total, root=0)
        return total[dofs]

    def synchronize_buffers(f_int):
        if rank == 0:
            comm.Gatherv(f_int, [gathered, counts, displs, MPI.DOUBLE], root=0)
            global_force[:] = 0.0
            np.add.at(global_force, gathered_dofs, gathered)
        else:
            comm.Gatherv(f_int, None, root=0)
        comm.Bcast(global_force, root=0)
        return global_force[dofs]

    synchronize = synchronize_pickle if args.comm == "pickle" else synchronize_buffers

    def update(f_ext, f_int):
        new = (dt * dt * (f_ext - f_int) / mass + 2.0 * d - (1.0 - half) * d_prev) / (1.0 + half)
        new[fixed] = 0.0
        return new

    t_product = t_sync = 0.0
    comm.Barrier()
    start = MPI.Wtime()
    for n in range(args.steps):
        t0 = MPI.Wtime()
        f_int = K @ d
        t1 = MPI.Wtime()
        f_ext = load * min(n * dt / t_ramp, 1.0)
        unsynchronized = update(f_ext, f_int)  # noqa: F841  (surrogate training data)
        t2 = MPI.Wtime()
        f_int = synchronize(f_int)
        t3 = MPI.Wtime()
        d, d_prev = update(f_ext, f_int), d
        t_product += t1 - t0
        t_sync += t3 - t2
    total = MPI.Wtime() - start
    per_rank = comm.gather({"rank": rank, "n_dofs": n_local, "t_m": t_product / args.steps,
                            "t_s": t_sync / args.steps, "t_t": total / args.steps}, root=0)
    final = comm.gather(d, root=0)
    if rank == 0:
        displacement = np.zeros(n_dofs)
        for values, ids in zip(final, all_dofs):
            displacement[ids] = values
        top = max(per_rank, key=lambda r: r["t_t"])
        result = {"kind": "paper-baseline", "comm": args.comm, "n_ranks": size, "n_steps": args.steps,
                  "ranks": per_rank, "max_average": top, "t_step": top["t_t"],
                  "loadavg": list(os.getloadavg()), "final_displacement": displacement.tolist()}
        tmp = args.output + ".tmp"
        with open(tmp, "w") as f:
            json.dump(result, f)
        os.replace(tmp, args.output)


if __name__ == "__main__":
    main()
