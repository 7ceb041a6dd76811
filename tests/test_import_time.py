"""Start-up: ``import jaxsync`` and the command line's parser import no numerical library,
and a command imports only what it uses (:mod:`jaxsync.lazy`, :mod:`jaxsync.cli`).

What is imported is checked in fresh interpreters; how long it takes is measured by
``benchmarks/bench_startup.py``, never asserted here. Laziness cannot hide a broken name:
every name of every lazily exported ``__all__`` is resolved, and the imports that type
checkers see (``if TYPE_CHECKING:``) are the ones made at run time.
"""

from __future__ import annotations

import argparse
import ast
import importlib
import json
import os
import pathlib
import subprocess
import sys
import types

import pytest

from jaxsync.lazy import lazy_exports

ROOT = pathlib.Path(__file__).resolve().parents[1]

# imported by none of: import jaxsync, building the parser, --help, --version
NUMERICAL = ("jax", "jaxlib", "numpy", "scipy", "skfem", "meshio", "h5py", "optax", "matplotlib", "gmsh",
             "pymetis", "tqdm", "mpi4py")
LAZY_PACKAGES = ("jaxsync", "jaxsync.fem", "jaxsync.fem.materials", "jaxsync.fem.forces", "jaxsync.cases",
                 "jaxsync.cli", "jaxsync.solve", "jaxsync.solve.coupling", "jaxsync.solve.executors",
                 "jaxsync.surrogate", "jaxsync.surrogate.models", "jaxsync.surrogate.training", "jaxsync.parallel",
                 "jaxsync.parallel.exchange", "jaxsync.perf", "jaxsync.io")


def imported_after(code: str, *args: str, cwd=None) -> set[str]:
    """The top-level names of the modules in ``sys.modules`` after ``code`` ran in a fresh
    interpreter (a ``SystemExit`` of the code, as from ``--help``, ends it normally)."""
    script = ("import json, sys\ntry:\n" + "".join(f"    {line}\n" for line in code.splitlines())
              + "except SystemExit:\n    pass\n"
              + "sys.stderr.write('\\nMODULES ' + json.dumps(sorted({m.split('.')[0] for m in sys.modules})))\n")
    done = subprocess.run([sys.executable, "-c", script, *args], capture_output=True, text=True, timeout=300,
                          cwd=cwd)
    assert "MODULES " in done.stderr, done.stderr
    return set(json.loads(done.stderr.rsplit("MODULES ", 1)[1]))


def test_import_jaxsync_imports_no_numerical_library():
    loaded = imported_after("import jaxsync\nassert jaxsync.__version__")
    assert not loaded & set(NUMERICAL), sorted(loaded & set(NUMERICAL))


def test_importing_the_packages_imports_no_numerical_library():
    loaded = imported_after("\n".join(f"import {name}" for name in LAZY_PACKAGES + (
        "jaxsync.app", "jaxsync.cli", "jaxsync.cli", "jaxsync.errors", "jaxsync.options")))
    assert not loaded & set(NUMERICAL), sorted(loaded & set(NUMERICAL))


@pytest.mark.parametrize("argv", [["--help"], ["--version"], ["simulate", "--help"], ["simulate", "--dt"],
                                  ["predict", "--help"], ["report", "--help"], ["finetune", "--help"],
                                  ["simulate", "--no-such-option"], []])
def test_the_parser_answers_without_jax(argv):
    """--help, --version, a subcommand's help and an argument error: the parser alone,
    as the console script runs it (``main`` with these arguments)."""
    loaded = imported_after("from jaxsync.cli import main\nmain(sys.argv[1:])", *argv)
    assert not loaded & set(NUMERICAL), sorted(loaded & set(NUMERICAL))


def test_building_and_using_the_parser_imports_no_numerical_library():
    code = """from jaxsync.cli import build_parser, parts_of
parser = build_parser()
for argv in (["simulate", "--parts", "2", "--steps", "5"], ["report", "a.h5", "b.h5"]):
    assert parts_of(parser.parse_args(argv)) in (0, 2)"""
    loaded = imported_after(code)
    assert not loaded & set(NUMERICAL), sorted(loaded & set(NUMERICAL))


