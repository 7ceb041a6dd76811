import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

import fem_reference as ref
import jaxsync
from jaxsync import CheckpointError, ProblemError, StabilityError
from jaxsync.io.checkpoint import committed_step
from jaxsync.solve import Progress


@pytest.fixture(scope="module")
def problem():
    return jaxsync.cantilever()


def tip_node(mesh):
    p = mesh.points
    return int(np.argmax(np.where(np.isclose(p[:, 0], p[:, 0].max()), p[:, 1] + p[:, 2], -np.inf)))


def free_dofs(problem):
    fixed, _ = problem.dirichlet_dofs()
    return fixed, np.setdiff1d(np.arange(problem.mesh.n_dofs), fixed)


def test_step_equals_scipy_reference_over_1000_steps():
    """Constant load (so f(0) != 0) and an initial velocity exercise the paper's start."""
    mesh = jaxsync.box_beam(6.0, 1.0, 1.0, (6, 1, 1))
    rng = np.random.default_rng(1)
    v0 = 0.01 * rng.standard_normal((mesh.n_nodes, 3))
    d0 = 1e-3 * rng.standard_normal((mesh.n_nodes, 3))
    b = np.array([0.1, -0.2, -0.5])
    problem = jaxsync.Problem(
        mesh, jaxsync.LinearElastic(1.0e6, 0.3, 1.0),
        dirichlet=(jaxsync.Dirichlet("x0"),),
        loads=(jaxsync.BodyForce(b, jaxsync.Constant()),), damping=0.7,
        initial_displacement=d0, initial_velocity=v0)
    dt = problem.dt
    traj = jaxsync.simulate(problem, 1000, dt=dt)
    # reference, written independently
    K = ref.stiffness(mesh.points, mesh.tets, 1.0e6, 0.3)
    M = ref.consistent_mass(mesh.points, mesh.tets, 1.0)
    m = ref.lumped_mass(mesh.points, mesh.tets, 1.0)
    f = ref.body_force(mesh.points, mesh.tets, b)
    fixed, free = free_dofs(problem)
    d0f, v0f = d0.ravel().copy(), v0.ravel().copy()
    d0f[fixed] = 0.0
    rhs = f - 0.7 * (M @ v0f) - K @ d0f
    a0 = np.zeros_like(d0f)
    a0[free] = spla.spsolve(M[free][:, free].tocsc(), rhs[free])
    dm1 = d0f - dt * v0f + 0.5 * dt**2 * a0
    dm1[fixed] = 0.0
    expected = ref.central_difference(K, m, lambda t: f, 0.7, dt, d0f, dm1, fixed,
                                      np.zeros(len(fixed)), 1000)
    got = traj.displacement.reshape(1001, -1)
    scale = np.abs(expected).max()
    assert np.abs(got - expected).max() <= 1e-11 * scale


def test_steady_state_matches_scipy_solve(problem):
    mat = problem.material
    K = ref.stiffness(problem.mesh.points, problem.mesh.tets, mat.E, mat.nu)
    f = ref.body_force(problem.mesh.points, problem.mesh.tets, [0.0, 0.0, -0.5])
    fixed, free = free_dofs(problem)
    u = np.zeros(problem.mesh.n_dofs)
    u[free] = spla.spsolve(K[free][:, free].tocsc(), f[free])
    np.testing.assert_allclose(jaxsync.steady_state(problem).ravel(), u, rtol=1e-10,
                               atol=1e-12 * np.abs(u).max())


def test_damped_run_converges_to_steady_state(problem):
    # alpha = 4/s damps the first bending mode (omega ~ 2.5 rad/s) within ~8 s
    damped = problem.replace(damping=4.0)
    traj = jaxsync.simulate(damped, 40000, save=40000)
    u = jaxsync.steady_state(damped)
    err = np.linalg.norm(traj.displacement[-1] - u) / np.linalg.norm(u)
    assert err < 1e-6


