"""The members of an ensemble: what its runs share and what is their own, set up in one
vectorised pass.

:func:`jaxsync.ensemble` advances n_runs runs of one system (mesh, element, supports,
constrained dofs, load and prescribed-displacement time functions, density scaling)
under ``jax.vmap``. Each run (member) may have its own

* material parameters: the scalar fields of the problem's material law (E, nu, rho of
  :class:`jaxsync.LinearElastic` and :class:`jaxsync.NeoHookean`; k1, k2... of a law of
  more parameters), mass-proportional damping alpha and stiffness-proportional damping
  beta;
* load magnitudes (a factor per load, or whole load vectors and Dirichlet values when the
  members are given as problems);
* initial displacement and velocity.

Nothing is assembled per member. The per-member data (:class:`RunData`, every leaf with
a leading runs axis) are injected into one shared :class:`~jaxsync.fem.ExplicitSystem`
inside the vmapped step (:func:`member_system`), in the cheapest form:

* the linear law's stiffness K = lambda K_lambda + mu K_mu
  (:meth:`jaxsync.fem.forces.Preassembled.unit_operators`, the two unit operators
  built once): where only E differs (nu shared) one copy of K(E=1, nu) with a scale E
  per member (:attr:`jaxsync.fem.BlockEll.scale`); where nu differs per-member
  blocks lambda_r K_lambda + mu_r K_mu (n_runs copies of the blocks: memory grows with the
  runs);
* the lumped mass rho_r M_1 (n_runs, n_nodes, 3), the damping coefficients as (n_runs,),
  a load factor per member and load applied to the shared load vectors;
* a hyperelastic law's parameters as a law whose leaves carry the runs axis (the element
  kernel vmapped over them).

The stable step holds for every member
(:func:`jaxsync.solve._ensemble_stability.check_members_dt`,
:func:`~jaxsync.solve.default_dt`): see
:func:`~jaxsync.solve.member_bounds` for the bound used.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ProblemError
from ..fem._stepper import ExplicitSystem, SolverState, build_system
from ..pytree import concrete_scalar, is_traced, pytree_dataclass

__all__ = ["Members", "RunData", "EnsembleSetup", "setup_of_members", "setup_of_problems", "member_system",
           "batched_system", "initial_states"]


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
    """

    material: Any = None
    damping: Any = None
    stiffness_damping: Any = None
    load_scale: Any = None
    initial_displacement: Any = None
    initial_velocity: Any = None

    def __post_init__(self):
        if self.material is not None and not isinstance(self.material, dict):
            raise ProblemError(f"Members.material must be a dict {{field: (n_runs,) array}} of the material law's "
                               f"fields (e.g. {{'E': E, 'nu': nu}}), got {type(self.material).__name__}")

    def _arrays(self) -> dict:
        """{name: array} of the fields given, the material's as ``material['E']``..."""
        out = {f"material[{k!r}]": v for k, v in (self.material or {}).items()}
        for name in ("damping", "stiffness_damping", "load_scale", "initial_displacement", "initial_velocity"):
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
                               "load_scale, initial_displacement or initial_velocity): it sets the number of runs")
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
                    "load_scale": (n_runs, n_loads)}
        for name, value in arrays.items():
            shape = np.shape(value)
            want = expected.get(name, (n_runs,))
            if name == "load_scale" and shape == (n_runs,):
                continue
            if shape != want:
                raise ProblemError(f"Members.{name} has shape {shape}; with {n_runs} runs (Members.{name0} has "
                                   f"{np.shape(first)}) it must be {want}: one entry per run"
                                   + (" (or (n_runs,), one factor for every load)" if name == "load_scale" else ""))
        _check_law_fields(problem, self.material or {})
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
                                                      **{k: _entry(v, run) for k, v in self.material.items()})
        for name in ("damping", "stiffness_damping", "initial_displacement", "initial_velocity"):
            if getattr(self, name) is not None:
                changes[name] = _entry(getattr(self, name), run)
        if self.load_scale is not None:
            factors = _load_scale(self.load_scale, len(problem.loads))[run]
            changes["loads"] = tuple(_scaled_load(load, factors[k]) for k, load in enumerate(problem.loads))
        return problem.replace(**changes)


def _entry(value, run: int):
    """Run ``run``'s entry of a per-run array (a Python float for a concrete scalar)."""
    x = value[run]
    scalar = concrete_scalar(x) if np.ndim(x) == 0 else None
    return scalar if scalar is not None else x


