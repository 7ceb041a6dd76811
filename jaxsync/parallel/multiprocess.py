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
   MPI ``Allreduce`` called from inside the compiled step (:func:`make_allreduce`:
   mpi4jax when installed, else jaxsync's own ``ctypes`` FFI handler, which every install
   has; an mpi4py host callback only where neither runs);
3. reads results as global numpy arrays; only rank 0 (:func:`is_main_process`) prints
   and writes files.

:func:`transport` says in one line which of these a run uses (``jaxsync simulate`` prints
it); a multi-process run that falls back to a slow path warns with a
:class:`TransportWarning` that names the fix.

An exception on any rank must end the whole job, never leave the others waiting in a
collective: :func:`abort_on_error` prints the error with its rank and calls
``MPI_Abort``, which makes ``mpiexec`` kill every rank and exit non-zero.

The only global state is what ``jax.distributed`` itself keeps (its client and the JAX
config options it needs, set once in :func:`initialize`) and the FFI targets of the
``ctypes`` MPI sum (:mod:`jaxsync.parallel`).
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
import traceback
import warnings
from collections.abc import Callable, Mapping

from ..errors import ConfigError, JaxsyncError
from ..options import Sync, choices
from ._mpi_ffi import ctypes_allreduce, ctypes_problem

__all__ = ["SYNC_METHODS", "ALLREDUCE_BACKENDS", "TransportWarning", "launched_size", "launched_by_mpi",
           "launched_rank",
           "initialize", "process_index", "process_count", "is_main_process",
           "abort_on_error", "world", "make_allreduce", "mpi4jax_available", "ctypes_available",
           "default_allreduce", "default_sync", "allreduce_text", "collective_text"]

SYNC_METHODS = choices(Sync)  # ("psum", "ppermute", "mpi", "halo"), defined in jaxsync.options
"""Per-step synchronization across devices and processes: XLA ``psum`` of the whole
interface (gloo/NCCL across processes), XLA ``ppermute`` neighbour exchange of only the
nodes two devices share, MPI Allreduce, or deep halos (an exchange of displacements every
k steps, :mod:`jaxsync.parallel.exchange`)."""

ALLREDUCE_BACKENDS = ("auto", "mpi4jax", "ctypes", "callback")
"""How the MPI Allreduce is called from the compiled step: ``mpi4jax`` (an XLA FFI custom
call in compiled C++, the ``mpi`` extra), ``ctypes`` (an XLA FFI custom call whose handler
is jaxsync's own ``ctypes`` function calling ``MPI_Allreduce``: every install, no compiler;
CPU devices), ``callback`` (``jax.pure_callback`` into mpi4py: a host round trip every
step), ``auto`` (:func:`default_allreduce`: the first of these that works here)."""

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


def launched_rank(environ: Mapping[str, str] | None = None) -> int | None:
    """This process's rank as the MPI launcher's environment gives it (MPICH/Hydra,
    Open MPI, MVAPICH, PMIx), or None outside a launcher; reads no MPI state."""
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
    rank = launched_rank()
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


# --------------------------------------------------------------------------- the sum inside the step

class TransportWarning(UserWarning):
    """A multi-process run exchanges its shared-node values through a slow path (a host
    callback, or gloo's psum between CPU processes) although a fast one exists; the message
    names the fix."""


def mpi4jax_available() -> bool:
    """True when mpi4jax (MPI called from XLA as an FFI custom call) can be imported."""
    try:
        import mpi4jax  # noqa: F401
    except Exception:  # noqa: BLE001 - ImportError or a broken build: use another backend
        return False
    return True


def ctypes_available() -> bool:
    """True when jaxsync's own XLA FFI handler (``backend="ctypes"`` of
    :func:`make_allreduce`) works in this process: JAX's FFI registers it, the MPI library
    behind mpi4py exposes ``MPI_Allreduce``, and an Allreduce on ``MPI.COMM_SELF`` inside a
    compiled function returns its input (checked once per process, on a CPU device; not a
    collective, but it starts JAX: in a multi-process run, call it after :func:`initialize`).
    Needs no compiler: the handler is a ``ctypes`` function."""
    return ctypes_problem() is None


def default_allreduce() -> str:
    """The backend ``"auto"`` resolves to in this process: ``"mpi4jax"`` when importable
    (built from source: the ``mpi`` extra), else ``"ctypes"`` (jaxsync's own FFI handler,
    in every install), else ``"callback"`` (slow; :class:`TransportWarning`). On GPUs
    only mpi4jax calls MPI from the device program; there the fallback is the callback.
    Starts JAX (after :func:`initialize` in a multi-process run)."""
    import jax

    if mpi4jax_available():
        return "mpi4jax"
    if jax.default_backend() == "cpu" and ctypes_available():
        return "ctypes"
    return "callback"