def energies(problem, dt, n_steps):
    """(total energy with centred velocities, the scheme's exactly conserved discrete
    energy 1/2 v_{n+1/2} M v_{n+1/2} + 1/2 d_n K d_{n+1}) over the run."""
    traj = jaxsync.simulate(problem, n_steps, dt=dt)
    d = traj.displacement.reshape(n_steps + 1, -1)
    mat = problem.material
    K = ref.stiffness(problem.mesh.points, problem.mesh.tets, mat.E, mat.nu)
    m = ref.lumped_mass(problem.mesh.points, problem.mesh.tets, mat.rho)
    v = (d[2:] - d[:-2]) / (2 * dt)
    Kd = (K @ d.T).T
    total = 0.5 * np.einsum("ti,i,ti->t", v, m, v) + 0.5 * np.einsum("ti,ti->t", d[1:-1], Kd[1:-1])
    vh = (d[1:] - d[:-1]) / dt
    discrete = 0.5 * np.einsum("ti,i,ti->t", vh, m, vh) + 0.5 * np.einsum("ti,ti->t", d[:-1], Kd[1:])
    return total, discrete


def test_energy_is_conserved_to_second_order(problem):
    """Undamped, unloaded run from a static deflection over 10^4 steps: the energy
    deviates by O(dt^2) (halving dt quarters it) and the scheme's discrete energy does not
    drift at all (round-off)."""
    u = jaxsync.steady_state(problem)
    free = problem.replace(loads=(), damping=0.0, initial_displacement=u)
    dt = 0.5 * problem.dt
    e1, h1 = energies(free, dt, 10000)
    e2, _ = energies(free, dt / 2, 20000)
    dev1 = np.abs(e1 - e1[0]).max() / e1[0]
    dev2 = np.abs(e2 - e2[0]).max() / e2[0]
    assert dev1 < 1e-5
    assert 3.0 < dev1 / dev2 < 5.0  # halving dt divides the deviation by ~4
    # round-off in the velocity differences limits this to ~1e-11; a drift of the
    # scheme would show at the O(dt^2) level of dev1 (~1e-7)
    assert np.abs(h1 - h1[0]).max() / h1[0] < 1e-3 * dev1


def test_first_bending_frequency_matches_eigenvalue(problem):
    """Released from the static deflection under a load along the lowest mode's bending
    direction, the tip oscillates at the lowest eigenfrequency of K x = w^2 M_lumped x."""
    mat = problem.material
    K = ref.stiffness(problem.mesh.points, problem.mesh.tets, mat.E, mat.nu)
    m = ref.lumped_mass(problem.mesh.points, problem.mesh.tets, mat.rho)
    fixed, free = free_dofs(problem)
    w2, modes = spla.eigsh(K[free][:, free].tocsc(), k=1, M=sp.diags(m[free]).tocsc(),
                           sigma=0, which="LM")
    f_expected = np.sqrt(w2[0]) / (2 * np.pi)
    mode = np.zeros(problem.mesh.n_dofs)
    mode[free] = modes[:, 0]
    tip = tip_node(problem.mesh)
    # the mesh's tetrahedral split makes the principal bending axes oblique: load along
    # the lowest mode's tip direction so that it alone is excited
    direction = mode.reshape(-1, 3)[tip] / np.linalg.norm(mode.reshape(-1, 3)[tip])
    load = 0.5 * direction
    loaded = problem.replace(loads=(jaxsync.BodyForce(load),))
    u = jaxsync.steady_state(loaded)
    free_vibration = loaded.replace(loads=(), damping=0.0, initial_displacement=u)
    n_steps = int(4.5 / f_expected / problem.dt)
    traj = jaxsync.simulate(free_vibration, n_steps)
    s = traj.displacement[:, tip, :] @ direction
    t = traj.times
    idx = np.flatnonzero((s[:-1] < 0) & (s[1:] >= 0))  # upward zero crossings
    crossings = t[idx] - s[idx] * (t[idx + 1] - t[idx]) / (s[idx + 1] - s[idx])
    assert len(crossings) >= 4
    period = np.mean(np.diff(crossings))
    assert 1 / period == pytest.approx(f_expected, rel=0.01)


