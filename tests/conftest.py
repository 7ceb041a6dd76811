"""Test configuration, set before jax is imported: two emulated CPU devices, float64, and
JAX's strict numpy rules as diffrax and equinox test with them -- no implicit dtype
promotion (``jnp.float32 + jnp.float64`` is an error, not a silent upcast) and no implicit
rank promotion (adding a (n,) to an (n, 1) array is an error, not an (n, n) result)."""

import os

os.environ["XLA_FLAGS"] = (
    os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"
).strip()
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
jax.config.update("jax_numpy_rank_promotion", "raise")


def pytest_configure(config):
    config.addinivalue_line("markers", "slow: long test, excluded from the default run")
    config.addinivalue_line("markers", "mpi: starts real processes with mpiexec")
