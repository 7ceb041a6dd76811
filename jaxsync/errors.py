"""Exception types of jaxsync.

Every error the package raises on bad input derives from :class:`JaxsyncError`, so a
caller can catch the whole family at once; each message names the problem and the fix.
"""

from __future__ import annotations


class JaxsyncError(Exception):
    """Base class of every error jaxsync raises on purpose."""


class MeshError(JaxsyncError, ValueError):
    """The mesh cannot be used: no tetrahedra, NaN coordinates, degenerate elements..."""


class MaterialError(JaxsyncError, ValueError):
    """Material parameters outside their physical range."""


class ProblemError(JaxsyncError, ValueError):
    """A problem definition that is inconsistent (unknown facet tag, bad shapes...)."""


class StabilityError(JaxsyncError, RuntimeError):
    """A time step above the stability bound, or a run that diverged (NaN/Inf, blow-up).

    Attributes:
        trajectory: a diverged run's snapshots saved before divergence (a
            :class:`jaxsync.Trajectory` whose ``result`` is ``Result.DIVERGED``), or None.
        trajectories: an ensemble's partial trajectories, one per run, or None.
        run: the ensemble run that diverged first (None otherwise); runs: all that did.
        elements: a hyperelastic run stopped by inverted elements: their indices (sorted
            int64 array), else None.
    """

    def __init__(self, message: str, *, trajectory=None, trajectories=None, run=None, runs=None, elements=None):
        super().__init__(message)
        self.trajectory, self.trajectories = trajectory, trajectories
        self.run, self.runs = run, runs
        self.elements = elements


class ConvergenceError(JaxsyncError, RuntimeError):
    """An iterative solve that did not converge: Newton's method for the static equilibrium
    of a hyperelastic problem (:func:`jaxsync.steady_state`).

    Attributes:
        increment: the load increment that failed (1-based), or None.
        residual: the relative residual reached (the free dofs' largest out-of-balance force
            over the load and reaction scale), or None.
        displacement: (n_nodes, 3) [cm] the last converged state (the end of the increment
            before), or None.
    """

    def __init__(self, message: str, *, increment=None, residual=None, displacement=None):
        super().__init__(message)
        self.increment, self.residual, self.displacement = increment, residual, displacement


class CheckpointError(JaxsyncError, RuntimeError):
    """A file jaxsync reads -- a trajectory, a surrogate file, a solver checkpoint, a training
    state -- that cannot be read or does not fit the run that tries to use it."""


class ConfigError(JaxsyncError, ValueError):
    """A configuration file (TOML) or command-line option that cannot be used."""


class PrecisionError(JaxsyncError, RuntimeError):
    """JAX is in float32 mode where the solver needs float64 (``jax_enable_x64``)."""


class PartitionError(JaxsyncError, ValueError):
    """A partition that cannot be made or used (bad part count, empty parts...)."""


class InferencePrecisionError(JaxsyncError, ValueError):
    """Reduced-precision surrogate inference that strays from the full-precision one by
    more than the stated bound (:func:`jaxsync.surrogate.check_inference_precision`)."""


class OutputError(JaxsyncError, OSError):
    """An output file or folder that cannot be written: a location that is not a
    writable folder (found before anything runs, :func:`jaxsync.io.check_writable`), or
    a write that failed (a full disk...). Also an :class:`OSError`, as the failure it
    reports."""


class SynchronizedRunWarning(RuntimeWarning):
    """A synchronization-avoiding run that predicts few or none of its steps: error control
    kept re-synchronizing, or a load jump near the end keeps the run synchronized. The
    result is right (synchronized steps are exact), but the run saves no time. A
    :class:`RuntimeWarning`, as it was before it had a class of its own."""