def test_grad_matches_finite_differences(problem):
    tip = tip_node(problem.mesh)
    dt = problem.dt

    @jax.jit  # one program for the four finite-difference runs (eager, each run's values compile anew)
    def tip_z(E, alpha):
        p = problem.replace(material=jaxsync.LinearElastic(E, 0.3, 1.0), damping=alpha)
        traj = jaxsync.simulate(p, 400, dt=dt, save=400)
        return traj.displacement[-1, tip, 2]

    E0, a0 = 1.0e6, 0.5
    gE, ga = jax.jit(jax.grad(tip_z, argnums=(0, 1)))(E0, a0)
    hE, ha = 1e-4 * E0, 1e-4
    fdE = (tip_z(E0 + hE, a0) - tip_z(E0 - hE, a0)) / (2 * hE)
    fda = (tip_z(E0, a0 + ha) - tip_z(E0, a0 - ha)) / (2 * ha)
    assert float(gE) == pytest.approx(float(fdE), rel=1e-5)
    assert float(ga) == pytest.approx(float(fda), rel=1e-5)


def test_grad_with_respect_to_nu_rho_and_load_is_finite_and_matches_fd(problem):
    tip = tip_node(problem.mesh)
    dt = problem.dt

    @jax.jit  # one program for the five runs below (eager, each run's values compile anew)
    def tip_z(nu, rho, load):
        p = problem.replace(material=jaxsync.LinearElastic(1.0e6, nu, rho),
                            loads=(jaxsync.BodyForce(jnp.array([0.0, 0.0, -1.0]) * load),))
        return jaxsync.simulate(p, 300, dt=dt, save=300).displacement[-1, tip, 2]

    grads = jax.jit(jax.grad(tip_z, argnums=(0, 1, 2)))(0.3, 1.0, 0.5)
    # linear in the load: d(tip)/d(load) = tip / load
    assert float(grads[2]) == pytest.approx(float(tip_z(0.3, 1.0, 0.5)) / 0.5, rel=1e-10)
    for i, (x, h) in enumerate(((0.3, 1e-5), (1.0, 1e-5))):
        args = [0.3, 1.0, 0.5]
        plus, minus = list(args), list(args)
        plus[i] += h
        minus[i] -= h
        fd = (tip_z(*plus) - tip_z(*minus)) / (2 * h)
        assert float(grads[i]) == pytest.approx(float(fd), rel=1e-5)


def test_save_every_and_times(problem):
    full = jaxsync.simulate(problem, 600)
    thinned = jaxsync.simulate(problem, 600, save=200)
    assert thinned.displacement.shape == (4, problem.mesh.n_nodes, 3)
    np.testing.assert_array_equal(thinned.displacement, full.displacement[::200])
    np.testing.assert_allclose(thinned.times, np.arange(4) * 200 * problem.dt)
    with pytest.raises(ProblemError, match="multiple of save_every"):
        jaxsync.simulate(problem, 601, save=200)


def test_chunking_does_not_change_the_result(problem):
    a = jaxsync.simulate(problem, 3000, save=10, executor=jaxsync.HostExecutor(chunk_steps=3000))
    b = jaxsync.simulate(problem, 3000, save=10, executor=jaxsync.HostExecutor(chunk_steps=700))
    np.testing.assert_array_equal(a.displacement, b.displacement)


def test_resumed_run_equals_uninterrupted_bit_for_bit(problem, tmp_path):
    ckpt = tmp_path / "run.ckpt.h5"
    full = jaxsync.simulate(problem, 6000, save=20, executor=jaxsync.HostExecutor(chunk_steps=1000))
    first = jaxsync.simulate(problem, 2000, save=20, executor=jaxsync.HostExecutor(chunk_steps=1000), checkpoint=ckpt)
    assert os.path.exists(ckpt)
    np.testing.assert_array_equal(first.displacement, full.displacement[:101])
    resumed = jaxsync.simulate(problem, 6000, save=20, executor=jaxsync.HostExecutor(chunk_steps=1000), checkpoint=ckpt)
    np.testing.assert_array_equal(resumed.displacement, full.displacement)
    np.testing.assert_array_equal(resumed.times, full.times)


