import logging

import jax
import numpy as np
import pytest

import jaxsync
from jaxsync import ProblemError, StabilityError
from jaxsync.surrogate.histories import read_shared_histories

FZ = (0.3, 0.5, 0.7)


def relative_error(a, b):
    return np.abs(np.asarray(a) - np.asarray(b)).max() / np.abs(np.asarray(b)).max()


@pytest.fixture(scope="module")
def mesh():
    return jaxsync.box_beam()


@pytest.fixture(scope="module")
def static(mesh):
    """(n_nodes, 3) static solution of the cantilever at f_z = 0.5 [cm]."""
    return jaxsync.steady_state(jaxsync.cantilever(mesh, body_force=(0, 0, -0.5)))


@pytest.fixture(scope="module")
def problems(mesh, static):
    """The cantilever at three loads; the second one starts from 1.2 times the static solution."""
    out = [jaxsync.cantilever(mesh, body_force=(0, 0, -fz)) for fz in FZ]
    out[1] = out[1].replace(initial_displacement=1.2 * static)
    return out


@pytest.fixture(scope="module")
def part(mesh):
    return jaxsync.partition(mesh, 2)


@pytest.fixture(scope="module")
def generated(problems, part):
    """3 runs of 300 steps in chunks of 100, saved every 10 steps, shared nodes every step."""
    return jaxsync.ensemble(problems, 300, partitions=part, labels=FZ, save=jaxsync.SaveAt(10, 1),
                            executor=jaxsync.HostExecutor(chunk_steps=100))


def test_ensemble_equals_separate_distributed_runs(problems, part, generated):
    assert len(generated) == len(problems)
    for problem, traj in zip(problems, generated):
        ref = jaxsync.simulate(problem, 300, partitions=part, save=jaxsync.SaveAt(10, 1))
        assert traj.displacement.shape == ref.displacement.shape == (31, problem.mesh.n_nodes, 3)
        assert relative_error(traj.displacement, ref.displacement) <= 1e-12
        np.testing.assert_array_equal(traj.times, ref.times)
        assert (traj.save_every, traj.shared_every, traj.shared_stride) == (10, 1, 1)
        assert ref.shared_every == traj.shared_every
        assert len(traj.parts) == len(ref.parts) == 2
        for mine, theirs in zip(traj.parts, ref.parts):
            np.testing.assert_array_equal(mine.shared_nodes, theirs.shared_nodes)
            np.testing.assert_array_equal(mine.elements, theirs.elements)
            assert mine.shared_displacement.shape == theirs.shared_displacement.shape == (301, 3 * mine.n_shared)
            assert relative_error(mine.shared_displacement, theirs.shared_displacement) <= 1e-12
        assert traj.stats.us_per_step > 0 and traj.stats.compile_seconds >= 0


def test_linearity_and_superposition(mesh, static):
    """Independent of simulate: the response is linear in the loads, the Dirichlet values
    and the initial displacement. Runs: f_z = 0.3 and 0.7 from rest; 0.5 from rest; 0.5
    from c u_s; no load from u_s; 0.5 with a prescribed clamp displacement g; no load with g."""
    c = -0.2
    g = (0.0, 1e-3, -2e-3)
    loaded = jaxsync.cantilever(mesh, body_force=(0, 0, -0.5))
    unloaded = jaxsync.cantilever(mesh, body_force=(0, 0, 0))
    moved_clamp = (jaxsync.Dirichlet("x0", value=g),)
    runs = [jaxsync.cantilever(mesh, body_force=(0, 0, -0.3)), jaxsync.cantilever(mesh, body_force=(0, 0, -0.7)),
            loaded, loaded.replace(initial_displacement=c * static), unloaded.replace(initial_displacement=static),
            loaded.replace(dirichlet=moved_clamp), unloaded.replace(dirichlet=moved_clamp)]
    trajs = jaxsync.ensemble(runs, 200, save=5, executor=jaxsync.HostExecutor(chunk_steps=100))
    assert not trajs[0].parts and "load_parameter" not in trajs[0].parameters  # no partitions, no labels
    d = [t.displacement for t in trajs]
    assert np.abs(d[0]).max() > 0
    assert relative_error(d[1], 0.7 / 0.3 * d[0]) <= 1e-11
    assert relative_error(d[3], d[2] + c * d[4]) <= 1e-11
    assert relative_error(d[5], d[2] + d[6]) <= 1e-11
    assert np.all(d[5][:, mesh.facet_nodes("x0")] == np.asarray(g))


