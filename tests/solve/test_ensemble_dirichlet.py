"""Ensemble members with their own Dirichlet values (``jaxsync.Members(dirichlet=...)``):
each run equals jaxsync.simulate of its own problem, the same runs given as problems give
the same, the gradient in the prescribed values equals central differences, and bad
shapes are refused."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsync
from jaxsync import ProblemError

QUIET = jaxsync.HostExecutor(progress=False)
N_STEPS = 200


def relative_error(a, b):
    return np.abs(np.asarray(a) - np.asarray(b)).max() / np.abs(np.asarray(b)).max()


@pytest.fixture(scope="module")
def base():
    """A beam clamped at x = 0 (a constant condition) and pulled along x at x = 10 (a
    condition following a ramp), under its own weight."""
    mesh = jaxsync.box_beam(10.0, 1.0, 1.0, (10, 1, 1))
    return jaxsync.Problem(
        mesh, jaxsync.LinearElastic(1.0e5, 0.3, 1.0),
        dirichlet=[jaxsync.Dirichlet("x0"),
                   jaxsync.Dirichlet("x1", value=(0.01, 0.0, 0.0), components=(0,), time=jaxsync.Ramp(2e-3))],
        loads=[jaxsync.BodyForce((0.0, 0.0, -0.5), time=jaxsync.Constant())], damping=1.0)


def test_members_with_their_own_dirichlet_values_equal_their_own_runs(base):
    values = np.zeros((3, 2, 3))
    values[:, 0] = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.002], [0.001, -0.001, 0.0]]  # the clamp, shifted
    values[:, 1, 0] = [0.01, 0.02, -0.005]  # the pull's amplitude
    members = jaxsync.Members(dirichlet=values)
    together = jaxsync.ensemble(base, N_STEPS, members=members, save=20, executor=QUIET)
    own = [members.problem(base, r) for r in range(3)]
    dt = together[0].dt
    as_problems = jaxsync.ensemble(own, N_STEPS, dt=dt, save=20, executor=QUIET)
    clamped, pulled = base.mesh.facet_nodes("x0"), base.mesh.facet_nodes("x1")
    for r, (problem, traj, again) in enumerate(zip(own, together, as_problems)):
        assert problem.dirichlet[0].value == tuple(values[r, 0])
        alone = jaxsync.simulate(problem, N_STEPS, dt=dt, save=20, executor=QUIET)
        assert relative_error(traj.displacement, alone.displacement) <= 1e-12, r
        assert relative_error(again.displacement, alone.displacement) <= 1e-12, r
        # the prescribed values themselves: the shifted clamp at every save, the ramped pull
        np.testing.assert_array_equal(np.asarray(traj.displacement)[:, clamped],
                                      np.broadcast_to(values[r, 0], (11, len(clamped), 3)))
        ramp = np.minimum(np.asarray(traj.times) / 2e-3, 1.0)
        np.testing.assert_allclose(np.asarray(traj.displacement)[:, pulled, 0],
                                   (values[r, 1, 0] * ramp)[:, None] * np.ones(len(pulled)), rtol=1e-12, atol=1e-18)


def test_gradient_in_the_dirichlet_values_matches_finite_differences(base):
    """A batched inverse problem in the prescribed motion: the pull's amplitude of every
    run (which also shifts its clamp) from the middle of the beam (jax.grad through the
    ensemble, through the constant and the time-dependent condition)."""
    middle = np.flatnonzero(np.isclose(base.points[:, 0], 5.0))
    dt = float(base.dt)
    truth = np.array([0.01, 0.015, 0.02])

    def values_of(amplitude):  # the pull (a moving condition) and a shift of the clamp (a constant one)
        return jnp.zeros((3, 2, 3)).at[:, 1, 0].set(amplitude).at[:, 0, 2].set(0.1 * amplitude)

    observed = jaxsync.ensemble(base, N_STEPS, members=jaxsync.Members(dirichlet=values_of(truth)), dt=dt,
                                save=20, executor=QUIET)
    data = jnp.stack([t.displacement[1:, middle] for t in observed])

    @jax.jit
    def loss(amplitude):
        runs = jaxsync.ensemble(base, N_STEPS, members=jaxsync.Members(dirichlet=values_of(amplitude)), dt=dt,
                                save=20)
        return 1e4 * jnp.sum((jnp.stack([t.displacement[1:, middle] for t in runs]) - data) ** 2)

    guess = np.array([0.012, 0.015, 0.017])
    gradient = np.asarray(jax.grad(loss)(jnp.asarray(guess)))
    assert abs(gradient[1]) < 1e-9 * np.abs(gradient).max()  # run 1's guess is its truth
    for r in (0, 2):
        step = np.zeros(3)
        step[r] = 1e-6
        fd = (float(loss(jnp.asarray(guess + step))) - float(loss(jnp.asarray(guess - step)))) / 2e-6
        assert gradient[r] == pytest.approx(fd, rel=1e-7), r


def test_dirichlet_values_of_the_wrong_shape_are_refused(base):
    shape = r"dirichlet has shape \(2, 3, 3\); .* must be \(2, 2, 3\).*problem.dirichlet"
    with pytest.raises(ProblemError, match=shape):
        jaxsync.ensemble(base, 10, members=jaxsync.Members(dirichlet=np.zeros((2, 3, 3))))
    with pytest.raises(ProblemError, match="dirichlet must be finite; run 1"):
        jaxsync.ensemble(base, 10, members=jaxsync.Members(dirichlet=np.array([np.zeros((2, 3)),
                                                                                np.full((2, 3), np.nan)])))
