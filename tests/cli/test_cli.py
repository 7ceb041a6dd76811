"""The ``jaxsync`` parser: every option documented, choices read from
:mod:`jaxsync.options`, one name for a count of parts, the console script.

The commands themselves: ``tests/cli/test_cli_simulate.py`` (simulate) and
``tests/cli/test_cli_pipeline.py`` (demo, predict, report)."""

import argparse
import subprocess
import sys

import pytest

import jaxsync
from jaxsync.cli import build_parser, main, parts_of
from jaxsync.options import Component, Compression, Mode, Sync, check_option, choices


def subcommands(parser):
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices


def option(parser, flag):
    return next(a for a in parser._actions if flag in a.option_strings)


def test_every_option_is_documented():
    parser = build_parser()
    commands = subcommands(parser)
    assert {"demo", "simulate", "train", "predict", "report"} <= set(commands)
    for name, p in commands.items():
        text = p.format_help()
        for action in p._actions:
            if not action.option_strings or "-h" in action.option_strings:
                continue
            if action.help == argparse.SUPPRESS:  # a former spelling, kept working
                documented = [a for a in p._actions if a.dest == action.dest and a is not action]
                assert documented and documented[0].help, f"{name} {action.option_strings} hides nothing"
                continue
            assert action.help, f"{name} {action.option_strings} has no help"
            assert action.option_strings[0] in text


def test_console_script_help():
    out = subprocess.run([sys.executable, "-m", "jaxsync.cli", "--help"], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0
    assert "simulate" in out.stdout and "demo" in out.stdout


def test_the_declared_console_script_and_its_former_target_are_the_command_line():
    """pyproject's ``jaxsync`` script names jaxsync.cli:main, and a script installed before the
    command line moved (``jaxsync.app.cli:main``) still runs the same function."""
    import tomllib
    from pathlib import Path

    from jaxsync.app.cli import main as former

    project = tomllib.loads((Path(__file__).parents[2] / "pyproject.toml").read_text())
    assert project["project"]["scripts"]["jaxsync"] == "jaxsync.cli:main"
    assert former is main
    out = subprocess.run([sys.executable, "-c", "import sys; from jaxsync.app.cli import main; sys.exit(main())",
                          "--version"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.startswith("jaxsync "), out.stderr


@pytest.mark.parametrize("command, flag, literal", [
    ("simulate", "--mode", Mode), ("predict", "--mode", Mode), ("simulate", "--sync", Sync),
    ("simulate", "--compression", Compression), ("predict", "--compression", Compression),
    ("report", "--component", Component),
])
def test_choices_come_from_the_option_types(command, flag, literal):
    assert tuple(option(subcommands(build_parser())[command], flag).choices) == choices(literal)


def test_predict_offers_every_synchronization_but_deep_halos():
    # the synchronization-avoiding run records shared-node histories every step, which deep
    # halos do not keep (the library refuses sync="halo" there too)
    offered = tuple(option(subcommands(build_parser())["predict"], "--sync").choices)
    assert offered == tuple(m for m in choices(Sync) if m != "halo")


def test_option_tuples_of_the_library_are_the_option_types():
    from jaxsync.fem.forces import MODES
    from jaxsync.parallel.multiprocess import SYNC_METHODS

    assert MODES == choices(Mode) and SYNC_METHODS == choices(Sync)


def test_check_option_names_the_allowed_values():
    assert check_option("mode", "recompute", Mode) == "recompute"
    with pytest.raises(jaxsync.ConfigError, match=r"sync must be one of 'psum', 'ppermute', 'mpi', 'halo', got 'nccl'"):
        check_option("sync", "nccl", Sync)
    with pytest.raises(jaxsync.ProblemError, match="mode must be one of"):
        check_option("mode", "sparse", Mode, error=jaxsync.ProblemError)
    with pytest.raises(jaxsync.ConfigError, match="got True"):  # a bool is not a component
        check_option("component", True, Component)
    with pytest.raises(jaxsync.ConfigError, match="got '2'"):
        check_option("component", "2", Component)
    with pytest.raises(TypeError):
        choices(str)


def test_a_count_of_parts_is_called_parts_everywhere():
    parser = build_parser()
    for argv in (["demo", "--parts", "3"], ["simulate", "--parts", "3"],
                 ["simulate", "--partitions", "3"]):  # the former spelling still works
        args = parser.parse_args(argv)
        assert args.parts == 3 and parts_of(args) == 3
    assert parts_of(parser.parse_args(["simulate"])) == 0
    assert "--partitions" not in subcommands(parser)["simulate"].format_help()


def test_no_command_prints_the_help(capsys):
    assert main([]) == 0
    assert "COMMAND" in capsys.readouterr().out


def test_demo_and_train_spell_the_surrogate_options_alike():
    """Same flags; the demo leaves them None for its case's defaults, which for the
    cantilever are jaxsync train's."""
    from jaxsync.app.demo import demo_defaults
    from jaxsync.cli.common import SURROGATE_OPTIONS

    commands = subcommands(build_parser())
    cantilever = demo_defaults("cantilever")
    for flags, _, dest, _ in SURROGATE_OPTIONS:
        demo, train = (option(commands[name], flags[0]) for name in ("demo", "train"))
        for action in (demo, train):
            assert action.dest == dest and set(flags) <= set(action.option_strings), flags
        assert demo.default is None and getattr(cantilever, dest) == train.default, flags
    assert option(commands["demo"], "--epochs").default is None
    assert cantilever.epochs == option(commands["train"], "--epochs").default


def test_predict_load_parameter_keeps_its_former_spelling():
    from jaxsync.cli import build_parser

    for flag in ("--load-parameter", "--cond"):
        args = build_parser().parse_args(["predict", "a.h5", "s.h5", flag, "0.4"])
        assert args.load_parameter == 0.4
