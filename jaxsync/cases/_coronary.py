"""The paper's coronary artery problem (Tong & Schiavazzi 2022, section 5.2).

A thick-walled, branching artery clamped at its inlet and outlets and inflated by a
pulsatile lumen pressure: E = 6.26e6 dyn/cm^2, nu = 0.4, rho = 1 g/cm^3, mass-proportional
damping alpha = 0.5 1/s; the pressure rises over the first second (the paper's ramp) and
then oscillates between 80 and 120 mmHg (1.067e5 and 1.6e5 barye) with period 0.833 s.
The paper's patient-specific mesh is not public: the default mesh is the generated
coronary tree of :func:`jaxsync.cases.coronary_mesh`.

Artificial mass scaling to the paper's step is :func:`jaxsync.mass_scaling`, which
returns the added mass::

    problem = coronary(mesh)
    scaled, added_percent = jaxsync.mass_scaling(problem, dt_target=5e-6)

The packaged ``jaxsync/data/coronary.toml`` describes the same problem for
``jaxsync simulate jaxsync/data/coronary.toml --mesh tree.msh``.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..errors import MeshError, ProblemError
from ..fem._loads import Periodic, Pressure, Ramp, TimeFunction
from ..fem._problem import Dirichlet, Problem
from ..fem.materials._linear_elastic import LinearElastic
from ..mesh import Mesh

__all__ = ["MMHG", "CORONARY_PERIOD", "DEFAULT_WAVEFORM", "coronary_material", "coronary_waveform",
           "coronary"]

MMHG = 1333.22
"""One millimetre of mercury in barye (dyn/cm^2)."""

CORONARY_PERIOD = 0.833
"""Period of the paper's pressure pulse [s] (72 beats per minute)."""

DEFAULT_WAVEFORM = (
    (0.0, 0.05, 0.12, 0.20, 0.28, 0.33, 0.37, 0.45, 0.60, 0.75),
    (1.067e5, 1.267e5, 1.533e5, 1.6e5, 1.493e5, 1.333e5, 1.387e5, 1.307e5, 1.173e5, 1.093e5),
)
"""One period of a coronary-like lumen pressure pulse: (times [s], pressures [barye]).

80, 95, 115, 120, 112, 100, 104, 98, 88 and 82 mmHg: a systolic rise to the paper's
maximum 1.6e5 barye (120 mmHg) at 0.2 s, a dicrotic notch and rebound at 0.33-0.37 s and
a diastolic decay back to the paper's minimum 1.067e5 barye (80 mmHg) at the period's
end (0.833 s, the value at t = 0). The same samples as the README's vessel example."""

CORONARY_FACETS = ("inlet", "outlet_1", "outlet_2", "outlet_3", "outlet_4", "outlet_5", "outlet_6",
                   "outlet", "lumen", "outer")
"""Facet sets written by :func:`jaxsync.cases.coronary_mesh`."""


def coronary_material() -> LinearElastic:
    """The paper's arterial wall: E = 6.26e6 dyn/cm^2, nu = 0.4, rho = 1 g/cm^3."""
    return LinearElastic(6.26e6, 0.4, 1.0)


def coronary_waveform(samples=None, *, period: float = CORONARY_PERIOD,
                      t_ramp: float = 1.0) -> TimeFunction:
    """The lumen pressure p(t) [barye]: ``Ramp(t_ramp) * Periodic(times, values, period)``.

    The periodic part interpolates the samples linearly and repeats with the period,
    starting at t = 0 (it is not delayed by the ramp): P(t) = interp(t mod period), and
    from the last sample it goes back linearly to the first one at t = period. The ramp
    R(t) = min(t / t_ramp, 1) multiplies it, so p(t) = R(t) P(t): p(t) = t / t_ramp *
    P(t) during the ramp and p(k period + t_i) = values[i] for every k period + t_i >=
    t_ramp.

    Args:
        samples: ``(times, values)``: (n,) strictly increasing times within [0, period]
            [s] and (n,) pressures [barye], n >= 2; None: :data:`DEFAULT_WAVEFORM`.
        period: [s] > 0 (the paper's 0.833 s).
        t_ramp: duration of the initial linear ramp [s] > 0 (the paper's 1 s).

    Raises:
        ProblemError: samples that are not a (times, values) pair of equal length >= 2,
            times not increasing or outside [0, period], a period or t_ramp <= 0.
    """
    times, values = _samples(DEFAULT_WAVEFORM if samples is None else samples)
    if not float(period) > 0:
        raise ProblemError(f"coronary waveform: the period must be positive, got {period} s")
    if not float(t_ramp) > 0:  # named here: the user gave t_ramp, not a Ramp
        raise ProblemError(f"coronary waveform: t_ramp (the initial ramp's duration) must be positive, got "
                           f"{t_ramp} s")
    return Ramp(float(t_ramp)) * Periodic(times, values, float(period))


