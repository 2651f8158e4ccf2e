"""The residual soft iron of a magnetometer, estimated from known rotations.

A calibration leaves part of the soft iron behind: the field is measured as
``m = (I + E) R_imu_P f_P + h`` with E symmetric and a few percent (the simulator's rough
calibration leaves 20-50 % of a 1-4 % distortion; phones after a figure-eight are similar).
Unlike hard iron, E turns the field by an amount that depends on the phone's heading: two
sides of a panorama sweep see different field directions and the panorama's place in the
world averages them. With the panorama's rotations known, E is linear in its six entries at a
given f_P (``E v = J(v) e``), so :mod:`.world_alignment` adds it to its least squares about
the previous solve's f_P (one Gauss-Newton step per IRLS iteration). Over one horizontal
sweep only part of E is observable (the column along the phone's vertical axis looks like
hard iron); the ridge keeps the rest near zero.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def soft_iron_jacobian(v: Array) -> Array:
    """d(E v)/de for each row of v (n, 3), with E = [[e0, e3, e4], [e3, e1, e5], [e4, e5, e2]]:
    shape (n, 3, 6)."""
    J = np.zeros((len(v), 3, 6))
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    J[:, 0, 0], J[:, 0, 3], J[:, 0, 4] = x, y, z
    J[:, 1, 1], J[:, 1, 3], J[:, 1, 5] = y, x, z
    J[:, 2, 2], J[:, 2, 4], J[:, 2, 5] = z, x, y
    return J


def symmetric_from_params(e: Array) -> Array:
    """The symmetric 3x3 matrix of the six entries ordered as in :func:`soft_iron_jacobian`."""
    return np.asarray(e, dtype=float)[_SYMMETRIC]


_SYMMETRIC = np.array([[0, 3, 4], [3, 1, 5], [4, 5, 2]])


# J(v) = sum_k _T[:, :, k] v_k: the Jacobian of soft_iron_jacobian as a constant tensor
# (row r, entry p, component k), and the products of two Jacobians it implies.
_T = np.zeros((3, 6, 3))
for _r, _p, _k in ((0, 0, 0), (0, 3, 1), (0, 4, 2), (1, 1, 1), (1, 3, 0), (1, 5, 2), (2, 2, 2), (2, 4, 0), (2, 5, 1)):
    _T[_r, _p, _k] = 1.0
_T_EE = np.einsum('rpk,rql->pqkl', _T, _T).reshape(36, 9)  # J^T J = _T_EE . (v v^T)
_T_FE = _T.transpose(0, 2, 1).reshape(9, 6)  # rows (r, k)
_T_RHS = _T.transpose(1, 0, 2).reshape(6, 9)  # columns (r, k)
_T_HE = _T.reshape(18, 3)


def soft_iron_normal_equations(w_win: Array, n_w: Array, S_w: Array, m_w: Array, f_lin: Array,
                               ridge: float) -> tuple[Array, Array, Array, Array]:
    """The soft-iron blocks of the normal equations of the windowed field fit.

    Per window: ``w`` its robust weight, ``n`` its sample count, ``S`` the sum of R_imu_P over
    its samples and ``m`` the sum of its field samples. The model term of a sample is
    ``J(R_imu_P f_lin) e``; within a window (0.5 s) the rotation changes little, so J is taken
    at the window's mean ``v = S f_lin / n`` (exact for the terms linear in R). Returns the blocks
    against f_P (3x6), against h (3x6), the 6x6 block (``ridge`` on its diagonal) and the
    right-hand side (6).

    J is linear in v, so every block is a fixed linear map of a weighted moment over the
    windows (sum w S^T v^T, sum w n v, sum w n v v^T, sum w m v^T): four products over the
    windows instead of one Jacobian per window (numpy's per-call cost on the (n, 3, 6) arrays
    was most of the cost)."""
    n = len(n_w)
    v = S_w.reshape(-1, 3).dot(f_lin).reshape(n, 3) / n_w[:, None]
    wv = v * w_win[:, None]
    wnv = wv * n_w[:, None]
    # sum_n w S[j, i] v[k] as [(j, i), k], then A_fe[i, p] = sum_jk T[j, p, k] N[j, i, k]
    # (ndarray.dot: less per-call cost than @ on these small arrays.)
    N = S_w.reshape(n, 9).T.dot(wv).reshape(3, 3, 3)
    A_fe = N.transpose(1, 0, 2).reshape(3, 9).dot(_T_FE)
    A_he = _T_HE.dot(n_w.dot(wv)).reshape(3, 6)
    A_ee = _T_EE.dot(wnv.T.dot(v).reshape(9)).reshape(6, 6)
    if ridge:
        A_ee += np.eye(6) * ridge
    rhs = _T_RHS.dot(m_w.T.dot(wv).reshape(9))
    return A_fe, A_he, A_ee, rhs
