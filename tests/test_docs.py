"""Every ```python block of README.md and of the documentation pages (docs/**/*.md) runs as
written.

Each file's blocks are executed in order, in fresh interpreters started in a temporary
working directory (the files a snippet writes land there), with the environment a user
has: one CPU device (the test session's emulated second device is not passed on), float64
only where the snippet asks for it.

Grouping, per file: a block that uses names it does not define itself (``problem`` from
the first block, say) continues the interpreter of the block before it; a block that
defines everything it uses starts a new interpreter. So a group is a run of blocks that
depend on each other, one test each, and a failure points at the file and line
(tracebacks show the page's own line numbers).

Markers, a comment on the first line of a block (``# README-test:`` is the older spelling
and still accepted):

- ``# docs-test: skip (reason)``: not run, nor are the later blocks of its group.
  Only for what cannot run in one plain process (``mpiexec``).
- ``# docs-test: slow (reason)``: the block and the rest of its group run only with
  ``python -m pytest -m slow``; the blocks before it still run by default.

The default run must stay fast: a page's unmarked blocks take seconds (small cases,
``progress=False``); anything long is marked slow.
"""

from __future__ import annotations

import ast
import builtins
import json
import os
import re
import socket
import subprocess
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
TIMEOUT_S = 900          # per group of blocks (a hang guard): a slow group trains with the library's
                         # defaults, two candidates per part (5-10 minutes on 2 busy cores)
MARKER = re.compile(r"^\s*#\s*(?:docs|README)-test:\s*(?P<kind>\w+)\s*(?P<reason>.*)$")
KINDS = ("skip", "slow")
FENCE_OPEN = re.compile(r"^(?P<indent>\s*)(?P<fence>`{3,}|~{3,})\s*(?:python|\{code-block\}\s+python)\s*$")


def documents() -> list[Path]:
    """README.md and every Markdown page of the documentation, in a stable order."""
    pages = sorted(p for p in DOCS.rglob("*.md") if "_build" not in p.parts) if DOCS.is_dir() else []
    return ([README] if README.exists() else []) + pages


def relative(path: Path) -> str:
    try:
        return path.resolve().relative_to(ROOT).as_posix()
    except ValueError:
        return path.name


@dataclass(frozen=True)
class Block:
    line: int            # line of the block's first code line in its file (1-based)
    source: str
    marker: str | None   # "skip", "slow" or None
    reason: str
    file: str = "README.md"

    @property
    def label(self) -> str:
        return f"{self.file}:{self.line}"


def python_blocks(text: str, file: str = "README.md") -> list[Block]:
    """The ```python fenced blocks of ``text``, with their first line numbers and markers."""
    blocks, lines, i = [], text.splitlines(), 0
    while i < len(lines):
        m = FENCE_OPEN.match(lines[i])
        if m:
            fence = m.group("fence")
            close = re.compile(rf"^\s*{re.escape(fence[0])}{{{len(fence)},}}\s*$")
            start, i = i + 1, i + 1
            while i < len(lines) and not close.match(lines[i]):
                i += 1
            body_lines = lines[start:i]
            # MyST directive options (":caption: ...") at the top of a {code-block}
            while body_lines and re.match(r"^\s*:\w[\w-]*:", body_lines[0]) and "{code-block}" in lines[start - 1]:
                body_lines, start = body_lines[1:], start + 1
            body = textwrap.dedent("\n".join(body_lines)) + "\n"
            first = next((ln for ln in body.splitlines() if ln.strip()), "")
            mk = MARKER.match(first)
            blocks.append(Block(line=start + 1, source=body,
                                marker=mk.group("kind") if mk else None,
                                reason=mk.group("reason").strip() if mk else "", file=file))
        i += 1
    return blocks


