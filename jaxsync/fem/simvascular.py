"""The earlier home of :mod:`jaxsync.mesh.simvascular` (SimVascular mesh folders): every
name it had is re-exported from there, so that ``from jaxsync.fem import simvascular``
still works. New code imports :mod:`jaxsync.mesh.simvascular`."""

from ..mesh.simvascular import *  # noqa: F403
from ..mesh.simvascular import NODE_IDS, __all__  # noqa: F401
