"""The members of an ensemble: what its runs share and what is their own, set up in one
vectorised pass.

:func:`jaxsync.ensemble` advances n_runs runs of one system (mesh, element, supports,
constrained dofs, load and prescribed-displacement time functions, density scaling)
under ``jax.vmap``. Each run (member) may have its own

* material parameters: the scalar fields of the problem's material law (E, nu, rho of
  :class:`jaxsync.LinearElastic` and :class:`jaxsync.NeoHookean`; k1, k2... of a law of
  more parameters), mass-proportional damping alpha and stiffness-proportional damping
  beta;
* load magnitudes (a factor per load, or whole load vectors when the members are given
  as problems) and the values of the Dirichlet conditions (the prescribed dofs shared);
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
from ..pytree import is_traced, pytree_dataclass
from ._members import Members, check_law_fields, law_fields, load_factors, prescribed_values

__all__ = ["RunData", "EnsembleSetup", "setup_of_members", "setup_of_problems", "member_system",
           "batched_system", "initial_states"]


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

    fixed_values, moving = (None, None) if members.dirichlet is None else prescribed_values(problem, members.dirichlet)

    return EnsembleSetup(
        base=problem, n_runs=n_runs, law={k: floats(v) for k, v in (members.material or {}).items()},
        damping=floats(members.damping), stiffness_damping=floats(members.stiffness_damping), load_vectors=None,
        load_scale=None if members.load_scale is None else load_factors(members.load_scale, len(problem.loads)),
        fixed_values=fixed_values, moving=moving, initial_displacement=floats(members.initial_displacement),
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
        check_law_fields(first, law)
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