def written_imports(*paths: str) -> set[str]:
    """The jaxsync modules named by the import statements of the files (module level and
    inside functions), relative ones resolved; ``from package import name`` counts the
    submodule ``package.name`` where there is one."""
    found = set()
    for path in paths:
        module = ".".join(pathlib.Path(path).with_suffix("").parts)
        package = module.rpartition(".")[0]
        for node in ast.walk(ast.parse((ROOT / path).read_text())):
            if isinstance(node, ast.Import):
                found |= {a.name for a in node.names if a.name.startswith("jaxsync")}
            elif isinstance(node, ast.ImportFrom):
                base = importlib.util.resolve_name("." * node.level + (node.module or ""), package) \
                    if node.level else node.module
                if not base.startswith("jaxsync"):
                    continue
                found.add(base)
                found |= {f"{base}.{a.name}" for a in node.names
                          if importlib.util.find_spec(base) is not None
                          and (ROOT / base.replace(".", "/") / f"{a.name}.py").exists()}
    return found


def test_report_imports_neither_optax_nor_gmsh():
    """Every module that ``jaxsync report`` and the report's writer (plots, figures) name,
    imported together; and the command itself, up to its first input."""
    modules = written_imports("jaxsync/cli/report.py", "jaxsync/app/plots.py", "jaxsync/app/figures.py")
    assert "jaxsync.solve.coupling._syncavoid" in modules and "jaxsync.io.trajectory" in modules
    loaded = imported_after("\n".join(f"import {m}" for m in sorted(modules)))
    assert not loaded & {"optax", "gmsh"}, sorted(loaded & {"optax", "gmsh"})


def test_report_command_imports_neither_optax_nor_gmsh(tmp_path):
    (tmp_path / "README").write_text("not empty\n")  # the folder of a failed run is cleaned up to here
    loaded = imported_after("from jaxsync.cli import main\nassert main(sys.argv[1:]) == 2",
                            "report", "missing.h5", "missing.h5", "-o", "report", cwd=tmp_path)
    assert "jax" in loaded and not loaded & {"optax", "gmsh"}, sorted(loaded & {"optax", "gmsh"})


def test_simulate_imports_neither_matplotlib_nor_optax():
    """Every module ``jaxsync simulate`` and the problem files' reader name."""
    modules = written_imports("jaxsync/cli/simulate.py", "jaxsync/app/config.py")
    assert "jaxsync.solve._solver" in modules
    loaded = imported_after("\n".join(f"import {m}" for m in sorted(modules)))
    assert not loaded & {"matplotlib", "optax"}, sorted(loaded & {"matplotlib", "optax"})


@pytest.mark.parametrize("package", LAZY_PACKAGES)
def test_every_exported_name_resolves(package):
    """Laziness hides no broken name: each name of ``__all__`` is a lazy export and
    resolves to the object of its module; ``dir()`` shows them all."""
    module = importlib.import_module(package)
    exports = lazy_exports(package)
    assert sorted(exports) == sorted(module.__all__)
    assert len(set(module.__all__)) == len(module.__all__)
    assert set(module.__all__) <= set(dir(module))
    for name in module.__all__:
        value = getattr(module, name)
        origin = importlib.import_module(exports[name])
        expected = getattr(origin, name) if origin is not module else importlib.import_module(f"{package}.{name}")
        assert value is expected, name
    namespace: dict = {}
    exec(f"from {package} import *", namespace)
    assert set(module.__all__) <= set(namespace)


