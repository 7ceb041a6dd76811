"""The shape of the code, checked on its syntax tree: options grouped into settings
objects (no public function with more than 12 parameters), no defaults read back from
signatures, no JAX internals, no module reaching into another's private names, and
implementation modules private behind their packages' exports (what the tests,
benchmarks, notebooks and documentation import is public)."""

import ast
import pathlib

ROOT = pathlib.Path(__file__).resolve().parents[1]
MAX_PARAMETERS = 12
SOURCES = ("jaxsync", "benchmarks")


def _modules(*folders):
    for folder in folders:
        yield from sorted((ROOT / folder).rglob("*.py"))


def _parameters(node, method: bool) -> list[str]:
    a = node.args
    names = [p.arg for p in a.posonlyargs + a.args + a.kwonlyargs]
    names += [p.arg for p in (a.vararg, a.kwarg) if p is not None]
    static = any(isinstance(d, ast.Name) and d.id == "staticmethod" for d in node.decorator_list)
    return names[1:] if method and not static and names else names


def _public_functions(tree):
    """(qualified name, parameter names) of every public function and every public method
    of a public class of a module."""
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and not node.name.startswith("_"):
            yield node.name, _parameters(node, method=False)
        elif isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
            for item in node.body:
                if isinstance(item, (ast.FunctionDef, ast.AsyncFunctionDef)) and (
                        not item.name.startswith("_") or item.name == "__init__"):
                    yield f"{node.name}.{item.name}", _parameters(item, method=True)


def _tree(path):
    return ast.parse(path.read_text(), filename=str(path))


def test_no_public_function_takes_more_than_12_parameters():
    too_many = [f"{path.relative_to(ROOT)}: {name} takes {len(params)}"
                for path in _modules(*SOURCES) for name, params in _public_functions(_tree(path))
                if len(params) > MAX_PARAMETERS]
    assert not too_many, "group options into settings objects: " + "; ".join(too_many)


def test_no_module_reads_defaults_from_a_signature():
    found = []
    for path in _modules(*SOURCES, "tests"):
        for node in ast.walk(_tree(path)):
            if (isinstance(node, ast.Attribute) and node.attr == "signature" and isinstance(node.value, ast.Name)
                    and node.value.id == "inspect") or (
                    isinstance(node, ast.ImportFrom) and node.module == "inspect"
                    and any(alias.name == "signature" for alias in node.names)):
                found.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not found, "read defaults from the settings dataclasses, not inspect.signature: " + ", ".join(found)


def test_no_jax_internals():
    found = [f"{path.relative_to(ROOT)}:{node.lineno}"
             for path in _modules(*SOURCES, "tests") for node in ast.walk(_tree(path))
             if isinstance(node, (ast.Import, ast.ImportFrom)) and any(
                 (name or "").startswith("jax._src") for name in
                 ([node.module] if isinstance(node, ast.ImportFrom) else [a.name for a in node.names]))]
    assert not found, "jax._src is JAX's private code (it changes without notice): " + ", ".join(found)


# mpi4py documents these as its handle utilities (mpi4py.MPI reference, "Utilities"); no
# public name gives the C size of a handle (int in MPICH, a pointer in Open MPI).
THIRD_PARTY_UTILITIES = {"MPI._sizeof"}


def test_no_private_name_is_imported_across_modules():
    """No ``from module import _name`` anywhere, and in the package and the benchmarks no
    ``module_or_object._name`` of something else (tests may look inside for white-box
    checks, through the objects they test)."""
    found = []
    for path in _modules(*SOURCES, "tests"):
        production = path.parts[len(ROOT.parts)] in SOURCES
        for node in ast.walk(_tree(path)):
            if isinstance(node, ast.ImportFrom):
                found += [f"{path.relative_to(ROOT)}:{node.lineno} {node.module}.{a.name}" for a in node.names
                          if a.name.startswith("_") and not a.name.startswith("__")]
            elif (production and isinstance(node, ast.Attribute) and node.attr.startswith("_")
                  and not node.attr.startswith("__") and isinstance(node.value, ast.Name)
                  and node.value.id not in ("self", "cls", "other", "os")
                  and f"{node.value.id}.{node.attr}" not in THIRD_PARTY_UTILITIES):
                found.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.value.id}.{node.attr}")
    assert not found, "make the name public (documented) or keep its use in its module: " + ", ".join(found)


