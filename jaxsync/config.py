"""Problems described by TOML files (the ``jaxsync simulate`` input).

Layout (every table optional; defaults give the paper's cantilever)::

    [mesh]                      # either a file ...
    file = "vessel.msh"         # any meshio-readable tetrahedral mesh
    # ... or the generated box beam
    length = 25.0
    width = 1.0
    height = 1.0
    divisions = [25, 1, 1]

    [material]
    E = 1.0e6                   # dyn/cm^2
    nu = 0.3
    rho = 1.0                   # g/cm^3

    [problem]
    kind = "cantilever"         # or "general" (then give [[dirichlet]] and loads)
    damping = 0.5               # alpha, 1/s
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
    t_ramp = 1.0                # optional ramp; t_off optional

    [[pressure]]                # kind = "general" only
    surface = "lumen"
    magnitude = 1.0             # barye (times the waveform)
    t_ramp = 1.0
    period = 0.833              # optional periodic waveform ...
    times = [0.0, 0.4, 0.833]   # ... given by samples
    values = [1.067e5, 1.6e5, 1.067e5]

    [run]
    n_steps = 20000
    save_every = 100
    # dt = 2.0e-4               # default: the CFL step
    output = "trajectory.h5"
    # xdmf = "trajectory.xdmf"
    # checkpoint = "run.ckpt.h5"
"""

from __future__ import annotations

import dataclasses
import os
import tomllib
from importlib import resources
from typing import Any

import numpy as np

from .errors import ConfigError, JaxsyncError
from .loads import BodyForce, Constant, Periodic, Pressure, Ramp, StepOff
from .material import LinearElastic
from .mesh import box_beam, read_mesh
from .problem import Dirichlet, Problem, cantilever

__all__ = ["RunConfig", "load_config", "default_config_path", "problem_from_config"]

_KNOWN = {
    "mesh": {"file", "length", "width", "height", "divisions"},
    "material": {"E", "nu", "rho"},
    "problem": {"kind", "damping", "body_force", "t_ramp", "t_off"},
    "run": {"n_steps", "save_every", "dt", "output", "xdmf", "checkpoint", "checkpoint_every"},
    "dirichlet": {"facet", "plane", "value", "components"},
    "body_force": {"vector", "t_ramp", "t_off"},
    "pressure": {"surface", "magnitude", "t_ramp", "t_off", "period", "times", "values"},
}


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Run options of a configuration file (see the module docstring)."""

    n_steps: int = 20000
    save_every: int = 100
    dt: float | None = None
    output: str = "trajectory.h5"
    xdmf: str | None = None
    checkpoint: str | None = None
    checkpoint_every: int | None = None


def default_config_path() -> str:
    """Path of the packaged cantilever configuration."""
    return str(resources.files("jaxsync") / "data" / "cantilever.toml")


def load_config(path: str | os.PathLike | None = None) -> dict:
    """Read and check a TOML configuration (the packaged cantilever when None)."""
    path = default_config_path() if path is None else os.fspath(path)
    try:
        with open(path, "rb") as f:
            config = tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(f"configuration file {path!r} does not exist") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: invalid TOML: {exc}") from exc
    for table, value in config.items():
        if table not in _KNOWN:
            raise ConfigError(f"{path}: unknown table [{table}]; known: {', '.join(sorted(_KNOWN))}")
        entries = value if isinstance(value, list) else [value]
        for entry in entries:
            unknown = set(entry) - _KNOWN[table]
            if unknown:
                raise ConfigError(f"{path}: unknown key(s) {sorted(unknown)} in [{table}]; "
                                  f"known: {sorted(_KNOWN[table])}")
    return config


def _time_function(entry: dict, where: str):
    t_ramp, t_off = entry.get("t_ramp"), entry.get("t_off")
    g = Ramp(float(t_ramp)) if t_ramp else Constant()
    if "period" in entry:
        if "times" not in entry or "values" not in entry:
            raise ConfigError(f"{where}: a periodic waveform needs 'times' and 'values'")
        wave = Periodic(np.asarray(entry["times"], float), np.asarray(entry["values"], float),
                        float(entry["period"]))
        g = wave if isinstance(g, Constant) else g * wave
    if t_off is not None:
        g = StepOff(float(t_off), g)
    return g


def problem_from_config(config: dict, *, mesh_file: str | None = None) -> tuple[Problem, RunConfig]:
    """Build the problem and run options of a configuration dictionary.

    ``mesh_file`` overrides ``[mesh] file``. Errors of the package's own types."""
    try:
        return _problem_from_config(config, mesh_file)
    except JaxsyncError:
        raise
    except (TypeError, ValueError, KeyError) as exc:
        raise ConfigError(f"bad configuration value: {exc}") from exc


