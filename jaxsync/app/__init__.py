"""The application layer: the pipelines behind the ``jaxsync`` command line
(:mod:`jaxsync.cli`, one module per subcommand) and what only they need.

- :mod:`.config`: problems described by TOML files (:mod:`.config_schema`: their tables read
  from the dataclasses they configure);
- :mod:`.demo`: the end-to-end pipeline behind ``jaxsync demo`` (:mod:`.demo_folder`, its
  output folder; :mod:`.run_estimate`, how long it will take; :mod:`.mass_scaling`, the
  mass-scaling check);
- :mod:`.plots`: the report (monitored nodes, ``summary.json``), :mod:`.figures`: its
  figures, and :mod:`.vessel_report`: the vessel section.

Nothing here is imported by the library layers (fem, parallel, solve, surrogate, perf).
"""
