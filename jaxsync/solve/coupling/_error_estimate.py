"""An estimate of the true error of a predicted phase, from the force balance it skips.

es_hat (paper eq. 26) sees only where neighbouring parts' predictions disagree; an error
that every part's network makes alike at a shared node stays invisible to it. This module
estimates the error itself.

The synchronized update of a shared dof is d(n+1) = S(d(n), d(n-1)), from the full
(summed) internal force. The predicted phase writes the prediction s(n+1) there instead,
and everywhere else it takes the synchronized update exactly. So the predicted run is
the synchronized run with a displacement injected at the shared dofs every step, the
*defect* delta(n) = s(n+1) - S(state(n)), and its error obeys

    e(n + 1) = A e(n) + B delta(n),

A the synchronized one-step propagator (stable), B the injection at the shared dofs. Summed
over the steps between two saved steps, the defect costs one exchange of the parts'
summed partial forces (:func:`jaxsync.solve.executors.defect_probe`: one collective per
saved step, every step's defect counted).

:class:`ErrorPropagator` runs that recursion in the lowest ``n_modes`` vibration modes of
the structure (K phi = omega^2 M phi on the free dofs, mass-orthonormal): each mode is a
scalar central-difference oscillator with the run's Rayleigh damping (damping ratio
alpha / (2 omega) + beta omega / 2, the beta K term from the backward velocity as the
stepper takes it), driven by phi^T M B delta at every step. The drive is exact and needs
no exchange beyond the probe's: the mean defect over the parts that hold a shared node is
a sum of terms each part knows (:func:`jaxsync.solve.executors.defect_probe`), so every part
drives the modes with its own share at the step it happened (the response at the next
probe, T^m e_1 for a defect m steps before it, from :meth:`ErrorPropagator.device_tables`)
and the host adds the parts' shares at each probe. (Spreading each block's summed defect
evenly over its steps instead loses, for the modes whose period nears the block, the
timing that keeps the true error bounded: under predictions that jitter from step to step
that estimate grew to 5-13x the error within 8 000-20 000 steps, and on `jaxsync demo
--case vessel` past 1 % of the amplitude after 120 000 steps while the error stayed at
0.7 %.) The estimate at a
probe is the largest nodal norm of sum_k q_k phi_k plus the quasi-static response of the
modes above those kept to the block's mean defect as a force (K^-1 f minus its kept
modes' part: one sparse solve per probe with a factorization made once) [cm].

What it sees: slow drifts that every part shares (a network's bias, an amplitude or
phase error of the motion), accumulated over the whole predicted stretch, and the free
vibration such errors leave behind (a defect at one moment excites the modes, which ring
on after the defect has gone: no instantaneous residual could see that). What it does
not: error in modes above the ``n_modes`` kept (high-frequency motion trapped between
clamped shared nodes; under step-to-step jitter the estimate is about half the error),
the timing of the defects within a block for the static remainder, and elastic supports'
dashpots (not in the modal damping).

Hyperelastic laws (:mod:`jaxsync.fem.materials`): the error of a finite-strain run obeys
the same recursion to first order in the error, with A the propagator of the tangent
stiffness K_T(u) = d f_int / d u of the state the run passes through. The propagator is
linear, so it is built from the tangent at one state (``displacement`` of
:meth:`ErrorPropagator.build`; :func:`jaxsync.fem.forces.tangent_matrix`, plus
the elastic supports' springs): by default the reference configuration (at rest, where
every law's tangent is its small-strain stiffness of the same E and nu, for HGO with the
fibres' stiffness as its tangent gives it), or, with ``ResyncTolerance(linearization=
"synchronized")``, the last synchronized state before each predicted stretch (rebuilt
there). It misses the change of the tangent along the run (stiffening with strain, the
change of the frequencies) and the error's own second-order terms; how far that matters
is measured on the hyperelastic vessel (``benchmarks/paper_hyperelastic_vessel.py``).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ...errors import ProblemError

__all__ = ["ErrorPropagator", "DEFAULT_MODES", "FLEXIBILITY_LIMIT", "linearised_stiffness"]

DEFAULT_MODES = 40
"""Modes kept by default (fewer where the mesh has fewer free dofs)."""

FLEXIBILITY_LIMIT = 6000
"""Shared dofs up to which the static remainder between them is made once (a dense
matrix of at most 288 MB) rather than solved for at every probe."""

_DENSE_LIMIT = 3000  # free dofs up to which the modes come from a dense eigensolver


@dataclasses.dataclass(frozen=True)
class ErrorPropagator:
    """The modal error recursion of a problem's predicted phase (see the module docstring).

    Attributes:
        modes: (n_nodes, 3, n_modes) mass-orthonormal modes, zero on prescribed dofs.
        omega: (n_modes,) circular frequencies [rad/s].
        injection: (n_interface, 3, n_modes) phi^T M at the partition's shared nodes
            (``partition.shared_nodes`` order): a defect (n_interface, 3) [cm] moves mode
            k by sum(injection[..., k] * delta) [cm g^(1/2)].
        transition: (n_modes, 2, 2) the one-step map of (q(n), q(n-1)) without injection.
        dt: the step [s].
        shared: (n_interface,) the shared nodes' ids.
        free: (n_free,) the free dofs (of the flattened (n_nodes, 3) field).
        mass: (n_nodes, 3) the lumped mass per dof [g].
        stiffness_solve: x = K^-1 f on the free dofs (a sparse factorization's solve).
        flexibility: (n_interface, 3, n_interface, 3) the static remainder at the shared
            nodes of a unit defect there (the residual flexibility (K^-1 - Phi Omega^-2
            Phi^T) M / dt^2 between shared dofs), made once where it holds at most
            :data:`FLEXIBILITY_LIMIT` dofs a side; None: one sparse solve per probe over
            the whole mesh instead.
    """

    modes: np.ndarray
    omega: np.ndarray
    injection: np.ndarray
    transition: np.ndarray
    dt: float
    shared: np.ndarray
    free: np.ndarray
    mass: np.ndarray
    stiffness_solve: object
    flexibility: np.ndarray | None = None
    _maps: dict = dataclasses.field(default_factory=dict, repr=False, compare=False)  # stride -> _over(stride)

    @classmethod
    def build(cls, problem, partition, dt: float, n_modes: int | None = None,
              displacement=None) -> "ErrorPropagator":
        """The propagator of ``problem`` run at step ``dt`` [s] over ``partition``'s shared
        nodes, with the ``n_modes`` lowest modes (default :data:`DEFAULT_MODES`).

        ``displacement``: (n_nodes, 3) [cm], the state whose tangent stiffness a
        hyperelastic law is linearised at (default: the reference configuration, at
        rest); a linear law's stiffness does not depend on it.

        Raises:
            ProblemError: ``n_modes`` not a positive whole number, or no free dof."""
        from scipy.sparse.linalg import LinearOperator, eigsh, splu

        n_modes = DEFAULT_MODES if n_modes is None else n_modes
        if isinstance(n_modes, bool) or not isinstance(n_modes, (int, np.integer)) or n_modes < 1:
            raise ProblemError(f"resync_tolerance: modes={n_modes!r} must be a whole number >= 1")
        lowered = problem.discrete
        fixed = np.asarray(lowered.fixed).reshape(-1)
        free = np.flatnonzero(~fixed)
        if not len(free):
            raise ProblemError("every dof is prescribed: there is no error to estimate")
        K = linearised_stiffness(problem, displacement).tocsr()[free][:, free].tocsc()
        solve = splu(K).solve  # once: the static remainder, and the eigensolver's shift-invert
        mass = np.repeat(np.asarray(lowered.mass, dtype=float), 3)[free]
        n_modes = int(min(n_modes, len(free) - 1 if len(free) > _DENSE_LIMIT else len(free)))
        scale = 1.0 / np.sqrt(mass)
        if len(free) <= _DENSE_LIMIT:
            import scipy.linalg

            A = (scale[:, None] * K.toarray()) * scale[None, :]
            omega2, vectors = scipy.linalg.eigh(A, subset_by_index=(0, n_modes - 1))
        else:
            # the lowest modes of M^-1/2 K M^-1/2 by shift-invert about 0, its inverse through K's factor
            A = LinearOperator(K.shape, matvec=lambda x: scale * (K @ (scale * x)), dtype=float)
            inverse = LinearOperator(K.shape, matvec=lambda x: solve(x / scale) / scale, dtype=float)
            omega2, vectors = eigsh(A, k=n_modes, sigma=0.0, which="LM", OPinv=inverse)
            order = np.argsort(omega2)
            omega2, vectors = omega2[order], vectors[:, order]
        phi = scale[:, None] * vectors  # mass-orthonormal: phi^T M phi = I
        modes = np.zeros((3 * problem.n_nodes, n_modes))
        modes[free] = phi
        modes = modes.reshape(problem.n_nodes, 3, n_modes)
        mass_full = np.repeat(np.asarray(lowered.mass, dtype=float)[:, None], 3, axis=1)
        shared = np.asarray(partition.shared_nodes)
        injection = modes[shared] * mass_full[shared][..., None]
        a = 0.5 * float(lowered.damping) * float(dt)
        omega2 = np.maximum(omega2, 0.0)
        # the stiffness-proportional damping beta omega^2 (q(n) - q(n-1)) / dt of the stepper
        b = float(lowered.stiffness_damping) * float(dt) * omega2
        c = (2.0 - float(dt) ** 2 * omega2 - b) / (1.0 + a)
        d = -(1.0 - a - b) / (1.0 + a)
        transition = np.stack([np.stack([c, d], -1), np.stack([np.ones_like(c), np.zeros_like(c)], -1)], -2)
        flexibility = _interface_flexibility(solve, free, shared, modes, np.sqrt(omega2), mass_full, float(dt))
        return cls(modes=modes, omega=np.sqrt(omega2), injection=injection, transition=transition, dt=float(dt),
                   shared=shared, free=free, mass=mass_full, stiffness_solve=solve, flexibility=flexibility)

    @property
    def n_modes(self) -> int:
        return int(self.omega.shape[0])

    def zero_state(self) -> np.ndarray:
        """(n_modes, 2) the modal error (q(n), q(n-1)) of a synchronized state: zero."""
        return np.zeros((self.n_modes, 2))

    def _over(self, stride: int) -> tuple[np.ndarray, np.ndarray]:
        """(T^stride (n_modes, 2, 2), sum_{j < stride} T^j e_1 (n_modes, 2)): ``stride``
        steps of every mode, and the response to a unit injection at each of them."""
        power = np.broadcast_to(np.eye(2), self.transition.shape).copy()
        total = np.zeros(self.transition.shape[:2])
        for _ in range(stride):
            total += power[:, :, 0]
            power = np.einsum("kij,kjl->kil", self.transition, power)
        return power, total

    def device_tables(self, columns, share, stride: int, width: int):
        """The tables with which every part drives the modes with its share of each step's
        defect (:func:`jaxsync.solve.executors.defect_probe`), stacked on the part axis.

        Args:
            columns: per part, the interface positions of its shared nodes (its slots).
            share: (n_interface,) 1 / the number of parts that hold each shared node.
            stride: steps between probes.
            width: shared slots per part (padded).

        Returns:
            ``(injection (P, width, 3, n_modes), share (P, width), response (P, stride,
            n_modes, 2))``: phi^T M and 1 / c at each part's slots (0 in padding), and the
            response of (q, q_prev) to a unit injection m steps before a probe, T^m e_1."""
        n_parts = len(columns)
        injection = np.zeros((n_parts, width, 3, self.n_modes))
        shares = np.zeros((n_parts, width))
        for p, cols in enumerate(columns):
            injection[p, :len(cols)] = self.injection[cols]
            shares[p, :len(cols)] = np.asarray(share)[cols]
        response = np.empty((stride, self.n_modes, 2))
        power = np.broadcast_to(np.eye(2), self.transition.shape).copy()
        for m in range(stride):
            response[m] = power[:, :, 0]
            power = np.einsum("kij,kjl->kil", self.transition, power)
        return injection, shares, np.broadcast_to(response, (n_parts,) + response.shape).copy()

    def propagate(self, state: np.ndarray, defects: np.ndarray, stride: int,
                  modal: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Advance the modal error through probes ``stride`` steps apart.

        Args:
            state: (n_modes, 2) modal error before the first probe's stretch.
            defects: (n_probes, n_interface, 3) the defects summed over the ``stride``
                steps that end at each probe [cm] (the static remainder's mean defect; and,
                without ``modal``, the modes' drive, spread evenly over the steps).
            stride: steps between probes.
            modal: (n_probes, n_modes, 2) the response at each probe of (q, q_prev) to the
                defects of its ``stride`` steps, each at the step it happened (the parts'
                shares added: :meth:`device_tables`); None: from ``defects`` spread evenly
                (exact only for a defect constant over the block).

        Returns:
            (state after the last probe, (n_probes,) estimated largest nodal error at each
            probe [cm])."""
        if stride not in self._maps:
            self._maps[stride] = self._over(stride)
        power, total = self._maps[stride]
        defects = np.asarray(defects, dtype=float)
        # each block's sum spread evenly over its steps
        driven = np.einsum("pnc,nck->pk", defects, self.injection) / stride
        amplitudes = np.empty_like(driven)  # q(n) of every mode at every probe
        for i, beta in enumerate(driven):
            drive = total * beta[:, None] if modal is None else modal[i]
            state = np.einsum("kij,kj->ki", power, state) + drive
            amplitudes[i] = state[:, 0]
        fields = np.einsum("ncm,pm->pnc", self.modes, amplitudes)
        if self.flexibility is not None:  # the static remainder at the shared nodes, where it peaks
            fields[:, self.shared] += np.einsum("icjd,pjd->pic", self.flexibility, defects) / stride
        else:
            fields += self._static_remainder(defects, stride)
        return state, np.sqrt((fields ** 2).sum(axis=2)).max(axis=1)

    def _static_remainder(self, defect_sums: np.ndarray, stride: int) -> np.ndarray:
        """(n_probes, n_nodes, 3) the quasi-static response of the modes above those kept
        to each block's mean defect as a force, f = M B delta / dt^2 [dyn]: K^-1 f minus
        its kept modes' part (the residual flexibility; the high modes answer a slowly
        varying force statically, within a period of theirs). One solve for all probes."""
        n_probes = len(defect_sums)
        force = np.zeros((n_probes,) + self.mass.shape)
        force[:, self.shared] = self.mass[self.shared] * defect_sums / (stride * self.dt ** 2)
        static = np.zeros((n_probes, self.mass.size))
        static[:, self.free] = self.stiffness_solve(force.reshape(n_probes, -1)[:, self.free].T).T
        low = np.einsum("ncm,pm->pnc", self.modes, np.einsum("ncm,pnc->pm", self.modes, force) / np.maximum(
            self.omega, 1e-300) ** 2)
        return static.reshape(force.shape) - low


def linearised_stiffness(problem, displacement=None):
    """The stiffness (scipy sparse, (n_dofs, n_dofs) [dyn/cm]) whose propagator A the
    estimate runs: the material law's tangent stiffness at ``displacement`` u (default
    zero: at rest; :meth:`jaxsync.fem.materials.MaterialLaw.tangent_stiffness`: a linear
    law's K, a hyperelastic law's K_T(u), :func:`jaxsync.fem.forces.tangent_matrix`,
    symmetrised), the elastic supports' springs added."""
    from ...fem.forces._support import spring_matrix

    K = problem.material.tangent_stiffness(problem, displacement)
    springs = spring_matrix(problem)
    return K if springs is None else (K + springs).tocsr()


def _interface_flexibility(solve, free, shared, modes, omega, mass, dt):
    """(n_interface, 3, n_interface, 3) the residual flexibility between the shared dofs,
    times their masses / dt^2 (see :class:`ErrorPropagator`), or None above
    :data:`FLEXIBILITY_LIMIT` shared dofs. Its columns by sparse solves, 512 at a time."""
    n_interface = len(shared)
    if 3 * n_interface > FLEXIBILITY_LIMIT:
        return None
    position = np.full(mass.size, -1)
    position[free] = np.arange(len(free))
    dofs = (3 * shared[:, None] + np.arange(3)).reshape(-1)  # the shared dofs, node-major
    at = position[dofs]  # -1 on prescribed ones: their defect is zero, their column too
    columns = np.flatnonzero(at >= 0)
    inverse = np.zeros((len(dofs), len(dofs)))
    rows = at >= 0
    for first in range(0, len(columns), 512):
        chunk = columns[first:first + 512]
        unit = np.zeros((len(free), len(chunk)))
        unit[at[chunk], np.arange(len(chunk))] = 1.0
        solved = solve(unit)
        inverse[np.ix_(rows, chunk)] = solved[at[rows]]
    kept = modes[shared].reshape(len(dofs), -1)
    remainder = inverse - (kept / np.maximum(omega, 1e-300) ** 2) @ kept.T
    flexibility = remainder * mass[shared].reshape(-1)[None, :] / dt ** 2
    return flexibility.reshape(n_interface, 3, n_interface, 3)
