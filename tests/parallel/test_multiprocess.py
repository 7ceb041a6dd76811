"""Multi-process runs under ``mpiexec -n 2`` (loopback only, every run under a timeout).

The runs start real processes: this file doubles as their worker script
(``mpiexec -n 2 python tests/parallel/test_multiprocess.py WORKER ...``). Each process gets one CPU
device; the coordinator of ``jax.distributed`` listens on 127.0.0.1 and hydra starts the
ranks with its ``fork`` launcher on localhost, so nothing leaves the machine.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

TIMEOUT_S = 120  # per mpiexec run; a hang fails the test instead of blocking the suite
# 600 steps (7 snapshots) of the cantilever per run: the runs' cost is starting the processes
# and compiling, and the resuming run (300 + 300 steps) compares with the same 7 snapshots
STEPS, SAVE_EVERY = 600, 100


# ---------------------------------------------------------------------------------------
# worker side (runs under mpiexec; no pytest, no conftest)

def _worker_sync(out_path: str) -> None:
    """Run the cantilever on 2 parts with each synchronization; rank 0 writes the
    trajectories as .npz."""
    from jaxsync.parallel import multiprocess

    with multiprocess.abort_on_error():
        multiprocess.initialize()
        import jax
        import numpy as np

        jax.config.update("jax_enable_x64", True)
        import jaxsync
        from jaxsync.fem import build_system
        from jaxsync.solve.executors import DistributedRunner

        problem = jaxsync.cantilever()
        system = build_system(problem, problem.dt)
        configs = {"psum": jaxsync.Psum(), "mpi-callback": jaxsync.Mpi(allreduce="callback"),
                   "mpi-ctypes": jaxsync.Mpi(allreduce="ctypes"),
                   "halo-4": jaxsync.Halo(4)}  # deep halos, exchanged through MPI
        if multiprocess.mpi4jax_available():
            configs["mpi-mpi4jax"] = jaxsync.Mpi(allreduce="mpi4jax")
        results = {"default": DistributedRunner(problem, system, 2, save_every=SAVE_EVERY).sync,
                   "default_allreduce": multiprocess.default_allreduce()}
        for name, sync in configs.items():
            traj = jaxsync.simulate(problem, STEPS, save=SAVE_EVERY, partitions=2, sync=sync,
                                    executor=jaxsync.HostExecutor(progress=False))
            results[name] = traj.displacement
        if multiprocess.is_main_process():
            np.savez(out_path, **results)


def _visco_cantilever():
    """A small cantilever of a two-branch Prony series (the worker's and the test's)."""
    import jaxsync
    from jaxsync.fem.materials import ViscoelasticNeoHookean

    law = ViscoelasticNeoHookean(1.0e6, 0.3, 1.0, betas=(1.0, 2.0), taus=(2.0e-3, 1.0e-2))
    return jaxsync.cantilever(jaxsync.box_beam(4.0, 1.0, 1.0, (8, 1, 1)), material=law,
                              body_force=(0.0, 0.0, -2.0e4), t_ramp=0.002, damping=50.0)


def _worker_visco(out_path: str) -> None:
    """The Prony-series cantilever on 2 parts, one per process, through the MPI sum and
    deep halos of depth 2 (the branch stresses of halo elements copied through MPI); rank 0
    writes the trajectories."""
    from jaxsync.parallel import multiprocess

    with multiprocess.abort_on_error():
        multiprocess.initialize()
        import jax
        import numpy as np

        jax.config.update("jax_enable_x64", True)
        import jaxsync

        problem = _visco_cantilever()
        results = {name: jaxsync.simulate(problem, 120, save=12, partitions=2, sync=sync,
                                          executor=jaxsync.HostExecutor(progress=False)).displacement
                   for name, sync in (("mpi", jaxsync.Mpi(allreduce="ctypes")), ("halo-2", jaxsync.Halo(2)))}
        if multiprocess.is_main_process():
            np.savez(out_path, **results)


def _worker_fail(kind: str) -> None:
    """Rank 1 fails while rank 0 waits in a collective that rank 1 never joins."""
    from jaxsync.parallel import multiprocess

    with multiprocess.abort_on_error():
        multiprocess.initialize()
        comm = multiprocess.world()
        if comm.Get_rank() == 1:
            if kind == "package":
                from jaxsync.errors import ConfigError

                raise ConfigError("rank-one config is broken; fix it")
            raise RuntimeError("rank-one bug")
        comm.Barrier()  # would wait forever without the abort


if __name__ == "__main__" and len(sys.argv) > 1:
    if sys.argv[1] == "sync":
        _worker_sync(sys.argv[2])
    elif sys.argv[1] == "visco":
        _worker_visco(sys.argv[2])
    elif sys.argv[1] == "fail":
        _worker_fail(sys.argv[2])
    sys.exit(0)


# ---------------------------------------------------------------------------------------
# test side

import numpy as np  # noqa: E402
import pytest  # noqa: E402

import jaxsync  # noqa: E402
from jaxsync.parallel import multiprocess  # noqa: E402
from jaxsync.solve import transport  # noqa: E402
from subprocess_env import free_port, without_emulated_devices  # noqa: E402

MPIEXEC = shutil.which("mpiexec")
needs_mpiexec = pytest.mark.skipif(MPIEXEC is None,
                                   reason="mpiexec not found on PATH (pip install mpich)")


def _mpiexec(*command, n: int = 2, cwd=None, timeout: float = TIMEOUT_S) -> subprocess.CompletedProcess:
    """``mpiexec -n n ...`` on localhost only, with one CPU device per rank, stopped after
    ``timeout`` seconds."""
    env = {**without_emulated_devices(), "JAX_PLATFORMS": "cpu"}  # one CPU device per rank
    env["JAX_COORDINATOR_ADDRESS"] = f"127.0.0.1:{free_port()}"
    version = subprocess.run([MPIEXEC, "--version"], capture_output=True, text=True, timeout=30)
    if "HYDRA" in version.stdout:  # MPICH / Intel MPI: no ssh, ranks on this host
        launcher = [MPIEXEC, "-launcher", "fork", "-hosts", "localhost"]
    else:
        launcher = [MPIEXEC]
    if isinstance(command[0], list):  # MPMD: one command per rank, ':'-separated
        args = launcher[:]
        for i, rank_command in enumerate(command[0]):
            args += ([":"] if i else []) + ["-n", "1", *rank_command]
    else:
        args = [*launcher, "-n", str(n), *command]
    try:
        return subprocess.run(args, capture_output=True, text=True, timeout=timeout, env=env,
                              cwd=cwd)
    except subprocess.TimeoutExpired as exc:
        pytest.fail(f"mpiexec run hung for {timeout} s: {' '.join(args)}\n"
                    f"stdout: {exc.stdout}\nstderr: {exc.stderr}")


def _jaxsync_cli() -> list[str]:
    return [sys.executable, "-m", "jaxsync.cli"]


@pytest.fixture(scope="module")
def reference():
    return jaxsync.simulate(jaxsync.cantilever(), STEPS, save=SAVE_EVERY)


def relative_error(a, b):
    return np.abs(a - b).max() / np.abs(b).max()


@pytest.mark.mpi
@needs_mpiexec
def test_cli_two_processes_equal_the_single_process_run_and_resume(tmp_path, reference):
    """``jaxsync simulate`` under ``mpiexec -n 2``: the first 300 steps, checkpointed across
    the processes (the state gathered from both, one writer), then resumed from the
    checkpoint to STEPS = 600 steps, equal to the single-process run. Each of the 2
    processes has one device: the stats count 2 devices in 2 processes (they used to say 1
    device, that of the writing rank). (One test, two mpiexec runs: the run to STEPS and
    the checkpointed run used to be separate tests, each paying the processes' start and
    compilation.)"""
    common = ["simulate", "--save-every", str(SAVE_EVERY), "-o", "run.h5", "--no-progress",
              "--checkpoint", "ck.h5", "--checkpoint-every", str(SAVE_EVERY)]
    first = _mpiexec(*_jaxsync_cli(), *common, "--steps", "300", cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    first_traj = jaxsync.Trajectory.load(tmp_path / "run.h5")
    assert relative_error(first_traj.displacement, reference.displacement[:4]) <= 1e-12  # steps 0 .. 300
    stats = first_traj.stats
    assert (stats.n_devices, stats.n_processes, stats.emulated) == (2, 2, False)
    assert "2 cpu devices in 2 processes" in first.stdout
    # only rank 0 printed and wrote; the header names the transport, the fast one by default
    assert first.stdout.count("wrote") == 1 and first.stdout.count("2 processes, 2 parts") == 1
    assert first.stdout.count("exchange: MPI Allreduce inside the compiled step (") == 1, first.stdout
    assert "between 2 processes" in first.stdout and "TransportWarning" not in first.stderr
    resumed = _mpiexec(*_jaxsync_cli(), *common, "--steps", str(STEPS), cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr
    assert "resumed from step 300" in resumed.stdout
    assert resumed.stdout.count("wrote") == 1
    traj = jaxsync.Trajectory.load(tmp_path / "run.h5")
    assert (traj.stats.n_devices, traj.stats.n_processes) == (2, 2)
    assert traj.displacement.shape == reference.displacement.shape
    assert relative_error(traj.displacement, reference.displacement) <= 1e-12
    assert len(traj.parts) == 2  # one part per process
    # the trajectory and the checkpoint, nothing else (no staging files left behind)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ck.h5", "run.h5"]


@pytest.mark.mpi
@needs_mpiexec
def test_psum_and_mpi_synchronization_across_processes(tmp_path, reference):
    path = tmp_path / "sync.npz"
    out = _mpiexec(sys.executable, __file__, "sync", str(path))
    assert out.returncode == 0, out.stderr
    with np.load(path) as runs:
        assert str(runs["default"]) == "mpi"  # the faster one across processes
        # MPI called from inside the compiled step: mpi4jax where built, else jaxsync's own handler
        assert str(runs["default_allreduce"]) == ("mpi4jax" if multiprocess.mpi4jax_available() else "ctypes")
        names = set(runs.files) - {"default", "default_allreduce"}
        assert {"psum", "mpi-callback", "mpi-ctypes", "halo-4"} <= names
        assert ("mpi-mpi4jax" in names) == multiprocess.mpi4jax_available()
        for name in names:
            assert relative_error(runs[name], reference.displacement) <= 1e-12, name


@pytest.mark.slow  # 90 s on 2 shared cores; the in-process partitioned and deep-halo tests are the fast ones
@pytest.mark.mpi
@needs_mpiexec
def test_a_viscoelastic_law_runs_across_processes_as_in_one(tmp_path):
    """The Prony series' internal variables across 2 processes: the MPI sum and deep halos
    (whose exchange carries the shared elements' branch stresses) equal one process."""
    path = tmp_path / "visco.npz"
    out = _mpiexec(sys.executable, __file__, "visco", str(path))
    assert out.returncode == 0, out.stderr
    reference = jaxsync.simulate(_visco_cantilever(), 120, save=12)
    with np.load(path) as runs:
        assert set(runs.files) == {"mpi", "halo-2"}
        for name in runs.files:
            assert relative_error(runs[name], reference.displacement) <= 1e-12, name


@pytest.mark.mpi
@needs_mpiexec
def test_bench_sync_measures_zeta_and_checks_the_cost_model_with_real_processes(tmp_path):
    bench = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "benchmarks",
                         "bench_sync.py")
    path = tmp_path / "sync.json"
    out = _mpiexec(sys.executable, bench, "--sizes", "12", "1200", "--steps", "50", "--solver-steps", "64",
                   "--repeats", "1", "--halo-depths", "1", "4", "--json", str(path))
    assert out.returncode == 0, out.stderr
    result = json.loads(path.read_text())
    assert result["processes"] == 2 and result["devices_per_process"] == 1
    solver = {r["method"]: r for r in result["rows"] if r["kind"] == "solver"}
    speedup = {r["method"]: r for r in result["rows"] if r["kind"] == "speedup"}
    assert {"psum-gloo", "mpi-ctypes", "mpi-callback"} <= set(solver)
    assert result["default_allreduce"] in ("mpi4jax", "ctypes") and result["cpu_collectives"] == "gloo"
    assert result["transport"].startswith("MPI Allreduce inside the compiled step")
    for row in solver.values():  # the exchange's cost: the synchronized step less the unsynchronized one
        assert row["us_per_exchange_best"] == pytest.approx(row["us_per_step_best"]
                                                            - speedup["nosync"]["us_per_step_best"])
    assert set(speedup) == {"nosync", "halo-1", "halo-4", "avoid-lstm-paper", "avoid-lstm-default",
                            "avoid-linear"}
    best = min(r["us_per_step_best"] for r in solver.values())
    for name, row in speedup.items():
        assert row["zeta"] == pytest.approx(best / row["us_per_step_best"])
    for name in ("halo-1", "halo-4"):  # exact, and exchanged through MPI across the processes
        assert speedup[name]["max_rel_diff_vs_psum"] <= 1e-12 and speedup[name]["transport"] == "mpi"
    assert speedup["avoid-linear"]["architecture"]["kind"] == "linear"
    for check in result["model_check"]:  # prediction and measurement, as the model defines them
        assert check["predicted_us"] > 0 and check["measured_us"] > 0
        assert check["relative_error"] == pytest.approx(check["predicted_us"] / check["measured_us"] - 1)
    assert "zeta" in out.stdout and "cost model" in out.stdout and "us/exchange" in out.stdout


