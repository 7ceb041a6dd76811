"""Problems described by TOML files (the ``jaxsync simulate`` input).

Layout (every table optional; defaults give the paper's cantilever)::

    [mesh]                      # either a file ...
    file = "vessel.msh"         # any meshio-readable tetrahedral mesh, or a SimVascular
                                # mesh folder (mesh-complete.mesh.vtu, mesh-surfaces/*.vtp:
                                # one facet set per face, named after the file)
    # ... or a generated left coronary tree (jaxsync.coronary_mesh; facet sets inlet,
    # outlet_1 .. outlet_6, outlet, lumen, outer) ...
    generate = "coronary_tree"
    target_elements = 8000      # tetrahedra, 5k to 400k
    # ... or the generated box beam (the default)
    length = 25.0
    width = 1.0
    height = 1.0
    divisions = [25, 1, 1]

    [material]
    model = "linear-elastic"    # (the default) or "neo-hookean", "nearly-incompressible-
                                # neo-hookean", "holzapfel-gasser-ogden", "standard-linear-
                                # solid" (E, nu, rho, beta, tau [s]): the catalogue
                                # jaxsync.app.config_schema.MATERIAL_MODELS; each law's keys
                                # are the fields of its class
    E = 1.0e6                   # dyn/cm^2 (all but holzapfel-gasser-ogden)
    nu = 0.3
    rho = 1.0                   # g/cm^3
    # holzapfel-gasser-ogden: mu, k1 (dyn/cm^2), k2, kappa_bulk (dyn/cm^2), fibre_angle
    # (degrees from the circumferential direction), fibre_axis = [x, y, z] are required;
    # rho (1.0), dispersion (0.0) and fibre_origin = [x, y, z] (a point on the axis,
    # [0, 0, 0]) optional. The fibres are jaxsync.helical_fibres of the element centroids.

    [problem]
    kind = "cantilever"         # or "general" (then give [[dirichlet]] and loads)
    element = "P1"              # or "P2": quadratic tetrahedra (bending, nu -> 0.5); the
                                # default is P2 on a quadratic (tetra10) mesh, else P1
    damping = 0.5               # alpha, 1/s (C = alpha M + beta K)
    stiffness_damping = 0.0     # beta, s (optional; damps a mode of frequency omega at
                                # (alpha + beta omega^2) / 2 and lowers the stable step)
    body_force = [0.0, 0.0, -0.5]
    t_ramp = 1.0
    # t_off = 3.0

    [[dirichlet]]               # kind = "general" only
    facet = "inlet"             # a facet set of the mesh, or
    # plane = { axis = 0, value = 0.0 }   # nodes with x == 0
    value = [0.0, 0.0, 0.0]
    components = [0, 1, 2]

    [[body_force]]              # kind = "general" only
    vector = [0.0, 0.0, -0.5]
    t_ramp = 1.0                # optional: the time keys of [[pressure]]

    [[pressure]]                # kind = "general" only
    surface = "lumen"
    magnitude = 1.0             # barye (times the waveform; default 1)
    t_ramp = 1.0
    period = 0.833              # optional periodic waveform ...
    times = [0.0, 0.4, 0.833]   # ... given by samples
    values = [1.067e5, 1.6e5, 1.067e5]
    # follower = true           # act on the deformed surface (hyperelastic [material] only)

    [[traction]]                # kind = "general" only: force per area in a fixed direction
    surface = "x1"
    vector = [0.0, 0.0, -10.0]  # dyn/cm^2 (times the time function, as for pressure)
    t_ramp = 1.0

    [[support]]                 # kind = "general" only: tissue around the wall (Robin)
    surface = "outer"
    stiffness = 1.0e6           # k_s, dyn/cm^3
    damping = 1.0e3             # c_s, dyn s/cm^3 (lumped dashpot)
    normal_only = false         # true: along the surface normal only

Every load and ``[[dirichlet]]`` entry takes the same time keys: ``t_ramp`` (a ramp to 1),
``period`` with ``times`` and ``values`` (one period of a waveform, sampled), ``t_off`` (off
from then on); a load without them is constant, and a ``[[dirichlet]]`` entry with them
prescribes a history: ``value`` times that time function. The run and the imaged geometry::

    [run]
    n_steps = 20000
    save_every = 100
    # dt = 2.0e-4               # default: the CFL step (of the mass-scaled problem)
    # mass_scaling_dt = 5.0e-6  # artificial mass scaling to this step [s], or
    # mass_scaling_beta = 2.5   # ... to beta times the CFL step (give at most one)
    output = "trajectory.h5"
    # xdmf = "trajectory.xdmf"
    # vtu = "trajectory"        # VTU series: trajectory.pvd and trajectory/trajectory_*.vtu
    # checkpoint = "run.ckpt.h5"
    # checkpoint_every = 10000

    [zero_pressure]             # the mesh is imaged under a pressure: jaxsync unload writes its unloaded
    pressure = 1.6e5            # geometry; barye, every follower [[pressure]] (default: their magnitudes)
    method = "newton"           # or "fixed-point" (backward displacement)
    tol = 1.0e-10
    max_iter = 50
    load_steps = 4
    output = "unloaded.vtu"     # .vtu, .vtk or .msh, facet sets kept
    start = "unloaded"          # jaxsync simulate runs from the unloaded geometry, or "prestressed" (the
                                # imaged geometry with its prestress), or "imaged" (as it is)
    prestress = "zero-pressure" # start = "prestressed": the route of jaxsync.prestress, or "mulf"

Types are checked: numbers are TOML numbers (``E = 6.26e6``, not ``"6.26e6"``), counts are
TOML integers (``n_steps = 20000``, not ``2e4``), vectors are lists of 3 numbers, names and
paths are strings; anything else is a :class:`ConfigError` naming the table and key. The
keys of ``[material]`` (those of its model), of ``[run]`` (:class:`RunConfig`) and of the
array tables (:class:`jaxsync.Dirichlet`, :class:`jaxsync.BodyForce`,
:class:`jaxsync.Pressure`, :class:`jaxsync.Traction`, :class:`jaxsync.ElasticSupport`), their
kinds and the required ones are read from the fields of the classes they configure
(:mod:`jaxsync.app.config_schema`, whose catalogue maps the model names to the laws).

Relative paths in a file (``[mesh] file``, ``[run] output``, ``xdmf``, ``vtu``, ``checkpoint``,
``[zero_pressure] output``) are
taken relative to the folder of the TOML file, so a case folder can be run from anywhere;
the outputs of the packaged default configuration go to the current directory.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import tomllib
from importlib import resources
from typing import Any

from ..cases import cantilever
from ..errors import ConfigError, JaxsyncError
from ..fem._problem import Problem
from ..mesh import Mesh, box_beam, read_mesh
from ..options import Element, MeshGenerator, ProblemKind, check_option
from .config_schema import (
    BOUNDARY_TABLES,
    DEFAULT_MATERIAL_MODEL,
    MATERIAL_MODELS,
    TomlPath,
    dataclass_schema,
    from_table,
)

__all__ = ["RunConfig", "load_config", "check_config", "default_config_path", "problem_from_config"]

# Entry types: "number" (int or float, not bool), "int", "string", "path" (a string,
# resolved against the TOML file's folder), (type, n) a list of n entries of that type
# (n None: any length >= 1), or a dict for an inline table. A table's schema is a dict of its
# keys, or a function (table, origin) -> dict where the keys depend on the table ([material]:
# those of its model). The tables that configure a class are read from its fields
# (jaxsync.app.config_schema): [material] from its law, [run] from RunConfig, and the array
# tables of loads, supports and prescribed motions from BOUNDARY_TABLES.
@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Run options of a configuration file (see the module docstring)."""

    n_steps: int = 20000
    save_every: int = 100
    dt: float | None = None
    output: TomlPath = "trajectory.h5"
    xdmf: TomlPath | None = None
    vtu: TomlPath | None = None
    """Prefix of a VTU series (``<vtu>.pvd`` and ``<vtu>/``; :meth:`jaxsync.Trajectory.to_vtu`)."""
    checkpoint: TomlPath | None = None
    checkpoint_every: int | None = None
    mass_scaling_dt: float | None = None
    mass_scaling_beta: float | None = None
    added_mass_percent: float | None = None
    """Total mass added by the mass scaling [%] (None: no mass scaling)."""


