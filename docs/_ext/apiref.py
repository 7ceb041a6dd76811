"""The API reference, generated from the package at build time.

``.. api-module:: jaxsync.fem`` documents one module of the reference: its docstring, a
summary table of every name in its ``__all__`` (first sentence of each docstring), then the
full entry of every name whose *canonical page* is this one. A name exported from several
modules of the reference (``jaxsync.simulate`` is ``jaxsync.solve.simulate``) is documented
once, on the first page of :data:`API_MODULES` that exports it, and linked from the others;
a module (``jaxsync.parallel.devices``) is documented on the page of the package that holds
it. So the reference follows ``__all__`` as it is: a name added to, or removed from, a
module's ``__all__`` appears or disappears without an edit here.

Cross-references in docstrings (``:func:`simulate```, ``:class:`~jaxsync.fem._stepper.SolverState```)
that Sphinx cannot find under the name written -- an implementation module's path, or a
re-exported name -- are resolved by identity: the object is imported and linked to the
place where it is documented (``missing-reference`` handler). Module references to
implementation modules (``:mod:`~jaxsync.fem.forces._total_lagrangian```) link to the nearest documented
package. What still does not resolve is left as plain code text, as Sphinx does by default.
"""

from __future__ import annotations

import ast
import importlib
import inspect
import re
import sys
import types

from docutils import nodes
from docutils.statemachine import StringList
from sphinx.util import logging
from sphinx.util.docutils import SphinxDirective
from sphinx.util.nodes import make_refnode

logger = logging.getLogger(__name__)

# Pages of the reference, in order: a name exported by several is documented on the first.
API_MODULES = (
    "jaxsync",
    "jaxsync.mesh",
    "jaxsync.fem",
    "jaxsync.parallel",
    "jaxsync.solve",
    "jaxsync.surrogate",
    "jaxsync.perf",
    "jaxsync.app.config",
    "jaxsync.metrics",
    "jaxsync.io",
    "jaxsync.options",
    "jaxsync.parallel.exchange",
    "jaxsync.solve.coupling",
    "jaxsync.solve.executors",
    "jaxsync.fem.materials",
    "jaxsync.fem.forces",
    "jaxsync.surrogate.models",
    "jaxsync.surrogate.training",
)


def public_names(module: types.ModuleType) -> list[str]:
    names = getattr(module, "__all__", None)
    if names is None:
        names = [n for n in vars(module) if not n.startswith("_")]
    return list(names)


def import_object(path: str):
    """The object named by a dotted path (module prefix imported, the rest by getattr), or None."""
    parts = path.split(".")
    for k in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:k]))
        except Exception:
            continue
        try:
            for attr in parts[k:]:
                obj = getattr(obj, attr)
        except AttributeError:
            return None
        return obj
    return None


def module_page(module_name: str) -> str | None:
    """The API module that documents the module ``module_name`` (the longest prefix)."""
    best = None
    for page in API_MODULES:
        if module_name == page or module_name.startswith(page + "."):
            if best is None or len(page) > len(best):
                best = page
    return best


def canonical_name(page: str, name: str, obj) -> str:
    """Where ``page.name`` is documented in full."""
    if isinstance(obj, types.ModuleType):
        home = module_page(obj.__name__)
        return obj.__name__ if home is not None else f"{page}.{name}"
    for candidate in API_MODULES:
        try:
            mod = importlib.import_module(candidate)
        except Exception:
            continue
        if name in public_names(mod) and getattr(mod, name, None) is obj:
            return f"{candidate}.{name}"
        # the same object under another name in an earlier module (rare): still the first
        for other in public_names(mod):
            if other != name and getattr(mod, other, None) is obj and not _is_plain_value(obj):
                return f"{candidate}.{other}"
    return f"{page}.{name}"


def _is_plain_value(obj) -> bool:
    return isinstance(obj, (int, float, str, bytes, bool, tuple, list, dict, frozenset, type(None)))


