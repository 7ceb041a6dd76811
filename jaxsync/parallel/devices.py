"""Which devices a run uses, and giving each part its own emulated CPU device.

On a CPU-only machine JAX shows ONE device unless told otherwise before it starts, so a
2-part run would put both parts on one device: no synchronization is then measured
(0 us/step) and every speed figure is meaningless. The command line therefore asks for
one emulated CPU device per part (:func:`request_cpu_devices`) before JAX initializes,
unless the user chose a count (``XLA_FLAGS=--xla_force_host_platform_device_count=N``,
``JAX_NUM_CPU_DEVICES``) or another platform. From Python, call it right after
``import jax`` (or set the flag). Every table, summary and JSON states the devices it
ran on (:func:`device_summary`).
"""

from __future__ import annotations

import os

__all__ = ["request_cpu_devices", "device_summary", "user_chose_devices", "jax_started", "DeviceWarning"]


def user_chose_devices(environ=None) -> bool:
    """True when the environment already fixes the CPU device count or the platform."""
    env = os.environ if environ is None else environ
    if "xla_force_host_platform_device_count" in env.get("XLA_FLAGS", ""):
        return True
    if env.get("JAX_NUM_CPU_DEVICES"):
        return True
    platforms = env.get("JAX_PLATFORMS", "").strip().lower()
    return bool(platforms) and platforms != "cpu"


def request_cpu_devices(n: int) -> bool:
    """Ask JAX for ``n`` emulated CPU devices (one per part) before it initializes.

    Returns True when the request was made; False when the user chose the devices (see
    :func:`user_chose_devices`), or JAX is already running (then the devices it has are
    used, and the run's statistics say how many). Harmless on machines with GPUs: the CPU
    devices are only the fallback there."""
    import jax

    n = int(n)
    if n < 2 or user_chose_devices():
        return False
    if jax_started():
        have = len(jax.devices("cpu")) if jax.default_backend() == "cpu" else n
        if have < n:
            import warnings

            warnings.warn(
                f"request_cpu_devices({n}) comes too late: JAX has already started with {have} CPU device"
                f"{'s' if have > 1 else ''}, and the count cannot change any more, so {n} parts will share "
                f"{have}; call it right after `import jax`, before any array is made or device queried, or set "
                f"XLA_FLAGS=--xla_force_host_platform_device_count={n} before starting Python",
                DeviceWarning, stacklevel=2)
        return False
    jax.config.update("jax_num_cpu_devices", n)
    return True


class DeviceWarning(UserWarning):
    """A request for devices that cannot be met (:func:`request_cpu_devices` after JAX
    has started): the run goes on with the devices JAX has."""


def jax_started() -> bool:
    """True once JAX has initialized its backends (after its first array or device query:
    device counts and collectives can no longer change). Found through the public config:
    JAX refuses a new CPU device count once started."""
    import jax

    current = jax.config.jax_num_cpu_devices
    try:
        jax.config.update("jax_num_cpu_devices", 2 if current != 2 else 3)
    except RuntimeError:
        return True
    jax.config.update("jax_num_cpu_devices", current)
    return False


def device_summary(devices=None, *, processes: int | None = None) -> dict:
    """{"n_devices", "n_processes", "device_kind", "platform", "emulated"} of a run on
    ``devices`` (default: all of JAX's devices, those of every process).

    ``n_devices`` counts the devices of every process of the run and ``n_processes`` the
    processes: with ``devices`` spread over processes (a ``psum`` across them), the
    processes they belong to; ``processes``: the run's processes when each passes only its
    own ``devices`` and reaches the others otherwise (MPI), so that the run holds
    ``processes`` times as many devices. ``emulated`` is True for several CPU devices in
    one process (they share the machine's cores and memory)."""
    import jax

    devices = list(jax.devices() if devices is None else devices)
    platform = devices[0].platform if devices else "none"
    if processes is not None and int(processes) > 1:
        n_processes = int(processes)
        n_devices = len(devices) * n_processes
    else:
        n_processes = len({getattr(d, "process_index", 0) for d in devices}) or 1
        n_devices = len(devices)
    return {"n_devices": n_devices, "n_processes": n_processes,
            "device_kind": devices[0].device_kind if devices else "none",
            "platform": platform,
            "emulated": bool(platform == "cpu" and len(devices) > 1 and n_processes == 1
                             and jax.process_count() == 1)}