class InterruptAfter(Progress):
    """A progress display that interrupts the run (as Ctrl-C would) at its n-th update,
    i.e. after n - 1 whole chunks and their checkpoints."""

    def __init__(self, n_updates: int):
        super().__init__(0, show=False)
        self.left = n_updates

    def update(self, steps: int) -> None:
        self.left -= 1
        if self.left == 0:
            raise KeyboardInterrupt


def test_interrupted_run_resumes(problem, tmp_path):
    """A run killed mid-way (here: interrupted in its fourth chunk) resumes from its last
    checkpoint and matches the uninterrupted run."""
    ckpt = tmp_path / "run.ckpt.h5"
    full = jaxsync.simulate(problem, 5000, save=50, executor=jaxsync.HostExecutor(chunk_steps=1000))
    with pytest.raises(KeyboardInterrupt):
        jaxsync.simulate(problem, 5000, save=50,
                         executor=jaxsync.HostExecutor(progress=InterruptAfter(4), chunk_steps=1000),
                         checkpoint=jaxsync.SolverCheckpoint(ckpt, every=1000))
    assert committed_step(ckpt) == 3000
    resumed = jaxsync.simulate(problem, 5000, save=50, executor=jaxsync.HostExecutor(chunk_steps=1000), checkpoint=ckpt)
    np.testing.assert_array_equal(resumed.displacement, full.displacement)


@pytest.mark.parametrize("seconds", [0.0, 1e9])
def test_checkpoints_come_by_wall_time_unless_an_interval_is_given(problem, tmp_path, monkeypatch,
                                                                    seconds):
    """Without checkpoint_every a run checkpoints once CHECKPOINT_SECONDS have passed since
    its last checkpoint (here: after every chunk, or never before its end); an interval
    in steps is kept to whatever the clock says."""
    import jaxsync.io.checkpoint as checkpoint

    monkeypatch.setattr(checkpoint, "CHECKPOINT_SECONDS", seconds)
    by_clock, by_steps = tmp_path / "clock.ckpt.h5", tmp_path / "steps.ckpt.h5"
    with pytest.raises(KeyboardInterrupt):
        jaxsync.simulate(problem, 1000, save=20,
                         executor=jaxsync.HostExecutor(progress=InterruptAfter(4), chunk_steps=200),
                         checkpoint=by_clock)
    assert committed_step(by_clock) == (600 if seconds == 0 else None)
    with pytest.raises(KeyboardInterrupt):
        jaxsync.simulate(problem, 1000, save=20,
                         executor=jaxsync.HostExecutor(progress=InterruptAfter(4), chunk_steps=200),
                         checkpoint=jaxsync.SolverCheckpoint(by_steps, every=400))
    assert committed_step(by_steps) == 400
    done = jaxsync.simulate(problem, 1000, save=20, executor=jaxsync.HostExecutor(chunk_steps=200), checkpoint=by_clock)
    assert committed_step(by_clock) == 1000  # always at the end
    np.testing.assert_array_equal(done.displacement,
                                  jaxsync.simulate(problem, 1000, save=20).displacement)


def test_interrupted_distributed_run_resumes_with_every_step_shared_histories(problem, tmp_path):
    """The parts' every-step shared histories (the training data) survive a resume:
    equal to the uninterrupted run's; a checkpoint without them is refused."""
    ckpt = tmp_path / "run.ckpt.h5"
    kwargs = dict(partitions=2, save=jaxsync.SaveAt(50, shared_every=1))
    chunks = jaxsync.HostExecutor(chunk_steps=500)
    full = jaxsync.simulate(problem, 2000, executor=chunks, **kwargs)
    with pytest.raises(KeyboardInterrupt):
        jaxsync.simulate(problem, 2000, executor=jaxsync.HostExecutor(progress=InterruptAfter(3), chunk_steps=500),
                         checkpoint=jaxsync.SolverCheckpoint(ckpt, every=500), **kwargs)
    assert committed_step(ckpt) == 1000
    resumed = jaxsync.simulate(problem, 2000, checkpoint=ckpt, executor=chunks, **kwargs)
    np.testing.assert_array_equal(resumed.displacement, full.displacement)
    for a, b in zip(resumed.parts, full.parts):
        assert a.shared_displacement.shape == (2001, b.shared_displacement.shape[1])
        np.testing.assert_array_equal(a.shared_displacement, b.shared_displacement)
    coarse = tmp_path / "coarse.ckpt.h5"
    jaxsync.simulate(problem, 1000, partitions=2, save=50, checkpoint=coarse)
    with pytest.raises(CheckpointError, match="every-step shared histories"):
        jaxsync.simulate(problem, 2000, checkpoint=coarse, executor=chunks, **kwargs)


