"""Files that appear only when complete: atomic writes (any file, HDF5, JSON) and
content checksums.

Every file jaxsync writes goes through :func:`atomic_path`: it is written under a
temporary name in the target folder and renamed over the target only when complete, so
a failed or interrupted write never replaces a good file. Outputs of several files that
belong together (an XDMF file and its data, a VTU series; any writer of
:mod:`jaxsync.io.writers`) go through :func:`staged_outputs`: written in a staging folder
beside them, and moved into place only when all are complete.

Writing can fail after a long computation (a full disk, a folder that became read-only):
:func:`atomic_path` then raises :class:`OutputError` (a :class:`jaxsync.JaxsyncError`
and an :class:`OSError`) naming the file, and :func:`check_writable` finds an unusable
location before anything runs. Inside :func:`recording_writes` every completed file is
recorded, so that a command can say which of its files were written (and kept) when a
later one fails.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import os
import shutil
import tempfile
from typing import Any, Mapping, Sequence

import numpy as np

from ..errors import OutputError

__all__ = ["host_tag", "process_alive", "atomic_path", "atomic_h5", "atomic_json", "array_checksum", "json_value",
           "STALE_TEMP_AGE_S", "OutputError", "check_writable", "recording_writes", "note_written",
           "os_reason", "write_failure", "claimed_outputs", "claim_output", "claiming", "OutputFile",
           "StagedOutputs", "staged_outputs"]


_RECORDERS: list[list[str]] = []


@dataclasses.dataclass
class _Claim:
    """An output a command declared: its lock file, whether an existing file may be
    replaced (``--force``), and whether this command has written it already."""

    path: str
    lock: str
    replace: bool
    written: bool = False
    created_folders: tuple[str, ...] = ()


_CLAIMS: list[dict[str, _Claim]] = []


@contextlib.contextmanager
def claimed_outputs():
    """The scope of :func:`claim_output` (a command line run wraps each command in one):
    the claims made inside are released, and their lock files removed, at the end."""
    claims: dict[str, _Claim] = {}
    _CLAIMS.append(claims)
    try:
        yield claims
    finally:
        _CLAIMS.remove(claims)
        for claim in claims.values():
            with contextlib.suppress(OSError):
                os.remove(claim.lock)
        for claim in claims.values():
            # the folders made for the locks (deepest first), where a failed run left them empty;
            # never one that existed before
            for folder in claim.created_folders:
                with contextlib.suppress(OSError):
                    os.rmdir(folder)


def _lock_owner(lock: str) -> str:
    try:
        with open(lock) as f:
            return f.read().strip()
    except OSError:
        return ""


def claiming() -> bool:
    """True inside :func:`claimed_outputs` (a command line run), where outputs are claimed."""
    return bool(_CLAIMS)


def claim_output(path: str | os.PathLike, *, replace: bool, folder: bool = False) -> None:
    """Declare ``path`` an output of the running command (inside :func:`claimed_outputs`).

    Takes the write lock ``.<name>.lock`` beside it, so that a second jaxsync process
    that claims the same output stops at once (:class:`OutputError` naming the process)
    instead of replacing the first one's result; a lock left by a process that is gone
    (on this host) is taken over. Then, unless ``replace``, the atomic writes of this
    command never replace a file at ``path`` that they did not write themselves: one
    that appears while the command runs (another program) is kept, and the new result
    is written beside it (:func:`atomic_path`). ``folder``: ``path`` is a folder that the
    command fills or replaces as a whole (its lock is beside it too)."""
    if not _CLAIMS:
        raise RuntimeError("claim_output needs an enclosing claimed_outputs() block")
    full = os.path.abspath(os.fspath(path))
    claims = _CLAIMS[-1]
    if full in claims:
        claims[full].replace = claims[full].replace or replace
        return
    check_writable(full, folder=folder)  # an unusable location is said as such, before any folder is made
    folder = os.path.dirname(full)
    created = []  # the folders this claim makes, deepest first
    missing = folder
    while not os.path.isdir(missing) and os.path.dirname(missing) != missing:
        created.append(missing)
        missing = os.path.dirname(missing)
    if created:
        try:
            os.makedirs(folder, exist_ok=True)
        except OSError as exc:
            raise write_failure(full, exc) from exc
    lock = os.path.join(folder, f".{os.path.basename(full)}.lock")
    me = f"{os.getpid()}@{host_tag()}"
    for _ in range(3):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            owner = _lock_owner(lock)
            pid, _, host = owner.partition("@")
            gone = (host == host_tag() and pid.isdigit() and not process_alive(int(pid))) or (
                not owner and _age(lock) > 5.0)
            if gone or (host != host_tag() and _age(lock) > STALE_TEMP_AGE_S):
                with contextlib.suppress(OSError):
                    os.remove(lock)
                continue
            raise OutputError(f"{path} is being written by another jaxsync process (pid {pid or '?'} on "
                              f"{host or 'an unknown host'}, lock {lock}); wait for it to finish, or choose "
                              "another output name") from None
        except OSError as exc:
            raise write_failure(full, exc) from exc
        with os.fdopen(fd, "w") as f:
            f.write(me)
        break
    else:
        raise OutputError(f"could not take the write lock {lock} of {path}; remove it if no jaxsync process "
                          "writes there, and run again")
    claims[full] = _Claim(full, lock, bool(replace), created_folders=tuple(created))


def _age(path: str) -> float:
    import time

    try:
        return time.time() - os.stat(path).st_mtime
    except OSError:
        return 0.0


def _claim_of(path: str) -> _Claim | None:
    full = os.path.abspath(path)
    for claims in reversed(_CLAIMS):
        if full in claims:
            return claims[full]
    return None


def _conflict_name(path: str) -> str:
    root, ext = os.path.splitext(path)
    k = 1
    while os.path.lexists(f"{root}.conflict-{k}{ext}"):
        k += 1
    return f"{root}.conflict-{k}{ext}"


def _commit(tmp: str, path: str, replace: bool = True) -> None:
    """Rename ``tmp`` onto ``path``. Without ``replace``, or for a claimed output that may
    not be replaced (:func:`claim_output`), only if no file is there (a hard link, which
    fails rather than replace): an existing file is kept, the new one is written beside it
    under a ``.conflict-<k>`` name, and :class:`OutputError` says so."""
    claim = _claim_of(path)
    if replace and (claim is None or claim.replace or claim.written):
        os.replace(tmp, path)
    else:
        try:
            os.link(tmp, path)  # atomic, and refuses an existing target
        except FileExistsError:
            _keep_beside(tmp, path, claim is not None and replace)
        except OSError:  # a file system without hard links
            if os.path.lexists(path):
                _keep_beside(tmp, path, claim is not None and replace)
            os.replace(tmp, path)
        else:
            os.remove(tmp)
    if claim is not None:
        claim.written = True


def _keep_beside(tmp: str, path: str, appeared: bool) -> None:
    kept = _conflict_name(path)
    os.replace(tmp, kept)
    note_written(kept)
    why = ("appeared while this command ran (another process wrote it)" if appeared
           else "exists and overwrite=False")
    raise OutputError(f"{path} {why}: it was left as it is, and the new result was written to {kept}")


@contextlib.contextmanager
def recording_writes():
    """Yield a list that collects the absolute path of every file completed inside the
    block (by :func:`atomic_path`, or given to :func:`note_written`), in order."""
    log: list[str] = []
    _RECORDERS.append(log)
    try:
        yield log
    finally:
        _RECORDERS.remove(log)


def note_written(path: str | os.PathLike) -> None:
    """Record ``path`` as written in every active :func:`recording_writes` (for files
    written another way than through :func:`atomic_path`)."""
    full = os.path.abspath(os.fspath(path))
    for log in _RECORDERS:
        if full not in log:
            log.append(full)


def os_reason(exc: BaseException) -> str:
    """An OS error's reason on one line (``No space left on device [Errno 28]``)."""
    if isinstance(exc, OSError) and exc.strerror:
        text = f"{exc.strerror} [Errno {exc.errno}]" if exc.errno else exc.strerror
    else:
        text = str(exc) or type(exc).__name__
    return " ".join(text.split())


