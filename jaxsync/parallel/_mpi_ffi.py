"""jaxsync's own MPI sum inside a compiled step: an XLA FFI handler, written with ctypes,
that calls ``MPI_Allreduce`` of the MPI library mpi4py loaded (every install has it; mpi4jax
is preferred where installed, :func:`jaxsync.parallel.multiprocess.make_allreduce`).

The only global state is the FFI targets (one per communicator, registered with JAX on
first use and kept for the life of the process, since XLA holds their addresses) and the
cached result of one self-test.
"""

from __future__ import annotations

import ctypes
import threading
from collections.abc import Callable

__all__ = ["ctypes_allreduce", "ctypes_problem"]


# The XLA FFI's C structures that the handler reads (xla/ffi/api/c_api.h, API version 0.x:
# fields are only ever appended, so these prefixes stay valid).

class _ExtensionBase(ctypes.Structure):
    _fields_ = [("struct_size", ctypes.c_size_t), ("type", ctypes.c_int), ("next", ctypes.c_void_p)]


class _ApiVersion(ctypes.Structure):
    _fields_ = [("struct_size", ctypes.c_size_t), ("extension_start", ctypes.c_void_p),
                ("major_version", ctypes.c_int), ("minor_version", ctypes.c_int)]


class _Metadata(ctypes.Structure):
    _fields_ = [("struct_size", ctypes.c_size_t), ("api_version", _ApiVersion), ("traits", ctypes.c_uint32)]


class _MetadataExtension(ctypes.Structure):
    _fields_ = [("extension_base", _ExtensionBase), ("metadata", ctypes.c_void_p)]


class _Values(ctypes.Structure):  # XLA_FFI_Args and XLA_FFI_Rets
    _fields_ = [("struct_size", ctypes.c_size_t), ("extension_start", ctypes.c_void_p), ("size", ctypes.c_int64),
                ("types", ctypes.c_void_p), ("values", ctypes.c_void_p)]


class _Attrs(ctypes.Structure):
    _fields_ = [("struct_size", ctypes.c_size_t), ("extension_start", ctypes.c_void_p), ("size", ctypes.c_int64),
                ("types", ctypes.c_void_p), ("names", ctypes.c_void_p), ("attrs", ctypes.c_void_p)]


class _CallFrame(ctypes.Structure):
    _fields_ = [("struct_size", ctypes.c_size_t), ("extension_start", ctypes.c_void_p), ("api", ctypes.c_void_p),
                ("ctx", ctypes.c_void_p), ("stage", ctypes.c_int), ("args", _Values), ("rets", _Values),
                ("attrs", _Attrs), ("future", ctypes.c_void_p)]


class _Buffer(ctypes.Structure):
    _fields_ = [("struct_size", ctypes.c_size_t), ("extension_start", ctypes.c_void_p), ("dtype", ctypes.c_int),
                ("data", ctypes.c_void_p), ("rank", ctypes.c_int64), ("dims", ctypes.c_void_p)]


class _Api(ctypes.Structure):
    _fields_ = [("struct_size", ctypes.c_size_t), ("extension_start", ctypes.c_void_p),
                ("api_version", _ApiVersion), ("internal_api", ctypes.c_void_p), ("error_create", ctypes.c_void_p)]


class _ErrorCreateArgs(ctypes.Structure):
    _fields_ = [("struct_size", ctypes.c_size_t), ("extension_start", ctypes.c_void_p),
                ("message", ctypes.c_char_p), ("errc", ctypes.c_int)]


_HANDLER = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p)  # XLA_FFI_Error* handler(XLA_FFI_CallFrame*)
_ERROR_CREATE = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.POINTER(_ErrorCreateArgs))
_EXTENSION_METADATA, _STAGE_EXECUTE, _ERROR_INTERNAL = 1, 3, 13
# XLA_FFI_DataType -> mpi4py datatype name
_FFI_DATATYPES = {11: "FLOAT", 12: "DOUBLE", 4: "INT32_T", 5: "INT64_T", 15: "C_FLOAT_COMPLEX",
                  18: "C_DOUBLE_COMPLEX"}
_REGISTERED: dict = {}  # MPI communicator handle -> (target name, handler, comm): kept alive, XLA holds the pointer
_CTYPES_PROBLEM: list = []  # the cached result of the self-test (empty: not run yet)
_PYTHON_THREADS: set = set()  # threads that keep a Python thread state between calls of the handler