def make_allreduce(comm=None, backend: str = "auto") -> Callable:
    """A traceable sum over the processes of ``comm``: ``f(x) -> sum_ranks x``.

    Usable inside ``jit``, ``lax.scan``, ``vmap`` and ``shard_map`` over ONE local device
    (mpi4jax carries an ordered effect that XLA refuses on several devices, and the other
    backends would call MPI from several threads). Every rank must call it the same number
    of times in the same order, as for any MPI collective; with ``"ctypes"`` and
    ``"callback"`` two sums in one program must depend on one another (as the steps of a
    scan do), since XLA may run independent calls in either order.

    Args:
        comm: an mpi4py communicator (default ``MPI.COMM_WORLD``).
        backend: ``"mpi4jax"`` (XLA FFI custom call into MPI, compiled C++: the ``mpi``
            extra), ``"ctypes"`` (an XLA FFI custom call whose handler is jaxsync's
            ``ctypes`` function calling the MPI library's ``MPI_Allreduce`` on the device
            buffers: no host copy, no compiler; CPU devices), ``"callback"``
            (``jax.pure_callback`` into mpi4py ``Allreduce``: a host round trip) or ``"auto"``
            (:func:`default_allreduce`). ``"auto"`` falling back to the callback between
            several processes warns with a :class:`TransportWarning` (on rank 0).

    Raises:
        ConfigError: unknown backend, or a backend requested that cannot run here (the
            message says why and what to install).
    """
    if backend not in ALLREDUCE_BACKENDS:
        raise ConfigError(f"allreduce backend must be one of {ALLREDUCE_BACKENDS}, got {backend!r}")
    comm = world() if comm is None else comm
    if backend == "auto":
        backend = default_allreduce()
        if backend == "callback" and comm.Get_size() > 1 and comm.Get_rank() == 0:
            warnings.warn(f"the MPI sum of every step goes through a host callback (slow): {_fast_path_fix()}",
                          TransportWarning, stacklevel=2)
    if backend == "mpi4jax":
        if not mpi4jax_available():
            raise ConfigError("mpi4jax is not installed; pip install -e '.[mpi]' (built with the mpicc of the "
                              "mpich dependency) or use backend='ctypes'")
        import mpi4jax
        from mpi4py import MPI

        def allreduce(x):
            return mpi4jax.allreduce(x, op=MPI.SUM, comm=comm)

        return allreduce
    if backend == "ctypes":
        problem = ctypes_problem()
        if problem is not None:
            raise ConfigError(f"the ctypes MPI sum cannot run here ({problem}); use backend='callback' or "
                              "pip install -e '.[mpi]' (mpi4jax)")
        return ctypes_allreduce(comm)
    return _callback_allreduce(comm)


def _fast_path_fix() -> str:
    """What to do when only the callback is left (why the ctypes handler cannot run)."""
    import jax

    if jax.default_backend() != "cpu":
        return (f"on {jax.default_backend()} devices only mpi4jax calls MPI from the device program: "
                "pip install -e '.[mpi]', or use --sync psum (NCCL)")
    return (f"jaxsync's ctypes FFI handler cannot run ({ctypes_problem()}); pip install -e '.[mpi]' "
            "(mpi4jax, built with mpicc), or upgrade jax and mpi4py")


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


# --------------------------------------------------------------------------- choosing and naming the transport

def default_sync() -> str:
    """The synchronization used when none is asked for.

    ``"psum"`` in one process, and across GPU processes (NCCL); ``"mpi"`` across CPU
    processes when mpi4py is importable: there JAX's psum goes through gloo, some hundred
    microseconds per exchange, against a few microseconds for an MPI Allreduce called from
    the compiled step (``benchmarks/bench_sync.py``; the numbers: docs/guides/clusters.md).
    Falling back to gloo's psum between CPU processes (no mpi4py) warns with a
    :class:`TransportWarning`."""
    import jax

    if process_count() == 1 or jax.default_backend() != "cpu":
        return "psum"
    try:
        world()
    except ConfigError as exc:
        if is_main_process():
            warnings.warn(f"the shared-node sums go through gloo's psum between processes (slow): {exc}",
                          TransportWarning, stacklevel=2)
        return "psum"
    return "mpi"


def _between() -> str:
    n = process_count()
    return f"between {n} processes" if n > 1 else "in one process"


def allreduce_text(allreduce: str = "auto") -> str:
    """How an MPI Allreduce of backend ``allreduce`` (one of :data:`ALLREDUCE_BACKENDS`)
    sums the shared-node values in this process's setting: one line for ``jaxsync
    simulate``'s header (:func:`jaxsync.solve.transport`)."""
    backend = allreduce if allreduce != "auto" else default_allreduce()
    if backend == "callback":
        fix = (_fast_path_fix() if allreduce == "auto"
               else "Mpi(allreduce='auto') calls MPI inside the step")
        return f"MPI Allreduce through an mpi4py host callback {_between()} (slow, a host round trip every step: {fix})"
    name = "mpi4jax" if backend == "mpi4jax" else "jaxsync's ctypes FFI handler"
    return f"MPI Allreduce inside the compiled step ({name}) {_between()}"


def collective_text(what: str, devices=None, n_parts: int | None = None) -> str:
    """How XLA's collective ``what`` (its words as printed: ``"psum"``, ``"ppermute
    (neighbouring devices only)"``) exchanges values over ``devices`` (default
    ``jax.devices()``) for a run of ``n_parts`` parts in this process's setting: one line
    for ``jaxsync simulate``'s header (:func:`jaxsync.solve.transport`)."""
    import jax

    devices = list(jax.devices() if devices is None else devices)
    if process_count() == 1 and n_parts:  # the runner takes as many as divide the parts
        devices = devices[:max(d for d in range(1, min(len(devices), n_parts) + 1) if n_parts % d == 0)]
    n, platform = len(devices), devices[0].platform
    if process_count() > 1 and platform == "cpu":
        return (f"gloo {what} {_between()} (slow, ~0.2-1 ms per exchange: --sync mpi calls MPI inside "
                "the step)")
    if n == 1:
        return "one device (the parts' sums stay on it: no exchange between devices)"
    if platform == "cpu":
        kind = "emulated CPU devices" if process_count() == 1 else "CPU devices"
    else:
        kind = "GPUs (NCCL)" if platform in ("gpu", "cuda") else f"{platform} devices"
    return f"XLA {what} over {n} {kind} {_between()}"
