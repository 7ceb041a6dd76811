"""The material-law protocol: a law defined here, through the public protocol only, runs
end to end like the built-in one it re-implements.

The law under test, :class:`OwnNeoHookean`, is the compressible neo-Hookean solid written
out in this file with jax.numpy (its own strain energy and first Piola stress, the
closed-form P = mu (F - F^-T) + lam ln J F^-T with numpy's determinant and inverse), so the
reference -- the built-in :class:`jaxsync.NeoHookean`, whose P is the autodiff of its
energy -- is an independent implementation of the same law. Both run on the same beam
and load: on one device, on two parts, and through a checkpoint; they must agree to
round-off, and the law's two-part run must equal its single-device run."""

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsync
from jaxsync.errors import CheckpointError, ProblemError
from jaxsync.fem.materials import FiniteStrainLaw, MaterialLaw, is_hyperelastic
from jaxsync.io.checkpoint import fingerprint
from jaxsync.perf.roofline import step_costs_for
from jaxsync.pytree import pytree_dataclass

E, NU, RHO = 1.0e6, 0.3, 1.0


@pytree_dataclass
class OwnNeoHookean(FiniteStrainLaw):
    """psi = mu/2 (I1 - 3) - mu ln J + lam/2 (ln J)^2, written here."""

    E: Any = 1.0e6
    nu: Any = 0.3
    rho: Any = 1.0

    point_flops = {"inverse and determinant": 60, "P": 40}

    @property
    def mu(self):
        return self.E / (2.0 * (1.0 + self.nu))

    @property
    def lam(self):
        return self.E * self.nu / ((1.0 + self.nu) * (1.0 - 2.0 * self.nu))

    def energy(self, F, fibres=None):
        log_j = jnp.log(jnp.linalg.det(F))
        return 0.5 * self.mu * (jnp.sum(F * F, axis=(-2, -1)) - 3.0) - self.mu * log_j + 0.5 * self.lam * log_j**2

    def first_piola(self, F, fibres=None):
        F_inv_t = jnp.swapaxes(jnp.linalg.inv(F), -1, -2)
        log_j = jnp.log(jnp.linalg.det(F))
        return self.mu * (F - F_inv_t) + (self.lam * log_j)[..., None, None] * F_inv_t


@pytest.fixture(scope="module")
def beam():
    return jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1))


def _problems(beam):
    """(the built-in law's cantilever, the same with the law of this file), loaded hard
    enough to leave the linear range (a tip deflection of about a tenth of the length)."""
    builtin = jaxsync.cantilever(beam, material=jaxsync.NeoHookean(E, NU, RHO), body_force=(0.0, 0.0, -2.0e4),
                                 t_ramp=0.002, damping=50.0)
    return builtin, builtin.replace(material=OwnNeoHookean(E, NU, RHO))


def test_the_law_of_this_file_is_a_material_law_and_its_stress_is_the_builtin_one():
    own, ref = OwnNeoHookean(E, NU, RHO), jaxsync.NeoHookean(E, NU, RHO)
    assert isinstance(own, MaterialLaw) and isinstance(ref, MaterialLaw)
    assert isinstance(jaxsync.LinearElastic(), MaterialLaw)
    assert is_hyperelastic(own) and not is_hyperelastic(jaxsync.LinearElastic())
    F = jnp.eye(3)[None] + 0.2 * jax.random.normal(jax.random.PRNGKey(0), (50, 3, 3))
    # each law's stress and tangent as one compiled program (not op by op)
    piola, tangent = jax.jit(lambda law, F: law.first_piola(F)), jax.jit(lambda law, F: law.tangent(F))
    np.testing.assert_allclose(piola(own, F), piola(ref, F), rtol=1e-12, atol=1e-12 * E)
    np.testing.assert_allclose(tangent(own, F[:5]), tangent(ref, F[:5]), rtol=1e-10, atol=1e-10 * E)
    assert own.internal_variables(7, 4) == {} and jaxsync.LinearElastic().internal_variables(7, 4) == {}


