"""The environment of the processes that tests start (documentation blocks, command lines,
``mpiexec`` ranks): the test session's without its emulated devices, so that each process
has the one CPU device a user's would, and keeps the session's other compiler flags and
its compilation cache (conftest)."""

import os
import re
import socket


def without_emulated_devices() -> dict[str, str]:
    """A copy of ``os.environ`` without ``--xla_force_host_platform_device_count`` in
    XLA_FLAGS (XLA_FLAGS dropped when nothing else is left), JAX_PLATFORMS cpu unless set."""
    env = dict(os.environ)
    flags = re.sub(r"--xla_force_host_platform_device_count=\d+", "", env.get("XLA_FLAGS", "")).strip()
    if flags:
        env["XLA_FLAGS"] = flags
    else:
        env.pop("XLA_FLAGS", None)
    env.setdefault("JAX_PLATFORMS", "cpu")
    return env


def free_port() -> int:
    """A TCP port free on the loopback interface (for a ``jax.distributed`` coordinator)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