def _private_module(name: str | None) -> bool:
    return any(part.startswith("_") and not part.startswith("__") for part in (name or "").split("."))


def _notebook_sources():
    import json

    for path in sorted((ROOT / "notebooks").glob("*.ipynb")):
        cells = json.loads(path.read_text())["cells"]
        code = "\n".join("".join(c["source"]) for c in cells if c["cell_type"] == "code")
        # IPython magics and shell lines are not Python
        code = "\n".join("" if line.lstrip().startswith(("%", "!")) else line for line in code.splitlines())
        yield path.relative_to(ROOT), ast.parse(code, filename=str(path))


def _docs_sources():
    """The ```python blocks of README.md and the documentation pages, as tests/test_docs.py
    runs them (file:line of each block)."""
    from test_docs import documents, python_blocks, relative

    for page in documents():
        for block in python_blocks(page.read_text(), relative(page)):
            yield block.label, ast.parse(block.source, filename=block.label)


def test_tests_benchmarks_notebooks_and_docs_import_only_public_modules():
    """Implementation modules (a ``_`` in the dotted path: ``jaxsync.mesh._read``) sit
    behind their package's re-exports, so that files can move without breaking a user's
    code: what the tests, benchmarks, notebooks and the documentation's code import is what
    a user may import."""
    trees = ([(path.relative_to(ROOT), _tree(path)) for path in _modules("tests", "benchmarks")]
             + list(_notebook_sources()) + list(_docs_sources()))
    found = []
    for where, tree in trees:
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.level == 0:
                names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            found += [f"{where}:{node.lineno} {n}" for n in names
                      if n and n.startswith("jaxsync") and _private_module(n)]
    assert not found, "import the public package that re-exports it: " + ", ".join(found)


# Packages whose implementation modules are private, behind the package's exports (its
# __init__: __all__, the lazy export map, the imports under TYPE_CHECKING); their
# subpackages are public packages that export their own names.
PRIVATE_IMPLEMENTATION = ("jaxsync/fem", "jaxsync/solve", "jaxsync/surrogate", "jaxsync/parallel")
# public modules there, and why
PUBLIC_MODULES = {
    "jaxsync/fem/mesh.py": "compatibility: the old import path of jaxsync.mesh",
    "jaxsync/fem/simvascular.py": "compatibility: the old import path of jaxsync.mesh.simvascular",
    "jaxsync/parallel/devices.py": "a namespace exported as a module (jaxsync.devices)",
    "jaxsync/parallel/multiprocess.py": "a namespace exported as a module (jaxsync.parallel.multiprocess)",
}


def test_implementation_modules_are_private():
    """Every module of jaxsync.fem, jaxsync.solve, jaxsync.surrogate and jaxsync.parallel
    (subpackages included) but the packages' ``__init__``/``__main__`` has a private name
    (``_stepper.py``): users import the packages, which export the names."""
    public = [name for path in _modules(*PRIVATE_IMPLEMENTATION)
              if path.name not in ("__init__.py", "__main__.py") and not path.name.startswith("_")
              and (name := path.relative_to(ROOT).as_posix()) not in PUBLIC_MODULES]
    assert not public, ("give these modules a private name (_module.py) and export their names from the package: "
                        + ", ".join(public))
    missing = [name for name in PUBLIC_MODULES if not (ROOT / name).exists()]
    assert not missing, "no longer there: " + ", ".join(missing)


MAX_MODULE_LINES = 600


def test_no_module_is_longer_than_600_lines():
    """A module holds one concept; one that grows past 600 lines holds several (split it)."""
    long = [f"{path.relative_to(ROOT)}: {n} lines" for path in _modules("jaxsync")
            if (n := len(path.read_text().splitlines())) > MAX_MODULE_LINES]
    assert not long, "split these modules by concept: " + ", ".join(long)