def free_names(source: str) -> set[str]:
    """Names a block reads without binding them anywhere in it (nor being builtins)."""
    tree = ast.parse(source)
    loaded, bound = set(), set(dir(builtins))
    for node in ast.walk(tree):
        if isinstance(node, ast.Name):
            (loaded if isinstance(node.ctx, ast.Load) else bound).add(node.id)
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            bound.update((a.asname or a.name).split(".")[0] for a in node.names)
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            bound.add(node.name)
        elif isinstance(node, ast.arg):
            bound.add(node.arg)
        elif isinstance(node, ast.ExceptHandler) and node.name:
            bound.add(node.name)
    return loaded - bound


def groups(blocks: list[Block]) -> list[list[Block]]:
    """Runs of blocks that share one interpreter (see the module docstring)."""
    out: list[list[Block]] = []
    for block in blocks:
        if out and free_names(block.source):
            out[-1].append(block)
        else:
            out.append([block])
    return out


def cases(text: str | None = None, file: str = "README.md"):
    """pytest params, one per test: each group up to its first skip marker; a slow
    marker splits the group into a default part (the blocks before it) and a slow whole.
    Without ``text``: the cases of README.md and of every documentation page."""
    if text is None:
        params = []
        for path in documents():
            params += cases(path.read_text(encoding="utf-8"), relative(path))
        return params
    params = []
    for group in groups(python_blocks(text, file)):
        for k, block in enumerate(group):
            if block.marker == "skip":
                group = group[:k]
                break
        if not group:
            continue
        slow_at = next((k for k, b in enumerate(group) if b.marker == "slow"), None)
        name = f"{group[0].label}-{group[-1].line}"
        if slow_at is None:
            params.append(pytest.param(group, id=name))
        else:
            if slow_at > 0:
                params.append(pytest.param(group[:slow_at], id=f"{group[0].label}-{group[slow_at - 1].line}"))
            params.append(pytest.param(group, id=f"{name}-slow", marks=pytest.mark.slow))
    return params


RUNNER = r"""
import json, sys, time
path, label, blocks = sys.argv[1], sys.argv[2], json.load(open(sys.argv[3]))
namespace = {"__name__": "__main__"}
for line, source in blocks:
    print(f"[docs-test] running the block at {label}:{line}", file=sys.stderr, flush=True)
    start = time.perf_counter()
    # pad with blank lines so that tracebacks show the page's own line numbers
    exec(compile("\n" * (line - 1) + source, path, "exec"), namespace)
    print(f"[docs-test] {label}:{line} took {time.perf_counter() - start:.1f} s",
          file=sys.stderr, flush=True)
"""


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def user_environment() -> dict[str, str]:
    """This process's environment without the test session's emulated devices."""
    env = dict(os.environ)
    flags = re.sub(r"--xla_force_host_platform_device_count=\d+", "", env.get("XLA_FLAGS", "")).strip()
    if flags:
        env["XLA_FLAGS"] = flags
    else:
        env.pop("XLA_FLAGS", None)
    env.setdefault("JAX_PLATFORMS", "cpu")
    env["PYTHONUNBUFFERED"] = "1"
    env["MPLBACKEND"] = "Agg"
    # A snippet that calls jaxsync.parallel.multiprocess.initialize() runs as a single rank; give
    # its jax.distributed coordinator a free port rather than the fixed one derived from
    # the host name, which a concurrent run on this machine may hold.
    env["JAX_COORDINATOR_ADDRESS"] = f"127.0.0.1:{free_port()}"
    # a project checkout not installed into the interpreter still imports jaxsync
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    return env


def check_markers(blocks: list[Block]) -> None:
    for block in blocks:
        ast.parse(block.source, filename=block.label)  # a syntax error names the block
        for k, line in enumerate(block.source.splitlines()):
            m = MARKER.match(line)
            if m:
                assert k == 0 or not any(s.strip() for s in block.source.splitlines()[:k]), \
                    f"{block.label}: a docs-test marker must be the block's first line"
                assert m.group("kind") in KINDS, f"{block.label}: unknown marker {m.group('kind')!r}"
                assert re.fullmatch(r"\(.+\)", m.group("reason")), \
                    f"{block.label}: say why in parentheses: # docs-test: {m.group('kind')} (why)"