@pytest.mark.slow  # the vessel and a 20 000-step refill cycle per timing; the cantilever test above is the fast one
@pytest.mark.mpi
@needs_mpiexec
def test_bench_sync_times_the_vessel_demo_surrogates_between_real_processes(tmp_path):
    """--case vessel: the vessel demo's tree, one part per process, its surrogates at
    n_s = 1 000 with the default smooth refill (16 network calls) and with every
    application (1 000)."""
    bench = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "benchmarks",
                         "bench_sync.py")
    path = tmp_path / "sync_vessel.json"
    # the solver rows over 1 000 steps; each surrogate's row runs its refill cycle of 20 000 steps
    out = _mpiexec(sys.executable, bench, "--case", "vessel", "--sizes", "12", "--steps", "20", "--solver-steps",
                   "1000", "--repeats", "1", "--halo-depths", "1", "--json", str(path), timeout=600)
    assert out.returncode == 0, out.stderr
    result = json.loads(path.read_text())
    assert result["case"] == "vessel" and result["n_dofs"] > 3000
    speedup = {r["method"]: r for r in result["rows"] if r["kind"] == "speedup"}
    assert {"nosync", "halo-1", "avoid-lstm-vessel-demo", "avoid-lstm-all", "avoid-linear"} == set(speedup)
    assert speedup["avoid-lstm-vessel-demo"]["refill_calls"] == 16 and speedup["avoid-lstm-all"]["refill_calls"] == 1000
    assert speedup["avoid-lstm-vessel-demo"]["steps"] == 20000  # one refill cycle, n_s n_f
    assert speedup["halo-1"]["max_rel_diff_vs_psum"] < 1e-12  # deep halos are exact