def test_foreign_or_corrupt_checkpoint_is_refused(problem, tmp_path):
    ckpt = tmp_path / "run.ckpt.h5"
    jaxsync.simulate(problem, 1000, save=10, checkpoint=ckpt)
    with pytest.raises(CheckpointError, match="different problem"):
        jaxsync.simulate(problem.replace(damping=0.1), 2000, save=10, checkpoint=ckpt)
    with pytest.raises(CheckpointError, match="beyond n_steps"):
        jaxsync.simulate(problem, 500, save=10, checkpoint=ckpt)
    ckpt.write_bytes(b"not an hdf5 file")
    with pytest.raises(CheckpointError, match="cannot read"):
        jaxsync.simulate(problem, 1000, save=10, checkpoint=ckpt)


@pytest.mark.parametrize("tamper", ["displacement", "previous", "snapshots", "step"])
def test_altered_checkpoint_is_refused(problem, tmp_path, tamper):
    """A checkpoint whose stored state was changed after writing (here 0.05 cm written
    into 10 nodes, or another step) is refused instead of resumed silently; an untouched
    copy still resumes bit for bit."""
    import shutil

    import h5py

    ckpt, intact = tmp_path / "run.ckpt.h5", tmp_path / "intact.ckpt.h5"
    jaxsync.simulate(problem, 400, save=20, executor=jaxsync.HostExecutor(chunk_steps=200), checkpoint=ckpt)
    shutil.copy(ckpt, intact)
    with h5py.File(ckpt, "r+") as f:
        if tamper == "step":  # the committed step of both commit slots
            commits = f["commit"][...]
            commits[:, 1] -= 20
            f["commit"][...] = commits
        else:  # every state slot, or every snapshot
            data = f[tamper][...]
            data[..., :10, :] = 0.05
            f[tamper][...] = data
    with pytest.raises(CheckpointError, match="fails its checksum.*delete it to start over"):
        jaxsync.simulate(problem, 800, save=20, executor=jaxsync.HostExecutor(chunk_steps=200), checkpoint=ckpt)
    resumed = jaxsync.simulate(problem, 800, save=20, executor=jaxsync.HostExecutor(chunk_steps=200), checkpoint=intact)
    full = jaxsync.simulate(problem, 800, save=20, executor=jaxsync.HostExecutor(chunk_steps=200))
    np.testing.assert_array_equal(resumed.displacement, full.displacement)


def _layout1_checkpoint(path, source, problem, dt, save_every, *, checksum=True):
    """A checkpoint as jaxsync wrote them before layout 2 (every array rewritten at each
    checkpoint, one checksum over them), from the checkpoint ``source``."""
    import h5py

    from jaxsync.io import array_checksum
    from jaxsync.io.checkpoint import fingerprint, load_checkpoint

    key = fingerprint(problem, dt, save_every)
    state, snapshots, _ = load_checkpoint(source, key, 10**9)
    arrays = {"displacement": np.asarray(state.displacement), "previous": np.asarray(state.previous),
              "snapshots": np.concatenate(snapshots)}
    with h5py.File(path, "w") as f:
        f.attrs["kind"] = "jaxsync-solver-checkpoint"
        f.attrs["fingerprint"] = key
        f.attrs["step"] = int(state.step)
        if checksum:
            f.attrs["checksum"] = array_checksum(arrays, {"kind": "jaxsync-solver-checkpoint",
                                                          "fingerprint": key, "step": int(state.step)})
        for name, array in arrays.items():
            f[name] = array


