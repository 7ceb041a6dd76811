"""The earlier home of the command line, now :mod:`jaxsync.cli`: a ``jaxsync`` console script
installed before the move (an editable install not reinstalled since) still calls
``jaxsync.app.cli:main``, which is :func:`jaxsync.cli.main`."""

from ..cli import main

__all__ = ["main"]
