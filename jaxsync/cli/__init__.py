"""The ``jaxsync`` command line: one module per subcommand (:mod:`.demo`, :mod:`.simulate`,
:mod:`.train`, :mod:`.predict`, :mod:`.finetune`, :mod:`.report`, :mod:`.unload`), the parser
and the dispatch in :mod:`.main`, and the helpers several commands share in :mod:`.common`
(refusing to overwrite outputs, the processes of an ``mpiexec`` run, common options).

Every subcommand module has ``add_parser(subparsers)``, which adds the subcommand and sets
``args.func`` to its ``run(args) -> int``; :func:`build_parser` builds the parser from them
and :func:`main` (the ``jaxsync`` console script) dispatches. Each module imports the solver
only inside ``run``, so that building the parser imports no numerical library
(``tests/test_import_time.py``); the parsers of ``demo`` and ``train``, whose defaults come
from the surrogate settings, are made on first use (:data:`DEFERRED_HELP`). The pipelines the
commands run (the demo, TOML problem files, reports and figures) are :mod:`jaxsync.app`'s.
"""

from typing import TYPE_CHECKING

from ..lazy import export_lazily

__all__ = ["main", "build_parser", "parts_of", "resume_hint", "DEFERRED_HELP"]

# where each name of __all__ is imported from on first use (jaxsync.lazy): the imports of TYPE_CHECKING below
__getattr__, __dir__ = export_lazily(__name__, {
    ".main": ("DEFERRED_HELP", "build_parser", "main", "parts_of", "resume_hint"),
})

if TYPE_CHECKING:
    from .main import DEFERRED_HELP, build_parser, main, parts_of, resume_hint
