"""The string (and small integer) options of jaxsync, defined once.

Each option is a :data:`typing.Literal` type: functions annotate their parameters with it,
the command line takes its ``choices=`` from it (:func:`choices`), and
:func:`check_option` refuses any other value with a message that names the allowed ones.
The tuples the modules expose (``jaxsync.fem.forces.MODES``,
``jaxsync.parallel.multiprocess.SYNC_METHODS``) are ``choices`` of these types.

- :data:`Element`: the finite element of a problem (:class:`jaxsync.Problem`'s ``element``,
  ``[problem] element``, ``jaxsync simulate --element``): ``"P1"`` (linear tetrahedra) or
  ``"P2"`` (quadratic tetrahedra, the choice for bending and for nearly incompressible
  tissue: ``benchmarks/bench_locking.py``).
- :data:`Mode`: the internal force of the explicit step (paper Remark 2): ``"preassembled"``
  (sparse K stored once) or ``"recompute"`` (element quantities formed every step), both
  for the linear law; or ``"total-lagrangian"`` (finite strain, a hyperelastic material:
  :mod:`jaxsync.fem.forces`, which a hyperelastic problem gets in any mode).
- :data:`Sync`: how the parts sum their shared-node forces every step: XLA ``psum`` of the
  whole interface, XLA ``ppermute`` exchange between neighbouring devices, or an MPI
  Allreduce; or ``"halo"``, deep halos (:mod:`jaxsync.parallel.exchange`): parts grown by k
  layers exchange displacements every k steps, exactly. There is no fixed default: ``sync=None`` everywhere means
  :func:`jaxsync.parallel.multiprocess.default_sync` (``"psum"`` in one process,
  ``"mpi"`` across CPU processes).
- :data:`Compression`: HDF5 compression of a trajectory's large datasets
  (``jaxsync simulate/predict --compression``; ``"none"`` is ``compression=None`` of
  :meth:`jaxsync.Trajectory.save`).
- :data:`Component`: a displacement component, 0, 1, 2 = x, y, z (``jaxsync report
  --component``).
- :data:`EpochRule`: the named epoch count of ``jaxsync train --epochs`` (besides a number):
  ``"paper"``, the paper's rule floor(log_gamma(eta_min / eta0)).
- :data:`ProblemKind`: ``[problem] kind`` of a TOML problem file (:mod:`jaxsync.app.config`):
  the packaged ``"cantilever"`` or a ``"general"`` problem with its own conditions and loads.
- :data:`MeshGenerator`: ``[mesh] generate`` of a TOML problem file: the ``"box_beam"``
  (default) or the ``"coronary_tree"`` of :func:`jaxsync.coronary_mesh`.
- :data:`ValidationSplit`: which training windows are held out for validation
  (:func:`jaxsync.surrogate.training.split_indices`): evenly ``"interleaved"`` (default) or the
  paper's seeded ``"random"`` subset.
- :data:`SurrogateModel`: the surrogate ``jaxsync train --model`` fits
  (:mod:`jaxsync.surrogate.models`): the ``"lstm"`` encoder-decoder (default) or the
  ``"linear"`` autoregressive baseline, fitted by least squares.
- :data:`LoadJumpWindows`: whether training takes the windows that straddle a recorded load
  jump (``jaxsync train --load-jump-windows``): ``"exclude"`` or ``"keep"``; by default
  excluded for the linear model and kept for the LSTM (measured, see
  :func:`jaxsync.surrogate.train_surrogates`).
- :data:`LoadJumps`: what a synchronization-avoiding run does where a load's time function
  jumps (:func:`jaxsync.simulate_sync_avoiding`): ``"synchronize"`` (stay synchronized until
  the networks' input history follows the jump) or ``"predict"`` (predict through it, as the
  paper did).
- :data:`ZeroPressureMethod`: how :func:`jaxsync.zero_pressure_geometry` finds the unloaded
  geometry (``jaxsync unload --method``): ``"newton"`` (the inverse problem) or
  ``"fixed-point"`` (backward displacement); :data:`LinearSolver`: its Newton updates'
  linear solver, ``"direct"`` or ``"krylov"``; :data:`PrestressMethod`: how
  :func:`jaxsync.prestress` finds the prestrain, ``"zero-pressure"`` or ``"mulf"``;
  :data:`ZeroPressureStart`: what ``jaxsync simulate`` runs from with a ``[zero_pressure]``
  table (``start``): ``"unloaded"`` (the zero-pressure geometry), ``"prestressed"`` (the
  imaged geometry with its prestress) or ``"imaged"`` (the imaged geometry as it is).
"""

