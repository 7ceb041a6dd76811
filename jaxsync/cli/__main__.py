"""``python -m jaxsync.cli``: the ``jaxsync`` command line (:func:`jaxsync.cli.main`), for
environments where the console script is not on the PATH (``mpiexec -n 2 python -m
jaxsync.cli ...``)."""

import sys

from .main import main

sys.exit(main())
