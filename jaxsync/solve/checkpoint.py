"""Resumable checkpoints of synchronized runs: the state (both displacement levels), the
snapshots and shared histories so far, a fingerprint of the problem that refuses foreign
files and a checksum that refuses altered ones. Written atomically (:mod:`jaxsync.io`)."""

from __future__ import annotations

import hashlib

import jax.numpy as jnp
import numpy as np

from ..errors import CheckpointError
from ..fem.stepper import SolverState
from ..io import array_checksum, atomic_h5

__all__ = ["fingerprint", "save_checkpoint", "load_checkpoint"]


def fingerprint(problem, dt: float, save_every: int) -> str:
    """Hash of everything that determines a trajectory, to refuse foreign checkpoints."""
    h = hashlib.sha256()
    mesh = problem.mesh
    for arr in (mesh.points, mesh.tets):
        h.update(np.ascontiguousarray(arr).tobytes())
    m = problem.material
    dofs, values = problem.dirichlet_dofs()
    h.update(np.asarray([float(m.E), float(m.nu), float(m.rho), float(problem.damping), dt,
                         save_every], dtype=float).tobytes())
    h.update(dofs.tobytes())
    h.update(values.tobytes())
    for v in problem.load_vectors()[0]:
        h.update(np.asarray(v, dtype=float).tobytes())
    for ic in (problem.initial_displacement, problem.initial_velocity, problem.density_scale):
        if ic is not None:
            h.update(np.asarray(ic, dtype=float).tobytes())
    return h.hexdigest()


_CHECKPOINT_KIND = "jaxsync-solver-checkpoint"


def _checkpoint_checksum(arrays: dict, fingerprint: str, step: int) -> str:
    """sha256 over the stored state arrays, the problem fingerprint and the step."""
    return array_checksum(arrays, {"kind": _CHECKPOINT_KIND, "fingerprint": str(fingerprint),
                                   "step": int(step)})


def save_checkpoint(path, fingerprint, state: SolverState, snapshots, recorded=None) -> None:
    """``recorded``: per part, the list of shared-history chunks kept every step."""
    arrays = {"displacement": np.asarray(state.displacement),
              "previous": np.asarray(state.previous),
              "snapshots": np.concatenate(snapshots, axis=0)}
    for p, chunks in enumerate(recorded or ()):
        arrays[f"shared_{p}"] = np.concatenate(chunks, axis=0)
    step_ = int(state.step)
    with atomic_h5(path) as f:
        f.attrs["kind"] = _CHECKPOINT_KIND
        f.attrs["fingerprint"] = fingerprint
        f.attrs["step"] = step_
        f.attrs["checksum"] = _checkpoint_checksum(arrays, fingerprint, step_)
        for name, array in arrays.items():
            f[name] = array


def load_checkpoint(path, fingerprint, n_steps, n_recorded: int = 0):
    """(state, snapshot chunks, per-part shared-history chunks or None); ``n_recorded``
    parts' every-step shared histories must be in the file when > 0."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("kind") != _CHECKPOINT_KIND:
                raise CheckpointError(f"{path} is not a jaxsync solver checkpoint; delete it or "
                                      "pass another checkpoint path")
            if f.attrs["fingerprint"] != fingerprint:
                raise CheckpointError(
                    f"checkpoint {path} was written by a different problem, dt or save_every; "
                    "delete it or pass another checkpoint path")
            step_ = int(f.attrs["step"])
            names = ["displacement", "previous", "snapshots"] + sorted(
                (k for k in f if k.startswith("shared_")), key=lambda k: int(k.split("_")[1]))
            arrays = {name: f[name][...] for name in names}
            stored = f.attrs.get("checksum")
    except CheckpointError:
        raise
    except Exception as exc:
        raise CheckpointError(f"cannot read checkpoint {path}: {exc}; delete it to start over") from exc
    if stored is None:
        raise CheckpointError(
            f"checkpoint {path} has no checksum (written by an older jaxsync), so its state "
            "cannot be verified; delete it to start over")
    if str(stored) != _checkpoint_checksum(arrays, fingerprint, step_):
        raise CheckpointError(
            f"checkpoint {path} fails its checksum: the stored state was altered or damaged "
            "after it was written, and resuming from it would give a wrong trajectory; "
            "delete it to start over")
    if step_ > n_steps:
        raise CheckpointError(f"checkpoint {path} is at step {step_}, beyond n_steps={n_steps}")
    recorded = None
    if n_recorded:
        if f"shared_{n_recorded - 1}" not in arrays:
            raise CheckpointError(
                f"checkpoint {path} holds no every-step shared histories (it was written with "
                "shared_every = save_every); delete it, or resume with the same shared_every")
        recorded = [[arrays[f"shared_{p}"]] for p in range(n_recorded)]
    state = SolverState(jnp.asarray(arrays["displacement"]), jnp.asarray(arrays["previous"]),
                        jnp.asarray(step_, dtype=jnp.int32))
    return state, [arrays["snapshots"]], recorded
