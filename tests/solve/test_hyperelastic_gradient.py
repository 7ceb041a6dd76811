"""Gradients of explicit hyperelastic runs with respect to the material parameters.

A short finite-strain run of a clamped beam (4 x 1 x 1 cm, 20 nodes, 24 tetrahedra) under
a pressure ramped onto its top face swings its free end by 3 to 4.5 cm within 300 steps
(large rotations). ``jax.grad`` of a scalar of its trajectory, through
:func:`jaxsync.simulate` (one device, and two parts with psum: ``tests/conftest.py``
emulates two CPU devices), is compared with central finite differences of the same loss
for every parameter of :class:`jaxsync.NeoHookean` (and the pressure's magnitude and the
damping), :class:`jaxsync.NearlyIncompressibleNeoHookean` and
:class:`jaxsync.HolzapfelGasserOgden` (helical fibres, partly stretched by the bending).

Finite differences: relative steps h = 3e-5, float64 (truncation ~ h^2 |f'''| / 6: at most
2e-8 relative here, for the nearly incompressible law's nu, on which its bulk modulus
depends as 1 / (1 - 2 nu); round-off ~ 1e-16 / h). Measured agreement: 6e-8 or better,
most parameters 1e-9 to 1e-11. HGO is checked at zero dispersion: with kappa > 0 its fibre
stress jumps where a family switches on (I4 = 1), so the loss has small jumps in the
parameters (:class:`jaxsync.HolzapfelGasserOgden`).

:func:`jaxsync.steady_state` runs Newton's method in numpy/scipy on the host, so it is not
traced by JAX: the static solution's derivative is checked here by the implicit function
theorem, du/dp = K_T^-1 (df/dp - d f_int/dp) with the tangent of
:func:`jaxsync.fem.forces.tangent_matrix`, against central differences of
``steady_state``.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsync
from jaxsync.fem.materials import (
    HolzapfelGasserOgden,
    NearlyIncompressibleNeoHookean,
    NeoHookean,
    helical_fibres,
)

N_STEPS, SAVE_EVERY = 300, 10
PRESSURE, T_RAMP, ALPHA = 3.0e4, 0.05, 5.0
H_RELATIVE = 3e-5


@pytest.fixture(scope="module")
def beam():
    return jaxsync.box_beam(4.0, 1.0, 1.0, (4, 1, 1))


def _fibres(mesh, angle=35.0):
    centres = mesh.points[mesh.tets].mean(axis=1)
    return helical_fibres(centres, axis=(1.0, 0.0, 0.0), angle=angle, origin=(0.0, 0.5, 0.5))


def _problem(mesh, material, pressure=PRESSURE, damping=ALPHA):
    """The clamped beam (x = 0) under a pressure on its top face (z = 1) ramped over T_RAMP."""
    problem = jaxsync.cantilever(mesh, material=material, body_force=(0.0, 0.0, 0.0), damping=damping)
    return problem.replace(loads=[jaxsync.Pressure(pressure, jaxsync.Ramp(T_RAMP), surface="z1")])


LAWS = {
    # name: (the parameters' values, a function of them to (material, pressure, damping))
    "neo-hookean": (
        dict(E=1.0e6, nu=0.3, pressure=PRESSURE, damping=ALPHA),
        lambda p, fibres: (NeoHookean(p["E"], p["nu"], 1.0), p["pressure"], p["damping"])),
    "nearly-incompressible": (
        dict(E=1.0e6, nu=0.45),
        lambda p, fibres: (NearlyIncompressibleNeoHookean(p["E"], p["nu"], 1.0), PRESSURE, ALPHA)),
    "hgo": (
        dict(mu=3.0e5, k1=2.0e5, k2=0.8, kappa_bulk=1.0e6, dispersion=0.0),
        lambda p, fibres: (HolzapfelGasserOgden(fibres=fibres, **p), PRESSURE, ALPHA)),
}


def make_loss(mesh, law, partitions=None):
    """(loss of a vector of the law's parameters, returning (loss, largest |u|), their names,
    their values)."""
    values, build = LAWS[law]
    names = tuple(values)
    fibres = _fibres(mesh)
    x0 = np.array([values[n] for n in names], dtype=float)
    # the default step of a hyperelastic problem is computed on the host from a concrete
    # law (it cannot follow traced parameters): take the reference problem's, pass it as dt
    dt = _problem(mesh, *build(values, fibres)).dt
    kwargs = {} if partitions is None else {"partitions": partitions}

    def loss(x):
        problem = _problem(mesh, *build(dict(zip(names, x)), fibres))
        u = jaxsync.simulate(problem, N_STEPS, dt=dt, save=SAVE_EVERY, **kwargs).displacement
        return jnp.mean(u ** 2), jnp.max(jnp.abs(u))  # [cm^2]: every node, component, saved time

    return loss, names, x0


def central_differences(f, x0, h_relative=H_RELATIVE):
    """d f / d x_i by central differences, steps h_relative |x_i| (h_relative for x_i = 0)."""
    out = []
    for i in range(len(x0)):
        h = h_relative * (abs(x0[i]) or 1.0)
        plus, minus = x0.copy(), x0.copy()
        plus[i] += h
        minus[i] -= h
        out.append((float(f(plus)) - float(f(minus))) / (2 * h))
    return np.array(out)


@pytest.fixture(scope="module")
def gradients(beam):
    """{(law, partitions): (gradient, central differences, loss, largest |u|, x0, names)}, filled on demand."""
    found = {}

    def get(law, partitions):
        if (law, partitions) not in found:
            loss, names, x0 = make_loss(beam, law, partitions)
            value_and_grad = jax.jit(jax.value_and_grad(loss, has_aux=True))
            (value, largest), grad = value_and_grad(x0)
            # the differences from the same compiled program's values (a run of this beam
            # costs a millisecond; a second compilation, of the forward run alone, seconds)
            forward = lambda x: value_and_grad(x)[0][0]  # noqa: E731
            found[law, partitions] = (np.asarray(grad), central_differences(forward, x0), float(value),
                                      float(largest), x0, names)
        return found[law, partitions]

    return get


def check_gradient(gradients, law, partitions):
    grad, fd, value, largest, x0, names = gradients(law, partitions)
    # the run is at finite strain: the free end moves by more than the beam's thickness
    assert largest > 1.0
    # every parameter matters: a relative sensitivity x dL/dx / L far above the FD error
    sensitivity = np.abs(grad * np.where(x0 == 0, 1.0, x0)) / value
    assert np.all(sensitivity > 1e-2), dict(zip(names, sensitivity))
    errors = np.abs(grad / fd - 1)
    assert np.all(errors < 1e-6), dict(zip(names, errors))


# the default run checks the gradient of a run with neo-hookean (the same test); the gradients of the other laws'
# forces in their parameters in test_hyperelastic.py::test_gradient_of_the_internal_force_wrt_parameters
@pytest.mark.filterwarnings("ignore::jaxsync.fem.LockingWarning")
@pytest.mark.parametrize("law", ["neo-hookean", pytest.param("nearly-incompressible", marks=pytest.mark.slow),
                                 pytest.param("hgo", marks=pytest.mark.slow)])
def test_material_gradient_equals_central_differences(gradients, law):
    check_gradient(gradients, law, None)


@pytest.mark.filterwarnings("ignore::jaxsync.fem.LockingWarning")
# the default run checks the partitioned gradient with neo-hookean (the same test); the hgo gradient
# on one device in test_material_gradient_equals_central_differences[hgo]
@pytest.mark.parametrize("law", [
    "neo-hookean",
    pytest.param("hgo", marks=pytest.mark.slow),
    pytest.param("nearly-incompressible", marks=pytest.mark.slow),
])
def test_partitioned_material_gradient_equals_central_differences(gradients, law):
    # two parts (psum): central differences of the partitioned run, and the single device's gradient
    check_gradient(gradients, law, 2)
    np.testing.assert_allclose(gradients(law, 2)[0], gradients(law, None)[0], rtol=1e-10)


def test_static_solution_gradient_by_the_implicit_function_theorem(beam):
    # steady_state is Newton's method on the host (numpy, scipy), not traced by JAX; its
    # derivative in the parameters follows from f_int(u(p), p) = f(p): du/dp at the free
    # dofs = K_T^-1 (df/dp - d f_int/dp), K_T = tangent_matrix(u), d f_int/dp by jax.jacfwd
    import dataclasses

    import scipy.sparse.linalg as spla

    from jaxsync.fem.forces import TotalLagrangian, tangent_matrix

    x0 = np.array([1.0e6, 0.3, PRESSURE])
    tip = int(np.argmax(beam.points[:, 0] + beam.points[:, 2]))  # the free end's top corner

    def static(x):
        return _problem(beam, NeoHookean(x[0], x[1], 1.0), x[2])

    problem = static(x0)
    u = jaxsync.steady_state(problem, load_steps=4, tol=1e-13)
    assert -u[tip, 2] > 1.0  # finite strain
    op = TotalLagrangian().operator(problem)
    K = tangent_matrix(op, u)
    f = np.sum([np.asarray(v).reshape(-1) for v in problem.load_vectors()[0]], axis=0)

    def out_of_balance(x):
        law = dataclasses.replace(op, material=NeoHookean(x[0], x[1], 1.0))
        return law.matvec(jnp.asarray(u)).reshape(-1) - f * (x[2] / x0[2])

    dr = np.asarray(jax.jacfwd(out_of_balance)(jnp.asarray(x0)))  # (n_dofs, 3)
    fixed, _ = problem.dirichlet_dofs()
    free = np.setdiff1d(np.arange(problem.n_dofs), fixed)
    du = np.zeros_like(dr)
    du[free] = -spla.splu(K[free][:, free].tocsc()).solve(dr[free])
    implicit = du[3 * tip + 2]
    # Newton to round-off (tol 1e-13), so that differences of u resolve 1e-9 of its derivative
    fd = central_differences(lambda x: jaxsync.steady_state(static(x), load_steps=4, tol=1e-13)[tip, 2], x0, 1e-4)
    np.testing.assert_allclose(implicit, fd, rtol=1e-6)