def _problem_from_config(config: dict, mesh_file: str | None):
    mesh_cfg = config.get("mesh", {})
    file = mesh_file or mesh_cfg.get("file")
    if file:
        mesh = read_mesh(file)
    else:
        mesh = box_beam(float(mesh_cfg.get("length", 25.0)), float(mesh_cfg.get("width", 1.0)),
                        float(mesh_cfg.get("height", 1.0)),
                        tuple(int(n) for n in mesh_cfg.get("divisions", (25, 1, 1))))
    mat = config.get("material", {})
    material = LinearElastic(float(mat.get("E", 1.0e6)), float(mat.get("nu", 0.3)),
                             float(mat.get("rho", 1.0)))
    prob = config.get("problem", {})
    kind = prob.get("kind", "cantilever")
    damping = float(prob.get("damping", 0.5))
    if kind == "cantilever":
        for table in ("dirichlet", "body_force", "pressure"):
            if table in config:
                raise ConfigError(f"[[{table}]] is only used with kind = \"general\"; the "
                                  "cantilever sets its own clamp and load")
        problem = cantilever(mesh, body_force=tuple(float(x) for x in prob.get("body_force", (0.0, 0.0, -0.5))),
                             damping=damping, t_ramp=float(prob.get("t_ramp", 1.0)),
                             t_off=prob.get("t_off"), material=material)
    elif kind == "general":
        problem = Problem(mesh=mesh, material=material, damping=damping,
                          dirichlet=tuple(_dirichlet(e, i) for i, e in enumerate(config.get("dirichlet", []))),
                          loads=tuple(_loads(config)))
    else:
        raise ConfigError(f"[problem] kind must be \"cantilever\" or \"general\", got {kind!r}")
    run = config.get("run", {})
    run_config = RunConfig(
        n_steps=int(run.get("n_steps", 20000)), save_every=int(run.get("save_every", 100)),
        dt=None if run.get("dt") is None else float(run["dt"]),
        output=str(run.get("output", "trajectory.h5")), xdmf=run.get("xdmf"),
        checkpoint=run.get("checkpoint"), checkpoint_every=run.get("checkpoint_every"))
    return problem, run_config


def _dirichlet(entry: dict, i: int) -> Dirichlet:
    value = tuple(float(x) for x in entry.get("value", (0.0, 0.0, 0.0)))
    components = tuple(int(c) for c in entry.get("components", (0, 1, 2)))
    if "facet" in entry:
        return Dirichlet(str(entry["facet"]), value, components)
    if "plane" in entry:
        axis, coord = int(entry["plane"]["axis"]), float(entry["plane"]["value"])
        if axis not in (0, 1, 2):
            raise ConfigError(f"[[dirichlet]] #{i}: plane axis must be 0, 1 or 2, got {axis}")

        def on_plane(points: np.ndarray, axis=axis, coord=coord) -> np.ndarray:
            tol = 1e-8 * max(float(np.ptp(points[:, axis])), 1.0)
            return np.abs(points[:, axis] - coord) <= tol

        return Dirichlet(on_plane, value, components)
    raise ConfigError(f"[[dirichlet]] #{i}: give 'facet' (a facet-set name) or 'plane'")


def _loads(config: dict) -> list[Any]:
    loads: list[Any] = []
    for i, entry in enumerate(config.get("body_force", [])):
        if "vector" not in entry:
            raise ConfigError(f"[[body_force]] #{i}: 'vector' is required")
        loads.append(BodyForce(tuple(float(x) for x in entry["vector"]),
                               _time_function(entry, f"[[body_force]] #{i}")))
    for i, entry in enumerate(config.get("pressure", [])):
        if "surface" not in entry:
            raise ConfigError(f"[[pressure]] #{i}: 'surface' (a facet-set name) is required")
        loads.append(Pressure(float(entry.get("magnitude", 1.0)),
                              _time_function(entry, f"[[pressure]] #{i}"), surface=str(entry["surface"])))
    return loads
