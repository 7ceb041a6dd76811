"""Files: every file jaxsync reads or writes, and the atomic writes they all go through.

=====================================  ======================================================
:mod:`.atomic`                         files that appear only when complete (:func:`atomic_path`,
                                       :func:`atomic_h5`, :func:`atomic_json`,
                                       :func:`staged_outputs`), output claims and
                                       :func:`check_writable`, content checksums
:mod:`.trajectory`                     :class:`~jaxsync.Trajectory`: a run's saved displacements,
                                       statistics and per-part histories (HDF5), and its
                                       XDMF/VTU exports
:mod:`.writers`                        the output formats (HDF5, XDMF, VTU) and their registry
                                       (:func:`~jaxsync.io.writers.register_writer`)
:mod:`.checkpoint`                     resumable checkpoints of synchronized runs
:mod:`.surrogate_file`                 surrogate files of trained replicas
                                       (:class:`~jaxsync.io.surrogate_file.SavedSurrogate`)
=====================================  ======================================================

The names of :mod:`.atomic` are exported here (``from jaxsync.io import atomic_json``);
the formats' names are in their modules. Mesh files are read and written by
:mod:`jaxsync.mesh` (through meshio).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ..lazy import export_lazily

__all__ = ["host_tag", "process_alive", "atomic_path", "atomic_h5", "atomic_json", "array_checksum", "json_value",
           "STALE_TEMP_AGE_S", "OutputError", "check_writable", "recording_writes", "note_written", "os_reason",
           "write_failure", "claimed_outputs", "claim_output", "claiming", "OutputFile", "StagedOutputs",
           "staged_outputs"]

# where each name of __all__ is imported from on first use (jaxsync.lazy)
__getattr__, __dir__ = export_lazily(__name__, {
    ".atomic": ("host_tag", "process_alive", "atomic_path", "atomic_h5", "atomic_json", "array_checksum",
                "json_value", "STALE_TEMP_AGE_S", "OutputError", "check_writable", "recording_writes",
                "note_written", "os_reason", "write_failure", "claimed_outputs", "claim_output", "claiming",
                "OutputFile", "StagedOutputs", "staged_outputs"),
})

if TYPE_CHECKING:
    from .atomic import (
        STALE_TEMP_AGE_S,
        OutputError,
        OutputFile,
        StagedOutputs,
        array_checksum,
        atomic_h5,
        atomic_json,
        atomic_path,
        check_writable,
        claim_output,
        claimed_outputs,
        claiming,
        host_tag,
        json_value,
        note_written,
        os_reason,
        process_alive,
        recording_writes,
        staged_outputs,
        write_failure,
    )
