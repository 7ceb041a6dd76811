"""``jaxsync unload``: the zero-pressure (unloaded) geometry of an imaged mesh
(:func:`jaxsync.zero_pressure_geometry`), written as a mesh file with its facet sets."""

from __future__ import annotations

import os

from ..options import Element, PrestressMethod, ZeroPressureMethod, ZeroPressureStart, check_option, choices
from . import common

DEFAULTS = {"method": "newton", "tol": 1e-10, "max_iter": 50, "load_steps": 4, "output": "unloaded.vtu",
            "start": "unloaded", "prestress": "zero-pressure"}
"""The ``[zero_pressure]`` values used when neither the file nor the command line gives them."""


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "unload", help="the zero-pressure geometry of an imaged mesh under its imaging pressure",
        description="Find the unloaded (zero-pressure) geometry of the mesh of a TOML problem file, taken as "
                    "imaged under its loads (the follower lumen pressure at --pressure, or at the [[pressure]] "
                    "magnitudes), and write it as a mesh file with the same topology and facet sets. Options "
                    "override the file's [zero_pressure] table. An existing output is never overwritten "
                    "without --force.")
    common.accept_negative_numbers(p)
    p.add_argument("config", help="TOML problem file with a hyperelastic [material] and a follower [[pressure]]")
    p.add_argument("--mesh", default=None, help="the imaged mesh file (or SimVascular folder), instead of [mesh]")
    p.add_argument("--element", choices=choices(Element), default=None, help="P1 or P2 ([problem] element)")
    p.add_argument("--pressure", type=float, default=None, metavar="P",
                   help="imaging pressure in barye: every follower [[pressure]] at this constant magnitude "
                        "([zero_pressure] pressure; default: the [[pressure]] magnitudes, time factor 1)")
    p.add_argument("--method", choices=choices(ZeroPressureMethod), default=None,
                   help="newton (the inverse problem, exact tangent) or fixed-point (backward displacement) "
                        f"([zero_pressure] method; default {DEFAULTS['method']})")
    p.add_argument("--tol", type=float, default=None,
                   help=f"convergence tolerance ([zero_pressure] tol; default {DEFAULTS['tol']:g})")
    p.add_argument("--max-iter", type=int, default=None,
                   help=f"iterations at most ([zero_pressure] max_iter; default {DEFAULTS['max_iter']})")
    p.add_argument("--load-steps", type=int, default=None,
                   help=f"pressure increments ([zero_pressure] load_steps; default {DEFAULTS['load_steps']})")
    p.add_argument("--output", "-o", default=None,
                   help="the unloaded mesh: .vtu, .vtk or .msh ([zero_pressure] output; default "
                        f"{DEFAULTS['output']})")
    p.add_argument("--force", action="store_true", help="overwrite an existing output file")
    p.set_defaults(func=run)


def settings(args, config: dict) -> dict:
    """The ``[zero_pressure]`` settings: the command line (``args``, or None) over the
    (path-resolved) file over :data:`DEFAULTS`, with ``pressure`` (None: the file's
    magnitudes)."""
    table = config.get("zero_pressure", {})
    found = {key: table.get(key, value) for key, value in DEFAULTS.items()}
    found["pressure"] = table.get("pressure")
    for key in ("pressure", "method", "tol", "max_iter", "load_steps", "output"):
        value = getattr(args, key, None)
        if value is not None:
            found[key] = value
    check_option("[zero_pressure] method", found["method"], ZeroPressureMethod)
    check_option("[zero_pressure] start", found["start"], ZeroPressureStart)
    check_option("[zero_pressure] prestress", found["prestress"], PrestressMethod)
    return found