def test_checkpoint_of_the_previous_layout_resumes_or_without_checksum_is_refused(problem, tmp_path):
    new, old, bare = tmp_path / "new.ckpt.h5", tmp_path / "old.ckpt.h5", tmp_path / "bare.ckpt.h5"
    jaxsync.simulate(problem, 200, save=20, executor=jaxsync.HostExecutor(chunk_steps=200), checkpoint=new)
    _layout1_checkpoint(old, new, problem, float(problem.dt), 20)
    _layout1_checkpoint(bare, new, problem, float(problem.dt), 20, checksum=False)
    full = jaxsync.simulate(problem, 400, save=20, executor=jaxsync.HostExecutor(chunk_steps=200))
    resumed = jaxsync.simulate(problem, 400, save=20, executor=jaxsync.HostExecutor(chunk_steps=200), checkpoint=old)
    np.testing.assert_array_equal(resumed.displacement, full.displacement)
    with pytest.raises(CheckpointError, match="no checksum.*delete it to start over"):
        jaxsync.simulate(problem, 400, save=20, executor=jaxsync.HostExecutor(chunk_steps=200), checkpoint=bare)


def test_checkpoints_append_only_their_new_rows(problem, tmp_path, monkeypatch):
    """The file is written whole once (atomically), then every checkpoint writes its new
    rows and its commit in place: the file keeps its size and structure, and no checkpoint
    rewrites the snapshots before it (that made checkpointed runs 1.8x slower)."""
    import h5py

    import jaxsync.io.checkpoint as checkpoint

    whole = []
    atomic_h5 = checkpoint.atomic_h5
    monkeypatch.setattr(checkpoint, "atomic_h5", lambda path: whole.append(path) or atomic_h5(path))
    ckpt = tmp_path / "run.ckpt.h5"
    kwargs = dict(save=20, executor=jaxsync.HostExecutor(chunk_steps=200),
                  checkpoint=jaxsync.SolverCheckpoint(ckpt, every=200))
    first = jaxsync.simulate(problem, 1000, **kwargs)  # 5 checkpoints
    assert len(whole) == 1
    with h5py.File(ckpt, "r") as f:
        assert f["snapshots"].shape == (51, problem.mesh.n_nodes, 3)  # room for the whole run
        assert f["commit"][:, :2].tolist() == [[5, 1000], [4, 800]]  # (sequence, step) per slot
        assert int(f.attrs["step"]) == 1000 == checkpoint.committed_step(ckpt)
    np.testing.assert_array_equal(first.displacement,
                                  jaxsync.simulate(problem, 1000, save=20).displacement)
    # a resumed run writes the file whole once more (room for its longer run), then appends
    resumed = jaxsync.simulate(problem, 2000, **kwargs)
    assert len(whole) == 2
    np.testing.assert_array_equal(resumed.displacement,
                                  jaxsync.simulate(problem, 2000, save=20).displacement)


def _storage(path):
    """(file bytes, [(offset, size)] of every dataset's raw data)."""
    import h5py

    with h5py.File(path, "r") as f:
        regions = [(f[name].id.get_offset(), f[name].id.get_storage_size()) for name in f]
    with open(path, "rb") as fh:
        return np.frombuffer(fh.read(), dtype=np.uint8), regions


def _toy_writer(path, n_steps=30):
    """A CheckpointWriter of a made-up run (5 nodes, one part recorded), and its blocks."""
    from jaxsync.fem import SolverState
    from jaxsync.io.checkpoint import CheckpointWriter

    def state(step):
        return SolverState(np.full((5, 3), step + 0.5), np.full((5, 3), step - 0.5), np.int32(step))

    def rows(i):  # the snapshots and shared rows of the i-th checkpoint (10 steps)
        return [np.full((10, 5, 3), float(i))], [[np.full((10, 4), -float(i))]]

    writer = CheckpointWriter(path, "toy", [np.zeros((1, 5, 3))], [[np.zeros((1, 4))]],
                              n_steps=n_steps, save_every=1)
    return writer, state, rows


