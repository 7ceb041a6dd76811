"""Multi-process runs: start-up under ``mpiexec``, rank helpers, abort-on-error and the
MPI sum used inside the compiled step.

A multi-process run is ``mpiexec -n N jaxsync simulate ...`` (or any script that calls
:func:`initialize` first). Every process:

1. calls :func:`initialize` before any other use of JAX: it joins the others with
   ``jax.distributed`` (ranks discovered through mpi4py), uses gloo for JAX's own CPU
   collectives and one CPU device per process;
2. builds the same problem and partition (rank 0's METIS result is broadcast), runs its
   share of the parts, and synchronizes shared-node forces every step, either with a
   ``psum`` across the processes (XLA collectives: gloo on CPU, NCCL on GPU) or with an
   MPI ``Allreduce`` called from inside the compiled step (:func:`make_allreduce`,
   mpi4jax when installed, else an mpi4py host callback);
3. reads results as global numpy arrays; only rank 0 (:func:`is_main_process`) prints
   and writes files.

An exception on any rank must end the whole job, never leave the others waiting in a
collective: :func:`abort_on_error` prints the error with its rank and calls
``MPI_Abort``, which makes ``mpiexec`` kill every rank and exit non-zero.

The only global state is what ``jax.distributed`` itself keeps (its client and the JAX
config options it needs, set once in :func:`initialize`).
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
import traceback
from collections.abc import Callable, Mapping

from ..errors import ConfigError, JaxsyncError
from ..options import Sync, choices

__all__ = ["SYNC_METHODS", "ALLREDUCE_BACKENDS", "launched_size", "launched_by_mpi",
           "initialize", "process_index", "process_count", "is_main_process",
           "abort_on_error", "world", "make_allreduce", "mpi4jax_available",
           "default_sync"]

SYNC_METHODS = choices(Sync)  # ("psum", "ppermute", "mpi", "halo"), defined in jaxsync.options
"""Per-step synchronization across devices and processes: XLA ``psum`` of the whole
interface (gloo/NCCL across processes), XLA ``ppermute`` neighbour exchange of only the
nodes two devices share, MPI Allreduce, or deep halos (an exchange of displacements every
k steps, :mod:`jaxsync.parallel.halo`)."""

ALLREDUCE_BACKENDS = ("auto", "mpi4jax", "callback")
"""How the MPI Allreduce is called from the compiled step: ``mpi4jax`` (an XLA FFI custom
call, no host round trip), ``callback`` (``jax.pure_callback`` into mpi4py), ``auto``
(mpi4jax when importable)."""

# (size variable, rank variable) set by common MPI launchers: MPICH/Intel MPI hydra and
# srun --mpi=pmi2 (PMI), Open MPI, MVAPICH, PMIx launchers.
_LAUNCHER_VARIABLES = (("PMI_SIZE", "PMI_RANK"), ("OMPI_COMM_WORLD_SIZE", "OMPI_COMM_WORLD_RANK"),
                       ("MV2_COMM_WORLD_SIZE", "MV2_COMM_WORLD_RANK"), ("PMIX_SIZE", "PMIX_RANK"))


def launched_size(environ: Mapping[str, str] | None = None) -> int:
    """Number of processes an MPI launcher started this process with (1 if none).

    Read from the launcher's environment variables (``PMI_SIZE``,
    ``OMPI_COMM_WORLD_SIZE``...), so it needs neither mpi4py nor JAX."""
    environ = os.environ if environ is None else environ
    for size, _ in _LAUNCHER_VARIABLES:
        value = environ.get(size, "")
        if value.strip().isdigit():
            return int(value)
    return 1


def launched_by_mpi(environ: Mapping[str, str] | None = None) -> bool:
    """True when an MPI launcher started this process as one of several ranks."""
    return launched_size(environ) > 1


def _launched_rank(environ: Mapping[str, str] | None = None) -> int | None:
    environ = os.environ if environ is None else environ
    for _, rank in _LAUNCHER_VARIABLES:
        value = environ.get(rank, "")
        if value.strip().isdigit():
            return int(value)
    return None


def world():
    """``mpi4py.MPI.COMM_WORLD`` (imports mpi4py, which initializes MPI).

    Raises:
        ConfigError: mpi4py (or an MPI library for it) is not installed."""
    try:
        from mpi4py import MPI
    except ImportError as exc:  # mpi4py missing, or no libmpi for it
        raise ConfigError(f"multi-process runs need mpi4py and an MPI library ({exc}); "
                          "pip install mpi4py mpich") from exc
    return MPI.COMM_WORLD


def initialize(*, cpu_devices: int | None = 1, coordinator_address: str | None = None,
               timeout_s: int = 300) -> int:
    """Join this process to the others started by ``mpiexec`` (``jax.distributed``).

    Must run in every process before any other use of JAX (array creation, ``jax.devices()``
    ...). Uses mpi4py to discover the rank, the number of processes and rank 0's host (the
    coordinator); on GPUs each process gets the GPU of its node-local rank. JAX's own CPU
    collectives use gloo. Idempotent: a second call returns at once.

    Args:
        cpu_devices: CPU devices per process (default 1: one part group per process);
            None leaves JAX's setting (``jax_num_cpu_devices`` / ``XLA_FLAGS``) alone.
        coordinator_address: ``host:port`` of the coordinator; default rank 0's host name
            and a port derived from it (or ``$JAX_COORDINATOR_ADDRESS``).
        timeout_s: seconds to wait for all processes to connect.

    Returns:
        the number of processes.

    Raises:
        ConfigError: mpi4py is missing, or JAX was used before this call.
    """
    import jax

    if jax.distributed.is_initialized():
        return jax.process_count()
    comm = world()  # fail early and clearly when mpi4py is missing
    from .devices import jax_started

    if jax_started():
        raise ConfigError("JAX was used before jaxsync.parallel.multiprocess.initialize(): call it at the "
                          "start of the program, before creating arrays or calling jax.devices()")
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    if cpu_devices is not None:
        jax.config.update("jax_num_cpu_devices", int(cpu_devices))
    try:
        jax.distributed.initialize(coordinator_address=coordinator_address,
                                   cluster_detection_method="mpi4py",
                                   initialization_timeout=int(timeout_s))
    except RuntimeError as exc:
        raise ConfigError(f"rank {comm.Get_rank()}: cannot join the other processes "
                          f"({exc}); check that all ranks run the same command and that the "
                          "coordinator address (JAX_COORDINATOR_ADDRESS) is reachable") from exc
    if jax.process_count() != comm.Get_size() or jax.process_index() != comm.Get_rank():
        raise ConfigError(f"jax.distributed sees process {jax.process_index()} of "
                          f"{jax.process_count()} but MPI rank {comm.Get_rank()} of "
                          f"{comm.Get_size()}; unset JAX_* distributed variables that "
                          "disagree with mpiexec")
    return jax.process_count()


def process_index() -> int:
    """This process's rank (0 in a single-process run)."""
    import jax

    return jax.process_index()


