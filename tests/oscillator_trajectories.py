"""Synthetic trajectories for the surrogate tests: the real :class:`jaxsync.Trajectory` type
and file format, whose parts' shared dofs are damped oscillators (tests/surrogate,
tests/cli)."""

import numpy as np

import jaxsync
from jaxsync.io.trajectory import PartHistory, Trajectory

NODES = (np.array([3, 8], np.int64), np.array([3, 8, 11], np.int64))


def oscillator_trajectory(n_steps=600, dt=0.05, save_every=1, load=None, nodes=NODES, synchronized=None):
    """A distributed trajectory (the real type and file format) whose parts' shared dofs are
    damped oscillators, one frequency per dof; the full field is not used by training."""
    t = np.arange(n_steps) * dt
    parts = []
    for p, ids in enumerate(nodes):
        freqs = 0.6 + 0.1 * np.arange(3 * ids.size) + 0.05 * p
        w = 2 * np.pi * freqs[None, :]
        disp = (1.0 if load is None else load) * np.exp(-0.02 * w * t[:, None]) * np.cos(w * t[:, None])
        parts.append(PartHistory(shared_nodes=np.asarray(ids, np.int64), elements=np.arange(2),
                                 shared_displacement=disp))
    mesh = jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1))
    return Trajectory(times=t * save_every, displacement=np.zeros((n_steps, mesh.n_nodes, 3)), mesh=mesh, dt=dt,
                      save_every=save_every, parameters={} if load is None else {"load_parameter": load},
                      parts=tuple(parts), synchronized=synchronized)


def write_trajectory(path, **kwargs):
    """:func:`oscillator_trajectory` saved to ``path`` with ``Trajectory.save``."""
    oscillator_trajectory(**kwargs).save(path)
    return path