def _load_scale(scale, n_loads: int):
    """(n_runs, n_loads) of a load_scale given as (n_runs,) or (n_runs, n_loads)."""
    xp = jnp if is_traced(scale) or isinstance(scale, jax.Array) else np
    scale = xp.asarray(scale, dtype=float)
    return xp.broadcast_to(scale[:, None], (scale.shape[0], n_loads)) if scale.ndim == 1 else scale


def _scaled_load(load, factor):
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


def _check_law_fields(problem, material: dict) -> None:
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


@pytree_dataclass
class RunData:
    """The per-run data of an ensemble's batched system: every leaf has a leading runs
    axis; a field None is the shared system's (:func:`member_system` puts them in).

    Attributes:
        load_vectors: (n_runs, n_loads, n_nodes, 3) nodal loads at full magnitude [dyn].
        load_scale: (n_runs, n_loads) factors of the shared load vectors.
        fixed_values: (n_runs, n_nodes, 3) constant prescribed values [cm].
        moving: (n_runs, n_moving, n_nodes, 3) values of the time-dependent conditions [cm].
        mass: (n_runs, n_nodes, 3) lumped mass [g].
        damping: (n_runs,) alpha [1/s]; stiffness_damping: (n_runs,) beta [s].
        stiffness_scale: (n_runs,) E of each run: the shared stiffness holds K(E=1, nu).
        stiffness_blocks: the stiffness operator's ``blocks`` with a leading runs axis
            (lambda_r K_lambda + mu_r K_mu).
        law: a hyperelastic law whose every leaf has the runs axis.
        dashpot: the supports' :class:`jaxsync.fem.forces.Dashpot` of each run (their
            update depends on the mass and alpha).
    """

    load_vectors: Any = None
    load_scale: Any = None
    fixed_values: Any = None
    moving: Any = None
    mass: Any = None
    damping: Any = None
    stiffness_damping: Any = None
    stiffness_scale: Any = None
    stiffness_blocks: Any = None
    law: Any = None
    dashpot: Any = None


def member_system(system: ExplicitSystem, run: RunData) -> ExplicitSystem:
    """One run's system: the shared ``system`` with the run's own data (``run``: one
    member's slice of a :class:`RunData`, inside ``jax.vmap`` over the runs)."""
    changes = {name: getattr(run, name) for name in ("load_vectors", "fixed_values", "moving", "mass", "damping",
                                                     "stiffness_damping", "dashpot")
               if getattr(run, name) is not None}
    if run.load_scale is not None:
        changes["load_vectors"] = system.load_vectors * run.load_scale[:, None, None]
    stiffness = system.stiffness
    if run.stiffness_scale is not None:
        stiffness = dataclasses.replace(stiffness, scale=run.stiffness_scale)
    if run.stiffness_blocks is not None:
        stiffness = dataclasses.replace(stiffness, blocks=run.stiffness_blocks)
    if run.law is not None:
        stiffness = dataclasses.replace(stiffness, material=run.law)
    return dataclasses.replace(system, stiffness=stiffness, **changes)


@dataclasses.dataclass(frozen=True)
class EnsembleSetup:
    """What the runs of an ensemble share and what is their own, on the host.

    Attributes:
        base: the problem of the shared system (run 0's, or the one given with members).
        n_runs: the runs.
        law: {field: (n_runs,)} the material law's fields that differ between runs.
        damping, stiffness_damping: (n_runs,) alpha [1/s] and beta [s], or None (shared).
        load_vectors: (n_runs, n_loads, n_nodes, 3) [dyn] or None; load_scale: (n_runs,
            n_loads) or None (the base's load vectors, shared).
        fixed_values: (n_runs, n_nodes, 3) [cm] or None; moving: (n_runs, n_moving,
            n_nodes, 3) [cm] or None (shared).
        initial_displacement, initial_velocity: (n_runs, n_nodes, 3) or None (the base's,
            for every run).
        member: run r's own problem, built on demand (messages, exact checks).
        problems: the problems given, or None (members).
    """

    base: Any
    n_runs: int
    law: dict
    damping: Any
    stiffness_damping: Any
    load_vectors: Any
    load_scale: Any
    fixed_values: Any
    moving: Any
    initial_displacement: Any
    initial_velocity: Any
    member: Callable[[int], Any]
    problems: tuple | None = None

    @property
    def varies(self) -> bool:
        """Whether the runs differ in material or damping (else the base's step and check hold)."""
        return bool(self.law) or self.damping is not None or self.stiffness_damping is not None

    def leaves(self):
        """Every per-run value (for the traced test)."""
        return (self.law, self.damping, self.stiffness_damping, self.load_vectors, self.load_scale,
                self.fixed_values, self.moving, self.initial_displacement, self.initial_velocity)

    def law_values(self) -> dict:
        """{field: (n_runs,)} of every field of :func:`law_fields`, the shared ones broadcast."""
        xp = jnp if is_traced(self.law, self.base.material) else np
        return {name: (xp.asarray(self.law[name], dtype=float) if name in self.law else
                       xp.full(self.n_runs, getattr(self.base.material, name), dtype=float))
                for name in law_fields(self.base.material)}

    def run_parameters(self, run: int) -> dict:
        """The trajectory parameters of run ``run`` that differ from the base's (concrete only)."""
        out = {}
        if self.law and not is_traced(self.law):
            m = dataclasses.replace(self.base.material, **{k: float(v[run]) for k, v in self.law.items()})
            out.update(E=float(m.E), nu=float(m.nu), rho=float(m.rho))
        for name in ("damping", "stiffness_damping"):
            value = getattr(self, name)
            if value is not None and not is_traced(value):
                out[name] = float(value[run])
        return out