def process_count() -> int:
    """Number of processes joined by ``jax.distributed`` (1 in a single-process run)."""
    import jax

    return jax.process_count()


def is_main_process() -> bool:
    """True on rank 0, the process that prints summaries and writes files."""
    return process_index() == 0


def _rank_for_messages() -> str:
    import jax

    if jax.distributed.is_initialized():
        return f"rank {jax.process_index()}/{jax.process_count()}"
    rank = _launched_rank()
    return f"rank {rank}/{launched_size()}" if rank is not None else "rank ?"


@contextlib.contextmanager
def abort_on_error(*, usage_exit_code: int = 2):
    """Inside this context, an exception on one rank ends the whole MPI job.

    The error is printed to stderr with the rank (one line for a :class:`JaxsyncError`,
    the full traceback otherwise), then ``MPI_Abort`` is called with exit code
    ``usage_exit_code`` (package errors) or 1 (anything else), so ``mpiexec`` terminates
    every rank and exits non-zero instead of leaving the others blocked in a collective.
    ``SystemExit`` with status 0 passes through."""
    try:
        yield
    except SystemExit as exc:
        if exc.code in (None, 0):
            raise
        _abort(f"exited with status {exc.code}", 1 if not isinstance(exc.code, int) else exc.code)
    except JaxsyncError as exc:
        _abort(f"error: {exc}", usage_exit_code)
    except BaseException:  # noqa: BLE001 - every failure must end all ranks
        _abort(traceback.format_exc().rstrip(), 1)