@pytest.mark.mpi
@needs_mpiexec
def test_failing_rank_ends_the_cli_run(tmp_path):
    """Rank 1 cannot read its mesh while rank 0 goes on into the collectives."""
    common = ["simulate", "--steps", str(STEPS), "-o", "run.h5", "--no-progress"]
    out = _mpiexec([_jaxsync_cli() + common,
                    _jaxsync_cli() + common + ["--mesh", str(tmp_path / "missing.msh")]],
                   cwd=tmp_path)
    assert out.returncode != 0
    assert "[rank 1/2] error: mesh file" in out.stderr, (out.stdout, out.stderr)
    assert not (tmp_path / "run.h5").exists()


@pytest.mark.mpi
@needs_mpiexec
@pytest.mark.parametrize("kind", ["package", "bug"])
def test_failing_rank_aborts_the_job_with_its_error(kind):
    out = _mpiexec(sys.executable, __file__, "fail", kind)
    assert out.returncode != 0
    if kind == "package":
        assert "[rank 1/2] error: rank-one config is broken; fix it" in out.stderr
    else:  # a bug keeps its traceback, each line tagged with the rank
        assert "[rank 1/2] Traceback" in out.stderr
        assert "[rank 1/2] RuntimeError: rank-one bug" in out.stderr