def first_sentence(obj, name: str = "") -> str:
    doc = inspect.getdoc(obj) if not _is_plain_value(obj) else None
    if not doc:
        doc = "\n".join(data_comment(name, obj)) if name else ""
    if not doc:
        return ""
    para = doc.strip().split("\n\n", 1)[0].replace("\n", " ")
    end = para.find(". ")
    text = para if end < 0 else para[: end + 1]
    return text


def directive_for(obj) -> str:
    if isinstance(obj, types.ModuleType):
        return "automodule"
    if inspect.isclass(obj):
        return "autoexception" if issubclass(obj, BaseException) else "autoclass"
    if inspect.isfunction(obj) or inspect.isbuiltin(obj) or inspect.ismethod(obj):
        return "autofunction"
    if callable(obj) and not _is_plain_value(obj):
        return "autofunction"
    return "autodata"


class ApiModule(SphinxDirective):
    """``.. api-module:: jaxsync.fem``: the reference page body of one module."""

    required_arguments = 1
    has_content = False

    def run(self):
        page = self.arguments[0]
        try:
            module = importlib.import_module(page)
        except Exception as exc:
            logger.warning(f"cannot import {page} to document it: {type(exc).__name__}: {exc}",
                           location=self.get_location())
            return []
        names = public_names(module)
        lines: list[str] = [f".. automodule:: {page}", "   :no-members:", ""]
        # summary table
        rows = []
        full = []
        for name in names:
            obj = getattr(module, name, None)
            if obj is None and name not in vars(module):
                logger.warning(f"{page}.__all__ names {name!r}, which the module does not define",
                               location=self.get_location())
                continue
            target = canonical_name(page, name, obj)
            kind = "mod" if isinstance(obj, types.ModuleType) else "obj"
            summary = escape_bars(first_sentence(obj, f"{page}.{name}"))
            if summary and rst_problems([summary]):
                summary = "``" + summary.replace("`", "") + "``"
            rows.append((f":py:{kind}:`{name} <{target}>`", summary))
            if isinstance(obj, types.ModuleType):
                if module_page(obj.__name__) == page:
                    full.append((name, obj, obj.__name__))
            elif target == f"{page}.{name}":
                full.append((name, obj, target))
        if rows:
            lines += [".. list-table::", "   :widths: 30 70", "   :class: api-summary", ""]
            for ref, summary in rows:
                lines += [f"   * - {ref}", f"     - {summary or ' '}"]
            lines.append("")
        # submodules last: an automodule changes the current module of what follows it
        full.sort(key=lambda entry: isinstance(entry[1], types.ModuleType))
        for name, obj, target in full:
            directive = directive_for(obj)
            if directive == "automodule":
                lines += [f".. rubric:: {target}", "", f".. automodule:: {target}", "   :members:", "",
                          f".. currentmodule:: {page}", ""]
            elif directive in ("autoclass", "autoexception"):
                lines += [f".. {directive}:: {target}", "   :members:", "   :show-inheritance:"]
                fields = getattr(obj, "_fields", None)          # a NamedTuple: its fields are its
                if isinstance(fields, tuple) and fields:        # docstring's Attributes, not members
                    lines.append("   :exclude-members: " + ", ".join(fields))
                lines.append("")
            elif directive == "autodata":
                value = "" if len(repr(obj)) <= 80 else "   :no-value:"
                lines += [f".. {directive}:: {target}"] + ([value] if value else []) + [""]
            else:
                lines += [f".. {directive}:: {target}", ""]
        container = nodes.container()
        self.state.nested_parse(StringList(lines, source=f"<api-module {page}>"), self.content_offset, container)
        return container.children


# -- docstrings as written: plain-text notation, data comments, a fallback ---------------

_LITERAL = re.compile(r"``.*?``|`[^`]*`")


