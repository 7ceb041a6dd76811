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

Printed output, checked like a doctest: what a block prints (its stdout, block by block;
stderr, warnings and progress bars are not compared) must be shown on the page in an
``output`` fence that follows the block, with nothing but blank lines between them::

    ```python
    print(f"stretch {l:.6f}")
    ```

    ```output
    stretch 0.964379
    ```

A block that prints and shows no output fails, and so does one whose output fence
disagrees with what it prints; the message shows both. The comparison:

- Text must match; whitespace is not compared (tables may realign), nor are leading and
  trailing blank lines.
- Numbers (integers, decimals, exponents: a run of digits not glued to a name, so
  ``x0``, ``P2`` and ``float32`` are text) are compared as numbers: the page's p and the
  run's r agree when |r - p| <= atol + rtol |p| + u, u one unit in the last decimal place
  that both show (the rounding of a printed number: ``0.964379`` against ``0.964380``;
  ``0.0`` against ``0.05`` gets u = 0.01 and disagrees). An integer, without a decimal
  point or exponent, gives u = 0: a count must be exact. Defaults: rtol = 1e-6, atol = 0;
  a fence sets its own, ```` ```output rtol=1e-3 ```` or ```` ```output atol=1e-12 ````
  (for round-off, shown as it came out on one machine: over ``2.0e-14``, any value below
  1e-12 agrees).
- ``...`` on the page matches any text, numbers and line breaks included (doctest's
  ELLIPSIS): write it for what depends on the machine -- timings, device names -- so that
  those are not compared.
- ```` ```output numbers=ignore ```` compares the text only: for output made of timings
  or of trained networks' results, whose numbers change from machine to machine (the
  page then shows one run's numbers as an example).

Comments in a block do not claim values it prints; its output fence shows them.
"""

from __future__ import annotations

import ast
import builtins
import json
import os
import re
import subprocess
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

import pytest

from subprocess_env import free_port, without_emulated_devices

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
TIMEOUT_S = 900          # per group of blocks (a hang guard): a slow group trains with the library's
                         # defaults, two candidates per part (5-10 minutes on 2 busy cores)
MARKER = re.compile(r"^\s*#\s*(?:docs|README)-test:\s*(?P<kind>\w+)\s*(?P<reason>.*)$")
KINDS = ("skip", "slow")
FENCE_OPEN = re.compile(r"^(?P<indent>\s*)(?P<fence>`{3,}|~{3,})\s*(?:python|\{code-block\}\s+python)\s*$")
OUTPUT_OPEN = re.compile(r"^(?P<indent>\s*)(?P<fence>`{3,}|~{3,})\s*output(?:\s+(?P<options>\S.*?))?\s*$")
DEFAULT_RTOL = 1e-6      # relative tolerance of printed numbers, unless an output fence says rtol=...
OUTPUT_OPTIONS = {"rtol": DEFAULT_RTOL, "atol": 0.0, "numbers": "compare"}    # an output fence's, and defaults


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
    output: str | None = None   # the output the page shows for the block (its output fence), if any
    output_line: int = 0        # first line of that output in the file (1-based)
    output_options: str = ""    # what follows "output" on the fence line ("rtol=1e-3 atol=1e-12")

    @property
    def label(self) -> str:
        return f"{self.file}:{self.line}"

    @property
    def options(self) -> dict:
        return output_options(self.output_options)


def closing_fence(fence: str) -> re.Pattern:
    return re.compile(rf"^\s*{re.escape(fence[0])}{{{len(fence)},}}\s*$")


def fence_body(lines: list[str], i: int, fence: str) -> tuple[list[str], int]:
    """The lines of the fenced block opened at line index ``i`` and the index of its closing line."""
    close, start = closing_fence(fence), i + 1
    i = start
    while i < len(lines) and not close.match(lines[i]):
        i += 1
    return lines[start:i], i


