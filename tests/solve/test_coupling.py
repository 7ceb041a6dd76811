"""One entry point with a typed coupling: ``simulate(coupling=Synchronized() |
SyncAvoiding(...), exchange=...)``.

Checked against the entry points it replaces (the default synchronized run, the
``sync=`` spelling, ``simulate_sync_avoiding``: bit for bit), against the synchronized
reference (a run whose every cycle is rejected equals it to round-off), against central
finite differences (the gradient in the coupling's surrogate weights), and the typed run
statistics against the flat records that files hold."""

import dataclasses
import warnings
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsync
from jaxsync import ProblemError
from jaxsync.pytree import pytree_dataclass, static_field
from jaxsync.solve.coupling import OraclePredictor
from jaxsync.surrogate.training import shared_dof_layout

N_S, N_P, N_F = 5, 3, 4
N_CRI = 40  # the networks' history: n_s n_p = 15 steps
N_STEPS = N_CRI + 3 * N_S * N_F + 10  # three refill cycles of 20 steps and a partial one


@pytest.fixture(scope="module")
def problem():
    return jaxsync.cantilever()


@pytest.fixture(scope="module")
def partition(problem):
    return jaxsync.partition(problem.mesh, 2)


@pytest.fixture(scope="module")
def reference(problem, partition):
    return jaxsync.simulate(problem, N_STEPS, partitions=partition)


