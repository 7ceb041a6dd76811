"""Performance analysis (paper section 7): what a step costs, measured, counted and modelled.

Modules:

* :mod:`~jaxsync.perf.measure` -- the one best-of, round-robin timing harness, and the
  machine's copy bandwidth and matmul flop rate;
* :mod:`~jaxsync.perf.kernels` -- the programs that are timed: stepper variants, one per
  stage, and the whole SPMD programs;
* :mod:`~jaxsync.perf.timing` -- the breakdowns: :func:`timing_breakdown` (t_e, t_m, t_s,
  t_o, t_t per part) and :func:`speedup_breakdown` (synchronized against
  synchronization-avoiding, zeta);
* :mod:`~jaxsync.perf.reports` -- their reports, tables and JSON;
* :mod:`~jaxsync.perf.roofline` -- bytes and flops per stage, counted, and the rates
  achieved at given times;
* :mod:`~jaxsync.perf.costmodel` -- the latency-bandwidth model of a synchronization and
  its projection to other interconnects.
"""


from typing import TYPE_CHECKING

from ..lazy import export_lazily

__all__ = [
    # breakdowns and their reports
    "timing_breakdown", "speedup_breakdown", "STAGES", "PartTiming", "TimingReport",
    "SpeedupReport", "max_average",
    # the measurement harness and the machine's rates
    "sample_times", "best_times", "best_time", "per_step_times", "copy_bandwidth",
    "matmul_flop_rate", "describe_devices",
    # roofline counting
    "StageCost", "ELEMENT_FLOPS", "HYPERELASTIC_POINT_FLOPS", "hyperelastic_element_cost", "step_costs",
    "step_costs_for", "surrogate_flop_breakdown",
    "surrogate_costs", "surrogate_step_cost", "RooflinePoint", "achieved", "achieved_stages",
    "roofline_table",
    # communication cost model
    "Interconnect", "INTERCONNECTS", "CommunicationPattern", "communication_pattern",
    "ALGORITHMS", "sync_time", "fit_interconnect", "InterconnectProjection", "Projection",
    "project", "relative_error",
]

# where each name of __all__ is imported from on first use (jaxsync.lazy): the imports of TYPE_CHECKING below
__getattr__, __dir__ = export_lazily(__name__, {
    ".costmodel": ("ALGORITHMS", "INTERCONNECTS", "CommunicationPattern", "Interconnect", "InterconnectProjection",
                   "Projection", "communication_pattern", "fit_interconnect", "project", "relative_error",
                   "sync_time"),
    ".measure": ("best_time", "best_times", "copy_bandwidth", "describe_devices", "matmul_flop_rate",
                 "per_step_times", "sample_times"),
    ".reports": ("STAGES", "PartTiming", "SpeedupReport", "TimingReport", "max_average"),
    ".roofline": ("ELEMENT_FLOPS", "HYPERELASTIC_POINT_FLOPS", "RooflinePoint", "StageCost", "achieved",
                  "achieved_stages", "hyperelastic_element_cost", "roofline_table", "step_costs", "step_costs_for",
                  "surrogate_costs", "surrogate_flop_breakdown", "surrogate_step_cost"),
    ".timing": ("speedup_breakdown", "timing_breakdown"),
})

if TYPE_CHECKING:
    from .costmodel import (
        ALGORITHMS,
        INTERCONNECTS,
        CommunicationPattern,
        Interconnect,
        InterconnectProjection,
        Projection,
        communication_pattern,
        fit_interconnect,
        project,
        relative_error,
        sync_time,
    )
    from .measure import (
        best_time,
        best_times,
        copy_bandwidth,
        describe_devices,
        matmul_flop_rate,
        per_step_times,
        sample_times,
    )
    from .reports import STAGES, PartTiming, SpeedupReport, TimingReport, max_average
    from .roofline import (
        ELEMENT_FLOPS,
        HYPERELASTIC_POINT_FLOPS,
        RooflinePoint,
        StageCost,
        achieved,
        achieved_stages,
        hyperelastic_element_cost,
        roofline_table,
        step_costs,
        step_costs_for,
        surrogate_costs,
        surrogate_flop_breakdown,
        surrogate_step_cost,
    )
    from .timing import speedup_breakdown, timing_breakdown