def setup_of_members(problem, members: Members) -> EnsembleSetup:
    """The setup of ``problem`` run with each member's arrays (:class:`Members`)."""
    from ..fem._problem import Problem

    if not isinstance(problem, Problem):
        raise ProblemError("members= gives the runs of ONE problem: call jaxsync.ensemble(problem, n_steps, "
                           f"members=...), not with {type(problem).__name__}")
    if not isinstance(members, Members):
        raise ProblemError(f"members must be a jaxsync.Members, got {type(members).__name__}")
    n_runs = members.check(problem)

    def floats(x):
        return None if x is None else (x if is_traced(x) or isinstance(x, jax.Array) else np.asarray(x, float))

    return EnsembleSetup(
        base=problem, n_runs=n_runs, law={k: floats(v) for k, v in (members.material or {}).items()},
        damping=floats(members.damping), stiffness_damping=floats(members.stiffness_damping), load_vectors=None,
        load_scale=None if members.load_scale is None else _load_scale(members.load_scale, len(problem.loads)),
        fixed_values=None, moving=None, initial_displacement=floats(members.initial_displacement),
        initial_velocity=floats(members.initial_velocity), member=lambda r: members.problem(problem, r))


def setup_of_problems(problems: tuple) -> EnsembleSetup:
    """The setup of runs given as problems: each one's loads, Dirichlet values, initial
    conditions, material and damping; the rest must be run 0's (:func:`_difference`)."""
    first = problems[0]
    traced = any(is_traced(p.material, p.damping, p.stiffness_damping, p.loads, p.initial_displacement,
                           p.initial_velocity) for p in problems)
    for index, problem in enumerate(problems[1:], start=1):
        what = _difference(problem, first)
        if what is not None:
            raise ProblemError(
                f"problem {index} of the ensemble differs from problem 0 in its {what}: the runs of an "
                "ensemble share one system (mesh, element, material law, supports, density scale, constrained "
                "dofs and time functions) and may differ only in material parameters, damping, load "
                f"magnitudes, Dirichlet values and initial conditions; run problem {index} separately with "
                "jaxsync.simulate")
    xp = jnp if traced else np

    def per_run(values):
        """(n_runs,) of the values, or None when every run has run 0's."""
        if all(v is values[0] for v in values) or (not is_traced(values) and len(set(map(float, values))) == 1):
            return None
        return jnp.stack([jnp.asarray(v, dtype=float) for v in values]) if traced else np.asarray(values, float)

    law = {}
    for name in law_fields(first.material):
        values = per_run([getattr(p.material, name) for p in problems])
        if values is not None:
            law[name] = values
    if law:
        _check_law_fields(first, law)
    vectors, fixed_values, moving = [], [], []
    for problem in problems:
        loads, _ = problem.load_vectors()
        vectors.append(xp.stack([xp.asarray(v) for v in loads]) if loads else xp.zeros((0, problem.n_nodes, 3)))
        _, values, history = problem.prescribed()
        fixed_values.append(values)
        moving.append(xp.stack([xp.asarray(v) for v, _ in history]) if history else None)

    def fields(name):
        values = [getattr(p, name) for p in problems]
        if all(v is None for v in values):
            return None
        return xp.stack([xp.zeros((first.n_nodes, 3)) if v is None else xp.asarray(v, dtype=float) for v in values])

    return EnsembleSetup(
        base=first, n_runs=len(problems), law=law, damping=per_run([p.damping for p in problems]),
        stiffness_damping=per_run([p.stiffness_damping for p in problems]), load_vectors=xp.stack(vectors),
        load_scale=None, fixed_values=xp.stack([xp.asarray(v) for v in fixed_values]),
        moving=None if moving[0] is None else xp.stack(moving), initial_displacement=fields("initial_displacement"),
        initial_velocity=fields("initial_velocity"), member=lambda r: problems[r], problems=problems)