@pytest.mark.parametrize("package", LAZY_PACKAGES)
def test_type_checking_imports_are_the_lazy_exports(package):
    """The imports under ``if TYPE_CHECKING:`` (what type checkers, IDEs and linters see)
    name each export with the module it is imported from at run time."""
    tree = ast.parse((ROOT / package.replace(".", "/") / "__init__.py").read_text())
    blocks = [node for node in tree.body if isinstance(node, ast.If) and isinstance(node.test, ast.Name)
              and node.test.id == "TYPE_CHECKING"]
    assert len(blocks) == 1
    seen = {}
    for node in blocks[0].body:
        assert isinstance(node, ast.ImportFrom)
        base = importlib.util.resolve_name("." * node.level + (node.module or ""), package) \
            if node.level else node.module
        for alias in node.names:
            assert alias.asname is None
            seen[alias.name] = base
    assert seen == lazy_exports(package)


def test_an_export_named_like_its_module_stays_the_export():
    """``jaxsync.cli.main`` is the function however its module was imported first (as with
    ``from .main import main``)."""
    code = """import jaxsync.cli.main
import types
from jaxsync.cli import main
import jaxsync
for f in (main, jaxsync.cli.main):
    assert callable(f) and not isinstance(f, types.ModuleType), f
assert jaxsync.cli.main is sys.modules["jaxsync.cli.main"].main
print("ok")"""
    done = subprocess.run([sys.executable, "-c", "import sys\n" + code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr


def test_submodules_are_attributes_and_unknown_names_are_not():
    import jaxsync

    assert jaxsync.io.trajectory.Trajectory is jaxsync.Trajectory
    assert isinstance(jaxsync.parallel.devices, types.ModuleType) and jaxsync.devices is jaxsync.parallel.devices
    assert isinstance(jaxsync.parallel.multiprocess, types.ModuleType)
    with pytest.raises(AttributeError, match="has no attribute 'no_such_name'"):
        jaxsync.no_such_name
    with pytest.raises(ImportError):
        from jaxsync import no_such_name  # noqa: F401


def test_notebook_use_works_and_float32_is_refused():
    """``import jaxsync; jaxsync.cantilever()`` in a fresh interpreter, and the solver still
    refuses to run in JAX's float32 mode (importing jaxsync changes no configuration)."""
    code = """import jaxsync
problem = jaxsync.cantilever()
try:
    jaxsync.simulate(problem, 2)
except jaxsync.PrecisionError as exc:
    print("refused:", "jax_enable_x64" in str(exc))
import jax
print("x64:", jax.config.jax_enable_x64)"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                          env={k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"})
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["refused:", "True", "x64:", "False"]


class _Recorder:
    """argparse's subparsers, recording the keywords of the one ``add_parser`` call."""

    def add_parser(self, name, **settings):
        self.name, self.settings = name, settings
        return argparse.ArgumentParser(prog=f"jaxsync {name}")


def _made_eagerly(name: str) -> argparse.ArgumentParser:
    from jaxsync.cli import demo
    from jaxsync.cli.train import add_train_parser

    parser = argparse.ArgumentParser(prog="jaxsync")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    {"demo": demo.add_parser, "train": add_train_parser}[name](subparsers)
    return subparsers.choices[name]


@pytest.mark.parametrize("name", ["demo", "train"])
def test_a_deferred_subcommand_is_the_one_its_module_makes(name):
    """``demo`` and ``train`` get their options on first use: the help line of
    ``jaxsync --help`` is the one their module gives, and their parser, once used, is the
    parser their module makes (same help, same defaults)."""
    from jaxsync.cli import DEFERRED_HELP, build_parser, demo
    from jaxsync.cli.train import add_train_parser

    recorder = _Recorder()
    {"demo": demo.add_parser, "train": add_train_parser}[name](recorder)
    assert recorder.name == name and recorder.settings["help"] == DEFERRED_HELP[name]
    main = build_parser()
    assert DEFERRED_HELP[name] in " ".join(main.format_help().split())
    deferred = next(a for a in main._actions if isinstance(a, argparse._SubParsersAction)).choices[name]
    eager = _made_eagerly(name)
    assert deferred.format_help() == eager.format_help()
    assert [a.option_strings for a in deferred._actions] == [a.option_strings for a in eager._actions]
    args = ["a.h5"] if name == "train" else []
    assert vars(main.parse_args([name, *args])) == {"command": name, **vars(eager.parse_args(args))}