def check_writable(path: str | os.PathLike, *, what: str = "output", folder: bool = False,
                   option: str | None = None) -> None:
    """Raise :class:`OutputError`, before anything runs, unless ``path`` can be written.

    ``path`` is a file (``folder=False``: it must not be a folder, and its folder must
    be writable) or a folder that the writer fills (``folder=True``: it must not be a
    file). A folder that does not exist yet counts as writable when the nearest one
    above it that exists is a writable folder (the writers create the rest). Writable
    means that a temporary file can really be created and removed there (permission
    bits say nothing for root, nor for read-only mounts). ``what`` names the output in
    the message and ``option`` the command-line option that chooses another location.
    """
    path = os.fspath(path)
    full = os.path.abspath(path)
    fix = f"choose another location{f' with {option}' if option else ''}"
    if not folder and os.path.isdir(full):
        raise OutputError(f"cannot write the {what} {path}: it is a folder; give a file name ({fix})")
    probe = full if folder else os.path.dirname(full)
    while not os.path.lexists(probe):
        parent = os.path.dirname(probe)
        if parent == probe:
            break
        probe = parent
    if not os.path.isdir(probe):
        raise OutputError(f"cannot write the {what} {path}: {probe} is a file, not a folder; {fix}")
    try:
        fd, tmp = tempfile.mkstemp(prefix=".jaxsync-write-check.", dir=probe)
    except OSError as exc:
        raise OutputError(f"cannot write the {what} {path}: the folder {probe} is not writable "
                          f"({os_reason(exc)}); {fix}, or make the folder writable") from None
    os.close(fd)
    with contextlib.suppress(OSError):
        os.remove(tmp)