def escape_bars(line: str) -> str:
    """``|x|`` in prose is an absolute value, not a substitution: escape the bars outside
    literals and roles; table rows and line blocks (a line starting with ``|``/``+``) stay."""
    stripped = line.lstrip()
    if "|" not in line or stripped.startswith(("|", "+")):
        return line
    out, pos = [], 0
    for m in _LITERAL.finditer(line):
        out.append(line[pos:m.start()].replace("\\|", "|").replace("|", "\\|"))
        out.append(m.group(0))
        pos = m.end()
    out.append(line[pos:].replace("\\|", "|").replace("|", "\\|"))
    return "".join(out)


_ORIGINAL: dict[str, list[str]] = {}


def before_napoleon(app, what, name, obj, options, lines):
    if what == "data":
        doc = inspect.getdoc(type(obj)) or ""
        if not lines or "\n".join(lines).strip() == doc.strip():
            lines[:] = data_comment(name, obj)
    lines[:] = [escape_bars(line) for line in lines]
    _ORIGINAL[name] = list(lines)


_ROLE = re.compile(r":[\w:.+-]+:`([^`]*)`")
_DEFAULT_ROLE = re.compile(r"(?<![`\\])`([^`]+)`(?![`_])")
_DIRECTIVE = re.compile(r"^(\s*)\.\. ([\w:.+-]+)::(.*)$")
_LITERAL_DIRECTIVES = ("math", "code-block", "code", "sourcecode", "highlight", "literalinclude",
                       "parsed-literal", "doctest", "testcode", "testoutput")


def _neutral(lines: list[str]) -> str:
    """The docstring with what only Sphinx knows made neutral: roles become literals, a
    directive's first line a paragraph (its options and content a block quote, or a literal
    block for math and code)."""
    out = []
    for line in lines:
        m = _DIRECTIVE.match(line)
        if m:
            indent, name = m.group(1), m.group(2).split(":")[-1]
            out += [indent + ("::" if name in _LITERAL_DIRECTIVES else "directive " + name), ""]
            continue
        # same lengths, so that the columns of a simple table stay where they are
        line = _ROLE.sub(lambda r: ("``" + r.group(1).replace("`", "") + "``").ljust(len(r.group(0))), line)
        out.append(_DEFAULT_ROLE.sub(lambda r: "*" + r.group(1).replace("*", "x").strip().ljust(
            len(r.group(1))) + "*", line))
    return "\n".join(out)


def rst_problems(lines: list[str]) -> list[str]:
    """Structural reST problems of a docstring, as plain docutils sees it once the roles and
    directives only Sphinx knows are made neutral (:func:`_neutral`); nothing is registered
    in Sphinx's environment."""
    from docutils.core import publish_doctree

    try:
        tree = publish_doctree(_neutral(lines), settings_overrides={
            "report_level": 5, "halt_level": 5, "warning_stream": False})
    except Exception:                 # a parse the check itself cannot do: not the docstring's fault
        return []
    return [m.astext() for m in tree.findall(nodes.system_message) if m["level"] >= 2]


def after_napoleon(app, what, name, obj, options, lines):
    problems = rst_problems(lines)
    if not problems:
        return
    if app.config.apiref_strict_docstrings:
        logger.warning(f"docstring of {name} is not valid reST: {problems[0].splitlines()[0]}",
                       type="apiref", subtype="docstring")
        return
    logger.info(f"[apiref] docstring of {name} shown as written (not valid reST: "
                f"{problems[0].splitlines()[0]})")
    original = _ORIGINAL.get(name, lines)
    lines[:] = ["::", ""] + ["    " + line.replace("\\|", "|") for line in original] + [""]


def data_comment(name: str, obj) -> list[str]:
    """The documentation of a module constant as its source gives it: a string after the
    assignment, else the comment lines above it and on its line."""
    short = name.rpartition(".")[2]
    for module in list(sys.modules.values()):
        modname = getattr(module, "__name__", "")
        if not modname.startswith("jaxsync") or getattr(module, short, None) is not obj:
            continue
        try:
            source = inspect.getsource(module)
        except (OSError, TypeError):
            continue
        found = _comment_in(source, short)
        if found is not None:
            return found
    return []