_RUN = dataclass_schema(RunConfig, exclude=("added_mass_percent",))  # the result of the scaling, not a key
_SCHEMA: dict[str, Any] = {
    "mesh": {"file": "path", "generate": "string", "target_elements": "int", "length": "number",
             "width": "number", "height": "number", "divisions": ("int", 3)},
    "material": lambda table, origin: _material_schema(table, origin),  # the keys of its model
    "problem": {"kind": "string", "element": "string", "damping": "number", "stiffness_damping": "number",
                "body_force": ("number", 3), "t_ramp": "number", "t_off": "number"},
    "run": dict(_RUN.keys),
    **{name: dict(table.schema.keys) for name, table in BOUNDARY_TABLES.items()},
    "zero_pressure": {"pressure": "number", "method": "string", "tol": "number", "max_iter": "int",
                      "load_steps": "int", "output": "path", "start": "string", "prestress": "string"},
}
_ARRAY_TABLES = tuple(BOUNDARY_TABLES)
_PATH_KEYS = (("mesh", "file"), *(("run", key) for key, kind in _RUN.keys.items() if kind == "path"),
              ("zero_pressure", "output"))


def default_config_path() -> str:
    """Path of the packaged cantilever configuration."""
    return str(resources.files("jaxsync") / "data" / "cantilever.toml")