def output_options(options: str) -> dict:
    """The options of an output fence (``rtol=1e-3 atol=1e-12``, ``numbers=ignore``), with
    their defaults; ValueError if malformed."""
    found = dict(OUTPUT_OPTIONS)
    for item in options.split():
        key, eq, value = item.partition("=")
        if not eq or key not in OUTPUT_OPTIONS:
            raise ValueError(f"unknown output option {item!r} (known: rtol=X, atol=X, numbers=ignore)")
        if key == "numbers":
            if value != "ignore":
                raise ValueError(f"numbers={value!r}: the option is numbers=ignore")
            found[key] = value
            continue
        try:
            found[key] = float(value)
        except ValueError:
            found[key] = float("nan")
        if not found[key] >= 0:
            raise ValueError(f"{key} must be a number >= 0, not {value!r}")
    return found


def attached_output(lines: list[str], i: int) -> tuple[str | None, int, str]:
    """The output fence that follows a block closed at line index ``i`` (only blank lines
    between): its text, first line (1-based) and options; (None, 0, "") if there is none."""
    j = i + 1
    while j < len(lines) and not lines[j].strip():
        j += 1
    m = OUTPUT_OPEN.match(lines[j]) if j < len(lines) else None
    if not m:
        return None, 0, ""
    body, _ = fence_body(lines, j, m.group("fence"))
    return textwrap.dedent("\n".join(body)) + "\n", j + 2, m.group("options") or ""


def python_blocks(text: str, file: str = "README.md") -> list[Block]:
    """The ```python fenced blocks of ``text``, with their first line numbers, markers and
    the output the page shows for them."""
    blocks, lines, i = [], text.splitlines(), 0
    while i < len(lines):
        m = FENCE_OPEN.match(lines[i])
        if m:
            start = i + 1
            body_lines, i = fence_body(lines, i, m.group("fence"))
            # MyST directive options (":caption: ...") at the top of a {code-block}
            while body_lines and re.match(r"^\s*:\w[\w-]*:", body_lines[0]) and "{code-block}" in lines[start - 1]:
                body_lines, start = body_lines[1:], start + 1
            body = textwrap.dedent("\n".join(body_lines)) + "\n"
            first = next((ln for ln in body.splitlines() if ln.strip()), "")
            mk = MARKER.match(first)
            output, output_line, options = attached_output(lines, i)
            blocks.append(Block(line=start + 1, source=body,
                                marker=mk.group("kind") if mk else None,
                                reason=mk.group("reason").strip() if mk else "", file=file,
                                output=output, output_line=output_line, output_options=options))
        i += 1
    return blocks


def output_fence_problems(text: str, file: str = "README.md") -> list[str]:
    """Output fences that follow no python block, or whose options are malformed."""
    attached = {b.output_line - 1 for b in python_blocks(text, file) if b.output is not None}
    problems = []
    for k, line in enumerate(text.splitlines()):
        m = OUTPUT_OPEN.match(line)
        if not m:
            continue
        if k + 1 not in attached:
            problems.append(f"{file}:{k + 1}: an output fence must follow a ```python block "
                            f"(only blank lines between them)")
        try:
            output_options(m.group("options") or "")
        except ValueError as exc:
            problems.append(f"{file}:{k + 1}: {exc}")
    return problems


# -- comparing what a block prints with what its page shows ---------------------------------

NUMBER = r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?"
OUTPUT_TOKEN = re.compile(rf"(?P<ellipsis>\.\.\.)|(?<![\w.])(?P<number>{NUMBER})|(?P<space>\s+)|(?P<text>.)", re.S)


def last_digit_unit(number: str) -> float:
    """One unit in the last decimal a printed number shows (0 for an integer: no rounding)."""
    mantissa, _, exponent = number.lower().partition("e")
    if "." not in mantissa and not exponent:
        return 0.0
    return 10.0 ** (int(exponent or 0) - len(mantissa.partition(".")[2]))


