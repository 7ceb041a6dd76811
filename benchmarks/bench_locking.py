"""Volumetric locking as nu -> 0.5: linear, quadratic and nodal-pressure tetrahedra against
analytic solutions.

Three elements on the same meshes:

- ``P1``: jaxsync's linear tetrahedron (``element="P1"``);
- ``P2``: jaxsync's quadratic tetrahedron (``element="P2"``; isoparametric on the curved
  mesh of the cylinder);
- ``P1-ANP``: the average-nodal-pressure linear tetrahedron of explicit soft-tissue
  solvers (Bonet & Burton 1998), built here from jaxsync's P1 operators: the deviatoric
  part of P1 and a volumetric energy (kappa / 2) sum_a V_a theta_a^2 on nodal volumetric
  strains theta_a, the volume-weighted average of div u over the elements around node a
  (V_a a quarter of their volumes). Its stiffness is
  K = mu (K_mu - 2/3 K_lambda) + kappa G^T A^T V_n^-1 A G with kappa = lambda + 2 mu / 3.

Cases (each error relative to the largest exact displacement):

- ``lame``: the plane-strain thick cylinder (radii 1 and 2) under internal pressure with
  its outer wall on springs (``jaxsync.ElasticSupport``), exact u_r = A r + B / r; the
  root-mean-square nodal error of u (u_z = 0 exact) on two unstructured meshes;
- ``cantilever``: the paper's beam (25 x 1 x 1, 25 x 2 x 2 cells) under its weight, tip
  deflection against Euler-Bernoulli's q L^4 / (8 E I) (bending: P1 and P1-ANP lock in
  shear whatever nu).

For each, the exact stable step 2 / omega_max (:func:`jaxsync.max_stable_dt`) that an
explicit run of that element takes, and the number of dofs: the cost of an explicit run is
about dofs x stencil / dt.

Usage: python benchmarks/bench_locking.py [--nu 0.3 0.45 0.49 0.499] [--quick]
    [--out benchmarks/results/locking.json]

``--quick``: the coarse cylinder only and nu 0.3 and 0.499 (the test's settings).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import experiments  # noqa: E402  (machine())
import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
import scipy.sparse as sp  # noqa: E402

import jaxsync  # noqa: E402
from jaxsync.io import atomic_json  # noqa: E402

DEFAULT_OUT = os.path.join(HERE, "results", "locking.json")
E = 1.0e6
ELEMENTS = ("P1", "P1-ANP", "P2")


def nodal_pressure_operators(problem):
    """The unit operators of the average-nodal-pressure tetrahedron on ``problem``'s P1
    space: K = lambda K_lambda' + mu K_mu' with K_lambda' = G^T A^T V_n^-1 A G and
    K_mu' = K_mu + 2/3 (K_lambda' - K_lambda) (see the module docstring)."""
    ops = problem.operators
    points, tets = problem.mesh.points, problem.mesh.tets
    n_elements = len(tets)
    X = points[tets]
    J = np.stack([X[:, 1] - X[:, 0], X[:, 2] - X[:, 0], X[:, 3] - X[:, 0]], axis=2)
    volumes = np.linalg.det(J) / 6.0
    grads = np.zeros((n_elements, 4, 3))
    grads[:, 1:] = np.linalg.inv(J)  # rows: gradients of the barycentric coordinates 1..3
    grads[:, 0] = -grads[:, 1:].sum(axis=1)
    # G u = V_e div u_e (one row per element); A averages element values onto the nodes
    G = sp.csr_matrix(((volumes[:, None, None] * grads).ravel(),
                       (np.repeat(np.arange(n_elements), 12), (3 * tets[:, :, None] + np.arange(3)).ravel())),
                      shape=(n_elements, 3 * len(points)))
    A = sp.csr_matrix((np.full(4 * n_elements, 0.25), (tets.ravel(), np.repeat(np.arange(n_elements), 4))),
                      shape=(len(points), n_elements))
    nodal_volumes = A @ volumes
    K_nodal = (G.T @ A.T @ sp.diags(1.0 / nodal_volumes) @ A @ G).tocsr()
    # sanity: the element-wise volumetric operator G^T V^-1 G is P1's K_lambda
    assert abs(G.T @ sp.diags(1.0 / volumes) @ G - ops.K_lambda).max() <= 1e-9 * abs(ops.K_lambda).max()
    # (a replaced operators object starts with no bounds: they are of the new K)
    return dataclasses.replace(ops, K_lambda=K_nodal, K_mu=(ops.K_mu + (2.0 / 3.0) * (K_nodal - ops.K_lambda)).tocsr())


def with_element(problem, element: str):
    if element == "P1-ANP":
        return problem.replace(element="P1", operators=nodal_pressure_operators(problem.replace(element="P1")))
    return problem.replace(element=element)


def lame_cylinder(size: float, nu: float):
    """The plane-strain cylinder problem (P1) and its exact radial displacement u_r(r)."""
    mesh = jaxsync.vessel_mesh(None, length=4.0, radius=1.0, wall=1.0, size=size, order=2)
    p, k = 1.0e4, 2.0e5
    problem = jaxsync.Problem(mesh, jaxsync.LinearElastic(E, nu, 1.0), element="P1",
                              dirichlet=[jaxsync.Dirichlet(face, components=(2,)) for face in ("inlet", "outlet")],
                              loads=[jaxsync.Pressure(p, jaxsync.Constant(), surface="lumen")],
                              supports=[jaxsync.ElasticSupport(k, surface="outer")])
    lam, mu = problem.material.lam, problem.material.mu
    a, b = 1.0, 2.0
    A, B = np.linalg.solve([[2 * (lam + mu), -2 * mu / a**2], [2 * (lam + mu) + k * b, -2 * mu / b**2 + k / b]],
                           [-p, 0.0])
    return problem, lambda r: A * r + B / r


def lame_error(problem, exact) -> float:
    u = jaxsync.steady_state(problem)
    x = problem.points
    r = np.hypot(x[:, 0], x[:, 1])
    exact_u = np.stack([exact(r) * x[:, 0] / r, exact(r) * x[:, 1] / r, 0.0 * r], axis=1)
    return float(np.sqrt(np.mean(np.sum((u - exact_u) ** 2, axis=1))) / np.abs(exact(r)).max())


def cantilever_error(problem) -> float:
    theory = 0.5 * 25.0**4 / (8 * E / 12.0)  # rho g = 0.5, I = 1/12
    tip = -jaxsync.steady_state(problem)[:, 2].min()
    return float((tip - theory) / theory)


def row(case: str, size, nu: float, element: str, problem, error: float, seconds: float) -> dict:
    return {"case": case, "size": size, "nu": nu, "element": element, "dofs": problem.n_dofs,
            "n_elements": problem.mesh.n_elements, "error": error,
            "stable_dt": float(jaxsync.max_stable_dt(problem)), "seconds": seconds}


def run(nus, sizes, cantilever: bool, progress: bool = True) -> list[dict]:
    rows = []
    for nu in nus:
        cases = [("lame", size, *lame_cylinder(size, nu)) for size in sizes]
        if cantilever:
            beam = jaxsync.cantilever(jaxsync.box_beam(25.0, 1.0, 1.0, (25, 2, 2)),
                                      material=jaxsync.LinearElastic(E, nu, 1.0))
            cases.append(("cantilever", None, beam, None))
        for case, size, base, exact in cases:
            for element in ELEMENTS:
                start = time.perf_counter()
                problem = with_element(base, element)
                error = lame_error(problem, exact) if case == "lame" else cantilever_error(problem)
                rows.append(row(case, size, nu, element, problem, error, time.perf_counter() - start))
                if progress:
                    r = rows[-1]
                    print(f"  {case:10s} size {size} nu {nu:<6g} {element:6s} dofs {r['dofs']:7d} "
                          f"error {100 * error:+8.3f} %  dt {r['stable_dt']:.3e} s", flush=True)
    return rows


def table(rows: list[dict]) -> str:
    lines = ["| case | size | nu | dofs P1 / P2 | P1 error % | P1-ANP error % | P2 error % | "
             "stable dt P1 / P1-ANP / P2 [s] |", "|---|---|---|---|---|---|---|---|"]
    keys = sorted({(r["case"], r["size"] or 0.0, r["nu"]) for r in rows}, key=lambda k: (k[0] != "lame", k[1], k[2]))
    for case, size, nu in keys:
        by = {r["element"]: r for r in rows if (r["case"], r["size"] or 0.0, r["nu"]) == (case, size, nu)}
        lines.append(f"| {case} | {size or '-'} | {nu:g} | {by['P1']['dofs']} / {by['P2']['dofs']} | "
                     + " | ".join(f"{100 * by[e]['error']:+.3g}" for e in ELEMENTS)
                     + " | " + " / ".join(f"{by[e]['stable_dt']:.2e}" for e in ELEMENTS) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--nu", type=float, nargs="+", default=None,
                        help="Poisson ratios (default 0.3 0.45 0.49 0.499; --quick 0.3 0.499)")
    parser.add_argument("--quick", action="store_true", help="the coarse cylinder only, nu 0.3 and 0.499")
    parser.add_argument("--quiet", action="store_true", help="no per-case lines")
    parser.add_argument("--out", default=DEFAULT_OUT, help="result JSON (default %(default)s)")
    args = parser.parse_args(argv)
    nus = args.nu or ((0.3, 0.499) if args.quick else (0.3, 0.45, 0.49, 0.499))
    sizes = (0.5,) if args.quick else (0.5, 0.35, 0.25)
    rows = run(nus, sizes, cantilever=not args.quick, progress=not args.quiet)
    text = table(rows)
    print(text)
    atomic_json(args.out, {"rows": rows, "quick": args.quick, "table": text, "machine": experiments.machine(),
                           "command": "python benchmarks/bench_locking.py" + (" --quick" if args.quick else "")})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