def _comment_in(source: str, short: str) -> list[str] | None:
    tree = ast.parse(source)
    lines = source.splitlines()
    body = tree.body
    for k, node in enumerate(body):
        targets = (node.targets if isinstance(node, ast.Assign)
                   else [node.target] if isinstance(node, ast.AnnAssign) else [])
        if not any(isinstance(t, ast.Name) and t.id == short for t in targets):
            continue
        nxt = body[k + 1] if k + 1 < len(body) else None
        if (isinstance(nxt, ast.Expr) and isinstance(nxt.value, ast.Constant)
                and isinstance(nxt.value.value, str)):
            return inspect.cleandoc(nxt.value.value).splitlines()
        comment = []
        i = node.lineno - 2
        while i >= 0 and lines[i].lstrip().startswith("#"):
            comment.insert(0, lines[i].lstrip()[1:].strip())
            i -= 1
        first = lines[node.lineno - 1]
        if "#" in first and not comment:
            comment = [first.split("#", 1)[1].strip()]
        return [escape_bars(c) for c in comment]
    return None


# -- resolving references by identity ---------------------------------------------------

def _documented(env) -> dict:
    return env.get_domain("py").objects


def _identity_map(env) -> dict[int, str]:
    cache = getattr(env, "_apiref_identity", None)
    objects = _documented(env)
    if cache is not None and cache[0] == len(objects):
        return cache[1]
    ids: dict[int, str] = {}
    for name, entry in objects.items():
        if entry.objtype not in ("class", "exception", "function", "module", "data"):
            continue
        obj = import_object(name)
        if obj is None or _is_plain_value(obj):
            continue
        ids.setdefault(id(obj), name)
    env._apiref_identity = (len(objects), ids)
    return ids


def resolve_missing(app, env, node, contnode):
    if node.get("refdomain") != "py":
        return None
    target = node.get("reftarget", "")
    if not target:
        return None
    objects = _documented(env)
    modname = node.get("py:module") or ""
    clsname = node.get("py:class") or ""
    bare = target.lstrip(".")
    candidates = [bare]
    if modname:
        candidates.append(f"{modname}.{bare}")
        if clsname:
            candidates.append(f"{modname}.{clsname}.{bare}")
        # a relative module path (:mod:`.model` inside jaxsync.surrogate)
        parent = modname
        while parent:
            candidates.append(f"{parent}.{bare}")
            parent = parent.rpartition(".")[0]
    ids = _identity_map(env)
    for cand in candidates:
        parts = cand.split(".")
        # the longest prefix that is a documented object, by identity; then the rest by name
        for k in range(len(parts), 0, -1):
            obj = import_object(".".join(parts[:k]))
            if obj is None or _is_plain_value(obj):
                continue
            home = ids.get(id(obj))
            if home is None and isinstance(obj, types.ModuleType):
                page = module_page(obj.__name__)
                home = page if page in objects else None
                if home is not None and k < len(parts):
                    home = None          # a name inside an undocumented module: not by module alone
            if home is None:
                continue
            full = ".".join([home] + parts[k:])
            if full in objects:
                entry = objects[full]
                return make_refnode(app.builder, node["refdoc"], entry.docname, entry.node_id, contnode, full)
            break
    # last resort: the one documented object whose name ends with the target
    if "." not in bare or bare.count(".") == 1 and bare[0].isupper():
        matches = [name for name in objects if name.endswith("." + bare)]
        if len(matches) == 1:
            entry = objects[matches[0]]
            return make_refnode(app.builder, node["refdoc"], entry.docname, entry.node_id, contnode, matches[0])
    return None


def drop_object_base(app, name, obj, options, bases):
    """``Bases: object`` says nothing."""
    if list(bases) == [object]:
        bases.clear()


def setup(app):
    app.add_config_value("apiref_strict_docstrings", False, "env")
    app.add_directive("api-module", ApiModule)
    app.connect("autodoc-process-docstring", before_napoleon, priority=100)
    app.connect("autodoc-process-docstring", after_napoleon, priority=900)
    app.connect("missing-reference", resolve_missing)
    app.connect("autodoc-process-bases", drop_object_base)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