# ---------------------------------------------------------------------------------------
# in-process checks (no mpiexec)

def test_launcher_environment_is_detected():
    assert multiprocess.launched_size({}) == 1 and not multiprocess.launched_by_mpi({})
    assert multiprocess.launched_size({"PMI_SIZE": "4", "PMI_RANK": "1"}) == 4
    assert multiprocess.launched_by_mpi({"OMPI_COMM_WORLD_SIZE": "2"})
    assert not multiprocess.launched_by_mpi({"PMI_SIZE": "1"})


@pytest.mark.skipif(not multiprocess.mpi4jax_available(),
                    reason="mpi4jax not installed: pip install -e '.[mpi]' (README, 'Running on clusters')")
def test_mpi4jax_allreduce_runs_inside_a_compiled_step():
    """One rank: the Allreduce through mpi4jax's XLA custom call is the identity."""
    import jax
    import jax.numpy as jnp

    allreduce = multiprocess.make_allreduce(None, "auto")
    x = jnp.arange(12.0).reshape(4, 3)
    step = jax.jit(lambda v: jax.lax.fori_loop(0, 5, lambda i, c: allreduce(c) * 1.0, v))
    np.testing.assert_array_equal(np.asarray(step(x)), np.asarray(x))
    # an XLA custom call into MPI, not a host callback
    text = jax.jit(allreduce).lower(x).as_text()
    assert "mpi_allreduce_ffi" in text and "callback" not in text


