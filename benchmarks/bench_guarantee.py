"""Is the error of a controlled synchronization-avoiding run within its tolerance?

For each case -- the demo's cantilever as ``jaxsync demo`` trains it (1e5 steps, the
library's training defaults), the cantilever and its skewed and step-off loads with
smaller networks over 32 000 steps, a deliberately weak surrogate (5 epochs), the linear
autoregressive surrogate, the generated vessel (3 500 tets, 4 parts) -- the script runs the synchronized reference
(2 emulated devices' worth of parts), trains LSTM surrogates on its first half
(:func:`jaxsync.surrogate.train_surrogates`), and runs the synchronization-avoiding solver

* with a tolerance of 1e9 cm (nothing triggers) to see how the error estimate
  (:mod:`jaxsync.solve.coupling`) tracks the true error over the whole run:
  quantiles of estimate / error over the predicted snapshots where the error is above
  5 % of its largest value;
* for each tolerance (a fraction of the reference's largest |displacement| at the shared
  nodes, fixed in cm), with ``indicator="estimate"`` (the default: es_hat and the
  estimate) and ``indicator="es_hat"`` (es_hat only), and with the estimate and online
  learning (``ResyncTolerance(learning=True)``: the surrogates learn from every re-synchronized
  stretch, :mod:`jaxsync.surrogate.training`): the largest nodal error against the
  synchronized run over every saved step, as a multiple of the tolerance, and the steps
  predicted.

The cost of the probe (one exchange of summed partial forces per saved step, and the
host's update of the estimate) is measured apart, on the cantilever and a 20 000-tet
vessel: the compiled steps of a predicted cycle with and without it, best of 5.

Usage: python benchmarks/bench_guarantee.py [--cases demo cantilever skewed step-off weak linear vessel]
       [--tolerances 0.02 0.1] [--work /tmp/jaxsync-guarantee]
       [--out benchmarks/results/guarantee.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
import warnings

import jax

import jaxsync

jaxsync.parallel.devices.request_cpu_devices(2)
jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from jaxsync.solve import ResyncTolerance, simulate_sync_avoiding  # noqa: E402


@dataclasses.dataclass(frozen=True)
class Case:
    name: str
    n_steps: int
    n_parts: int = 2
    n_s: int = 150
    n_past: int = 20
    n_future: int = 20
    n_hidden: int | None = 50  # None: the library's default (as jaxsync demo trains)
    n_layers: int | None = 1
    epochs: int | None = 150
    n_candidates: int | None = 1
    save_every: int = 50
    model: str = "lstm"

    def problem(self):
        if self.name == "vessel":
            from jaxsync.app.demo import vessel_problem

            return vessel_problem(3500)[1]
        body = (0.0, -0.5, -0.5) if self.name == "skewed" else (0.0, 0.0, -0.5)
        return jaxsync.cantilever(body_force=body, t_off=3.0 if self.name == "step-off" else None)


CASES = {
    # jaxsync demo's cantilever: 1e5 steps, the library's training defaults
    "demo": Case("demo", 100000, n_hidden=None, n_layers=None, epochs=None, n_candidates=None),
    # shorter runs, smaller networks (n_H 50, one layer, 150 epochs, one candidate)
    "cantilever": Case("cantilever", 32000),
    "skewed": Case("skewed", 32000),
    "step-off": Case("step-off", 32000),
    "weak": Case("weak", 32000, epochs=5),
    "linear": Case("linear", 32000, model="linear"),
    "vessel": Case("vessel", 200000, n_parts=4, n_s=500, n_past=10, n_future=10, n_hidden=32, epochs=300,
                   save_every=500),
}


def train(case: Case, problem, folder: str):
    """(reference, partition, saved surrogate) of ``case``, trained on the first half."""
    from jaxsync.surrogate import ArchitectureChoice, Sampling, TrainingChecks, TrainingState
    from jaxsync.surrogate.training import TrainConfig, train_surrogates

    os.makedirs(folder, exist_ok=True)
    parts = jaxsync.partition(problem.mesh, case.n_parts, seed=0)
    shared_every = 1 if case.name != "vessel" else case.n_s
    reference = jaxsync.simulate(problem, case.n_steps, partitions=parts,
                                 save=jaxsync.SaveAt(case.save_every, shared_every),
                                 executor=jaxsync.HostExecutor(progress=False))
    path = os.path.join(folder, "synchronized.h5")
    reference.save(path)
    given = lambda **kw: {k: v for k, v in kw.items() if v is not None}  # noqa: E731
    trained = train_surrogates(
        path, architecture=ArchitectureChoice(model=case.model, **given(n_hidden=case.n_hidden,
                                                                         n_layers=case.n_layers)),
        sampling=Sampling(n_s=case.n_s, n_past=case.n_past, n_future=case.n_future, train_fraction=0.5, seed=0),
        optimizer=TrainConfig(**given(n_epochs=case.epochs, n_candidates=case.n_candidates)),
        checks=TrainingChecks(emse_applications=0), state=TrainingState(os.path.join(folder, "surrogate")),
        progress=False).write(os.path.join(folder, "surrogate"))
    return reference, parts, trained.saved, trained.train_seconds


def nodal_error(online, reference) -> np.ndarray:
    """(n_saved,) the largest nodal |error| [cm] at each saved step."""
    return np.linalg.norm(np.asarray(online.displacement) - np.asarray(reference.displacement), axis=2).max(axis=1)


def run_case(case: Case, tolerances, work: str) -> dict:
    problem = case.problem()
    start = time.perf_counter()
    reference, parts, saved, train_seconds = train(case, problem, os.path.join(work, case.name))
    amplitude = max(float(np.abs(np.asarray(reference.displacement)[:, p.shared_nodes]).max()) for p in parts.parts)
    n_cri = case.n_s * case.n_past

    def online(tolerance):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            return simulate_sync_avoiding(problem, case.n_steps, partitions=parts, surrogates=saved, n_cri=n_cri,
                                          save=case.save_every, resync_tolerance=tolerance,
                                          executor=jaxsync.HostExecutor(progress=False))

    tracking = online(ResyncTolerance(absolute=1e9))
    err, est = nodal_error(tracking, reference), np.asarray(tracking.error_estimate)
    seen = np.isfinite(est) & (err > 0.05 * err.max())
    ratio = est[seen] / err[seen]
    row = {"case": case.name, "settings": dataclasses.asdict(case), "n_cri": n_cri, "train_seconds": train_seconds,
           "shared_amplitude_cm": amplitude, "free_max_error_cm": float(err.max()),
           "estimate_over_error": {q: float(np.quantile(ratio, v)) for q, v in
                                   (("min", 0), ("p10", .1), ("median", .5), ("p90", .9), ("max", 1))},
           "us_per_step_predicted_probed": tracking.stats.us_per_step_predicted, "runs": []}
    print(f"{case.name}: free run max error {err.max():.3e} cm ({100 * err.max() / amplitude:.2f} % of the "
          f"shared amplitude {amplitude:.3e} cm); estimate/error p10 {row['estimate_over_error']['p10']:.2f}, "
          f"median {row['estimate_over_error']['median']:.2f}, p90 {row['estimate_over_error']['p90']:.2f}",
          flush=True)
    for fraction in tolerances:
        for indicator, learning in (("estimate", False), ("es_hat", False), ("estimate", True)):
            tolerance = ResyncTolerance(relative=fraction, amplitude=amplitude, indicator=indicator,
                                        learning=learning)
            traj = online(tolerance)
            e = nodal_error(traj, reference).max()
            st = traj.stats
            label = indicator + (" + learning" if learning else "")
            run = {"tolerance_fraction": fraction, "tolerance_cm": fraction * amplitude, "indicator": label,
                   "online_learning": learning,
                   "n_surrogate_updates": len(st.surrogate_updated_at) if learning else 0,
                   "seconds_updating": st.seconds_updating if learning else 0.0,
                   "max_error_cm": float(e), "max_error_over_tolerance": float(e / (fraction * amplitude)),
                   "n_predicted_steps": st.n_predicted_steps, "n_steps_after_n_cri": case.n_steps - n_cri,
                   "n_resynchronizations": st.n_resynchronizations,
                   "us_per_step_predicted": st.us_per_step_predicted,
                   "us_per_step_synchronized": st.us_per_step_synchronized}
            row["runs"].append(run)
            print(f"  tol {100 * fraction:g} % ({fraction * amplitude:.3e} cm), {label:>8}: max error "
                  f"{run['max_error_over_tolerance']:.2f} x tol, predicted {st.n_predicted_steps} of "
                  f"{case.n_steps - n_cri}, {st.n_resynchronizations} re-synchronizations, "
                  f"{(st.us_per_step_predicted or float('nan')):.1f} us per predicted step", flush=True)
    row["wall_seconds"] = time.perf_counter() - start
    return row


def probe_cost(name: str, steps: int, save_every: int, repeats: int = 5) -> dict:
    """us per step of a predicted cycle's steps with and without the defect probe (the
    compiled second half of a monitored cycle, best of ``repeats`` calls, alternating),
    and of the host's estimate update per probe, on the cantilever or the vessel
    (20 000 tets), 2 parts on 2 emulated devices."""
    from jaxsync.fem import build_system, initial_state
    from jaxsync.solve.coupling import ErrorPropagator, OraclePredictor
    from jaxsync.solve.executors import DistributedRunner, PredictedPhase
    from jaxsync.surrogate.training import shared_dof_layout

    if name == "vessel":
        from jaxsync.app.demo import vessel_problem

        problem = vessel_problem(20000)[1]
    else:
        problem = jaxsync.cantilever()
    parts = jaxsync.partition(problem.mesh, 2, seed=0)
    system = build_system(problem, problem.dt)
    runner = DistributedRunner(problem, system, parts, save_every=save_every)
    n_dof, _ = shared_dof_layout(parts)
    oracle = OraclePredictor(np.zeros((2, steps, n_dof)), first_step=1, n_s=steps, n_past=1, n_future=1)
    phase = PredictedPhase(runner, oracle, save_every=save_every)
    state = runner.from_global(initial_state(problem, system))
    buffer = runner.put(np.zeros((2, steps, n_dof)))
    pred, _, _ = phase.rollout(buffer, 0, steps)
    best = {False: np.inf, True: np.inf}
    for probe in (False, True):
        jax.block_until_ready(phase.apply(state, pred, steps, probe))  # compiled and warm
    for _ in range(repeats):
        for probe in (False, True):
            start = time.perf_counter()
            jax.block_until_ready(phase.apply(state, pred, steps, probe))
            best[probe] = min(best[probe], (time.perf_counter() - start) / steps)
    propagator = ErrorPropagator.build(problem, parts, problem.dt)
    defects = np.random.default_rng(0).normal(size=(steps // save_every, len(parts.shared_nodes), 3)) * 1e-9
    propagator.propagate(propagator.zero_state(), defects, save_every)  # its stride's maps made once
    host = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        propagator.propagate(propagator.zero_state(), defects, save_every)
        host = min(host, (time.perf_counter() - start) / steps)
    out = {"case": name, "n_dofs": 3 * problem.n_nodes, "steps_per_call": steps, "save_every": save_every,
           "us_per_step_plain": 1e6 * best[False], "us_per_step_probed": 1e6 * best[True],
           "us_per_step_host_estimate": 1e6 * host}
    print(f"probe cost, {name} ({out['n_dofs']} dofs, a probe every {save_every} steps): "
          f"{out['us_per_step_plain']:.2f} -> {out['us_per_step_probed']:.2f} us per step on the devices, "
          f"+ {out['us_per_step_host_estimate']:.2f} us per step on the host", flush=True)
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="*", default=list(CASES), choices=list(CASES))
    parser.add_argument("--tolerances", nargs="+", type=float, default=[0.02, 0.1],
                        help="tolerances as fractions of the shared-node amplitude")
    parser.add_argument("--work", default=os.path.join("/tmp", "jaxsync-guarantee"))
    parser.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "guarantee.json"))
    args = parser.parse_args(argv)
    from jaxsync.io import atomic_json
    from jaxsync.parallel.devices import device_summary

    costs = [probe_cost("cantilever", 3000, 50), probe_cost("vessel", 1000, 100)]
    rows = [run_case(CASES[name], args.tolerances, args.work) for name in args.cases]
    print()
    print(f"{'case':>9} {'tol %':>6} {'indicator':>20} {'max err / tol':>13} {'predicted':>10} {'resyncs':>7} "
          f"{'us/pred':>8}")
    for row in rows:
        for r in row["runs"]:
            print(f"{row['case']:>9} {100 * r['tolerance_fraction']:>6g} {r['indicator']:>20} "
                  f"{r['max_error_over_tolerance']:>13.2f} {r['n_predicted_steps']:>10} "
                  f"{r['n_resynchronizations']:>7} {(r['us_per_step_predicted'] or float('nan')):>8.1f}")
    atomic_json(args.out, {"date": time.strftime("%Y-%m-%d"), **device_summary(), "probe_cost": costs,
                           "rows": rows})
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