STALE_TEMP_AGE_S = 3600.0
"""A temporary file of :func:`atomic_path` whose writer cannot be checked (another host,
or written by an older jaxsync) counts as abandoned when unmodified for this long."""


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, replace: bool = True):
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success,
    delete it on failure.

    ``replace=False``: never replace a file at ``path`` (one there from the start, or one
    that another process writes meanwhile): it is kept, the new file is written beside it
    as ``<stem>.conflict-<k><ext>`` and :class:`OutputError` names both. The outputs a
    command claimed (:func:`claim_output`) are protected the same way.

    The temporary file is ``.<name>.<pid>@<host>.<random>.tmp``. A writer killed hard
    (SIGKILL, power loss) cannot delete it, so every write first removes the temporary
    files of the same target left by writers that are gone: on this host, those whose
    process no longer exists; from another host or an older jaxsync (no owner in the
    name), those unmodified for :data:`STALE_TEMP_AGE_S`. Live concurrent writers keep
    theirs."""
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    prefix = f".{os.path.basename(path)}."
    try:
        os.makedirs(folder, exist_ok=True)
        _remove_stale_temporaries(folder, prefix)
        fd, tmp = tempfile.mkstemp(prefix=f"{prefix}{os.getpid()}@{host_tag()}.", suffix=".tmp",
                                   dir=folder)
        os.close(fd)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600 files; give the usual permissions
    except OutputError:
        raise
    except OSError as exc:
        raise write_failure(path, exc) from exc
    try:
        yield tmp
        _commit(tmp, path, replace)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        if isinstance(exc, OSError) and not isinstance(exc, OutputError):
            raise write_failure(path, exc) from exc
        raise
    note_written(path)


@dataclasses.dataclass(frozen=True)
class OutputFile:
    """One file (or folder, ``folder=True``) that a write produces: its final ``path`` and
    what it is (``what``, for messages: ``"XDMF data file"``)."""

    path: str
    what: str = "output"
    folder: bool = False


class StagedOutputs:
    """The staging area of one multi-file write (:func:`staged_outputs`).

    :meth:`path` gives, for each declared output, the path to write it at: a file or
    folder of the same name inside a hidden staging folder beside the output, so that
    files which refer to each other by name (an ``.xdmf`` and its ``.h5``) stay consistent,
    and renaming them into place is atomic (the same file system)."""

    def __init__(self, outputs: Sequence[OutputFile], *, replace: bool = True):
        self.outputs = tuple(outputs)
        self._replace = replace
        self._declared = {os.path.abspath(o.path): o for o in self.outputs}
        self._folders: dict[str, str] = {}  # target folder -> its staging folder

    def path(self, target: str | os.PathLike) -> str:
        """Where to write the declared output ``target`` (its staged path)."""
        full = os.path.abspath(os.fspath(target))
        if full not in self._declared:
            known = ", ".join(o.path for o in self.outputs)
            raise OutputError(f"{os.fspath(target)} is not an output of this write (declared: {known}): a writer "
                              "writes only the outputs it declares")
        folder = os.path.dirname(full)
        if folder not in self._folders:
            name = os.path.basename(full)  # an OSError here is the write's failure (staged_outputs)
            os.makedirs(folder, exist_ok=True)
            _remove_stale_temporaries(folder, f".{name}.", suffix=".stage")
            self._folders[folder] = tempfile.mkdtemp(prefix=f".{name}.{os.getpid()}@{host_tag()}.", suffix=".stage",
                                                     dir=folder)
        return os.path.join(self._folders[folder], os.path.basename(full))

    def __enter__(self) -> "StagedOutputs":
        return self

    def __exit__(self, kind, exc, traceback) -> bool:
        """On a normal exit, move the staged outputs into place; remove the staging
        folders in every case."""
        try:
            if kind is None:
                self._commit(self._replace)
        finally:
            self._discard()
        return False

    def _commit(self, replace: bool) -> None:
        """Move the staged outputs into place in their declared order; a failure puts back
        what earlier outputs replaced (those already moved stay written)."""
        undo: list = []
        try:
            for output in self.outputs:
                full = os.path.abspath(output.path)
                staging = self._folders.get(os.path.dirname(full))
                staged = None if staging is None else os.path.join(staging, os.path.basename(full))
                if staged is None or not os.path.lexists(staged):
                    continue  # declared, not written (nothing to show for it)
                if output.folder:
                    _commit_folder(staged, full, replace, undo)
                else:
                    _keep_previous(full, staging, replace, undo)
                    _commit(staged, full, replace)
                note_written(full)
        except BaseException:
            for restore in reversed(undo):
                with contextlib.suppress(OSError):
                    restore()
            raise

    def _discard(self) -> None:
        for staging in self._folders.values():
            shutil.rmtree(staging, ignore_errors=True)


def _keep_previous(path: str, staging: str, replace: bool, undo: list) -> None:
    """A hard link to the file at ``path`` (the previous output) in the staging folder,
    so that a failed commit can put it back."""
    claim = _claim_of(path)
    if not (replace and (claim is None or claim.replace or claim.written)) or not os.path.isfile(path):
        return
    backup = os.path.join(staging, os.path.basename(path) + ".previous")
    with contextlib.suppress(OSError):
        os.link(path, backup)
        undo.append(lambda: os.replace(backup, path))
        return
    # no hard links: no way back for this file (it is replaced atomically all the same)


def _commit_folder(staged: str, path: str, replace: bool, undo: list) -> None:
    """Rename the staged folder onto ``path``; an earlier folder there (only when it may be
    replaced) goes aside first and comes back on failure."""
    claim = _claim_of(path)
    may_replace = replace and (claim is None or claim.replace or claim.written)
    if os.path.lexists(path):
        if not may_replace:
            raise OutputError(f"{path} exists and may not be replaced: it was left as it is; remove it, or choose "
                              "another location")
        aside = staged + ".previous"
        os.rename(path, aside)
        undo.append(lambda: os.rename(aside, path))
    os.rename(staged, path)
    undo.append(lambda: os.rename(path, staged))
    if claim is not None:
        claim.written = True


@contextlib.contextmanager
def staged_outputs(outputs: Sequence[OutputFile], *, main: str | os.PathLike | None = None,
                   replace: bool = True):
    """Write several files (and folders) that appear together, only when all are complete.

    Yields a :class:`StagedOutputs`: write each declared output at
    ``staged.path(output.path)``. When the block ends normally they are moved into place
    in the order of ``outputs`` (each file atomically, as :func:`atomic_path` does, with
    the same ``replace`` rules, and a folder replaces an earlier one only where a file
    would be replaced, else :class:`OutputError`; put the file that refers to the others
    last); when it raises, nothing is moved and the staging folders are removed, so a
    failed write leaves earlier outputs as they were (and should a move fail, the files
    already replaced are put back where the file system has hard links). An
    :class:`OSError` becomes an :class:`OutputError` naming ``main`` (default: the last
    output). A writer killed hard leaves a hidden
    ``.<name>.<pid>@<host>.<random>.stage`` folder, removed by the next write there once
    its process is gone."""
    outputs = tuple(outputs)
    main = os.fspath(main) if main is not None else (outputs[-1].path if outputs else "output")
    try:
        with StagedOutputs(outputs, replace=replace) as staged:
            yield staged
    except BaseException as exc:
        if isinstance(exc, OSError) and not isinstance(exc, OutputError):
            raise write_failure(main, exc) from exc
        raise


def write_failure(path: str, exc: OSError) -> OutputError:
    """The :class:`OutputError` of a failed write of ``path`` (the previous file, if
    any, is left as it was)."""
    import errno

    fixes = {errno.ENOSPC: "free space, or choose another location, and run again",
             errno.EDQUOT: "free space within your quota, or choose another location, and run again",
             errno.EISDIR: "it is a folder: give a file name",
             errno.EEXIST: "a file is in the way of a folder of the path: choose another location",
             errno.ENOTDIR: "a part of the path is a file, not a folder: choose another location",
             errno.ENOENT: "its folder cannot be made there: choose another location",
             errno.EACCES: "the folder is not writable: choose another location, or make it writable",
             errno.EROFS: "the file system is read-only: choose another location"}
    fix = fixes.get(getattr(exc, "errno", None), "choose another location, and run again")
    return OutputError(f"could not write {path}: {os_reason(exc)} ({fix})")


def host_tag() -> str:
    """This host's name as it goes into temporary file and folder names (letters, digits,
    '-'): with the writer's pid it tells whether a leftover is stale."""
    import re
    import socket

    return re.sub(r"[^A-Za-z0-9-]", "-", socket.gethostname())[:64] or "host"