def load_config(path: str | os.PathLike | None = None) -> dict:
    """Read and check a TOML configuration (the packaged cantilever when None).

    Unknown tables or keys and entries of the wrong type raise :class:`ConfigError`.
    Relative paths in the file (``[mesh] file``, ``[run] output``, ``xdmf``, ``vtu``,
    ``checkpoint``) are returned joined to the file's folder, except for the packaged
    configuration, whose outputs stay relative to the current directory."""
    packaged = path is None or _is_packaged(os.fspath(path))
    path = default_config_path() if path is None else os.fspath(path)
    try:
        with open(path, "rb") as f:
            config = tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(f"configuration file {path!r} does not exist") from None
    except IsADirectoryError:
        raise ConfigError(f"configuration file {path!r} is a folder; give a .toml file") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: invalid TOML: {exc}") from exc
    except UnicodeDecodeError:  # TOML is UTF-8 text: a binary file (an .h5 given in place of the .toml)
        raise ConfigError(f"configuration file {path!r} is not a TOML text file (it holds binary data: an HDF5 "
                          "trajectory or surrogate given in place of the configuration?); give the .toml "
                          "problem file, e.g. jaxsync simulate problem.toml") from None
    except PermissionError:
        raise ConfigError(f"configuration file {path!r} cannot be read (permission denied)") from None
    check_config(config, origin=path)
    if not packaged:
        base = os.path.dirname(path)
        for table, key in _PATH_KEYS:
            if key in config.get(table, {}):
                value = os.path.expanduser(config[table][key])
                config[table][key] = value if os.path.isabs(value) else os.path.join(base, value)
    return config


def _is_packaged(path: str) -> bool:
    try:
        return os.path.samefile(path, default_config_path())
    except OSError:
        return False


def check_config(config: dict, origin: str = "configuration") -> None:
    """Raise :class:`ConfigError` for unknown tables or keys and for entries of the wrong
    type (see the module docstring); ``origin`` (the file name) starts each message."""
    if not isinstance(config, dict):
        raise ConfigError(f"{origin}: a configuration is a dictionary of tables, got "
                          f"{type(config).__name__}")
    for table, value in config.items():
        if table not in _SCHEMA:
            raise ConfigError(f"{origin}: unknown table [{table}]; known: {', '.join(sorted(_SCHEMA))}")
        if table in _ARRAY_TABLES:
            if not isinstance(value, list) or not all(isinstance(e, dict) for e in value):
                raise ConfigError(f"{origin}: {table!r} must be an array of tables: write each "
                                  f"entry under its own [[{table}]] header (two brackets)")
            entries = [(f"[[{table}]] #{i}", entry) for i, entry in enumerate(value)]
        else:
            if not isinstance(value, dict):
                raise ConfigError(f"{origin}: {table!r} must be a table: write its entries "
                                  f"under a [{table}] header")
            entries = [(f"[{table}]", value)]
        for where, entry in entries:
            schema = _SCHEMA[table]
            _check_table(entry, schema(entry, origin) if callable(schema) else schema, where, origin)
            if table in BOUNDARY_TABLES:
                _check_required(entry, BOUNDARY_TABLES[table].schema, where, origin)
    _check_material(config.get("material", {}), origin)
    run = config.get("run", {})
    if "mass_scaling_dt" in run and "mass_scaling_beta" in run:
        raise ConfigError(f"{origin}: [run] gives both mass_scaling_dt and mass_scaling_beta; "
                          "give only one (the target step in s, or its ratio to the CFL step)")
    for key in ("mass_scaling_dt", "mass_scaling_beta"):
        if key in run and not run[key] > 0:
            raise ConfigError(f"{origin}: [run] {key} = {run[key]!r} must be positive")