def numbers_agree(page: str, run: str, rtol: float = DEFAULT_RTOL, atol: float = 0.0) -> bool:
    """Whether the run's printed number agrees with the page's (see the module docstring)."""
    p, r = float(page), float(run)
    allowed = atol + rtol * abs(p) + min(last_digit_unit(page), last_digit_unit(run))
    return abs(r - p) <= allowed * (1 + 1e-9)


def output_regex(tokens: list[re.Match]) -> str:
    """A regular expression of the page's output tokens: numbers captured, ``...`` any text,
    whitespace optional everywhere."""
    parts = []
    for t in tokens:
        if t.lastgroup == "ellipsis":
            parts.append(".*?")
        elif t.lastgroup == "number":
            parts.append(rf"(?<![\w.])((?>{NUMBER}))")
        elif t.lastgroup == "text":
            parts.append(re.escape(t.group()))
    return r"\s*" + r"\s*".join(parts) + r"\s*"


def compare_output(page: str, run: str, rtol: float = DEFAULT_RTOL, atol: float = 0.0,
                   numbers: str = "compare") -> str | None:
    """None when ``run`` (what a block printed) agrees with ``page`` (the output its page
    shows), else why not. ``numbers="ignore"``: the text alone."""
    tokens = [t for t in OUTPUT_TOKEN.finditer(page.strip()) if t.lastgroup != "space"]
    m = re.fullmatch(output_regex(tokens), run, re.S)
    if m is None:
        # how far the page's text agrees with the run, to point at the first difference
        k = len(tokens)
        while k > 0 and re.match(output_regex(tokens[:k]), run, re.S) is None:
            k -= 1
        if not tokens:
            return "the page shows no output, but the block prints"
        shown = page.strip()
        at = tokens[k].start() if k < len(tokens) else len(shown)
        line = shown[:at].count("\n")
        return f"the text differs from line {line + 1} of the page's output on: {shown.splitlines()[line]!r}"
    if numbers == "ignore":
        return None
    shown = [t.group() for t in tokens if t.lastgroup == "number"]
    wrong = [(p, r) for p, r in zip(shown, m.groups()) if not numbers_agree(p, r, rtol, atol)]
    if wrong:
        return (f"{len(wrong)} of its {len(shown)} numbers differ beyond rtol {rtol:g}"
                + (f", atol {atol:g}" if atol else "")
                + " (page -> run): " + ", ".join(f"{p} -> {r}" for p, r in wrong[:8])
                + (", ..." if len(wrong) > 8 else ""))
    return None


def output_mismatch(block: Block, printed: str) -> str | None:
    """Why the output ``block`` printed disagrees with its page, or None."""
    if block.output is None:
        if not printed.strip():
            return None
        return (f"{block.label}: the block prints, but the page shows no output; put what it prints "
                f"below it (numbers that depend on the machine as ...):\n```output\n{printed.rstrip()}\n```")
    why = compare_output(block.output, printed, **block.options)
    if why is None:
        return None
    return (f"{block.label}: the output shown at {block.file}:{block.output_line} disagrees with what "
            f"the block prints: {why}\n--- the page ---\n{block.output.rstrip()}\n"
            f"--- the run ---\n{printed.rstrip()}")


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
import contextlib, io, json, sys, time
path, label, blocks, report = sys.argv[1], sys.argv[2], json.load(open(sys.argv[3])), sys.argv[4]
namespace = {"__name__": "__main__"}


class Tee(io.TextIOBase):
    # what a block prints: kept for the comparison with its page, and passed on
    def __init__(self, stream):
        self.stream, self.kept = stream, io.StringIO()

    def write(self, text):
        self.stream.write(text)
        return self.kept.write(text)

    def flush(self):
        self.stream.flush()

    def isatty(self):
        return False

    @property
    def encoding(self):
        return getattr(self.stream, "encoding", "utf-8")