def process_alive(pid: int) -> bool:
    """Whether process ``pid`` of this host still runs (True when it cannot be told, so
    that its files are kept)."""
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


def _remove_stale_temporaries(folder: str, prefix: str, suffix: str = ".tmp") -> None:
    """Delete ``<prefix><pid>@<host>.<random><suffix>`` files (``.stage``: folders) whose
    writer is gone, and ``<prefix><random>.tmp`` files (older jaxsync) unmodified for
    STALE_TEMP_AGE_S."""
    import re
    import time

    owned = re.compile(re.escape(prefix) + r"(\d+)@([A-Za-z0-9-]+)\.[A-Za-z0-9_]+" + re.escape(suffix) + "$")
    legacy = re.compile(re.escape(prefix) + r"[a-z0-9_]{8}\.tmp$")  # mkstemp's 8 characters
    try:
        names = [n for n in os.listdir(folder) if n.startswith(prefix) and n.endswith(suffix)]
    except OSError:
        return
    host, now = host_tag(), time.time()
    for name in names:
        full = os.path.join(folder, name)
        match = owned.match(name)
        try:
            if match and match.group(2) == host:
                stale = not process_alive(int(match.group(1)))
            elif match or legacy.match(name):
                stale = now - os.stat(full).st_mtime > STALE_TEMP_AGE_S
            else:
                continue  # another target's temporary whose name starts alike
            if stale and os.path.isfile(full):
                os.remove(full)
            elif stale and suffix == ".stage" and os.path.isdir(full) and not os.path.islink(full):
                shutil.rmtree(full, ignore_errors=True)
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
def atomic_h5(path: str | os.PathLike, *, replace: bool = True):
    """Open a new HDF5 file for writing that appears at ``path`` only when complete
    (``replace``: as for :func:`atomic_path`)."""
    import h5py

    with atomic_path(path, replace=replace) as tmp:
        with h5py.File(tmp, "w") as f:
            yield f


def json_value(value):
    """``value`` with numpy scalars and arrays turned into Python numbers and lists (for
    ``json.dump``), and every non-finite number (nan, inf) turned into None: JSON has no
    NaN or Infinity (``json.dump`` would write bare tokens that strict readers refuse),
    so a value that was not measured, or is unbounded, is written as null."""
    if isinstance(value, dict):
        return {str(k): json_value(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_value(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_value(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def atomic_json(path: str | os.PathLike, data, *, indent: int = 2) -> None:
    """Write ``data`` (numpy values allowed) as JSON to ``path``, atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, "w") as f:
            json.dump(json_value(data), f, indent=indent)
            f.write("\n")