class _MpiSum:
    """The XLA FFI handler of one communicator: ``MPI_Allreduce(MPI_SUM)`` from the call's
    argument buffer into its result buffer, on the device (host) memory XLA gives it.

    Runs as a ``ctypes`` callback (it takes the GIL for a few microseconds per call; each of
    XLA's threads that calls it keeps a Python thread state from its first call on); the
    count and datatype come from the buffer, so one handler serves every shape and dtype,
    batched calls (``vmap``) included."""

    _EXT = _CallFrame.extension_start.offset
    _API = _CallFrame.api.offset
    _STAGE = _CallFrame.stage.offset
    _ARG = _CallFrame.args.offset + _Values.values.offset
    _RET = _CallFrame.rets.offset + _Values.values.offset
    _DTYPE, _DATA, _RANK, _DIMS = (_Buffer.dtype.offset, _Buffer.data.offset, _Buffer.rank.offset,
                                   _Buffer.dims.offset)

    def __init__(self, comm):
        from mpi4py import MPI

        handle_type = {4: ctypes.c_int, 8: ctypes.c_void_p}[MPI._sizeof(MPI.Comm)]
        function = ctypes.CDLL(MPI.__file__).MPI_Allreduce  # the MPI library that mpi4py uses
        function.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int, handle_type, handle_type, handle_type]
        function.restype = ctypes.c_int
        self.mpi_allreduce = function
        self.comm = comm
        self.handles = (MPI.SUM.handle, comm.handle)
        self.datatypes = {code: getattr(MPI, name).handle for code, name in _FFI_DATATYPES.items()}
        self.callback = _HANDLER(self)

    def __call__(self, frame):
        read, read64, read32 = ctypes.c_void_p.from_address, ctypes.c_int64.from_address, ctypes.c_int32.from_address
        thread = threading.get_ident()
        if thread not in _PYTHON_THREADS:
            # XLA's worker threads are not Python's: ctypes would create and delete a Python
            # thread state around every call (measured ~20 us a call). One extra
            # PyGILState_Ensure, never released, keeps this thread's state for good.
            _PYTHON_THREADS.add(thread)
            ctypes.pythonapi.PyGILState_Ensure()
        try:
            if read(frame + self._EXT).value:
                return self._metadata(frame)
            if read32(frame + self._STAGE).value != _STAGE_EXECUTE:
                return None
            arg = read(read(frame + self._ARG).value).value  # XLA_FFI_Buffer* of the one argument
            ret = read(read(frame + self._RET).value).value  # and of the one result
            dims = read(arg + self._DIMS).value
            count = 1
            for i in range(read64(arg + self._RANK).value):
                count *= read64(dims + 8 * i).value
            dtype = self.datatypes.get(read32(arg + self._DTYPE).value)
            if dtype is None or count > 2**31 - 1:
                return self._error(frame, f"cannot sum {count} values of XLA dtype {read32(arg + self._DTYPE).value} "
                                   "with MPI (float32/64, int32/64, complex; fewer than 2**31)")
            op, comm = self.handles
            code = self.mpi_allreduce(read(arg + self._DATA).value, read(ret + self._DATA).value, count, dtype,
                                      op, comm)
            return None if code == 0 else self._error(frame, f"MPI_Allreduce returned error code {code}")
        except Exception as exc:  # noqa: BLE001 - an exception must become XLA's error, not a success
            return self._error(frame, f"{type(exc).__name__}: {exc}")

    @classmethod
    def _metadata(cls, frame):
        """Answer XLA's query for the handler's API version (at registration): the runtime's
        own, of which the handler reads only fields that every 0.x version has."""
        extension = _ExtensionBase.from_address(ctypes.c_void_p.from_address(frame + cls._EXT).value)
        if extension.type != _EXTENSION_METADATA:
            return None
        metadata = _Metadata.from_address(_MetadataExtension.from_address(ctypes.addressof(extension)).metadata)
        runtime = _Api.from_address(ctypes.c_void_p.from_address(frame + cls._API).value).api_version
        if runtime.major_version != 0:
            return cls._error(frame, f"XLA FFI API {runtime.major_version}.{runtime.minor_version} is newer "
                                  "than jaxsync's MPI sum (0.x); use allreduce='callback'")
        metadata.api_version.struct_size = ctypes.sizeof(_ApiVersion)
        metadata.api_version.extension_start = None
        metadata.api_version.major_version = runtime.major_version
        metadata.api_version.minor_version = runtime.minor_version
        metadata.traits = 0
        return None

    @classmethod
    def _error(cls, frame, message: str):
        api = _Api.from_address(ctypes.c_void_p.from_address(frame + cls._API).value)
        args = _ErrorCreateArgs(ctypes.sizeof(_ErrorCreateArgs), None, f"jaxsync MPI sum: {message}".encode(),
                                _ERROR_INTERNAL)
        return _ERROR_CREATE(api.error_create)(ctypes.byref(args))


def _register(comm) -> str:
    """The FFI target name of ``comm``'s handler, registered on first use."""
    import jax

    key = comm.handle
    if key not in _REGISTERED:
        name = f"jaxsync_mpi_allreduce_{len(_REGISTERED)}"
        handler = _MpiSum(comm)
        jax.ffi.register_ffi_target(name, jax.ffi.pycapsule(handler.callback), platform="cpu")
        _REGISTERED[key] = (name, handler)
    return _REGISTERED[key][0]


def ctypes_allreduce(comm) -> Callable:
    """A function x -> the sum of x over ``comm``'s processes, an XLA FFI call into MPI
    from inside the compiled step (its target registered on first use)."""
    import jax

    name = _register(comm)

    def allreduce(x):
        return jax.ffi.ffi_call(name, jax.ShapeDtypeStruct(x.shape, x.dtype), has_side_effect=True,
                                vmap_method="expand_dims")(x)

    return allreduce


def ctypes_problem() -> str | None:
    """None when the ctypes handler works here (module-level cache of one self-test), else
    why not."""
    if not _CTYPES_PROBLEM:
        _CTYPES_PROBLEM.append(_self_test())
    return _CTYPES_PROBLEM[0]


def _self_test() -> str | None:
    try:
        import jax
        import numpy as np
        from mpi4py import MPI
    except ImportError as exc:
        return f"{exc}"
    if not (hasattr(jax, "ffi") and hasattr(jax.ffi, "pycapsule")):
        return f"jax {jax.__version__} has no jax.ffi.pycapsule"
    try:
        allreduce = ctypes_allreduce(MPI.COMM_SELF)
        x = np.arange(6.0).reshape(2, 3)
        with jax.default_device(jax.local_devices(backend="cpu")[0]):
            y = np.asarray(jax.jit(lambda v: allreduce(v) + 0.0)(x))
    except Exception as exc:  # noqa: BLE001 - any failure means: use another backend
        return f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
    return None if np.array_equal(x, y) else "the MPI sum on MPI.COMM_SELF returned wrong values"