printed = []
for line, source in blocks:
    print(f"[docs-test] running the block at {label}:{line}", file=sys.stderr, flush=True)
    start = time.perf_counter()
    tee = Tee(sys.stdout)
    try:
        with contextlib.redirect_stdout(tee):
            # pad with blank lines so that tracebacks show the page's own line numbers
            exec(compile("\n" * (line - 1) + source, path, "exec"), namespace)
    finally:
        printed.append([line, tee.kept.getvalue()])
        with open(report, "w") as f:
            json.dump(printed, f)
    print(f"[docs-test] {label}:{line} took {time.perf_counter() - start:.1f} s",
          file=sys.stderr, flush=True)
"""


def user_environment() -> dict[str, str]:
    """This process's environment without the test session's emulated devices."""
    env = without_emulated_devices()
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
    text = README.read_text(encoding="utf-8")
    blocks = python_blocks(text)
    assert blocks, "README.md has no ```python blocks"
    check_markers(blocks)
    assert not output_fence_problems(text), "\n".join(output_fence_problems(text))
    # the first block stands alone: every group starts with a block that defines its names
    assert not free_names(blocks[0].source), f"first block uses undefined {free_names(blocks[0].source)}"


@pytest.mark.parametrize("path", [p for p in documents() if p != README], ids=relative)
def test_docs_page_blocks_are_valid(path):
    text = path.read_text(encoding="utf-8")
    blocks = python_blocks(text, relative(path))
    check_markers(blocks)
    assert not output_fence_problems(text, relative(path)), "\n".join(output_fence_problems(text, relative(path)))
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
    report = tmp_path / "printed.json"
    where = f"{group[0].file} blocks at lines {[b.line for b in group]}"
    try:
        proc = subprocess.run([sys.executable, str(script), str(path), group[0].file, str(spec), str(report)],
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
    printed = dict(json.loads(report.read_text()))
    wrong = [why for b in group if (why := output_mismatch(b, printed[b.line])) is not None]
    if wrong:
        pytest.fail("\n\n".join(wrong), pytrace=False)


# -- the output check itself, independent of the pages ------------------------------------------

def test_output_fences_attach_to_the_block_before_them():
    page = ("```python\nprint(1)\n```\n\n```output\n1\n```\n\ntext\n\n"
            "```python\nx = 2\n```\ntext\n```output rtol=1e-3\n2\n```\n\n"
            "````{code-block} python\nprint(3.0)\n````\n````output rtol=0.01\n3.0\n````\n")
    blocks = python_blocks(page, "docs/page.md")
    assert [(b.output, b.output_line, b.options["rtol"]) for b in blocks] == [
        ("1\n", 6, DEFAULT_RTOL), (None, 0, DEFAULT_RTOL), ("3.0\n", 23, 0.01)]
    # the second output fence follows text, not a block
    assert output_fence_problems(page, "docs/page.md") == [
        "docs/page.md:15: an output fence must follow a ```python block (only blank lines between them)"]
    assert output_fence_problems("```python\nprint(1)\n```\n```output tol=1\n1\n```\n")[0].startswith(
        "README.md:4: unknown output option 'tol=1'")
    assert output_options("atol=1e-12 numbers=ignore") == {"rtol": DEFAULT_RTOL, "atol": 1e-12, "numbers": "ignore"}
    for wrong in ("rtol=-1", "atol=x", "numbers=some", "rtol"):
        with pytest.raises(ValueError):
            output_options(wrong)


def test_output_comparison_numbers_text_and_ellipsis():
    shown = "follower=True: stretch 0.964379\nfollower=False: stretch 0.961821\n"
    assert compare_output(shown, shown) is None
    # a wrong number on the page fails, and the message names both
    why = compare_output(shown, "follower=True: stretch 1.000000\nfollower=False: stretch 1.000000\n")
    assert "2 of its 2 numbers differ" in why and "0.964379 -> 1.000000" in why
    # the rounding of the last printed digit is not a difference; one more unit is
    assert compare_output("stretch 0.964379", "stretch 0.964380") is None
    assert compare_output("stretch 0.964379", "stretch 0.964381") is not None
    # a relative tolerance, from an output fence's rtol=
    assert compare_output("error 3.512e-05 cm", "error 3.498e-05 cm") is not None
    assert compare_output("error 3.512e-05 cm", "error 3.498e-05 cm", rtol=1e-2) is None
    # an absolute tolerance, for round-off
    assert compare_output("2.0403817524439205e-14", "3.1e-15") is not None
    assert compare_output("2.0403817524439205e-14", "3.1e-15", atol=1e-12) is None
    assert compare_output("2.0403817524439205e-14", "3.1e-11", atol=1e-12) is not None
    # numbers=ignore: the text alone
    assert compare_output("t_s 15.67 us, 2 x cpu", "t_s 7.1 us, 2 x cpu", numbers="ignore") is None
    assert compare_output("t_s 15.67 us, 2 x cpu", "t_m 7.1 us, 2 x cpu", numbers="ignore") is not None
    # counts are exact; a zero shown as 0.0 is not matched by a small number printed in full
    assert compare_output("27000 steps predicted", "0 steps predicted") is not None
    assert compare_output("27000 steps predicted", "27001 steps predicted") is not None
    assert compare_output("0.0", "0.05") is not None
    assert compare_output("1e5 steps", "100000.0 steps") is None
    # text must match; whitespace does not count; names with digits are text
    assert "text differs from line 2" in compare_output("a 1\nP1 tip 2.0", "a 1\nP2 tip 2.0")
    assert compare_output("| a |  1.5 |\n| bb | 12.25 |", "| a | 1.5 |\n| bb | 12.25 |") is None
    assert compare_output("[1 2]", "[12]") is not None
    assert compare_output("float32 blocks", "float64 blocks") is not None
    # an ellipsis matches anything, lines and numbers included; the rest is still compared
    assert compare_output("took ... s, error 1.5e-03", "took 12.3 s, error 1.5e-03") is None
    assert compare_output("t_e ...\ntotal 4 steps", "t_e 1.2 us\nt_m 3.4 us\ntotal 4 steps") is None
    assert compare_output("took ... s, error 1.5e-03", "took 12.3 s, error 2.5e-03") is not None
    assert compare_output("round-off ...", "round-off 1.7763568394002505e-15") is None
    # nothing shown against something printed, and the reverse
    assert compare_output("", "1\n") is not None
    assert compare_output("1", "") is not None


def test_output_mismatch_messages_show_page_and_run():
    block = python_blocks("```python\nprint(0.5)\n```\n\n```output\n0.25\n```\n", "docs/p.md")[0]
    why = output_mismatch(block, "0.5\n")
    assert why.startswith("docs/p.md:2: the output shown at docs/p.md:6 disagrees")
    assert "--- the page ---\n0.25\n--- the run ---\n0.5" in why
    assert output_mismatch(block, "0.5000000001\n") is not None
    assert output_mismatch(block, "0.25\n") is None
    silent = python_blocks("```python\nprint(0.5)\n```\n", "docs/p.md")[0]
    assert "shows no output" in output_mismatch(silent, "0.5\n") and "```output\n0.5\n```" in output_mismatch(
        silent, "0.5\n")
    assert output_mismatch(silent, "") is None


def test_runner_keeps_each_blocks_output(tmp_path):
    blocks = [[1, "print('a', 1)\n"], [3, "x = 2\n"], [5, "print(x)\nprint(x + 1)\n"]]
    (tmp_path / "blocks.json").write_text(json.dumps(blocks))
    (tmp_path / "runner.py").write_text(RUNNER)
    proc = subprocess.run([sys.executable, str(tmp_path / "runner.py"), "page.md", "page.md",
                           str(tmp_path / "blocks.json"), str(tmp_path / "printed.json")],
                          cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert json.loads((tmp_path / "printed.json").read_text()) == [[1, "a 1\n"], [3, ""], [5, "2\n3\n"]]
    assert proc.stdout == "a 1\n2\n3\n"     # passed on as well