def test_batch_compiles_once(problems, caplog):
    """Three runs, four chunks: one compilation of the batched stepper."""
    jax.clear_caches()  # count from a cold start, whatever ran before
    with jax.log_compiles(), caplog.at_level(logging.WARNING):
        trajs = jaxsync.ensemble(problems, 200, save=5, executor=jaxsync.HostExecutor(chunk_steps=50))
    compiled = [r for r in caplog.records if "_advance_runs" in r.getMessage() and "XLA compilation" in r.getMessage()]
    assert len(compiled) == 1
    assert len(trajs) == 3 and trajs[0].n_saved == 41


def test_labels_are_load_parameters(generated, tmp_path):
    for fz, traj in zip(FZ, generated):
        assert traj.parameters["load_parameter"] == fz
        path = tmp_path / f"run_{fz}.h5"
        traj.save(path)
        back = jaxsync.Trajectory.load(path)
        assert back.parameters["load_parameter"] == fz
        assert read_shared_histories(back).load_parameter == fz
        assert read_shared_histories(traj).load_parameter == fz


@pytest.mark.parametrize("other, what", [
    (lambda mesh: jaxsync.cantilever(jaxsync.box_beam(25.0, 1.0, 1.0, (25, 1, 2))), "mesh"),
    (lambda mesh: jaxsync.cantilever(mesh, material=jaxsync.LinearElastic(2.0e6, 0.3, 1.0)), "stiffness"),
    (lambda mesh: jaxsync.cantilever(mesh, material=jaxsync.LinearElastic(1.0e6, 0.3, 2.0)), "mass"),
    (lambda mesh: jaxsync.cantilever(mesh, damping=0.1), "damping"),
    (lambda mesh: jaxsync.cantilever(mesh, t_off=3.0), "load time functions"),
])
def test_refuses_problems_of_other_systems(mesh, other, what):
    runs = [jaxsync.cantilever(mesh), jaxsync.cantilever(mesh, body_force=(0, 0, -0.6)), other(mesh)]
    with pytest.raises(ProblemError, match=f"problem 2 .*{what}.*jaxsync.simulate"):
        jaxsync.ensemble(runs, 10)


def test_refuses_bad_arguments(mesh):
    runs = [jaxsync.cantilever(mesh), jaxsync.cantilever(mesh, body_force=(0, 0, -0.6))]
    with pytest.raises(ProblemError, match="2 labels for 3 problems"):
        jaxsync.ensemble(runs + [runs[0]], 10, labels=(0.5, 0.6))
    with pytest.raises(ProblemError, match="at least one problem"):
        jaxsync.ensemble([], 10)
    with pytest.raises(ProblemError, match="not a multiple of save_every"):
        jaxsync.ensemble(runs, 10, save=3)
    with pytest.raises(ProblemError, match="shared_every needs a distributed run"):
        jaxsync.ensemble(runs, 10, save=jaxsync.SaveAt(2, 1))
    with pytest.raises(StabilityError, match="stability bound"):
        jaxsync.ensemble(runs, 10, dt=100 * runs[0].dt)


def test_divergence_names_the_run(mesh):
    """Run 1 carries an absurd load: its tip passes the blow-up limit within a few dozen steps."""
    runs = [jaxsync.cantilever(mesh), jaxsync.cantilever(mesh, body_force=(0, 0, -1e12)),
            jaxsync.cantilever(mesh, body_force=(0, 0, -0.6))]
    with pytest.raises(StabilityError, match=r"run 1 \(label 1e\+12\) of the ensemble diverged") as info:
        jaxsync.ensemble(runs, 100, save=jaxsync.SaveAt(5, 1), executor=jaxsync.HostExecutor(chunk_steps=50),
                         labels=(0.5, 1e12, 0.6), partitions=2)
    err = info.value
    assert err.run == 1 and err.runs == (1,)
    assert len(err.trajectories) == 3 and err.trajectory is err.trajectories[1]
    n_saved = err.trajectory.n_saved
    assert 1 < n_saved < 21
    for traj in err.trajectories:
        assert traj.n_saved == n_saved and np.isfinite(traj.displacement).all()
        assert all(p.shared_displacement.shape[0] == (n_saved - 1) * 5 + 1 for p in traj.parts)