def test_readme_has_python_blocks_and_valid_markers():
    blocks = python_blocks(README.read_text(encoding="utf-8"))
    assert blocks, "README.md has no ```python blocks"
    check_markers(blocks)
    # the first block stands alone: every group starts with a block that defines its names
    assert not free_names(blocks[0].source), f"first block uses undefined {free_names(blocks[0].source)}"


@pytest.mark.parametrize("path", [p for p in documents() if p != README], ids=relative)
def test_docs_page_blocks_are_valid(path):
    blocks = python_blocks(path.read_text(encoding="utf-8"), relative(path))
    check_markers(blocks)
    if blocks:
        assert not free_names(blocks[0].source), \
            f"{blocks[0].label}: the page's first block uses undefined {free_names(blocks[0].source)}"


def test_grouping_follows_dependencies():
    source = ("```python\nimport math\nx = math.pi\n```\n\ntext\n\n"
              "```python\nprint(x)\n```\n\n```python\n# README-test: skip (needs mpiexec)\nimport os\n```\n")
    blocks = python_blocks(source)
    assert [b.line for b in blocks] == [2, 9, 13]
    assert [b.marker for b in blocks] == [None, None, "skip"]
    assert free_names(blocks[1].source) == {"x"}
    assert [[b.line for b in g] for g in groups(blocks)] == [[2, 9], [13]]
    assert free_names("def f(a):\n    return a + b\n") == {"b"}
    assert [[b.line for b in c.values[0]] for c in cases(source)] == [[2, 9]]
    assert free_names("import numpy as np\n[i for i in range(3)]\nprint(np)\n") == set()


def test_slow_and_skip_markers_split_groups():
    fence = "```python\n{}\n```\n"
    source = "".join(fence.format(body) for body in (
        "x = 1", "y = x", "# docs-test: slow (trains for minutes)\nz = y", "print(z)",
        "import os", "# README-test: skip (needs mpiexec)\nw = os.sep", "print(w)"))
    found = [([b.line for b in c.values[0]], [m.name for m in c.marks]) for c in cases(source)]
    assert found == [([2, 5], []), ([2, 5, 8, 12], ["slow"]), ([15], [])]


def test_cases_are_per_file_and_myst_code_blocks_count():
    page = "# A page\n\n````{code-block} python\n:caption: a caption\nimport os\n````\n\n```bash\nls\n```\n"
    blocks = python_blocks(page, "docs/page.md")
    assert [(b.label, b.source) for b in blocks] == [("docs/page.md:5", "import os\n")]
    assert [c.id for c in cases(page, "docs/page.md")] == ["docs/page.md:5-5"]
    ids = [c.id for c in cases()]
    assert len(ids) == len(set(ids)), "two tests with the same id"
    assert any(i.startswith("README.md:") for i in ids)


@pytest.mark.parametrize("group", cases())
def test_docs_blocks_run(group, tmp_path):
    path = ROOT / group[0].file
    spec = tmp_path / "blocks.json"
    spec.write_text(json.dumps([[b.line, b.source] for b in group]))
    workdir = tmp_path / "work"
    workdir.mkdir()
    script = tmp_path / "runner.py"
    script.write_text(RUNNER)
    where = f"{group[0].file} blocks at lines {[b.line for b in group]}"
    try:
        proc = subprocess.run([sys.executable, str(script), str(path), group[0].file, str(spec)],
                              cwd=workdir, env=user_environment(), capture_output=True,
                              text=True, timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired as exc:
        said = (exc.stderr or b"")
        said = said.decode(errors="replace") if isinstance(said, bytes) else said
        pytest.fail(f"{where} ran longer than {TIMEOUT_S} s; shorten them or mark the long one "
                    f"'# docs-test: slow (why)'\n{said[-4000:]}")
    if proc.returncode != 0:
        pytest.fail(f"{where} failed (exit status {proc.returncode}):\n{proc.stderr[-6000:]}\n"
                    f"--- stdout ---\n{proc.stdout[-2000:]}", pytrace=False)
    # per-block timings, shown with pytest -rA
    print("\n".join(ln for ln in proc.stderr.splitlines() if ln.startswith("[docs-test]")))
