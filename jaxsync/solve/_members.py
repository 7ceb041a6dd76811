"""The runs of an ensemble of one problem given as arrays over the runs
(:class:`Members`): their checks, each run's own problem, and the per-run values they
set (load factors, prescribed displacements).

:func:`jaxsync.ensemble` sets up the runs in one vectorised pass from these arrays
(:mod:`jaxsync.solve`'s ensemble members); no :class:`jaxsync.Problem` is built per run.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ProblemError
from ..pytree import concrete_scalar, is_traced, pytree_dataclass

__all__ = ["Members", "law_fields", "check_law_fields", "load_factors", "scaled_load", "run_entry",
           "prescribed_values"]


@pytree_dataclass
class Members:
    """The runs of an ensemble of one problem, as arrays over the runs (no Problem per run).

    ``jaxsync.ensemble(problem, n_steps, members=Members(...))``: run r is ``problem`` with
    the r-th entry of every array given here; a field left None is the problem's own for
    every run. At least one field is needed (it sets n_runs). A pytree: the arrays may be
    JAX tracers (``jax.grad`` of a loss over the runs with respect to them).

    Attributes:
        material: {field: (n_runs,) array} of the problem's material law's scalar fields:
            ``"E"`` Young's modulus [dyn/cm^2] (> 0), ``"nu"`` Poisson ratio
            (-1 < nu < 0.5), ``"rho"`` density [g/cm^3] (> 0) of
            :class:`jaxsync.LinearElastic` and of the hyperelastic laws given by E and nu
            (:class:`jaxsync.NeoHookean`...); a law of other parameters by their names
            (``"k1"`` of :class:`jaxsync.HolzapfelGasserOgden`...). Laws with internal
            variables or a prestress are refused.
        damping: (n_runs,) mass-proportional damping alpha [1/s] (>= 0).
        stiffness_damping: (n_runs,) stiffness-proportional damping beta [s] (>= 0).
        load_scale: (n_runs, n_loads) factor of each of the problem's loads (in the order of
            ``problem.loads``; its magnitude, vector or pressure times the factor), or
            (n_runs,) one factor for all of them. Not with follower pressures (their one
            copy is shared).
        initial_displacement: (n_runs, n_nodes, 3) [cm].
        initial_velocity: (n_runs, n_nodes, 3) [cm/s].
        dirichlet: (n_runs, n_conditions, 3) the value [cm] of each of the problem's
            Dirichlet conditions (in the order of ``problem.dirichlet``; its ``value`` for
            that run, on the components the condition prescribes): a constant condition
            holds it at every step, one with a time function follows ``value * g(t)``.
            The prescribed dofs are the problem's for every run.
    """

    material: Any = None
    damping: Any = None
    stiffness_damping: Any = None
    load_scale: Any = None
    initial_displacement: Any = None
    initial_velocity: Any = None
    dirichlet: Any = None

    def __post_init__(self):
        if self.material is not None and not isinstance(self.material, dict):
            raise ProblemError(f"Members.material must be a dict {{field: (n_runs,) array}} of the material law's "
                               f"fields (e.g. {{'E': E, 'nu': nu}}), got {type(self.material).__name__}")

    def _arrays(self) -> dict:
        """{name: array} of the fields given, the material's as ``material['E']``..."""
        out = {f"material[{k!r}]": v for k, v in (self.material or {}).items()}
        for name in ("damping", "stiffness_damping", "load_scale", "initial_displacement", "initial_velocity",
                     "dirichlet"):
            if getattr(self, name) is not None:
                out[name] = getattr(self, name)
        return out

    @property
    def n_runs(self) -> int:
        """The runs: the leading length of the arrays (0 when none is given)."""
        arrays = self._arrays()
        return int(np.shape(next(iter(arrays.values())))[0]) if arrays and np.ndim(
            next(iter(arrays.values()))) else 0

    def check(self, problem) -> int:
        """n_runs, after checking every array against ``problem`` (shapes; ranges where
        concrete).

        Raises:
            ProblemError: no array, arrays of different run counts or wrong shapes, a field
                the material law does not have, values out of range (E or rho <= 0, nu
                outside (-1, 0.5), negative damping), load factors with follower pressures,
                a law with internal variables.
        """
        arrays = self._arrays()
        if not arrays:
            raise ProblemError("Members needs at least one per-run array (material, damping, stiffness_damping, "
                               "load_scale, initial_displacement, initial_velocity or dirichlet): it sets the "
                               "number of runs")
        name0, first = next(iter(arrays.items()))
        if np.ndim(first) == 0:
            raise ProblemError(f"Members.{name0} must have a leading runs axis, got a scalar: give one value per run")
        n_runs = int(np.shape(first)[0])
        if n_runs == 0:
            raise ProblemError(f"Members.{name0} has no runs (length 0): give at least one run")
        n = problem.n_nodes
        n_loads = len(problem.loads)
        expected = {"damping": (n_runs,), "stiffness_damping": (n_runs,),
                    "initial_displacement": (n_runs, n, 3), "initial_velocity": (n_runs, n, 3),
                    "load_scale": (n_runs, n_loads), "dirichlet": (n_runs, len(problem.dirichlet), 3)}
        for name, value in arrays.items():
            shape = np.shape(value)
            want = expected.get(name, (n_runs,))
            if name == "load_scale" and shape == (n_runs,):
                continue
            if shape != want:
                which = "" if name == name0 else f" (Members.{name0} has {np.shape(first)})"
                raise ProblemError(f"Members.{name} has shape {shape}; with {n_runs} runs{which} it must be {want}: "
                                   "one entry per run"
                                   + (" (or (n_runs,), one factor for every load)" if name == "load_scale" else "")
                                   + (" (a value (x, y, z) [cm] per run and Dirichlet condition, in the order of "
                                      "problem.dirichlet)" if name == "dirichlet" else ""))
        check_law_fields(problem, self.material or {})
        for name, value in arrays.items():
            _check_values(name, value)
        if self.load_scale is not None and any(getattr(load, "follower", False) for load in problem.loads):
            raise ProblemError("Members.load_scale scales every load of a run, but the problem has follower "
                               "pressures, whose one copy all runs share: give the runs as problems "
                               "(jaxsync.ensemble([...])) with the same follower pressures, or drop load_scale")
        return n_runs

    def problem(self, problem, run: int):
        """Run ``run``'s own :class:`jaxsync.Problem`: ``problem`` with the run's entries
        (what :func:`jaxsync.simulate` of that run alone takes)."""
        changes = {}
        if self.material:
            changes["material"] = dataclasses.replace(problem.material,
                                                      **{k: run_entry(v, run) for k, v in self.material.items()})
        for name in ("damping", "stiffness_damping", "initial_displacement", "initial_velocity"):
            if getattr(self, name) is not None:
                changes[name] = run_entry(getattr(self, name), run)
        if self.load_scale is not None:
            factors = load_factors(self.load_scale, len(problem.loads))[run]
            changes["loads"] = tuple(scaled_load(load, factors[k]) for k, load in enumerate(problem.loads))
        if self.dirichlet is not None:
            values = self.dirichlet[run]
            changes["dirichlet"] = tuple(dataclasses.replace(bc, value=values[k] if is_traced(values) else
                                                             tuple(float(x) for x in values[k]))
                                         for k, bc in enumerate(problem.dirichlet))
        return problem.replace(**changes)