def _material_schema(material: dict, origin: str) -> dict:
    """The [material] keys: ``model`` and the keys of that model (:mod:`jaxsync.app.config_schema`);
    ConfigError for a key that no model takes (known: those of every model) or an
    unknown model."""
    known = {"model": "string"}
    for entry in MATERIAL_MODELS.values():
        known.update({k: v for k, v in entry.schema.keys.items() if k not in known})
    unknown = set(material) - set(known)
    if unknown:
        raise ConfigError(f"{origin}: unknown key(s) {sorted(unknown)} in [material]; known: {sorted(known)}")
    model = material.get("model", DEFAULT_MATERIAL_MODEL)
    if "model" in material:
        _check_entry(model, "string", "[material] model", "model", origin)
    if model not in MATERIAL_MODELS:
        models = ", ".join(f'"{m}"' for m in MATERIAL_MODELS)
        raise ConfigError(f"{origin}: [material] model = {_shown(model)} is not a material model; allowed: {models}")
    schema = MATERIAL_MODELS[model].schema
    foreign = [k for k in material if k not in schema.keys and k != "model"]
    if foreign:
        raise ConfigError(f"{origin}: [material] key(s) {', '.join(sorted(foreign))} are not parameters of model = "
                          f"\"{model}\"; its keys: model, {', '.join(schema.keys)}")
    return {"model": "string", **schema.keys}


def _check_material(material: dict, origin: str) -> None:
    """The keys that the [material] model needs (the others are checked by its schema)."""
    model = material.get("model", DEFAULT_MATERIAL_MODEL)
    _check_required(material, MATERIAL_MODELS[model].schema, f"[material] model = \"{model}\"", origin,
                    leading=("model",))


def _material(material: dict, mesh):
    """The material law of a checked [material] table (:data:`jaxsync.app.config_schema.MATERIAL_MODELS`)."""
    return MATERIAL_MODELS[material.get("model", DEFAULT_MATERIAL_MODEL)].build(material, mesh)


def _check_required(entry: dict, schema, where: str, origin: str, leading=()) -> None:
    """ConfigError naming the required keys of ``schema`` that ``entry`` lacks (``leading``:
    keys of the table listed before the schema's, as ``model`` of [material])."""
    missing = [key for key in schema.required if key not in entry]
    if missing:
        raise ConfigError(f"{origin}: {where} needs {', '.join(missing)}; its keys: "
                          f"{', '.join((*leading, *schema.keys))} ({', '.join(schema.required)} required)")


def _check_table(entry: dict, schema: dict, where: str, origin: str) -> None:
    unknown = set(entry) - set(schema)
    if unknown:
        raise ConfigError(f"{origin}: unknown key(s) {sorted(unknown)} in {where}; "
                          f"known: {sorted(schema)}")
    for key, value in entry.items():
        _check_entry(value, schema[key], f"{where} {key}", key, origin)


_EXPECTED = {"number": "a number (int or float)", "int": "an integer",
             "string": "a string", "path": "a path (a string)", "bool": "true or false"}


def _expected(spec) -> str:
    if isinstance(spec, dict):
        inner = ", ".join(f"{k} = <{_EXPECTED[v].split(' (')[0].removeprefix('a ').removeprefix('an ')}>"
                          for k, v in spec.items())
        return f"an inline table {{ {inner} }}"
    if isinstance(spec, tuple):
        kind, n = spec
        noun = {"number": "numbers", "int": "integers", "string": "strings"}[kind]
        return f"a list of {n} {noun}" if n else f"a non-empty list of {noun}"
    return _EXPECTED[spec]


