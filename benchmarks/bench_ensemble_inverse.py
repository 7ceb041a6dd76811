"""Gradients through an ensemble of vessels: many noisy observations fitted at once.

A batched inverse problem on the demo's vessel (``jaxsync.app.demo.vessel_problem``: the
generated coronary tree of about ``--size`` tetrahedra under the paper's pulsatile lumen
pressure, mass-scaled to 2.5 times its CFL step). Each of ``--members`` vessels has its own
unknown Young's modulus E_r, drawn from E_0 U(0.7, 1.3) (seeded); its "measurement" is the
displacement of ``--observed`` wall nodes (drawn among the lumen's nodes, seeded) at every
``--save``-th of ``--steps`` steps, computed by :func:`jaxsync.ensemble` at the true moduli
plus Gaussian noise of standard deviation sigma = ``--noise`` times the RMS of the
noise-free observations (independent per member, per node, per component, per time).

All E_r are recovered together from theta_r = log(E_r / E_0), starting at theta = 0, by
Gauss-Newton, member by member but in batched runs: member r's residuals r_r (its
predictions minus its data, over nodes, components and saves) depend on theta_r alone, so

- ONE reverse-mode gradient of the summed loss 1/2 sum_r |r_r|^2 (``jax.grad`` through the
  whole ensemble run, checkpointed: :class:`jaxsync.TracedExecutor`'s default adjoint)
  gives every member's g_r = J_r . r_r, J_r = d r_r / d theta_r, at once;
- the curvature J_r . J_r comes from central differences of the residuals with every
  member perturbed at once (theta +- 1e-4: two batched forward runs), and only scales the
  step: the fixed point, g = 0, is that of the exact gradient;
- the step is theta_r -= g_r / (J_r . J_r); the fit stops when the largest step is below
  1e-10 or after ``--iterations`` iterations.

(Forward mode, ``jax.jvp``, would give every J_r in one pass, but the stiffness product
has a custom reverse pass (``jax.custom_vjp``: a gather instead of scatter-adds, 5x faster
gradients), which JAX does not differentiate in forward mode.)

Reported per member: the recovered and true E, the relative error, and the error in units
of the Cramer-Rao standard deviation of the estimate, sigma / |J_r| (at the estimate);
for a correct estimator and model these are standard normal, so the table's ``max |z|``
should be a few units at most. Beside it, the reverse-mode gradient of the summed
least-squares loss (``jax.grad`` through the ensemble, in log E: the program the fit
uses) against central finite differences of the loss (step 1e-5 in log E) for two
members, at the start (E = E_0 for every member, where the gradient is far from zero), and the times of one
forward run, one forward-mode derivative and one gradient (each compiled first, then
timed once; the batched run advances all members in one program,
``stats``-free :class:`jaxsync.TracedExecutor`).

Usage: python benchmarks/bench_ensemble_inverse.py [--members 16] [--steps 2000]
    [--save 100] [--observed 40] [--noise 0.01] [--size 3500] [--iterations 10] [--seed 0]
    [--quick] [--out benchmarks/results/ensemble_inverse.json]

``--quick``: 3 members, 200 steps saved every 20, 12 observed nodes (the test's settings).
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
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jaxsync  # noqa: E402
from jaxsync.app.demo import vessel_problem  # noqa: E402

RESULTS = os.path.join(HERE, "results", "ensemble_inverse.json")


def draw(problem, n_members: int, n_observed: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(true E (n_members,) [dyn/cm^2], observed node ids (n_observed,)), seeded."""
    rng = np.random.default_rng(seed)
    E0 = float(problem.material.E)
    truth = E0 * rng.uniform(0.7, 1.3, n_members)
    lumen = np.unique(problem.mesh.facet_set("lumen"))
    fixed = np.unique(problem.dirichlet_dofs()[0] // 3)
    candidates = np.setdiff1d(lumen, fixed)
    nodes = np.sort(rng.choice(candidates, size=min(n_observed, len(candidates)), replace=False))
    return truth, nodes


def make_predict(problem, n_steps: int, save: int, nodes: np.ndarray, dt: float):
    """predict(E (n,)) -> (n, n_saves, n_observed, 3) displacements [cm] at the observed
    nodes after the start, one batched run (jit-compiled)."""
    nodes = jnp.asarray(nodes)
    executor = jaxsync.TracedExecutor()

    @jax.jit
    def predict(E):
        runs = jaxsync.ensemble(problem, n_steps, members=jaxsync.Members(material={"E": E}), dt=dt, save=save,
                                executor=executor)
        return jnp.stack([run.displacement[1:, nodes] for run in runs])

    return predict


def misfit(predict, data, E0: float, n_members: int):
    """(residuals(theta) (n, m), loss(theta) = 1/2 sum |r|^2, its compiled gradient) in
    theta = log(E / E0): one reverse-mode program, for the fit and for its check."""
    def residuals(theta):
        return (predict(E0 * jnp.exp(theta)) - data).reshape(n_members, -1)

    def loss(theta):
        return 0.5 * jnp.sum(residuals(theta) ** 2)

    return residuals, jax.jit(loss), jax.jit(jax.grad(loss))


def gauss_newton(residuals, gradient, n_members: int, iterations: int,
                 epsilon: float = 1e-4) -> tuple[np.ndarray, list, np.ndarray]:
    """(theta (n,), history of the largest |step|, J_r . J_r (n,) at the estimate) of the
    per-member Gauss-Newton fit of log(E_r / E0) (module docstring)."""
    def information(theta):  # J_r . J_r by central differences, all members at once
        J = (residuals(theta + epsilon) - residuals(theta - epsilon)) / (2.0 * epsilon)
        return jnp.sum(J * J, axis=1)

    theta = jnp.zeros(n_members)
    steps = []
    for _ in range(iterations):
        step = -gradient(theta) / information(theta)
        theta = theta + step
        steps.append(float(jnp.max(jnp.abs(step))))
        if steps[-1] < 1e-10:
            break
    return np.asarray(theta), steps, np.asarray(information(theta))


def gradient_check(loss, gradient, theta: np.ndarray, members=(0, 1), step: float = 1e-5) -> list[dict]:
    """jax.grad of the loss in theta = log E against central differences of it, per member."""
    g = np.asarray(gradient(jnp.asarray(theta)))
    out = []
    for r in members:
        e = np.zeros_like(theta)
        e[r] = step
        fd = (float(loss(jnp.asarray(theta + e))) - float(loss(jnp.asarray(theta - e)))) / (2 * step)
        out.append({"member": int(r), "grad": float(g[r]), "central_difference": fd,
                    "relative_difference": abs(float(g[r]) - fd) / abs(fd)})
    return out


def timed(call, *args) -> float:
    """Seconds of one call after a first (compiling) one."""
    jax.block_until_ready(call(*args))
    start = time.perf_counter()
    jax.block_until_ready(call(*args))
    return time.perf_counter() - start


def run(*, members: int, steps: int, save: int, observed: int, noise: float, size, iterations: int,
        seed: int) -> dict:
    """The benchmark (module docstring): a dict of its settings and results."""
    _, problem, _ = vessel_problem(size)
    dt = float(problem.dt)
    truth, nodes = draw(problem, members, observed, seed)
    predict = make_predict(problem, steps, save, nodes, dt)
    clean = predict(jnp.asarray(truth))
    sigma = noise * float(jnp.sqrt(jnp.mean(clean ** 2)))
    data = clean + sigma * jnp.asarray(np.random.default_rng(seed + 1).standard_normal(clean.shape))
    E0 = float(problem.material.E)
    residuals, loss, gradient = misfit(predict, data, E0, members)
    start = time.perf_counter()
    theta, history, information = gauss_newton(residuals, gradient, members, iterations)
    fit_seconds = time.perf_counter() - start
    estimate = E0 * np.exp(theta)
    std = sigma / np.sqrt(information)  # Cramer-Rao, in theta = log E
    z = (theta - np.log(truth / E0)) / std
    checks = gradient_check(loss, gradient, np.zeros(members))  # at the start, away from g = 0
    return {
        "settings": {"members": members, "steps": steps, "save": save, "observed": int(len(nodes)),
                     "noise": noise, "size": size, "iterations": iterations, "seed": seed},
        "problem": {"tets": problem.mesh.n_elements, "dofs": problem.n_dofs, "dt": dt, "E0": E0},
        "sigma_cm": sigma,
        "members": [{"E_true": float(t), "E_fit": float(e), "relative_error": float(e / t - 1.0),
                     "cramer_rao_relative_std": float(s), "z": float(zz)}
                    for t, e, s, zz in zip(truth, estimate, std, z)],
        "max_abs_z": float(np.max(np.abs(z))),
        "max_relative_error": float(np.max(np.abs(estimate / truth - 1.0))),
        "gauss_newton_steps": history,
        "fit_seconds": fit_seconds,
        "gradient_check": checks,
        "seconds": {"forward": timed(predict, jnp.asarray(estimate)), "gradient": timed(gradient, jnp.asarray(theta))},
        "device": jax.devices()[0].device_kind,
        "machine": experiments.machine(),
    }


def table(result: dict) -> str:
    s, p = result["settings"], result["problem"]
    lines = [f"vessel: {p['tets']} tets, {p['dofs']} dofs, dt {p['dt']:.3e} s; {s['members']} members, "
             f"{s['steps']} steps saved every {s['save']}, {s['observed']} nodes observed, noise "
             f"{100 * s['noise']:g} % of the RMS signal (sigma {result['sigma_cm']:.3e} cm)",
             "", "| member | E true | E fit | rel. error | Cramer-Rao std | z |", "|---|---|---|---|---|---|"]
    for r, m in enumerate(result["members"]):
        lines.append(f"| {r} | {m['E_true']:.5e} | {m['E_fit']:.5e} | {m['relative_error']:+.2e} | "
                     f"{m['cramer_rao_relative_std']:.2e} | {m['z']:+.2f} |")
    t = result["seconds"]
    lines += ["", f"Gauss-Newton: {len(result['gauss_newton_steps'])} iterations, largest steps "
              + ", ".join(f"{x:.1e}" for x in result["gauss_newton_steps"]) + f"; {result['fit_seconds']:.1f} s",
              f"max |z| {result['max_abs_z']:.2f}; largest relative error {result['max_relative_error']:.2e}",
              "gradient vs central differences: " + ", ".join(
                  f"member {c['member']} {c['relative_difference']:.1e}" for c in result["gradient_check"]),
              f"one batched run {t['forward']:.2f} s, its gradient {t['gradient']:.2f} s ({result['device']})"]
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--members", type=int, default=None, help="vessels fitted at once (default 16)")
    parser.add_argument("--steps", type=int, default=None, help="steps of every run (default 2000)")
    parser.add_argument("--save", type=int, default=None, help="observation stride in steps (default 100)")
    parser.add_argument("--observed", type=int, default=None, help="observed wall nodes (default 40)")
    parser.add_argument("--noise", type=float, default=0.01, help="noise sigma over the RMS signal (default 0.01)")
    parser.add_argument("--size", default=None, help="target tetrahedra of the vessel (default 3500)")
    parser.add_argument("--iterations", type=int, default=10, help="most Gauss-Newton iterations (default 10)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="3 members, 200 steps, 12 nodes")
    parser.add_argument("--out", default=RESULTS)
    args = parser.parse_args(argv)
    quick = {"members": 3, "steps": 200, "save": 20, "observed": 12, "size": 3500}
    full = {"members": 16, "steps": 2000, "save": 100, "observed": 40, "size": 3500}
    chosen = {k: getattr(args, k) if getattr(args, k) is not None else (quick if args.quick else full)[k]
              for k in full}
    chosen["size"] = int(chosen["size"])
    if chosen["steps"] % chosen["save"]:
        parser.error(f"--steps {chosen['steps']} must be a multiple of --save {chosen['save']}")
    result = run(noise=args.noise, iterations=args.iterations, seed=args.seed, **chosen)
    result["table"] = table(result)
    result["command"] = " ".join(["python benchmarks/bench_ensemble_inverse.py"] + list(
        sys.argv[1:] if argv is None else argv))
    print(result["table"])
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    from jaxsync.io import atomic_json

    atomic_json(args.out, result)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
