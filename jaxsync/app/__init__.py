"""The application layer: the ``jaxsync`` command line and what only it needs.

- :mod:`.cli`: the parser and dispatch (console script ``jaxsync``);
  :mod:`.commands`: one module per subcommand (demo, simulate, predict, report) and
  their shared helpers; :mod:`.train`: ``jaxsync train``;
- :mod:`.config`: problems described by TOML files;
- :mod:`.demo`: the end-to-end pipeline behind ``jaxsync demo``;
- :mod:`.plots`: the report (monitored nodes, ``summary.json``) and :mod:`.figures`: its
  figures.

Nothing here is imported by the library layers (fem, parallel, solve, surrogate, perf).
"""