def start_problem(problem, config: dict) -> tuple[object, str | None]:
    """(the problem ``jaxsync simulate`` runs, a line saying what it did) for a file with a
    ``[zero_pressure]`` table (``problem`` and None without one): its mesh is taken as
    imaged under every follower pressure at ``pressure`` (time factor 1), and ``start``
    says what the run starts from:

    * ``"unloaded"``: the zero-pressure geometry (:func:`jaxsync.zero_pressure_geometry`
      with the table's ``method``, ``tol``, ``max_iter``, ``load_steps``; the same as
      ``jaxsync unload`` writes), with the file's loads, supports and clamps;
    * ``"prestressed"``: the imaged geometry with the prestrain of
      :func:`jaxsync.prestress` (route ``prestress``) and the stress-free state's mass
      (its ``density_scale``, times a mass scaling's); in equilibrium at the imaging
      pressure, so the file's loads should start there;
    * ``"imaged"``: the imaged geometry as it is.
    """
    import numpy as np

    if "zero_pressure" not in config:
        return problem, None
    found = settings(None, config)
    if found["start"] == "imaged":
        return problem, None
    imaging = imaging_problem(problem, found["pressure"])
    options = dict(tol=found["tol"], max_iter=found["max_iter"], load_steps=found["load_steps"])
    if found["start"] == "unloaded":
        from ..solve._zero_pressure import zero_pressure_geometry

        result = zero_pressure_geometry(imaging, method=found["method"], **options)
        moved = float(np.abs(result.points - problem.points).max())
        return result.problem(problem), (f"start: the unloaded geometry ({result.method}, {result.iterations} "
                                         f"iterations, final residual {result.residuals[-1]:.3e}; largest node "
                                         f"move {moved:.4g} cm)")
    from ..solve._prestress import prestress

    result = prestress(imaging, method=found["prestress"], **options)
    scale = result.density_scale if problem.density_scale is None else (
        np.asarray(problem.density_scale) * result.density_scale)
    return problem.replace(material=result.material, density_scale=scale), (
        f"start: the imaged geometry prestressed ({result.method}, {result.iterations} iterations; out of balance "
        f"{result.residual:.3e} at the imaging pressure)")


def imaging_problem(problem, pressure):
    """``problem`` with every follower pressure at the constant magnitude ``pressure``
    [barye] (None: unchanged)."""
    import dataclasses

    from ..errors import ConfigError
    from ..fem._loads import Constant
    from ..fem.forces._follower import follower_loads

    followers = follower_loads(problem)
    if not followers:
        raise ConfigError("jaxsync unload needs the lumen pressure as a follower load: add follower = true to its "
                          "[[pressure]] table (and a hyperelastic [material] model)")
    if pressure is None:
        return problem
    loads = tuple(dataclasses.replace(load, magnitude=float(pressure), time=Constant())
                  if any(load is f for f in followers) else load for load in problem.loads)
    return problem.replace(loads=loads)


def run(args) -> int:
    import warnings

    import numpy as np

    from ..app.config import load_config, problem_from_config
    from ..mesh import write_mesh
    from ..solve._zero_pressure import zero_pressure_geometry

    config = load_config(args.config)
    found = settings(args, config)
    output = found["output"]
    common.check_outputs((output, "unloaded mesh", "-o"))
    common.refuse_to_overwrite([output], force=args.force,
                               inputs=[args.config, args.mesh, config.get("mesh", {}).get("file")])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        problem, _ = problem_from_config(config, mesh_file=args.mesh, element=args.element)
    common.report_warnings(caught)
    problem = imaging_problem(problem, found["pressure"])
    result = zero_pressure_geometry(problem, method=found["method"], tol=found["tol"], max_iter=found["max_iter"],
                                    load_steps=found["load_steps"])
    with common.writing(output):
        write_mesh(result.mesh, output, replace=args.force)
    moved = float(np.abs(result.points - problem.points).max())
    print(f"unloaded geometry ({result.method}): {result.iterations} iterations, final residual "
          f"{result.residuals[-1]:.3e}; largest node move {moved:.4g} cm; wrote {os.path.abspath(output)} "
          f"(facet sets {', '.join(result.mesh.facet_sets)})")
    return 0