def test_a_checkpoint_after_the_first_changes_only_rows_and_its_commit(tmp_path):
    """After the whole file is written, a checkpoint writes into the datasets' storage
    (allocated at the start) and the 8 bytes of the step attribute only: no HDF5
    structure changes, so a crash cannot damage what the last commit points at."""
    path = tmp_path / "toy.h5"
    writer, state, rows = _toy_writer(path)
    writer.commit(state(10), *rows(1))
    before, regions = _storage(path)
    writer.commit(state(20), *rows(2))
    after, regions_after = _storage(path)
    assert regions_after == regions and len(after) == len(before)
    outside = np.ones(len(before), bool)
    for offset, size in regions:
        outside[offset:offset + size] = False
    changed = np.nonzero((before != after) & outside)[0]
    assert len(changed) and changed.max() - changed.min() < 8  # the int64 step attribute


_CRASH_CHILD = """
import os, signal, sys
import h5py
sys.path[:0] = [sys.argv[3], os.path.dirname(sys.argv[3])]  # the test file and the helpers beside tests/
from test_solver import _toy_writer
writer, state, rows = _toy_writer(sys.argv[1])
writer.commit(state(10), *rows(1))
writer.commit(state(20), *rows(2))
calls, kill_at = [0], int(sys.argv[2])
def counted(write):
    def wrapper(*args, **kwargs):
        if calls[0] == kill_at:
            os.kill(os.getpid(), signal.SIGKILL)  # no HDF5 close, no buffer flushed
        calls[0] += 1
        return write(*args, **kwargs)
    return wrapper
h5py.Dataset.__setitem__ = counted(h5py.Dataset.__setitem__)
h5py.AttributeManager.modify = counted(h5py.AttributeManager.modify)
writer.commit(state(30), *rows(3))
"""


def test_a_process_killed_at_any_write_of_a_checkpoint_leaves_a_correct_one(tmp_path):
    """A process killed (SIGKILL) before each write of its third checkpoint, in turn:
    what it leaves resumes from the second checkpoint (commit not complete) or the third,
    every row and the state exactly as committed; never anything else."""
    import signal
    import subprocess
    import sys

    from jaxsync.io.checkpoint import committed_step, load_checkpoint

    writes = 7  # snapshots, shared rows, 2 state slots, commit, its checksum, step hint
    here = os.path.dirname(os.path.abspath(__file__))
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    children = [subprocess.Popen([sys.executable, "-c", _CRASH_CHILD, str(tmp_path / f"k{k}.h5"),
                                  str(k), here], env=env, stderr=subprocess.PIPE, text=True)
                for k in range(writes + 1)]
    for k, child in enumerate(children):
        _, err = child.communicate(timeout=120)
        assert child.returncode == (-signal.SIGKILL if k < writes else 0), err
        state, snapshots, shared = load_checkpoint(tmp_path / f"k{k}.h5", "toy", 30, n_recorded=1)
        step = int(state.step)
        assert step == (20 if k < 6 else 30), k  # complete once its checksum is written
        if k != 5:  # killed between the commit and its checksum: the hint may say either
            assert committed_step(tmp_path / f"k{k}.h5") == (20 if k < 5 else 30)
        n = step // 10
        np.testing.assert_array_equal(state.displacement, np.full((5, 3), step + 0.5))
        np.testing.assert_array_equal(state.previous, np.full((5, 3), step - 0.5))
        expected = np.concatenate([np.zeros((1, 5, 3))] + [np.full((10, 5, 3), float(i)) for i in range(1, n + 1)])
        np.testing.assert_array_equal(snapshots[0], expected)
        np.testing.assert_array_equal(shared[0][0], -expected[:, :4, 0])