def test_ctypes_allreduce_runs_inside_a_compiled_step():
    """One rank: jaxsync's own FFI handler is the identity, inside jit, scan and vmap, for every
    dtype MPI sums; it is an XLA custom call, not a host callback; an unsupported dtype is XLA's
    error, not a silent wrong sum."""
    pytest.importorskip("mpi4py")
    import jax
    import jax.numpy as jnp

    assert multiprocess.ctypes_available()
    allreduce = multiprocess.make_allreduce(None, "ctypes")
    x = jnp.arange(12.0).reshape(4, 3)
    step = jax.jit(lambda v: jax.lax.fori_loop(0, 5, lambda i, c: allreduce(c) * 1.0, v))
    np.testing.assert_array_equal(np.asarray(step(x)), np.asarray(x))
    batched = jnp.stack([x, 2 * x])
    np.testing.assert_array_equal(np.asarray(jax.jit(jax.vmap(allreduce))(batched)), np.asarray(batched))
    for dtype in (jnp.float32, jnp.int32, jnp.int64, jnp.complex128):
        v = jnp.arange(5).astype(dtype)
        np.testing.assert_array_equal(np.asarray(jax.jit(allreduce)(v)), np.asarray(v))
    text = jax.jit(allreduce).lower(x).as_text()
    assert "jaxsync_mpi_allreduce" in text and "callback" not in text
    with pytest.raises(Exception, match="jaxsync MPI sum: cannot sum 5 values"):
        jax.jit(allreduce)(jnp.arange(5, dtype=jnp.uint8)).block_until_ready()


def test_transport_names_each_synchronization():
    """The header line of a partitioned run, in this process (2 emulated CPU devices)."""
    import jax

    assert transport(None, 2) == "XLA psum over 2 emulated CPU devices in one process"
    assert transport("psum", 2) == transport(None, 2)
    assert transport("ppermute", 4) == ("XLA ppermute (neighbouring devices only) over 2 emulated "
                                                     "CPU devices in one process")
    assert transport(None, 3) == "one device (the parts' sums stay on it: no exchange between devices)"
    assert transport(jaxsync.Halo(4), 2) == (
        "deep halos of depth 4, both displacement levels exchanged every 4 steps by XLA psum over 2 emulated "
        "CPU devices in one process")
    assert transport(jaxsync.Psum(devices=jax.devices()[:1]), 2).startswith("one device")
    pytest.importorskip("mpi4py")
    assert transport(jaxsync.Mpi(allreduce="ctypes"), 2) == (
        "MPI Allreduce inside the compiled step (jaxsync's ctypes FFI handler) in one process")
    if multiprocess.mpi4jax_available():
        assert transport("mpi", 2) == "MPI Allreduce inside the compiled step (mpi4jax) in one process"
    callback = transport(jaxsync.Mpi(allreduce="callback"), 2)
    assert callback.startswith("MPI Allreduce through an mpi4py host callback in one process (slow")