def run_entry(value, run: int):
    """Run ``run``'s entry of a per-run array (a Python float for a concrete scalar)."""
    x = value[run]
    scalar = concrete_scalar(x) if np.ndim(x) == 0 else None
    return scalar if scalar is not None else x


def load_factors(scale, n_loads: int):
    """(n_runs, n_loads) of a load_scale given as (n_runs,) or (n_runs, n_loads)."""
    xp = jnp if is_traced(scale) or isinstance(scale, jax.Array) else np
    scale = xp.asarray(scale, dtype=float)
    return xp.broadcast_to(scale[:, None], (scale.shape[0], n_loads)) if scale.ndim == 1 else scale


def scaled_load(load, factor):
    """``load`` with its magnitude (a pressure's) or vector (a body force's, a traction's) times ``factor``."""
    from ..fem._loads import Pressure

    if isinstance(load, Pressure):
        return dataclasses.replace(load, magnitude=factor * load.magnitude)
    return dataclasses.replace(load, vector=factor * jnp.asarray(load.vector, dtype=float)
                               if is_traced(factor, load.vector) else factor * np.asarray(load.vector, dtype=float))


_RANGES = {"material['E']": ("Young's modulus [dyn/cm^2]", 0.0, None, "give E > 0"),
           "material['rho']": ("density [g/cm^3]", 0.0, None, "give rho > 0"),
           "material['nu']": ("Poisson ratio", -1.0, 0.5, "give -1 < nu < 0.5 (nu = 0.5 is incompressible)"),
           "damping": ("mass-proportional damping alpha [1/s]", None, None, "give alpha >= 0"),
           "stiffness_damping": ("stiffness-proportional damping beta [s]", None, None, "give beta >= 0")}


