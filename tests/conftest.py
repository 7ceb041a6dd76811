"""Test configuration, set before jax is imported: two emulated CPU devices, float64, and
JAX's strict numpy rules as diffrax and equinox test with them -- no implicit dtype
promotion (``jnp.float32 + jnp.float64`` is an error, not a silent upcast) and no implicit
rank promotion (adding a (n,) to an (n, 1) array is an error, not an (n, n) result)."""

import os
import shutil
import tempfile

os.environ["XLA_FLAGS"] = (
    os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"
).strip()
# The suite's time goes to compiling, not running, its programs: without LLVM's
# optimization passes XLA:CPU compiles them faster than the slower machine code costs
# (test_follower + test_syncavoid + test_boundary: 283 s -> 199 s on 2 cores). The results
# agree to round-off, not bit for bit (2 000 cantilever steps and 500 neo-Hookean ones:
# 1e-13 of the largest displacement apart; no fast-math at either level), and every test
# compares with its references at round-off tolerances or runs both sides here. The
# programs users run, and every benchmark, compile at the default level, and so do the
# notebooks' kernels (tests/test_notebook.py: long inverse problems, where the level pays:
# 283 s -> 181 s). A level given in XLA_FLAGS by the caller is kept.
if "--xla_backend_optimization_level" not in os.environ["XLA_FLAGS"]:
    os.environ["XLA_FLAGS"] += " --xla_backend_optimization_level=0"
# For the same reason the fusions are emitted by XLA:CPU's elemental emitters rather than its
# MLIR fusion emitters, which take longer to compile what these small programs run:
# test_halo + test_follower 70 s -> 46 s, test_vessel_demo 96 s -> 65 s (one process, at
# level 0 both). The arithmetic is the same HLO; the tests' tolerances are the round-off ones
# above. A setting given in XLA_FLAGS by the caller is kept.
if "--xla_cpu_use_fusion_emitters" not in os.environ["XLA_FLAGS"]:
    os.environ["XLA_FLAGS"] += " --xla_cpu_use_fusion_emitters=false"
os.environ.setdefault("JAX_PLATFORMS", "cpu")

# One XLA compilation cache for the test session: most of the suite's time is compiling, and
# many tests compile the same programs (the cantilever's stepper, the training step, ...) in
# either xdist worker or in the interpreters that tests start (documentation blocks,
# notebooks, command lines), which inherit these variables. Only the compilation is skipped:
# a cache hit is the executable XLA compiled from the same program with the same options.
# The folder is new for every session (a test run never reads an earlier run's programs)
# and removed at its end; a JAX_COMPILATION_CACHE_DIR set by the user is used as it is, and
# JAXSYNC_TEST_XLA_CACHE=0 turns the cache off.
_OWN_CACHE = None
if os.environ.get("JAXSYNC_TEST_XLA_CACHE", "1") != "0" and "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    _OWN_CACHE = tempfile.mkdtemp(prefix="jaxsync-tests-xla-cache-")
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _OWN_CACHE
    # every program, not only those that compile for more than a second (the default)
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
jax.config.update("jax_numpy_rank_promotion", "raise")


def pytest_configure(config):
    config.addinivalue_line("markers", "slow: long test, excluded from the default run")
    config.addinivalue_line("markers", "mpi: starts real processes with mpiexec")


def pytest_unconfigure(config):
    # the process that made the session's cache removes it (the xdist workers inherited it)
    if _OWN_CACHE is not None:
        shutil.rmtree(_OWN_CACHE, ignore_errors=True)