def _samples(samples) -> tuple[np.ndarray, np.ndarray]:
    """(times (n,), values (n,)) float64 arrays of a ``(times, values)`` pair."""
    try:
        times, values = samples
        return np.asarray(times, dtype=float), np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        raise ProblemError("coronary waveform samples must be a pair (times [s], pressures "
                           "[barye]) of equal-length number sequences, e.g. "
                           "jaxsync.cases.DEFAULT_WAVEFORM") from None


def coronary(mesh: Mesh | None = None, *, waveform=None, period: float = CORONARY_PERIOD,
             t_ramp: float = 1.0, material: LinearElastic | None = None, damping=0.5,
             outlets: str | Sequence[str] = "outlet", stiffness_damping=0.0) -> Problem:
    """The paper's coronary problem: a clamped artery under pulsatile lumen pressure.

    - Material :func:`coronary_material` (E = 6.26e6 dyn/cm^2, nu = 0.4, rho = 1 g/cm^3)
      unless ``material`` is given; damping alpha = ``damping`` [1/s] and beta =
      ``stiffness_damping`` [s] (Rayleigh, C = alpha M + beta K; beta = 0 by default).
    - Every displacement component fixed on the facet set ``inlet`` and on the outlet
      set(s) ``outlets``.
    - ``jaxsync.Pressure(1.0, coronary_waveform(...), surface="lumen")``: the pressure in
      barye is the time function itself (load magnitude 1), positive into the wall, so it
      inflates the vessel. :func:`jaxsync.steady_state` (time factor 1) therefore gives
      the response to 1 barye; scale it by the pressure of interest.
    - Zero initial conditions. The step is the CFL step (``problem.dt``, about 2e-6 s on
      the paper's mesh); ``jaxsync.mass_scaling(problem, dt_target=5e-6)`` returns the
      scaled problem and the added mass in percent (+21.13 % in the paper; it depends on
      the mesh's smallest elements).

    Args:
        mesh: a tetrahedral mesh [cm] with facet sets ``inlet``, ``lumen`` and the
            outlets; None generates the default
            :func:`jaxsync.cases.coronary_mesh`.
        waveform: ``(times, pressures)`` samples of one period (see
            :func:`coronary_waveform`; None: :data:`DEFAULT_WAVEFORM`), or a ready
            :class:`jaxsync.fem.TimeFunction` giving p(t) [barye] (then ``period``
            and ``t_ramp`` are not used).
        period: of the pulse [s].
        t_ramp: of the initial ramp [s].
        material: the wall's :class:`jaxsync.LinearElastic`.
        damping: alpha [1/s].
        outlets: the facet set, or sequence of sets, clamped besides the inlet (default
            ``"outlet"``, the union of the generated tree's ``outlet_1`` ... ``outlet_6``).
        stiffness_damping: beta [s] (>= 0; may be a JAX tracer): the stiffness-proportional
            damping (:class:`jaxsync.Problem`'s ``stiffness_damping``), which also lowers the
            stable step.

    Raises:
        MeshError: the mesh lacks one of the facet sets (the message names them).
        ProblemError: bad waveform samples, period, ramp, damping or stiffness damping.
    """
    if mesh is None:  # the package's generator (gmsh is imported only here)
        from . import coronary_mesh

        mesh = coronary_mesh()
    outlets = (outlets,) if isinstance(outlets, str) else tuple(outlets)
    if not outlets or not all(isinstance(name, str) for name in outlets):
        raise ProblemError(f"coronary: outlets must be a facet-set name or a non-empty sequence "
                           f"of names, got {outlets!r}")
    _require_facets(mesh, ("inlet", *outlets, "lumen"))
    time = (waveform if isinstance(waveform, TimeFunction)
            else coronary_waveform(waveform, period=period, t_ramp=t_ramp))
    clamps = tuple(Dirichlet(name) for name in ("inlet", *outlets))
    return Problem(mesh=mesh, material=coronary_material() if material is None else material,
                   dirichlet=clamps, loads=(Pressure(1.0, time, surface="lumen"),), damping=damping,
                   stiffness_damping=stiffness_damping)


def _require_facets(mesh: Mesh, names: Sequence[str]) -> None:
    """Raise :class:`MeshError` naming every facet set of ``names`` that ``mesh`` lacks
    or holds empty."""
    if not isinstance(mesh, Mesh):
        raise ProblemError(f"coronary: mesh must be a jaxsync.Mesh (or None), got {type(mesh).__name__}")
    missing = [name for name in dict.fromkeys(names) if len(mesh.facet_sets.get(name, ())) == 0]
    if missing:
        found = ", ".join(sorted(mesh.facet_sets)) or "none"
        raise MeshError(
            f"coronary: the mesh lacks the facet set(s) {', '.join(missing)} (found: {found}); "
            f"the problem clamps 'inlet' and the outlets and loads 'lumen'. "
            f"jaxsync.coronary_mesh writes {', '.join(CORONARY_FACETS)}; "
            "tag your own mesh's surfaces as gmsh physical groups with these names, or pass "
            "outlets= the names of your outlet sets")