def _shown(value) -> str:
    """A value as it reads in TOML."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list):
        return "[" + ", ".join(_shown(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {_shown(v)}" for k, v in value.items()) + " }"
    return repr(value)


def _kind_of(value) -> str:
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, int):
        return "an integer"
    if isinstance(value, float):
        return "a float" if math.isfinite(value) else "not finite"
    if isinstance(value, list):
        return f"a list of {len(value)}"
    if isinstance(value, dict):
        return "a table"
    return f"a {type(value).__name__}"


def _scalar_ok(value, kind: str) -> bool:
    if kind == "bool":
        return isinstance(value, bool)
    if kind == "number":
        return (isinstance(value, (int, float)) and not isinstance(value, bool)
                and math.isfinite(value))
    if kind == "int":
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, str) and (kind != "path" or value != "")


def _hint(value, kind: str, key: str) -> str:
    if kind in ("number", "int") and isinstance(value, str):
        try:
            number = float(value)
        except ValueError:
            return ""
        if kind == "number" or number.is_integer():
            text = value.strip() if kind == "number" else str(int(number))
            return f": write {key} = {text} without the quotes"
    if kind == "int" and isinstance(value, float) and value.is_integer():
        return f": write {key} = {int(value)} (a TOML integer has no decimal point or exponent)"
    return ""


def _check_entry(value, spec, where: str, key: str, origin: str) -> None:
    def fail(detail: str, hint: str = "") -> ConfigError:
        return ConfigError(f"{origin}: {where} = {_shown(value)} {detail}; expected "
                           f"{_expected(spec)}{hint}")

    if isinstance(spec, dict):
        if not isinstance(value, dict):
            raise fail(f"is {_kind_of(value)}")
        missing = [k for k in spec if k not in value]
        if missing:
            raise fail(f"lacks {', '.join(missing)}")
        unknown = set(value) - set(spec)
        if unknown:
            raise fail(f"has unknown key(s) {sorted(unknown)}")
        for k, v in value.items():
            if not _scalar_ok(v, spec[k]):
                raise fail(f"has {k} = {_shown(v)}, {_kind_of(v)}", _hint(v, spec[k], k))
        return
    if isinstance(spec, tuple):
        kind, n = spec
        if not isinstance(value, list):
            raise fail(f"is {_kind_of(value)}")
        if (n is not None and len(value) != n) or not value:
            raise fail(f"has {len(value)} entries")
        for i, v in enumerate(value):
            if not _scalar_ok(v, kind):
                raise fail(f"has entry {i} = {_shown(v)}, {_kind_of(v)}")
        return
    if not _scalar_ok(value, spec):
        raise fail(f"is {_kind_of(value)}" if not (spec == "path" and value == "")
                   else "is empty", _hint(value, spec, key))


def problem_from_config(config: dict, *, mesh_file: str | Mesh | None = None,
                        mass_scaling_dt: float | None = None,
                        mass_scaling_beta: float | None = None,
                        element: Element | None = None) -> tuple[Problem, RunConfig]:
    """Build the problem and run options of a configuration dictionary.

    ``mesh_file`` (a file name, or a :class:`jaxsync.Mesh`) overrides ``[mesh] file`` and
    ``element`` ``[problem] element``;
    ``mass_scaling_dt`` or ``mass_scaling_beta`` (at most one) override the ``[run]`` mass
    scaling. With mass scaling, the returned problem is the scaled one (its ``dt``, the
    default step, is the target step) and ``RunConfig.added_mass_percent`` the added mass;
    :func:`jaxsync.mass_scaling` warns (:class:`jaxsync.MassScalingWarning`) above 10 %.
    Errors of the package's own types."""
    check_config(config)
    if mass_scaling_dt is not None and mass_scaling_beta is not None:
        raise ConfigError("give only one of mass_scaling_dt (the target step in s) and "
                          "mass_scaling_beta (its ratio to the CFL step)")
    for name, value in (("mass_scaling_dt", mass_scaling_dt), ("mass_scaling_beta", mass_scaling_beta)):
        if value is not None and not (isinstance(value, (int, float)) and not isinstance(value, bool)
                                      and math.isfinite(value) and value > 0):
            raise ConfigError(f"{name} must be a positive number, got {value!r}")
    if element is not None:
        check_option("element", element, Element)
    try:
        return _problem_from_config(config, mesh_file, mass_scaling_dt, mass_scaling_beta, element)
    except JaxsyncError:
        raise
    except (TypeError, ValueError, KeyError) as exc:
        raise ConfigError(f"bad configuration value: {exc}") from exc


