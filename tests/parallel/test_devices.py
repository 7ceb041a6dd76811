"""Each part gets its own emulated CPU device from the command line (unless the user chose),
and every run says which devices it used. These start fresh processes: the test process
already has its two devices (conftest)."""

import os
import subprocess
import sys

import numpy as np
import pytest

import jaxsync
from jaxsync.parallel.devices import device_summary, user_chose_devices


def _run_cli(args, tmp_path, extra_env=None):
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_NUM_CPU_DEVICES",
                                                             "JAX_PLATFORMS", "JAX_ENABLE_X64")}
    env.update(extra_env or {})
    return subprocess.run([sys.executable, "-m", "jaxsync.cli", *args], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)


def test_simulate_gives_each_part_its_own_device(tmp_path):
    done = _run_cli(["simulate", "--parts", "3", "--steps", "200", "--save-every", "100",
                     "-o", "run.h5", "--no-progress"], tmp_path)
    assert done.returncode == 0, done.stderr
    assert "3 cpu devices, emulated" in done.stdout
    traj = jaxsync.Trajectory.load(tmp_path / "run.h5")
    assert traj.stats.n_devices == 3 and traj.stats.device_kind == "cpu"
    assert traj.stats.emulated
    assert traj.stats.compile_seconds > 0 and traj.stats.us_per_step > 0


def test_the_users_device_count_is_respected(tmp_path):
    done = _run_cli(["simulate", "--parts", "2", "--steps", "100", "--save-every", "100",
                     "-o", "run.h5", "--no-progress"], tmp_path,
                    {"XLA_FLAGS": "--xla_force_host_platform_device_count=1"})
    assert done.returncode == 0, done.stderr
    assert "1 cpu device, 2 parts per device)" in done.stdout
    assert jaxsync.Trajectory.load(tmp_path / "run.h5").stats.n_devices == 1


def test_zero_steps_report_no_speed(tmp_path):
    """--steps 0 used to print the compilation as 1685091.0 us/step."""
    done = _run_cli(["simulate", "--steps", "0", "-o", "run.h5", "--no-progress"], tmp_path)
    assert done.returncode == 0, done.stderr
    assert "no steps run" in done.stdout and "us/step" not in done.stdout


def test_user_choice_is_read_from_the_environment():
    assert not user_chose_devices({})
    assert user_chose_devices({"XLA_FLAGS": "--xla_force_host_platform_device_count=4"})
    assert user_chose_devices({"JAX_NUM_CPU_DEVICES": "4"})
    assert user_chose_devices({"JAX_PLATFORMS": "cuda"})
    assert not user_chose_devices({"JAX_PLATFORMS": "cpu", "XLA_FLAGS": "--xla_cpu_foo"})


def test_device_summary_and_run_statistics():
    import jax

    info = device_summary()
    assert info == {"n_devices": 2, "n_processes": 1, "device_kind": "cpu", "platform": "cpu",
                    "emulated": True}
    assert device_summary(jax.devices()[:1])["emulated"] is False
    problem = jaxsync.cantilever()
    single = jaxsync.simulate(problem, 20)
    assert single.stats.n_devices == 1
    split = jaxsync.simulate(problem, 20, partitions=2)
    assert split.stats.n_devices == 2 and split.stats.emulated
    np.testing.assert_allclose(split.displacement, single.displacement, rtol=0, atol=1e-13)


def test_device_summary_counts_the_devices_and_processes_of_a_multi_process_run():
    """Devices of two processes (a psum across them), or each process's own device of a
    run that reaches the others through MPI: both are 2 devices in 2 processes."""
    import types

    import jax

    def device(process):
        return types.SimpleNamespace(platform="cpu", device_kind="cpu", process_index=process)

    spread = device_summary([device(0), device(1)])
    assert (spread["n_devices"], spread["n_processes"], spread["emulated"]) == (2, 2, False)
    own = device_summary(jax.devices()[:1], processes=2)
    assert (own["n_devices"], own["n_processes"], own["emulated"]) == (2, 2, False)
    assert device_summary(jax.devices(), processes=1)["n_processes"] == 1


def test_request_after_jax_started_changes_nothing():
    from jaxsync.parallel.devices import request_cpu_devices

    assert request_cpu_devices(4) is False  # JAX already runs here: its devices stay
    import jax

    assert len(jax.devices()) == 2


def test_a_request_after_jax_started_says_it_comes_too_late():
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_NUM_CPU_DEVICES")}
    code = ("import warnings, jax; jax.numpy.zeros(1)\n"
            "from jaxsync.parallel.devices import DeviceWarning, request_cpu_devices\n"
            "with warnings.catch_warnings(record=True) as w:\n"
            "    warnings.simplefilter('always')\n"
            "    assert request_cpu_devices(4) is False\n"
            "assert len(jax.devices()) == 1\n"
            "print([(c.category.__name__, str(c.message)) for c in w])")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "DeviceWarning" in out.stdout and "comes too late" in out.stdout and "4 parts will share 1" in out.stdout


@pytest.mark.parametrize("command", [["demo", "--parts", "4"]])
def test_parts_of_a_command_are_read_without_jax(command):
    from jaxsync.cli import build_parser, parts_of

    assert parts_of(build_parser().parse_args(command)) == 4
