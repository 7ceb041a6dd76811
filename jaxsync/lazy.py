"""Lazy exports: a package's names imported from their modules on first use.

``import jaxsync`` imports no numerical library (JAX, SciPy, scikit-fem, h5py, meshio,
optax, gmsh, matplotlib): each package's ``__init__`` declares where its names live
(:func:`export_lazily`, the ``from module import names`` it would otherwise run) and gets
back the module ``__getattr__`` and ``__dir__`` of PEP 562. A name's module, and what that
module imports, is imported the first time the name is used (``jaxsync.cantilever()``,
``from jaxsync import simulate``); the name is then an ordinary attribute of the package.
``__all__``, ``dir()`` and ``from package import *`` see every name before it is imported,
and a submodule (``jaxsync.io.trajectory``) is imported on first access as if the package had
imported it. Each ``__init__`` also imports its names under ``typing.TYPE_CHECKING``, so
that type checkers, IDEs and linters see them.

An export named like a submodule of its package (the function ``jaxsync.cli.main`` of the
module ``jaxsync.cli.main``) stays the export when that submodule is imported, as after
``from .main import main``: the import system's binding of the submodule on the package is
not kept (:class:`LazyPackage`).
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
import types
from collections.abc import Callable, Iterable, Mapping

__all__ = ["export_lazily", "lazy_exports", "LazyPackage"]

# {package: {exported name: absolute name of the module it is imported from}}
_ORIGINS: dict[str, dict[str, str]] = {}


def _import_from(module_name: str, name: str, package: str):
    """What ``from module_name import name`` binds in ``package`` (``module_name`` the
    package itself: its submodule ``name``)."""
    if module_name == package:
        return importlib.import_module(f"{package}.{name}")
    module = importlib.import_module(module_name)
    try:
        return getattr(module, name)
    except AttributeError:
        raise ImportError(f"{package}.{name} is exported from {module_name}, which has no {name!r}") from None


def lazy_exports(package: str) -> dict[str, str]:
    """{name: absolute name of the module it is imported from} of the lazy exports of
    ``package`` (empty for a package without them)."""
    return dict(_ORIGINS.get(package, {}))


class LazyPackage(types.ModuleType):
    """The type of a package with lazy exports: a submodule bound on the package under the
    name of an export that is not that submodule is not kept (the export is imported on
    first use instead), so that ``jaxsync.cli.main`` stays the function after
    ``import jaxsync.cli.main``, as with eager imports."""

    def __setattr__(self, name: str, value) -> None:
        origin = _ORIGINS.get(self.__name__, {}).get(name)
        submodule = f"{self.__name__}.{name}"
        if (origin is not None and origin != self.__name__ and isinstance(value, types.ModuleType)
                and value.__name__ == submodule):
            return
        super().__setattr__(name, value)


def export_lazily(package: str, exports: Mapping[str, Iterable[str]]) -> tuple[Callable, Callable]:
    """Make the names of ``exports`` attributes of ``package`` imported on first use.

    Args:
        package: the package's ``__name__`` (it must be in ``sys.modules``: call this from
            its ``__init__``).
        exports: {module: names}, each entry the ``from module import names`` the package
            would run; modules relative to ``package`` (``".mesh"``; ``"."``: submodules of
            the package itself) or absolute.

    Returns:
        The package's module ``__getattr__`` and ``__dir__`` (PEP 562): assign them to
        those names in the ``__init__``.

    Raises:
        ValueError: a name exported twice.
    """
    origins: dict[str, str] = {}
    for module_name, names in exports.items():
        absolute = importlib.util.resolve_name(module_name, package) if module_name.startswith(".") else module_name
        for name in names:
            if name in origins:
                raise ValueError(f"{package} exports {name!r} twice ({origins[name]}, {absolute})")
            origins[name] = absolute
    _ORIGINS[package] = origins
    module = sys.modules[package]
    module.__class__ = LazyPackage
    namespace = vars(module)

    def __getattr__(name: str):
        origin = origins.get(name)
        if origin is not None:
            value = _import_from(origin, name, package)
            namespace[name] = value  # imported once: an ordinary attribute from now on
            return value
        if not name.startswith("__") and importlib.util.find_spec(f"{package}.{name}") is not None:
            return importlib.import_module(f"{package}.{name}")  # a submodule, bound on the package
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__() -> list[str]:
        return sorted(set(namespace) | set(origins))

    return __getattr__, __dir__
