"""The folder a demo writes: refused before anything runs where it holds an earlier demo or
cannot be written, filled while staged beside its final place, and installed whole
(a run that fails or is interrupted leaves the earlier folder as it was)."""

from __future__ import annotations

import os
import shutil
import tempfile

__all__ = ["DEMO_FILES", "check_demo_output", "staging_folder", "retarget_paths", "install_folder"]

DEMO_FILES = ("summary.json", "synchronized.h5", "online.h5", "surrogate", "report")
"""What a demo writes into its folder: a folder holding any of them holds a demo (which
``jaxsync demo`` replaces only with ``--force``)."""


def check_demo_output(out: str, *, force: bool = False) -> None:
    """Refuse, before anything runs, a demo folder ``out`` that holds the files of a
    demo (:data:`DEMO_FILES`) unless ``force`` (:class:`jaxsync.ConfigError`), or that
    cannot be written (:class:`jaxsync.io.OutputError`: the run is staged beside it, so
    the folder above must be writable too)."""
    from ..errors import ConfigError
    from ..io.atomic import check_writable

    out = os.path.abspath(os.fspath(out))
    if os.path.isdir(out) and not force:
        found = [name for name in DEMO_FILES if os.path.lexists(os.path.join(out, name))]
        if found:
            raise ConfigError(f"{out} holds the files of an earlier demo ({', '.join(found)}); pass --force to "
                              "replace them, or choose another folder with -o/--out")
    check_writable(out, what="demo folder", folder=True, option="-o/--out")
    check_writable(os.path.dirname(out), what="folder of the demo folder", folder=True, option="-o/--out")
    from ..io.atomic import claim_output, claiming

    if claiming():  # the command line: a second demo writing the same folder stops at once
        claim_output(out, replace=force, folder=True)


_STAGING = ".partial-"
_ASIDE = ".old-"


def staging_folder(final: str) -> str:
    """A new, empty folder beside ``final`` for the run's files
    (``<name>.partial-<pid>@<host>.<random>``), after removing the staging and set-aside
    folders of ``final`` left by runs on this host that are gone (killed hard).

    Its permissions are those of the folder it replaces, or for a new one the usual
    ones (``0o777`` less the umask, as :func:`os.makedirs` gives), with the owner's
    always full (the run writes into it): not the ``0o700`` of :func:`tempfile.mkdtemp`,
    which the folder would keep once renamed into place."""
    import stat

    staging = _new_folder_beside(final, _STAGING, clean=True)
    if os.path.isdir(final):
        mode = stat.S_IMODE(os.stat(final).st_mode)
    else:
        umask = os.umask(0)
        os.umask(umask)
        mode = 0o777 & ~umask
    os.chmod(staging, mode | stat.S_IRWXU)
    return staging


def _new_folder_beside(final: str, marker: str, *, clean: bool = False) -> str:
    import re

    from ..io.atomic import host_tag, process_alive

    parent, name = os.path.split(final)
    os.makedirs(parent, exist_ok=True)
    host = host_tag()
    if clean:
        left = re.compile(re.escape(name) + r"(?:" + re.escape(_STAGING) + "|" + re.escape(_ASIDE)
                          + r")(\d+)@([A-Za-z0-9-]+)\.[A-Za-z0-9_]+$")
        for entry in os.listdir(parent):
            match = left.match(entry)
            full = os.path.join(parent, entry)
            if (match and match.group(2) == host and not process_alive(int(match.group(1)))
                    and os.path.isdir(full) and not os.path.islink(full)):
                shutil.rmtree(full, ignore_errors=True)
    return tempfile.mkdtemp(prefix=f"{name}{marker}{os.getpid()}@{host}.", dir=parent)


def retarget_paths(staging: str, final: str) -> None:
    """Make the JSON files of ``staging`` name ``final`` where they name a path in
    ``staging`` (``surrogate/train_summary.json`` names its trajectory and files)."""
    import json

    from ..io.atomic import atomic_json

    def retarget(value):
        if isinstance(value, str) and (value == staging or value.startswith(staging + os.sep)):
            return final + value[len(staging):]
        if isinstance(value, list):
            return [retarget(v) for v in value]
        if isinstance(value, dict):
            return {k: retarget(v) for k, v in value.items()}
        return value

    for folder, _, names in os.walk(staging):
        for name in names:
            if name.endswith(".json"):
                path = os.path.join(folder, name)
                with open(path) as f:
                    data = json.load(f)
                new = retarget(data)
                if new != data:
                    atomic_json(path, new)


def install_folder(staging: str, final: str) -> None:
    """Put the complete folder ``staging`` in the place of ``final``.

    ``final`` absent: one rename. Present: it is renamed aside
    (``<name>.old-<pid>@<host>.<random>``), ``staging`` renamed in, the entries of the old folder
    that are not a demo's (:data:`DEMO_FILES`; a user's own files) moved into the new one,
    and the old folder deleted. ``final`` holds the old set or the new one at every moment
    but the one between the two renames."""
    if not os.path.lexists(final):
        os.rename(staging, final)
        return
    aside = _new_folder_beside(final, _ASIDE)
    os.rmdir(aside)  # a free name beside final
    os.rename(final, aside)
    try:
        os.rename(staging, final)
    except BaseException:
        os.rename(aside, final)  # put the old folder back
        raise
    kept = []  # a user's own files, that could not be moved: the old folder stays
    for entry in os.listdir(aside):
        if entry in DEMO_FILES:
            continue
        try:
            if os.path.lexists(os.path.join(final, entry)):
                raise FileExistsError(entry)
            os.rename(os.path.join(aside, entry), os.path.join(final, entry))
        except OSError:
            kept.append(entry)
    if kept:
        import warnings

        warnings.warn(f"{final}: the earlier folder, with {', '.join(kept)}, is kept as {aside}", UserWarning,
                      stacklevel=2)
    else:
        shutil.rmtree(aside, ignore_errors=True)