def _problem_from_config(config: dict, mesh_file: str | None, scaling_dt, scaling_beta, element):
    mesh_cfg = config.get("mesh", {})
    file = mesh_file or mesh_cfg.get("file")
    generator = check_option("[mesh] generate", mesh_cfg.get("generate", "box_beam"), MeshGenerator)
    if isinstance(file, Mesh):
        mesh = file
    elif file:
        mesh = read_mesh(file)
    elif generator == "coronary_tree":
        from ..cases import coronary_mesh

        mesh = coronary_mesh(target_elements=mesh_cfg.get("target_elements"))
    else:
        mesh = box_beam(float(mesh_cfg.get("length", 25.0)), float(mesh_cfg.get("width", 1.0)),
                        float(mesh_cfg.get("height", 1.0)),
                        tuple(int(n) for n in mesh_cfg.get("divisions", (25, 1, 1))))
    material = _material(config.get("material", {}), mesh)
    prob = config.get("problem", {})
    kind = check_option("[problem] kind", prob.get("kind", "cantilever"), ProblemKind)
    element = element or prob.get("element")
    if element is not None:
        check_option("[problem] element", element, Element)
    damping = float(prob.get("damping", 0.5))
    stiffness_damping = float(prob.get("stiffness_damping", 0.0))
    if kind == "cantilever":
        for table in ("dirichlet", "body_force", "pressure", "traction", "support"):
            if table in config:
                raise ConfigError(f"[[{table}]] is only used with kind = \"general\"; the "
                                  "cantilever sets its own clamp and load")
        t_off = prob.get("t_off")
        problem = cantilever(mesh, body_force=tuple(float(x) for x in prob.get("body_force", (0.0, 0.0, -0.5))),
                             damping=damping, stiffness_damping=stiffness_damping,
                             t_ramp=float(prob.get("t_ramp", 1.0)),
                             t_off=None if t_off is None else float(t_off), material=material, element=element)
    else:  # "general"
        cantilever_keys = [key for key in ("body_force", "t_ramp", "t_off") if key in prob]
        if cantilever_keys:
            raise ConfigError(f"[problem] {', '.join(cantilever_keys)}: only used with kind = \"cantilever\"; a "
                              "general problem takes its loads from [[body_force]], [[pressure]] and [[traction]] "
                              "tables (each with its own t_ramp, t_off...)")
        tables = {name: _entries(config, name, mesh) for name in BOUNDARY_TABLES}
        problem = Problem(mesh=mesh, material=material, damping=damping, stiffness_damping=stiffness_damping,
                          element=element, dirichlet=tables["dirichlet"],
                          loads=tables["body_force"] + tables["pressure"] + tables["traction"],
                          supports=tables["support"])
    run = config.get("run", {})
    if scaling_dt is None and scaling_beta is None:  # no override: the file's
        scaling_dt, scaling_beta = run.get("mass_scaling_dt"), run.get("mass_scaling_beta")
    percent = None
    if scaling_dt is not None or scaling_beta is not None:
        from ..fem._timestep import mass_scaling

        problem, percent = mass_scaling(
            problem, None if scaling_beta is None else float(scaling_beta),
            dt_target=None if scaling_dt is None else float(scaling_dt))
    # the [run] keys given, coerced as RunConfig's fields take them (the others keep its defaults), and
    # the mass scaling applied (the options' override of the file's)
    run_config = from_table(RunConfig, run, _RUN, extra={
        "mass_scaling_dt": None if scaling_dt is None else float(scaling_dt),
        "mass_scaling_beta": None if scaling_beta is None else float(scaling_beta),
        "added_mass_percent": percent})
    return problem, run_config


def _entries(config: dict, name: str, mesh) -> tuple:
    """The instances of the checked array table ``[[name]]`` (:data:`BOUNDARY_TABLES`)."""
    out = []
    for i, entry in enumerate(config.get(name, [])):
        try:
            out.append(BOUNDARY_TABLES[name].build(entry, mesh))
        except ConfigError as exc:
            raise ConfigError(f"[[{name}]] #{i}: {exc}") from None
    return tuple(out)
