"""Files that appear only when complete: atomic writes (any file, HDF5, JSON) and
content checksums.

Every file jaxsync writes goes through :func:`atomic_path`: it is written under a
temporary name in the target folder and renamed over the target only when complete, so
a failed or interrupted write never replaces a good file.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
from typing import Any, Mapping

import numpy as np

__all__ = ["atomic_path", "atomic_h5", "atomic_json", "array_checksum", "json_value",
           "STALE_TEMP_AGE_S"]

STALE_TEMP_AGE_S = 3600.0
"""A temporary file of :func:`atomic_path` whose writer cannot be checked (another host,
or written by an older jaxsync) counts as abandoned when unmodified for this long."""


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success,
    delete it on failure.

    The temporary file is ``.<name>.<pid>@<host>.<random>.tmp``. A writer killed hard
    (SIGKILL, power loss) cannot delete it, so every write first removes the temporary
    files of the same target left by writers that are gone: on this host, those whose
    process no longer exists; from another host or an older jaxsync (no owner in the
    name), those unmodified for :data:`STALE_TEMP_AGE_S`. Live concurrent writers keep
    theirs."""
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    prefix = f".{os.path.basename(path)}."
    _remove_stale_temporaries(folder, prefix)
    fd, tmp = tempfile.mkstemp(prefix=f"{prefix}{os.getpid()}@{_host_tag()}.", suffix=".tmp",
                               dir=folder)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600 files; give the usual permissions
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise


def _host_tag() -> str:
    """This host's name as it goes into temporary file names (letters, digits, '-')."""
    import re
    import socket

    return re.sub(r"[^A-Za-z0-9-]", "-", socket.gethostname())[:64] or "host"


def _process_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    except OSError:
        return True  # cannot tell: keep the file
    return True


def _remove_stale_temporaries(folder: str, prefix: str) -> None:
    """Delete ``<prefix><pid>@<host>.<random>.tmp`` files whose writer is gone, and
    ``<prefix><random>.tmp`` files (older jaxsync) unmodified for STALE_TEMP_AGE_S."""
    import re
    import time

    owned = re.compile(re.escape(prefix) + r"(\d+)@([A-Za-z0-9-]+)\.[A-Za-z0-9_]+\.tmp$")
    legacy = re.compile(re.escape(prefix) + r"[a-z0-9_]{8}\.tmp$")  # mkstemp's 8 characters
    try:
        names = [n for n in os.listdir(folder) if n.startswith(prefix) and n.endswith(".tmp")]
    except OSError:
        return
    host, now = _host_tag(), time.time()
    for name in names:
        full = os.path.join(folder, name)
        match = owned.match(name)
        try:
            if match and match.group(2) == host:
                stale = not _process_alive(int(match.group(1)))
            elif match or legacy.match(name):
                stale = now - os.stat(full).st_mtime > STALE_TEMP_AGE_S
            else:
                continue  # another target's temporary whose name starts alike
            if stale and os.path.isfile(full):
                os.remove(full)
        except OSError:
            continue  # removed meanwhile, or not ours to remove


def array_checksum(arrays: Mapping[str, np.ndarray], meta: Mapping[str, Any]) -> str:
    """sha256 (hex) over named arrays (name, dtype, shape and bytes of each, in name order)
    and JSON-serialisable metadata: stored in a file, it shows whether the file's content
    was altered after it was written."""
    digest = hashlib.sha256()
    for name in sorted(arrays):
        array = np.ascontiguousarray(arrays[name])
        digest.update(name.encode())
        digest.update(array.dtype.str.encode())
        digest.update(repr(array.shape).encode())
        digest.update(array.tobytes())
    digest.update(json.dumps(dict(meta), sort_keys=True).encode())
    return digest.hexdigest()


@contextlib.contextmanager
def atomic_h5(path: str | os.PathLike):
    """Open a new HDF5 file for writing that appears at ``path`` only when complete."""
    import h5py

    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            yield f


def json_value(value):
    """``value`` with numpy scalars and arrays turned into Python numbers and lists (for
    ``json.dump``)."""
    if isinstance(value, dict):
        return {str(k): json_value(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_value(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


def atomic_json(path: str | os.PathLike, data, *, indent: int = 2) -> None:
    """Write ``data`` (numpy values allowed) as JSON to ``path``, atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, "w") as f:
            json.dump(json_value(data), f, indent=indent)
            f.write("\n")