from __future__ import annotations

import numbers
from typing import Literal, get_args

from .errors import ConfigError, JaxsyncError, PartitionError

__all__ = ["Element", "Mode", "Sync", "Compression", "Component", "EpochRule", "ProblemKind", "MeshGenerator",
           "ValidationSplit", "SurrogateModel", "LoadJumpWindows", "LoadJumps", "ZeroPressureMethod", "LinearSolver",
           "PrestressMethod", "ZeroPressureStart", "choices", "check_option",
           "DEFAULT_MODE",
           "DEFAULT_COMPRESSION", "DEFAULT_COMPONENT", "check_halo_depth"]

Element = Literal["P1", "P2"]
Mode = Literal["preassembled", "recompute", "total-lagrangian"]
Sync = Literal["psum", "ppermute", "mpi", "halo"]
Compression = Literal["gzip", "lzf", "none"]
Component = Literal[0, 1, 2]
EpochRule = Literal["paper"]
ProblemKind = Literal["cantilever", "general"]
MeshGenerator = Literal["box_beam", "coronary_tree"]
ValidationSplit = Literal["interleaved", "random"]
SurrogateModel = Literal["lstm", "linear"]
LoadJumpWindows = Literal["exclude", "keep"]
LoadJumps = Literal["synchronize", "predict"]
ZeroPressureMethod = Literal["newton", "fixed-point"]
LinearSolver = Literal["direct", "krylov"]
PrestressMethod = Literal["zero-pressure", "mulf"]
ZeroPressureStart = Literal["unloaded", "prestressed", "imaged"]

DEFAULT_MODE: Mode = "preassembled"
DEFAULT_COMPRESSION: Compression = "gzip"
DEFAULT_COMPONENT: Component = 2


def choices(option) -> tuple:
    """The allowed values of an option type, in order: ``choices(Mode)`` is
    ``("preassembled", "recompute", "total-lagrangian")``."""
    values = get_args(option)
    if not values:
        raise TypeError(f"{option!r} is not a Literal type")
    return values


def check_option(name: str, value, option, *, error: type[JaxsyncError] = ConfigError):
    """Return ``value`` if it is one of the values of the ``Literal`` type ``option``.

    Raises:
        ConfigError (or ``error``): naming ``name``, the allowed values and ``value``.
    """
    allowed = choices(option)
    if not any(_same_kind(value, a) and value == a for a in allowed):
        names = ", ".join(repr(a) for a in allowed)
        raise error(f"{name} must be one of {names}, got {value!r}")
    return value


def _same_kind(value, allowed) -> bool:
    """A string for a string choice; an integer (not a bool, which equals 0 or 1) for an
    integer choice."""
    if isinstance(allowed, str):
        return isinstance(value, str)
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def check_halo_depth(halo_depth) -> int:
    """``halo_depth`` (deep halos: steps between two exchanges) as a positive int, or
    :class:`~jaxsync.PartitionError` naming the fix."""
    if isinstance(halo_depth, bool) or not isinstance(halo_depth, numbers.Integral) or halo_depth < 1:
        raise PartitionError(f"halo_depth must be a positive integer (steps between exchanges), "
                             f"got {halo_depth!r}")
    return int(halo_depth)
