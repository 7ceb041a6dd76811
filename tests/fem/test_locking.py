"""Nearly incompressible tissue: P1 locks, P2 does not (much), measured against the Lamé
cylinder's exact solution by benchmarks/bench_locking.py; the warning that points P1 users
at P2, and P2 selected from a configuration and the command line."""

import json
import warnings

import numpy as np
import pytest

import jaxsync
from benchmark_scripts import load_benchmark
from jaxsync.app.config import problem_from_config
from jaxsync.errors import ConfigError


def test_locking_benchmark_quick_measures_p1_locking_and_p2_not(tmp_path):
    bench = load_benchmark("bench_locking")
    out = tmp_path / "locking.json"
    assert bench.main(["--quick", "--quiet", "--out", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    error = {(r["element"], r["nu"]): abs(r["error"]) for r in rows}
    assert set(error) == {(e, nu) for e in ("P1", "P1-ANP", "P2") for nu in (0.3, 0.499)}
    assert error["P1", 0.499] > 0.4 and error["P1", 0.499] > 5 * error["P1", 0.3]  # locked
    assert error["P1-ANP", 0.499] < 3 * error["P1-ANP", 0.3] and error["P1-ANP", 0.499] < 0.25 * error["P1", 0.499]
    assert error["P2", 0.499] < 0.03 and error["P2", 0.3] < 0.005
    assert all(r["stable_dt"] > 0 and r["dofs"] > 0 for r in rows)


def test_nodal_pressure_operator_is_the_averaged_volumetric_energy():
    """K_lambda' u . u = sum_a V_a theta_a^2 with theta_a the volume-averaged divergence
    around node a, computed here element by element with numpy."""
    bench = load_benchmark("bench_locking")
    problem = jaxsync.cantilever(jaxsync.box_beam(3.0, 1.0, 1.0, (3, 2, 2)))
    ops = bench.nodal_pressure_operators(problem)
    rng = np.random.default_rng(0)
    u = rng.standard_normal((problem.mesh.n_nodes, 3))
    mesh = problem.mesh
    divergence, volume = np.zeros(mesh.n_elements), mesh.volumes()
    for e, tet in enumerate(mesh.tets):
        X = mesh.points[tet]
        grads = np.linalg.inv(np.column_stack([X[1] - X[0], X[2] - X[0], X[3] - X[0]]))  # rows: barycentric gradients
        gradients = np.vstack([-grads.sum(axis=0), grads])
        divergence[e] = np.sum(gradients * u[tet])
    nodal_volume, nodal_sum = np.zeros(mesh.n_nodes), np.zeros(mesh.n_nodes)
    for e, tet in enumerate(mesh.tets):
        nodal_volume[tet] += volume[e] / 4
        nodal_sum[tet] += volume[e] / 4 * divergence[e]
    theta = nodal_sum / nodal_volume
    energy = np.sum(nodal_volume * theta**2)
    assert u.ravel() @ (ops.K_lambda @ u.ravel()) == pytest.approx(energy, rel=1e-12)
    assert u.ravel() @ (problem.operators.K_lambda @ u.ravel()) == pytest.approx(np.sum(volume * divergence**2),
                                                                                    rel=1e-12)


def test_p1_warns_from_nu_045_and_p2_does_not():
    mesh = jaxsync.box_beam()
    with pytest.warns(jaxsync.LockingWarning, match="element='P2'"):
        jaxsync.cantilever(mesh, material=jaxsync.LinearElastic(1e6, 0.45, 1.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        jaxsync.cantilever(mesh, material=jaxsync.LinearElastic(1e6, 0.449, 1.0))
        jaxsync.cantilever(mesh, material=jaxsync.LinearElastic(1e6, 0.499, 1.0), element="P2")


def test_element_from_the_configuration_and_its_override():
    config = {"material": {"nu": 0.3}, "problem": {"element": "P2"}, "run": {"n_steps": 10}}
    problem, _ = problem_from_config(config)
    assert problem.element == "P2" and problem.n_nodes > problem.mesh.n_nodes
    problem, _ = problem_from_config(config, element="P1")
    assert problem.element == "P1"
    with pytest.raises(ConfigError, match="'P1', 'P2'"):
        problem_from_config({"problem": {"element": "P3"}})
    with pytest.raises(ConfigError, match=r"\[problem\] element"):
        problem_from_config({"problem": {"element": 2}})


def test_static_solve_of_nearly_incompressible_p2_and_a_rotation_left_free():
    """At nu = 0.4999 K is ill-conditioned (the static solve refines its answer and is not
    mistaken for singular); a clamp on one line leaves a rotation free: singular."""
    beam = jaxsync.box_beam(25.0, 1.0, 1.0, (25, 2, 2))
    theory = 0.5 * 25.0**4 / (8 * 1.0e6 / 12.0)
    stiff = jaxsync.cantilever(beam, material=jaxsync.LinearElastic(1e6, 0.4999, 1.0), element="P2")
    assert -jaxsync.steady_state(stiff)[:, 2].min() == pytest.approx(theory, rel=0.08)
    line = jaxsync.Dirichlet(lambda p: (p[:, 0] == 0.0) & (p[:, 1] == 0.0))
    with pytest.raises(jaxsync.ProblemError, match="singular"):
        jaxsync.steady_state(stiff.replace(dirichlet=[line]))
