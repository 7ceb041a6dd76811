"""The subcommands of the ``jaxsync`` command line, one module each.

Every module has ``add_parser(subparsers)``, which adds the subcommand and sets
``args.func`` to its ``run(args) -> int``; :mod:`jaxsync.app.cli` builds the parser from
them and dispatches. ``jaxsync train`` lives with its training code in
:mod:`jaxsync.app.train`. Helpers shared by several commands (refusing to overwrite
outputs, the processes of an ``mpiexec`` run, common options) are in :mod:`.common`.
Each module imports the solver only inside ``run``, so that building the parser imports
no numerical library (``tests/test_import_time.py``); the parsers of ``demo`` and
``train``, whose defaults come from the surrogate settings, are made on first use
(:data:`jaxsync.app.cli.DEFERRED_HELP`).
"""