def shifted_oracle(reference, partition, shift):
    """Replays the synchronized run's shared displacements after N_CRI, ``shift`` steps late."""
    n_dof, counts = shared_dof_layout(partition)
    length = N_S * N_F
    future = np.zeros((partition.n_parts, -(-(N_STEPS - N_CRI) // length) * length, n_dof))
    for p, part in enumerate(partition.parts):
        values = reference.displacement[N_CRI + 1:, part.shared_nodes].reshape(N_STEPS - N_CRI, -1)
        future[p, :len(values), :counts[p]] = values
    return OraclePredictor(np.roll(future, shift, axis=1), first_step=N_CRI + 1, n_s=N_S, n_past=N_P, n_future=N_F)


@pytree_dataclass
class Extrapolation:
    """A predictor that works from its input history (so es_hat is not zero): each part
    continues its last shared values with ``scale`` times their last one-step change
    (``scale``: one value per part, stacked on the part axis like a surrogate's weights;
    ``n_dof``: the padded shared dofs per part, which the traced executor reads)."""

    scale: Any
    n_dof: int = static_field()
    n_s: int = static_field(default=N_S)
    n_past: int = static_field(default=N_P)
    n_future: int = static_field(default=N_F)

    def predict(self, buffer, step):
        ahead = jnp.arange(1, self.n_s * self.n_future + 1, dtype=buffer.dtype)[:, None]
        return buffer[-1][None] + jnp.reshape(self.scale, ()) * ahead * (buffer[-1] - buffer[-2])[None]


def extrapolation(partition, scale):
    return Extrapolation(jnp.full(partition.n_parts, scale), shared_dof_layout(partition)[0])


def assert_same_run(a, b):
    """Bit-for-bit the same trajectory, and the same statistics apart from timings."""
    np.testing.assert_array_equal(np.asarray(a.displacement), np.asarray(b.displacement))
    np.testing.assert_array_equal(np.asarray(a.times), np.asarray(b.times))
    assert (a.synchronized is None) == (b.synchronized is None)
    if a.synchronized is not None:
        np.testing.assert_array_equal(np.asarray(a.synchronized), np.asarray(b.synchronized))
    assert len(a.parts) == len(b.parts)
    for pa, pb in zip(a.parts, b.parts):
        assert pa.arrays().keys() == pb.arrays().keys()
        for name, value in pa.arrays().items():
            np.testing.assert_array_equal(np.asarray(value), np.asarray(pb.arrays()[name]))
    assert a.parameters == b.parameters
    assert type(a.stats) is type(b.stats)
    untimed = lambda st: {k: v for k, v in st.to_dict().items()  # noqa: E731
                          if "seconds" not in k and not k.startswith("us_per_step")}
    assert untimed(a.stats) == untimed(b.stats)


def test_the_synchronized_coupling_is_the_default_run(problem, partition, reference):
    """coupling=Synchronized() and the exchange under both of its names give the default
    run bit for bit, on one device and on two parts; the statistics are typed."""
    single = jaxsync.simulate(problem, 60, save=10)
    assert_same_run(single, jaxsync.simulate(problem, 60, save=10, coupling=jaxsync.Synchronized()))
    for kwargs in ({"coupling": jaxsync.Synchronized()}, {"exchange": jaxsync.Psum()}, {"sync": jaxsync.Psum()},
                   {"coupling": jaxsync.Synchronized(), "exchange": "psum"}):
        assert_same_run(reference, jaxsync.simulate(problem, N_STEPS, partitions=partition, **kwargs))
    st = reference.stats
    assert type(st) is jaxsync.SynchronizedStats and isinstance(st, jaxsync.RunStats)
    assert st.us_per_step > 0 and st.compile_seconds >= 0 and st.n_devices == 2
    # a field of another kind of run reads None, as on the one record it replaces
    assert st.n_cri is None and st.resynchronized_at is None and st.dirichlet_max_abs_predicted is None
    with pytest.raises(AttributeError, match="no field 'not_a_statistic'"):
        st.not_a_statistic  # noqa: B018


def test_the_sync_avoiding_coupling_is_simulate_sync_avoiding(problem, partition, reference):
    """simulate(coupling=SyncAvoiding(...)) and simulate_sync_avoiding: bit for bit, with
    and without error control."""
    late = shifted_oracle(reference, partition, 3)
    coupled = jaxsync.simulate(problem, N_STEPS, partitions=partition,
                               coupling=jaxsync.SyncAvoiding(late, N_CRI))
    assert_same_run(coupled, jaxsync.simulate_sync_avoiding(problem, N_STEPS, partitions=partition,
                                                            surrogates=late, n_cri=N_CRI))
    st = coupled.stats
    assert type(st) is jaxsync.SyncAvoidingStats
    assert (st.n_steps, st.n_cri, st.n_synchronized_steps, st.n_predicted_steps) == (N_STEPS, N_CRI, N_CRI,
                                                                                     N_STEPS - N_CRI)
    assert st.us_per_step is None and st.us_per_step_predicted > 0 and st.resync_tolerance is None
    # late predictions: the run is not the synchronized one
    assert np.abs(coupled.displacement - reference.displacement).max() > 1e-6 * np.abs(reference.displacement).max()

    coupling = jaxsync.SyncAvoiding(extrapolation(partition, 1.0), N_CRI, tolerance="0.5%", load_jumps="predict")
    assert coupling.tolerance == jaxsync.ResyncTolerance(relative=0.005)  # parsed once, stored typed
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", jaxsync.SynchronizedRunWarning)
        controlled = jaxsync.simulate(problem, N_STEPS, partitions=partition, coupling=coupling)
        alias = jaxsync.simulate_sync_avoiding(problem, N_STEPS, partitions=partition,
                                               surrogates=extrapolation(partition, 1.0), n_cri=N_CRI,
                                               resync_tolerance="0.5%", load_jumps="predict")
    assert_same_run(controlled, alias)
    st = controlled.stats
    assert st.resync_tolerance == "0.5 %" and st.n_resynchronizations == len(st.resynchronized_at) >= 1
    assert st.n_synchronized_steps + st.n_predicted_steps == N_STEPS and st.load_jumps is None


def test_every_rejected_cycle_gives_the_synchronized_run(problem, partition, reference):
    """A tolerance no prediction meets: every cycle is rejected before it is used, so the
    coupling's re-synchronization policy recomputes the whole run synchronized, equal to
    the synchronized reference to round-off."""
    coupling = jaxsync.SyncAvoiding(extrapolation(partition, 1.0), N_CRI, tolerance=1e-12)
    with pytest.warns(jaxsync.SynchronizedRunWarning, match="mostly synchronized"):
        traj = jaxsync.simulate(problem, N_STEPS, partitions=partition, coupling=coupling)
    scale = np.abs(reference.displacement).max()
    np.testing.assert_allclose(traj.displacement, reference.displacement, rtol=0, atol=1e-12 * scale)
    assert traj.stats.n_predicted_steps == 0 and traj.stats.n_synchronized_steps == N_STEPS
    assert bool(np.all(traj.synchronized))


def test_the_traced_coupling_is_a_pytree_and_the_alias(problem, partition):
    """The traced executor: the coupling (a pytree whose leaves are its surrogate's
    arrays) runs the alias's run bit for bit."""
    coupling = jaxsync.SyncAvoiding(extrapolation(partition, 0.5), N_CRI, load_jumps="predict")
    leaves, treedef = jax.tree_util.tree_flatten(coupling)
    assert len(leaves) == 1 and jax.tree_util.tree_unflatten(treedef, leaves) == coupling
    traced = jaxsync.simulate(problem, N_STEPS, partitions=partition, coupling=coupling,
                              executor=jaxsync.TracedExecutor())
    alias = jaxsync.simulate_sync_avoiding(problem, N_STEPS, partitions=partition, surrogates=coupling.surrogates,
                                           n_cri=N_CRI, load_jumps="predict", executor=jaxsync.TracedExecutor())
    np.testing.assert_array_equal(np.asarray(traced.displacement), np.asarray(alias.displacement))
    np.testing.assert_array_equal(np.asarray(traced.synchronized), np.arange(N_STEPS + 1) <= N_CRI)


@pytest.mark.slow
def test_the_coupling_is_differentiable_in_its_surrogate(problem, partition):
    """The gradient of a tip displacement in the surrogate's scale (a pytree leaf of the
    coupling, under jax.grad of the coupling) matches central finite differences of the
    same compiled run."""
    coupling = jaxsync.SyncAvoiding(extrapolation(partition, 0.5), N_CRI, load_jumps="predict")
    tip = int(np.argmax(problem.mesh.points[:, 0]))
    dt = float(problem.dt)

    @jax.jit
    def tip_z(c):
        return jaxsync.simulate(problem, N_STEPS, dt=dt, partitions=partition, coupling=c).displacement[-1, tip, 2]

    grad = jax.grad(tip_z)(coupling)
    assert isinstance(grad, jaxsync.SyncAvoiding)  # the derivative in each part's scale
    h = 1e-4
    shifted = lambda d: dataclasses.replace(coupling, surrogates=extrapolation(partition, 0.5 + d))  # noqa: E731
    finite = (tip_z(shifted(h)) - tip_z(shifted(-h))) / (2 * h)
    assert abs(float(finite)) > 0
    np.testing.assert_allclose(float(jnp.sum(grad.surrogates.scale)), float(finite), rtol=1e-6)


def test_bad_couplings_are_refused_with_the_fix(problem, partition, reference):
    late = shifted_oracle(reference, partition, 0)
    with pytest.raises(ProblemError, match=r"not a coupling: pass jaxsync.Synchronized\(\)"):
        jaxsync.simulate(problem, 10, coupling="sync-avoiding")
    with pytest.raises(ProblemError, match=r"the class: pass an instance"):
        jaxsync.simulate(problem, 10, coupling=jaxsync.Synchronized)
    with pytest.raises(ProblemError, match="sync= is another name for exchange="):
        jaxsync.simulate(problem, 10, partitions=partition, exchange="psum", sync="psum")
    with pytest.raises(ProblemError, match="needs a distributed run: pass partitions="):
        jaxsync.simulate(problem, 10, exchange="psum")
    with pytest.raises(ProblemError, match="SyncAvoiding needs a distributed run: pass partitions="):
        jaxsync.simulate(problem, N_STEPS, coupling=jaxsync.SyncAvoiding(late, N_CRI))
    with pytest.raises(ProblemError, match="load_jumps='sometimes': use 'synchronize'"):
        jaxsync.SyncAvoiding(late, N_CRI, load_jumps="sometimes")
    with pytest.raises(ProblemError, match="n_cri=40.0 must be a whole number"):
        jaxsync.SyncAvoiding(late, 40.0)
    with pytest.raises(ProblemError, match="neither a length in cm"):
        jaxsync.SyncAvoiding(late, N_CRI, tolerance="lots")
    with pytest.raises(ProblemError, match="n_cri=10 is too small"):
        jaxsync.simulate(problem, N_STEPS, partitions=partition, coupling=jaxsync.SyncAvoiding(late, 10))
    with pytest.raises(ProblemError, match="checkpoint= resumes synchronized runs"):
        jaxsync.simulate(problem, N_STEPS, partitions=partition, coupling=jaxsync.SyncAvoiding(late, N_CRI),
                         checkpoint="never-written.h5")


def test_stats_of_files_load_as_their_kind(tmp_path, reference):
    """The flat records of files written with one record for every kind of run load as
    the kind they hold; saved trajectories keep their kind and their keys."""
    sync = {"us_per_step": 12.5, "compile_seconds": 0.5, "n_devices": 2, "platform": "cpu"}
    online = {"compile_seconds": 1.0, "n_steps": 100, "n_cri": 40, "n_synchronized_steps": 60,
              "n_predicted_steps": 40, "resynchronized_at": [60, 80], "es_hat_trigger": np.array([1e-3, 2e-3]),
              "us_per_step_predicted": 3.0, "from_a_newer_jaxsync": 1}
    full = {"n_steps": 100, "n_cri": 40, "n_synchronized_steps": 40, "n_predicted_steps": 60,
            "dirichlet_max_abs_predicted": 1e-3, "us_per_step_predicted": 2.0}
    loaded = [jaxsync.RunStats.from_dict(d) for d in (sync, online, full, {"compile_seconds": 2.0}, {})]
    assert [type(st) for st in loaded] == [jaxsync.SynchronizedStats, jaxsync.SyncAvoidingStats,
                                           jaxsync.FullSystemStats, jaxsync.RunStats, jaxsync.RunStats]
    assert loaded[0].to_dict() == sync
    assert loaded[1].resynchronized_at == (60, 80) and loaded[1].es_hat_trigger == (1e-3, 2e-3)
    assert "from_a_newer_jaxsync" not in loaded[1].to_dict() and loaded[1].us_per_step is None
    assert loaded[2].to_dict() == full
    assert jaxsync.SyncAvoidingStats.from_dict(sync) == jaxsync.SyncAvoidingStats(compile_seconds=0.5, n_devices=2,
                                                                                   platform="cpu")
    path = tmp_path / "run.h5"
    reference.save(path)
    back = jaxsync.Trajectory.load(path).stats
    assert back == reference.stats and type(back) is jaxsync.SynchronizedStats
    assert back.to_dict().keys() == reference.stats.to_dict().keys()


def test_steady_state_returns_one_type():
    """A linear and a hyperelastic law give a SteadyState (an ndarray): the linear one
    satisfies K u = f at the free dofs (scipy's K of the problem) and has no residuals;
    the hyperelastic one's residuals are one converged Newton history per increment. The
    deprecated history=True gives the pair it gave before."""
    from jaxsync.fem.forces import stiffness_matrix

    mesh = jaxsync.box_beam(4.0, 1.0, 1.0, (4, 2, 2))
    linear = jaxsync.cantilever(mesh)
    u = jaxsync.steady_state(linear)
    assert type(u) is jaxsync.SteadyState and isinstance(u, np.ndarray) and u.shape == (len(mesh.points), 3)
    assert u.residuals == ()
    K = stiffness_matrix(linear)
    f = sum(np.asarray(v, dtype=float).reshape(-1) for v in linear.load_vectors()[0])
    fixed, _ = linear.dirichlet_dofs()
    free = np.setdiff1d(np.arange(K.shape[0]), fixed)
    np.testing.assert_allclose((K @ u.reshape(-1))[free], f[free], rtol=0, atol=1e-9 * np.abs(f).max())
    assert type(u * 2.0) is np.ndarray and type(u[:, 2].min()) is np.float64  # new fields are plain arrays

    nonlinear = linear.replace(material=jaxsync.NeoHookean(1.0e6, 0.3, 1.0))
    v = jaxsync.steady_state(nonlinear, load_steps=2, tol=1e-10)
    assert type(v) is jaxsync.SteadyState and len(v.residuals) == 2
    assert all(increment[-1] <= 1e-10 for increment in v.residuals)
    with pytest.warns(DeprecationWarning, match="u.residuals"):
        pair = jaxsync.steady_state(nonlinear, load_steps=2, tol=1e-10, history=True)
    np.testing.assert_array_equal(pair[0], v)
    assert pair[1] == [list(r) for r in v.residuals]