def test_the_own_law_steps_like_the_builtin_one(beam):
    builtin, own = _problems(beam)
    a, b = builtin.time_step, own.time_step
    assert a.rule == b.rule and a.law == "NeoHookean" and b.law == "OwnNeoHookean"
    np.testing.assert_allclose(b.dt, a.dt, rtol=1e-10)
    np.testing.assert_allclose(own.element_steps(), builtin.element_steps(), rtol=1e-10)


def test_single_device_and_two_part_runs_of_the_own_law_match_the_builtin_law(beam):
    builtin, own = _problems(beam)
    dt = float(builtin.dt)
    ref = jaxsync.simulate(builtin, 400, dt=dt, save=50)
    one = jaxsync.simulate(own, 400, dt=dt, save=50)
    two = jaxsync.simulate(own, 400, dt=dt, save=50, partitions=2)
    scale = float(np.max(np.abs(ref.displacement)))
    assert scale > 0.2  # finite strain: a tenth of the 4 cm beam
    np.testing.assert_allclose(one.displacement, ref.displacement, rtol=0, atol=1e-11 * scale)
    np.testing.assert_allclose(two.displacement, one.displacement, rtol=0, atol=1e-12 * scale)


def test_checkpoint_round_trip_of_the_own_law(beam, tmp_path):
    builtin, own = _problems(beam)
    dt = float(builtin.dt)
    executor = jaxsync.HostExecutor(chunk_steps=100)
    full = jaxsync.simulate(own, 400, dt=dt, save=50, executor=executor)
    path = tmp_path / "own.ckpt.h5"
    jaxsync.simulate(own, 200, dt=dt, save=50, executor=executor, checkpoint=str(path))
    resumed = jaxsync.simulate(own, 400, dt=dt, save=50, executor=executor, checkpoint=str(path))
    np.testing.assert_array_equal(resumed.displacement, full.displacement)
    ref = jaxsync.simulate(builtin, 400, dt=dt, save=50, executor=executor)
    np.testing.assert_allclose(resumed.displacement, ref.displacement, rtol=0,
                               atol=1e-11 * float(np.max(np.abs(ref.displacement))))
    # the law is part of the fingerprint: the built-in law does not resume the own law's run
    assert fingerprint(own, dt, 50) != fingerprint(builtin, dt, 50)
    with pytest.raises(CheckpointError, match="different problem"):
        jaxsync.simulate(builtin, 400, dt=dt, save=50, executor=executor, checkpoint=str(path))


def test_the_own_law_takes_follower_pressure_and_its_static_solution_is_the_builtin_one(beam):
    builtin, own = _problems(beam)
    load = jaxsync.Pressure(2.0e3, surface="x1", follower=True)
    u_ref = jaxsync.steady_state(builtin.replace(loads=(load,)))
    u_own = jaxsync.steady_state(own.replace(loads=(load,)))
    np.testing.assert_allclose(u_own, u_ref, rtol=0, atol=1e-9 * float(np.max(np.abs(u_ref))))
    with pytest.raises(ProblemError, match="follower pressure"):
        own.replace(material=jaxsync.LinearElastic(E, NU, RHO), loads=(load,))


def test_the_own_law_is_costed_from_its_declared_flops(beam):
    builtin, own = _problems(beam)
    ref, mine = step_costs_for(builtin), step_costs_for(own)
    m = beam.n_elements
    # the same traffic (no fibres, no state); the stress's flops those it declares
    assert mine["t_e"].bytes == ref["t_e"].bytes
    own_stress, ref_stress = 100, sum(jaxsync.NeoHookean.point_flops.values())
    assert mine["t_e"].flops - ref["t_e"].flops == m * (own_stress - ref_stress)


def test_an_object_that_is_no_material_law_is_refused_naming_what_it_lacks(beam):
    @pytree_dataclass
    class Incomplete:
        E: Any = 1.0
        nu: Any = 0.3
        rho: Any = 1.0

    with pytest.raises(ProblemError, match="lacks finite_strain, state_dependent_tangent, force_model"):
        jaxsync.cantilever(beam, material=Incomplete())