def _check_values(name: str, value) -> None:
    """Range checks of a concrete per-run array (tracers pass)."""
    if is_traced(value):
        return
    try:
        x = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ProblemError(f"Members.{name} must hold numbers, got {value!r}") from None
    if not np.all(np.isfinite(x)):
        bad = np.argwhere(~np.isfinite(x))[0]
        raise ProblemError(f"Members.{name} must be finite; run {int(bad[0])} has {x[tuple(bad)]}")
    what, above, below, hint = _RANGES.get(name, (None, None, None, ""))
    if name in ("damping", "stiffness_damping"):
        above = None
        bad = np.flatnonzero(x < 0)
    elif above is not None:
        bad = np.flatnonzero((x <= above) | ((x >= below) if below is not None else False))
    elif name.startswith("material["):  # another law parameter: positive, as the laws require theirs
        bad = np.flatnonzero(x <= 0)
        what, hint = "law parameter", "give positive values (the law's own range)"
    else:
        return
    if len(bad):
        r = int(bad[0])
        raise ProblemError(f"Members.{name} ({what}) of run {r} is {x[r]:g}: {hint}"
                           + (f" (also runs {[int(b) for b in bad[1:6]]}...)" if len(bad) > 1 else ""))


def law_fields(material) -> tuple:
    """The names of a material law's scalar parameters that members may vary."""
    from ..fem.materials._linear_elastic import LinearElastic

    if isinstance(material, LinearElastic):
        return ("E", "nu", "rho")
    return tuple(f.name for f in dataclasses.fields(material) if f.name != "fibres"
                 and (is_traced(getattr(material, f.name)) or concrete_scalar(getattr(material, f.name)) is not None))


def check_law_fields(problem, material: dict) -> None:
    """The member material fields are the law's, and a law that members vary has no state."""
    if not material:
        return
    law = problem.material
    allowed = law_fields(law)
    unknown = [k for k in material if k not in allowed]
    if unknown:
        raise ProblemError(f"Members.material has {unknown}, which {type(law).__name__} does not have as a scalar "
                           f"parameter: give some of {list(allowed)}")
    if law.finite_strain and (getattr(law, "constant_state", False)
                              or law.internal_variables(1, 1)):
        raise ProblemError(f"the {type(law).__name__} law carries internal variables or a prestress, which an "
                           "ensemble's members cannot vary: run each parameter set separately with jaxsync.simulate, "
                           "or vary only loads and initial conditions")


def prescribed_values(problem, dirichlet) -> tuple:
    """(fixed values (n_runs, n_nodes, 3) [cm], moving values (n_runs, n_moving, n_nodes,
    3) [cm] or None) of every run's Dirichlet values ``dirichlet`` (n_runs,
    n_conditions, 3) on ``problem``'s prescribed dofs: the arrays
    :class:`~jaxsync.fem.DiscreteProblem` holds for one problem (``fixed_values``,
    ``moving``), for all runs at once (a NumPy array, or a JAX array where ``dirichlet``
    is traced)."""
    xp = jnp if is_traced(dirichlet) or isinstance(dirichlet, jax.Array) else np
    values = xp.asarray(dirichlet, dtype=float)
    owner = problem.dirichlet_owner().reshape(-1, 3)
    masks = np.stack([owner == k for k in range(len(problem.dirichlet))]).astype(float)  # (n_cond, n_nodes, 3)
    moving = [k for k, bc in enumerate(problem.dirichlet) if bc.time is not None]
    constant = [k for k, bc in enumerate(problem.dirichlet) if bc.time is None]
    fixed = xp.einsum("rkc,knc->rnc", values[:, constant], masks[constant])
    if not moving:
        return fixed, None
    return fixed, values[:, moving, None, :] * masks[moving][None]
