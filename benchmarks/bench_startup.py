"""Start-up time of the command line and of ``import jaxsync``.

Each case is a fresh process, timed from start to exit (wall clock), best of the rounds
(:func:`jaxsync.perf.measure.sample_times`: one untimed run of each, then round-robin
rounds). The cases:

- ``python``: the interpreter alone (``python -c pass``), the floor of every other case;
- ``import jaxsync``: the package's import (names imported on first use);
- ``jaxsync.cantilever()``: the notebook style of use, the library imported by the names
  it uses and the paper's cantilever built;
- ``--version``, ``--help``, ``simulate --help``, ``simulate --dt`` (an argument error):
  answered by the parser alone, which imports no numerical library;
- ``train --help``: the options of ``train`` take their defaults from the surrogate
  settings (JAX, optax), so its help imports them;
- ``simulate --print-config``: a command that runs, with the imports of ``simulate``;
- ``report missing.h5 missing.h5``: ``jaxsync report`` up to reading its first input (its
  imports), ending in its one-line error.

For each case the JSON also lists the heavy libraries the process imported (from a run
with ``-X importtime``).

Usage: python benchmarks/bench_startup.py [--repeats 7] [--out benchmarks/results/startup.json]
    [--baseline DIR]

``--baseline DIR``: also time every case with the package of another checkout (``DIR``
holds its ``jaxsync/``, put first on ``PYTHONPATH``; e.g. ``git worktree add /tmp/base
HEAD~1``), in the same rounds, so that both see the same load of the machine.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import experiments  # noqa: E402  (machine())
import numpy as np  # noqa: E402

from jaxsync.io import atomic_json  # noqa: E402
from jaxsync.perf.measure import sample_times  # noqa: E402

DEFAULT_OUT = os.path.join(HERE, "results", "startup.json")

# the libraries whose import the lazy package and parser avoid until they are used
HEAVY = ("jax", "scipy", "skfem", "meshio", "h5py", "optax", "matplotlib", "gmsh", "pymetis", "tqdm", "numpy")


def cases(cli: list[str]) -> dict[str, list[str]]:
    """{case: argv} (``cli``: the argv that starts the command line)."""
    python = [sys.executable]
    return {
        "python": python + ["-c", "pass"],
        "import jaxsync": python + ["-c", "import jaxsync"],
        "jaxsync.cantilever()": python + ["-c", "import jaxsync; jaxsync.cantilever()"],
        "jaxsync --version": cli + ["--version"],
        "jaxsync --help": cli + ["--help"],
        "jaxsync simulate --help": cli + ["simulate", "--help"],
        "jaxsync simulate --dt": cli + ["simulate", "--dt"],
        "jaxsync train --help": cli + ["train", "--help"],
        "jaxsync simulate --print-config": cli + ["simulate", "--print-config"],
        "jaxsync report missing.h5 missing.h5": cli + ["report", "missing.h5", "missing.h5", "-o", "report"],
    }


def command_line() -> list[str]:
    """The argv of the ``jaxsync`` console script beside this Python (else on the PATH,
    else ``python -m jaxsync.cli``)."""
    script = os.path.join(os.path.dirname(sys.executable), "jaxsync")
    if os.path.exists(script):
        return [script]
    if shutil.which("jaxsync"):
        return [shutil.which("jaxsync")]
    return [sys.executable, "-m", "jaxsync.cli"]


def environment(checkout: str | None) -> dict:
    """This process's environment, with ``checkout`` first on ``PYTHONPATH`` (None: as it is)."""
    env = dict(os.environ)
    if checkout:
        env["PYTHONPATH"] = os.pathsep.join([os.path.abspath(checkout)] + [p for p in [env.get("PYTHONPATH")] if p])
    return env


def run(argv: list[str], cwd: str, env: dict) -> subprocess.CompletedProcess:
    return subprocess.run(argv, cwd=cwd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                          timeout=600)


def heavy_imports(argv: list[str], cwd: str, env: dict) -> tuple[list[str], int]:
    """(the libraries of :data:`HEAVY` the process imports, its exit status)."""
    done = run(argv, cwd, {**env, "PYTHONPROFILEIMPORTTIME": "1"})
    imported = set()
    for line in done.stderr.splitlines():
        if line.startswith("import time:") and line.count("|") == 2:
            imported.add(line.rsplit("|", 1)[1].strip().split(".")[0])
    return [name for name in HEAVY if name in imported], done.returncode


def measure(commands: dict, checkouts: dict, repeats: int) -> dict:
    """{(checkout label, case): (samples [s], heavy imports, exit status)}, every case of
    every checkout timed in the same round-robin rounds."""
    # a working folder with a file in it: the commands' outputs and their clean-up stay inside
    with tempfile.TemporaryDirectory(prefix="jaxsync-startup-") as cwd:
        with open(os.path.join(cwd, "README"), "w") as f:
            f.write("bench_startup.py's working folder\n")
        calls = {(label, name): (run, (cmd, cwd, environment(path)))
                 for name, cmd in commands.items() for label, path in checkouts.items()}
        samples = sample_times(calls, repeats)
        return {key: (samples[key], *heavy_imports(*args)) for key, (_, args) in calls.items()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=7, help="timed rounds (default: %(default)s)")
    parser.add_argument("--out", default=DEFAULT_OUT, help="JSON file (default: %(default)s)")
    parser.add_argument("--baseline", default=None, metavar="DIR",
                        help="also time the package of this checkout (the folder holding its jaxsync/)")
    args = parser.parse_args(argv)
    commands = cases(command_line())
    checkouts = {"this": None, **({"baseline": args.baseline} if args.baseline else {})}
    results = measure(commands, checkouts, args.repeats)
    rows = []
    for name, cmd in commands.items():
        shown = ["python" if cmd[0] == sys.executable else os.path.basename(cmd[0])] + cmd[1:]
        row = {"case": name, "command": " ".join(shown)}
        for label in checkouts:
            samples, heavy, status = results[label, name]
            prefix = "" if label == "this" else f"{label}_"
            row.update({f"{prefix}best_s": float(np.min(samples)), f"{prefix}median_s": float(np.median(samples)),
                        f"{prefix}samples_s": [float(t) for t in samples], f"{prefix}imports": heavy,
                        f"{prefix}exit_status": status})
        rows.append(row)
    width = max(len(r["case"]) for r in rows)
    head = f"{'case':{width}s}  best [s]  median [s]"
    if args.baseline:
        head += "  baseline best [s]  baseline median [s]"
    lines = [head + "  imports", "-" * (len(head) + 40)]
    for r in rows:
        line = f"{r['case']:{width}s}  {r['best_s']:8.3f}  {r['median_s']:10.3f}"
        if args.baseline:
            line += f"  {r['baseline_best_s']:17.3f}  {r['baseline_median_s']:19.3f}"
        lines.append(line + f"  {', '.join(r['imports']) or '-'}")
    text = "\n".join(lines)
    print(text)
    atomic_json(args.out, {"rows": rows, "repeats": args.repeats, "table": text, "baseline": args.baseline,
                           "machine": experiments.machine()})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