def _difference(problem, reference) -> str | None:
    """What ``problem`` has that its ensemble's runs must share but differs from run 0's, or None."""
    from ..fem.forces._follower import follower_loads

    mesh, ref_mesh = problem.mesh, reference.mesh
    if mesh is not ref_mesh and not (np.array_equal(mesh.points, ref_mesh.points)
                                     and np.array_equal(mesh.tets, ref_mesh.tets)):
        return "mesh (points or tetrahedra)"
    if problem.element != reference.element:
        return "element (P1 or P2)"
    law, ref_law = problem.material, reference.material
    if type(law) is not type(ref_law):
        return f"material law ({type(law).__name__}, not {type(ref_law).__name__})"
    _, times = problem.load_vectors()
    _, ref_times = reference.load_vectors()
    fixed, _, moving = problem.prescribed()
    ref_fixed, _, ref_moving = reference.prescribed()
    checks = (
        ("fibre directions", lambda: _same(getattr(law, "fibres", None), getattr(ref_law, "fibres", None))),
        ("lumped mass (density_scale)", lambda: _same(problem.density_scale, reference.density_scale)),
        ("number of loads", lambda: len(times) == len(ref_times)),
        ("constrained dofs (which dofs are fixed)", lambda: np.array_equal(fixed, ref_fixed)),
        ("prescribed-displacement time functions", lambda: len(moving) == len(ref_moving)
         and _same(tuple(g for _, g in moving), tuple(g for _, g in ref_moving))),
        ("elastic supports", lambda: _same(problem.supports, reference.supports)),
        ("load time functions (ramp, switch-off time, waveform)", lambda: _same(tuple(times), tuple(ref_times))),
        ("follower pressures (surfaces, magnitudes, time functions: one copy for all runs)",
         lambda: _same(tuple(follower_loads(problem)), tuple(follower_loads(reference)))),
    )
    for what, same in checks:
        if not same():
            return what
    return None


def _same(a, b) -> bool:
    """Equal pytrees: the same structure (node types included) and equal leaves."""
    leaves_a, tree_a = jax.tree_util.tree_flatten(a)
    leaves_b, tree_b = jax.tree_util.tree_flatten(b)
    if tree_a != tree_b:
        return False
    for x, y in zip(leaves_a, leaves_b):
        if x is y:
            continue
        if is_traced(x, y):  # traced values of the runs: unchecked
            continue
        if np.shape(x) != np.shape(y) or not np.array_equal(np.asarray(x), np.asarray(y)):
            return False
    return True