def test_a_damaged_last_commit_resumes_from_the_one_before(problem, tmp_path):
    """A torn last commit (here its checksum overwritten) fails its check; the run then
    resumes from the previous commit, which a checkpoint never overwrites, bit for bit."""
    import h5py

    ckpt = tmp_path / "run.ckpt.h5"
    kwargs = dict(save=20, executor=jaxsync.HostExecutor(chunk_steps=200))
    jaxsync.simulate(problem, 600, checkpoint=jaxsync.SolverCheckpoint(ckpt, every=200), **kwargs)  # at 200, 400, 600
    with h5py.File(ckpt, "r+") as f:
        last = int(np.argmax(f["commit"][:, 0]))
        assert int(f["commit"][last, 1]) == 600
        f["commit_checksum"][last] = b"0" * 64
    from jaxsync.io.checkpoint import fingerprint, load_checkpoint

    state, _, _ = load_checkpoint(ckpt, fingerprint(problem, float(problem.dt), 20), 1000)
    assert int(state.step) == 400
    resumed = jaxsync.simulate(problem, 1000, checkpoint=ckpt, **kwargs)
    np.testing.assert_array_equal(resumed.displacement,
                                  jaxsync.simulate(problem, 1000, **kwargs).displacement)


def test_diverging_run_stops_with_the_stability_error_and_keeps_snapshots(problem):
    dt = 1.5 * jaxsync.max_stable_dt(problem)
    with pytest.raises(StabilityError, match="diverged") as info:
        jaxsync.simulate(problem, 20000, dt=dt, save=10,
                         executor=jaxsync.HostExecutor(chunk_steps=1000, check_stability=False))
    partial = info.value.trajectory
    assert partial.n_saved >= 1
    assert np.all(np.isfinite(partial.displacement))
    np.testing.assert_allclose(partial.times, np.arange(partial.n_saved) * 10 * dt)


def test_pressure_and_prescribed_displacement():
    """A bar pulled by a prescribed end displacement reaches the uniform-strain solution;
    a pressure on the free end compresses it as E A u / L = p A predicts."""
    mesh = jaxsync.box_beam(4.0, 1.0, 1.0, (4, 2, 2))
    mat = jaxsync.LinearElastic(1.0e3, 0.0, 1.0)
    x0 = jaxsync.Dirichlet("x0", components=(0,))
    pin_y = jaxsync.Dirichlet(lambda p: (p[:, 1] == 0), components=(1,))
    pin_z = jaxsync.Dirichlet(lambda p: (p[:, 2] == 0), components=(2,))
    pulled = jaxsync.Problem(mesh, mat, dirichlet=(x0, pin_y, pin_z,
                                                   jaxsync.Dirichlet("x1", (0.04, 0, 0), (0,))))
    u = jaxsync.steady_state(pulled)
    np.testing.assert_allclose(u[:, 0], 0.01 * mesh.points[:, 0], atol=1e-12)
    pushed = jaxsync.Problem(mesh, mat, dirichlet=(x0, pin_y, pin_z),
                             loads=(jaxsync.Pressure(2.0, surface="x1"),))
    u = jaxsync.steady_state(pushed)
    np.testing.assert_allclose(u[:, 0], -2.0 / 1.0e3 * mesh.points[:, 0], atol=1e-12)


def test_problem_validation(problem):
    with pytest.raises(ProblemError, match="damping"):
        problem.replace(damping=-1.0)
    with pytest.raises(ProblemError, match="initial_displacement"):
        problem.replace(initial_displacement=np.zeros((3, 3)))
    with pytest.raises(jaxsync.MeshError, match="no facet set named 'lumen'"):
        jaxsync.Problem(problem.mesh, loads=(jaxsync.Pressure(1.0, surface="lumen"),))
    with pytest.raises(ProblemError, match="selects no node"):
        jaxsync.Problem(problem.mesh, dirichlet=(jaxsync.Dirichlet(lambda p: p[:, 0] < -1),))
    with pytest.raises(ProblemError, match="singular"):
        jaxsync.steady_state(jaxsync.Problem(problem.mesh, loads=problem.loads))


def test_replace_reuses_the_assembled_operators(problem):
    other = problem.replace(material=jaxsync.LinearElastic(2.0e6, 0.3, 1.0))
    assert other.operators is problem.operators