def _abort(message: str, code: int) -> None:
    where = _rank_for_messages()
    text = "\n".join(f"[{where}] {line}" for line in message.splitlines())
    with contextlib.suppress(Exception):
        sys.stdout.flush()
    print(text, file=sys.stderr, flush=True)
    time.sleep(0.5)  # let the launcher forward the message before MPI_Abort kills the job
    world().Abort(int(code) or 1)
    os._exit(int(code) or 1)  # not reached: MPI_Abort does not return


def mpi4jax_available() -> bool:
    """True when mpi4jax (MPI called from XLA as an FFI custom call) can be imported."""
    try:
        import mpi4jax  # noqa: F401
    except Exception:  # noqa: BLE001 - ImportError or a broken build: use the callback
        return False
    return True


def make_allreduce(comm=None, backend: str = "auto") -> Callable:
    """A traceable sum over the processes of ``comm``: ``f(x) -> sum_ranks x``.

    Usable inside ``jit``, ``lax.scan``, ``vmap`` and ``shard_map`` over ONE local device
    (mpi4jax carries an ordered effect that XLA refuses on several devices, and a host
    callback would call MPI from several threads). Every rank must call it the same
    number of times in the same order, as for any MPI collective.

    Args:
        comm: an mpi4py communicator (default ``MPI.COMM_WORLD``).
        backend: ``"mpi4jax"`` (XLA FFI custom call into MPI, no host round trip),
            ``"callback"`` (``jax.pure_callback`` into mpi4py ``Allreduce``) or
            ``"auto"`` (mpi4jax when importable).

    Raises:
        ConfigError: unknown backend, or mpi4jax requested but not installed.
    """
    if backend not in ALLREDUCE_BACKENDS:
        raise ConfigError(f"allreduce backend must be one of {ALLREDUCE_BACKENDS}, got {backend!r}")
    comm = world() if comm is None else comm
    if backend == "auto":
        backend = "mpi4jax" if mpi4jax_available() else "callback"
    if backend == "mpi4jax":
        if not mpi4jax_available():
            raise ConfigError("mpi4jax is not installed; pip install mpi4jax (with mpicc on "
                              "PATH, e.g. after pip install mpich) or use backend='callback'")
        import mpi4jax
        from mpi4py import MPI

        def allreduce(x):
            return mpi4jax.allreduce(x, op=MPI.SUM, comm=comm)

        return allreduce
    return _callback_allreduce(comm)


def _callback_allreduce(comm) -> Callable:
    import jax
    import numpy as np
    from mpi4py import MPI

    def host_sum(x):
        x = np.ascontiguousarray(x)
        out = np.empty_like(x)
        comm.Allreduce(x, out, op=MPI.SUM)
        return out

    def allreduce(x):
        # one host call per step even when several parts share the device (expand_dims)
        return jax.pure_callback(host_sum, jax.ShapeDtypeStruct(x.shape, x.dtype), x,
                                 vmap_method="expand_dims")

    return allreduce


def default_sync() -> str:
    """The synchronization used when none is asked for.

    ``"psum"`` in one process, and across GPU processes (NCCL); ``"mpi"`` across CPU
    processes when mpi4py is importable: there JAX's psum goes through gloo, measured at
    0.4-1.1 ms per step against 5-30 us for mpi4jax's Allreduce and 0.13-0.45 ms for the
    mpi4py callback (``benchmarks/bench_sync.py``, 2 processes, 12-1002 doubles)."""
    import jax

    if process_count() == 1 or jax.default_backend() != "cpu":
        return "psum"
    try:
        world()
    except ConfigError:
        return "psum"
    return "mpi"