def batched_system(setup: EnsembleSetup, dt, n_steps: int | None = None) -> tuple[ExplicitSystem, RunData]:
    """(the shared system, the runs' own data) of an ensemble: one
    :func:`~jaxsync.fem.build_system` of the base problem, then the per-run
    arrays in the forms of the module docstring (no assembly per run). ``n_steps``: the
    steps every run takes, which choose the stiffness product's form as for one run of
    ``n_runs * n_steps`` steps (:func:`jaxsync.fem.forces.run_force_model`: the
    batched product streams every run's field); None: the fused form."""
    from ..fem._assembly import lumped_mass
    from ..fem.forces._internal_force import Preassembled, run_force_model
    from ..fem.forces._support import dashpot, dashpot_blocks
    from ..fem.materials._linear_elastic import first_lame, shear_modulus

    base, n = setup.base, setup.n_runs
    model = Preassembled() if n_steps is None else run_force_model(Preassembled(), base, n * n_steps)
    system = build_system(base, dt, model)
    run = {}
    if setup.load_vectors is not None:
        run["load_vectors"] = jnp.asarray(setup.load_vectors, dtype=float)
    if setup.load_scale is not None:
        run["load_scale"] = jnp.asarray(setup.load_scale, dtype=float)
    if setup.fixed_values is not None:
        run["fixed_values"] = jnp.asarray(setup.fixed_values, dtype=float)
    if setup.moving is not None:
        run["moving"] = jnp.asarray(setup.moving, dtype=float)
    for name in ("damping", "stiffness_damping"):
        if getattr(setup, name) is not None:
            run[name] = jnp.asarray(getattr(setup, name), dtype=float)
    law = setup.law
    values = setup.law_values() if law else {}
    if "rho" in law:  # M = rho M_1, as Problem.lumped_mass forms it
        unit = jnp.asarray(lumped_mass(base.space, base.density_scale))
        run["mass"] = jnp.repeat((jnp.asarray(values["rho"])[:, None] * unit[None, :])[:, :, None], 3, axis=2)
    if base.material.finite_strain:
        if any(k != "rho" for k in law):  # the law's parameters, every leaf with the runs axis
            held = system.stiffness.material
            broadcast = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(jnp.asarray(x, dtype=float), (n,)
                                                                          + jnp.shape(x)), held)
            run["law"] = dataclasses.replace(broadcast, **{k: jnp.asarray(v, dtype=float) for k, v in law.items()})
    elif "E" in law or "nu" in law:  # K = lambda K_lambda + mu K_mu from the two unit operators
        K_lambda, K_mu = model.unit_operators(base)
        if "nu" not in law:  # one copy of K(E=1, nu), E per run as its scale
            nu = base.material.nu
            lam, mu = first_lame(1.0, nu), shear_modulus(1.0, nu)
            blocks = jax.tree_util.tree_map(lambda a, b: lam * a + mu * b, K_lambda.blocks, K_mu.blocks)
            system = dataclasses.replace(system, stiffness=dataclasses.replace(K_lambda, blocks=blocks))
            run["stiffness_scale"] = jnp.asarray(values["E"], dtype=float)
        else:  # blocks per run
            E, nu = jnp.asarray(values["E"]), jnp.asarray(values["nu"])
            lam, mu = first_lame(E, nu), shear_modulus(E, nu)

            def combine(a, b):
                shape = (n,) + (1,) * a.ndim
                return lam.reshape(shape) * a[None] + mu.reshape(shape) * b[None]

            run["stiffness_blocks"] = jax.tree_util.tree_map(combine, K_lambda.blocks, K_mu.blocks)
            system = dataclasses.replace(system, stiffness=K_lambda)
    if system.dashpot is not None and ("mass" in run or "damping" in run):
        mass = run.get("mass", jnp.broadcast_to(system.mass, (n,) + system.mass.shape))
        damping = run.get("damping", jnp.broadcast_to(system.damping, (n,)))
        run["dashpot"] = jax.vmap(dashpot, in_axes=(0, 0, None, None, None))(mass, damping, system.dt,
                                                                             dashpot_blocks(base), system.fixed)
    return system, RunData(**run)


@jax.jit
def _member_starts(system, runs, adjacency, unit_mass, rho, d0, v0):
    """(d0, d(-1)) of every run (:func:`jaxsync.fem.initial_state`'s start, vmapped),
    the consistent mass rho_r M_1 (M_1's blocks under the scale rho_r)."""
    from ..fem._sparse import BlockEll
    from ..fem._stepper import start_levels

    def one(run, rho, d0, v0):
        mass = BlockEll(adjacency, unit_mass, symmetric=True, scale=rho)
        return start_levels(member_system(system, run), mass, d0, v0)

    return jax.vmap(one)(runs, rho, d0, v0)


def initial_states(setup: EnsembleSetup, system: ExplicitSystem, runs: RunData) -> SolverState:
    """The runs' states before step 0, stacked on a leading runs axis (the start of
    :func:`jaxsync.fem.initial_state`, every run in one vmapped program)."""
    from ..fem._assembly import consistent_mass
    from ..fem._reference_element import n_quadrature_points
    from ..fem._sparse import block_ell_values

    base, n = setup.base, setup.n_runs
    shape = (n, base.n_nodes, 3)

    def field(value, own):
        if value is not None:
            return jnp.asarray(value, dtype=float)
        return jnp.zeros(shape) if own is None else jnp.broadcast_to(jnp.asarray(own, dtype=float), shape)

    d0 = field(setup.initial_displacement, base.initial_displacement)
    v0 = field(setup.initial_velocity, base.initial_velocity)
    adjacency, _, _, M_1 = base.operators.block_ell
    if base.density_scale is not None:
        M_1 = block_ell_values(consistent_mass(base.mesh, base.density_scale), adjacency)
    rho = setup.law_values()["rho"] if "rho" in setup.law else jnp.full(n, base.material.rho, dtype=float)
    d0, previous = _member_starts(system, runs, jnp.asarray(adjacency), jnp.asarray(M_1), jnp.asarray(rho, dtype=float),
                           d0, v0)
    variables = base.material.internal_variables(base.mesh.n_elements, n_quadrature_points(base.space))
    variables = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (n,) + jnp.shape(x)), variables)
    return SolverState(d0, previous, jnp.zeros(n, dtype=jnp.int32), variables)