def test_fallback_to_the_callback_warns_with_the_fix(monkeypatch):
    """Where neither mpi4jax nor the ctypes handler runs, 'auto' takes the callback: between
    processes that warns (rank 0) and the transport line says so, both with the fix."""
    pytest.importorskip("mpi4py")

    class TwoRanks:  # what make_allreduce asks of a communicator before any sum
        def Get_size(self):
            return 2

        def Get_rank(self):
            return 0

    monkeypatch.setattr(multiprocess, "mpi4jax_available", lambda: False)
    monkeypatch.setattr(multiprocess, "ctypes_problem", lambda: "jax.ffi is broken here")
    assert multiprocess.default_allreduce() == "callback"
    with pytest.warns(multiprocess.TransportWarning, match=r"host callback \(slow\).*jax.ffi is broken.*\[mpi\]"):
        multiprocess.make_allreduce(TwoRanks(), "auto")
    assert "slow" in transport("mpi", 2) and "pip install -e '.[mpi]'" in transport("mpi", 2)
    with pytest.raises(jaxsync.ConfigError, match="ctypes MPI sum cannot run here"):
        multiprocess.make_allreduce(TwoRanks(), "ctypes")


def test_plain_install_defaults_to_an_allreduce_inside_the_step():
    """Without mpi4jax (a plain ``pip install -e .``), a fresh process resolves the default
    MPI sum to jaxsync's ctypes FFI handler, not the host callback."""
    pytest.importorskip("mpi4py")
    code = ("import sys; sys.modules['mpi4jax'] = None\n"  # as if mpi4jax were not installed
            "import jaxsync\n"
            "from jaxsync.parallel import multiprocess\n"
            "from jaxsync.solve import transport\n"
            "print(multiprocess.default_allreduce())\n"
            "print(transport('mpi', 2))\n")
    env = {**without_emulated_devices(), "JAX_PLATFORMS": "cpu"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=TIMEOUT_S, env=env)
    assert out.returncode == 0, out.stderr
    backend, line = out.stdout.splitlines()[-2:]
    assert backend == "ctypes"
    assert line == "MPI Allreduce inside the compiled step (jaxsync's ctypes FFI handler) in one process"


def test_single_process_defaults_to_psum():
    assert multiprocess.default_sync() == "psum"


@pytest.mark.mpi
def test_mpi_sync_in_one_process_equals_psum(reference):
    """One MPI rank (singleton): the Allreduce is the identity, both parts on one device."""
    pytest.importorskip("mpi4py")
    import jax

    from jaxsync.fem import build_system
    from jaxsync.solve.executors import DistributedRunner

    problem = jaxsync.cantilever()
    system = build_system(problem, problem.dt)
    backends = ["callback", "ctypes"] + (["mpi4jax"] if multiprocess.mpi4jax_available() else [])
    for backend in backends:
        traj = jaxsync.simulate(problem, STEPS, save=SAVE_EVERY, partitions=2,
                                sync=jaxsync.Mpi(allreduce=backend, devices=jax.devices()[:1]),
                                executor=jaxsync.HostExecutor(progress=False))
        assert relative_error(traj.displacement, reference.displacement) <= 1e-12, backend
    with pytest.raises(jaxsync.ConfigError, match="one device"):
        DistributedRunner(problem, system, 2, save_every=SAVE_EVERY, sync="mpi")
    with pytest.raises(jaxsync.ConfigError, match="sync must be"):
        DistributedRunner(problem, system, 2, save_every=SAVE_EVERY, sync="nccl")


@pytest.mark.mpi
def test_initialize_after_jax_use_is_refused():
    pytest.importorskip("mpi4py")
    import jax

    jax.devices()  # JAX is in use in this test process
    with pytest.raises(jaxsync.ConfigError, match="before"):
        multiprocess.initialize()
