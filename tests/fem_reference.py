"""Independent NumPy/SciPy reference implementations used by the tests.

Nothing here imports jaxsync: P1 tetrahedral elasticity is assembled from the textbook
formula K_e = V_e B^T D B, and the explicit update is written out with SciPy sparse.
"""

import numpy as np
import scipy.sparse as sp


def p1_gradients(points, tets):
    """(n_elements, 4, 3) gradients of the barycentric shape functions, and volumes."""
    X = points[tets]  # (m, 4, 3)
    A = np.concatenate([np.ones((len(tets), 4, 1)), X], axis=2)  # rows [1, x, y, z]
    C = np.linalg.inv(A)  # columns: coefficients of each shape function
    grads = np.transpose(C[:, 1:, :], (0, 2, 1))  # (m, 4, 3)
    vol = np.abs(np.linalg.det(A)) / 6.0
    return grads, vol


def elasticity_matrix(E, nu):
    lam = E * nu / ((1 + nu) * (1 - 2 * nu))
    mu = E / (2 * (1 + nu))
    D = np.zeros((6, 6))
    D[:3, :3] = lam
    D[np.arange(3), np.arange(3)] += 2 * mu
    D[np.arange(3, 6), np.arange(3, 6)] = mu
    return D


def stiffness(points, tets, E, nu):
    """Global K (CSR), node-interleaved dofs, Voigt strain (xx, yy, zz, yz, xz, xy)."""
    grads, vol = p1_gradients(points, tets)
    m = len(tets)
    B = np.zeros((m, 6, 12))
    for a in range(4):
        gx, gy, gz = grads[:, a, 0], grads[:, a, 1], grads[:, a, 2]
        c = 3 * a
        B[:, 0, c] = gx
        B[:, 1, c + 1] = gy
        B[:, 2, c + 2] = gz
        B[:, 3, c + 1], B[:, 3, c + 2] = gz, gy
        B[:, 4, c], B[:, 4, c + 2] = gz, gx
        B[:, 5, c], B[:, 5, c + 1] = gy, gx
    D = elasticity_matrix(E, nu)
    Ke = np.einsum("mki,kl,mlj,m->mij", B, D, B, vol)
    dofs = (3 * tets[:, :, None] + np.arange(3)).reshape(m, 12)
    rows = np.repeat(dofs, 12, axis=1).ravel()
    cols = np.tile(dofs, (1, 12)).ravel()
    n = 3 * len(points)
    return sp.coo_matrix((Ke.ravel(), (rows, cols)), shape=(n, n)).tocsr()


def consistent_mass(points, tets, rho):
    """Consistent P1 mass: rho V_e / 20 (1 + delta_ab) per component."""
    _, vol = p1_gradients(points, tets)
    local = (np.ones((4, 4)) + np.eye(4)) / 20.0
    n = len(points)
    rows, cols, vals = [], [], []
    for a in range(4):
        for b in range(4):
            for c in range(3):
                rows.append(3 * tets[:, a] + c)
                cols.append(3 * tets[:, b] + c)
                vals.append(rho * vol * local[a, b])
    return sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(3 * n, 3 * n)).tocsr()


def lumped_mass(points, tets, rho):
    """(3 n,) lumped mass per dof: rho V_e / 4 at each node of e."""
    _, vol = p1_gradients(points, tets)
    m = np.zeros(len(points))
    np.add.at(m, tets, np.repeat(rho * vol[:, None] / 4.0, 4, axis=1))
    return np.repeat(m, 3)


def body_force(points, tets, b):
    """(3 n,) nodal loads of a constant body force b: V_e / 4 b at each node."""
    _, vol = p1_gradients(points, tets)
    f = np.zeros((len(points), 3))
    np.add.at(f, tets.ravel(), np.repeat(vol / 4.0, 4)[:, None] * np.asarray(b)[None, :])
    return f.ravel()


def central_difference(K, m, f_of_t, alpha, dt, d0, dm1, fixed, values, n_steps):
    """Plain SciPy loop of the lumped central-difference update; returns all states
    (n_steps + 1, n_dofs) from d0. ``f_of_t(t)`` is evaluated at the current time."""
    out = np.empty((n_steps + 1, len(d0)))
    out[0] = d0
    d, prev = d0.copy(), dm1.copy()
    a = 0.5 * alpha * dt
    for n in range(n_steps):
        new = (dt**2 * (f_of_t(n * dt) - K @ d) / m + 2 * d - (1 - a) * prev) / (1 + a)
        new[fixed] = values
        prev, d = d, new
        out[n + 1] = d
    return out
