"""Rotation helpers shared by the cores, the simulator and the evaluation.

Conventions (../shared/DESIGN.md section 3):

* ``R_a_b`` is the 3x3 matrix that rotates vectors from frame b into frame a
  (``v_a = R_a_b @ v_b``). A TransformStamped with frame_id a and child_frame_id b carries R_a_b.
* Quaternion arrays say their order in their name: ``quat_xyzw`` (ROS messages, scipy) or
  ``quat_wxyz`` (gtsam, most filter papers).
* World frame ``enu``: x east, y north, z up. ``camera_optical``: z forward, x right, y down.

Everything here is plain numpy/scipy and works on single rotations or stacks of shape (N, 3, 3).
"""
from __future__ import annotations

import math
from collections.abc import Sequence

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation, Slerp

Array = NDArray[np.float64]


def quat_xyzw_to_matrix(quat_xyzw: ArrayLike) -> Array:
    """Rotation matrix (or stack of shape (..., 3, 3)) from quaternions in (x, y, z, w) order,
    normalised first.

    One quaternion (the per-frame and per-message case) is the closed form scipy's
    ``Rotation.from_quat(q).as_matrix()`` evaluates, in Python floats with the same operations in
    the same order: bit-identical to scipy, the same ValueError for a zero or NaN quaternion, and
    ~3.3 us instead of ~7.7 us (scipy's object and checks). Stacks stay with scipy: its compiled
    loop beats the same expression in numpy (1,000 quaternions ~21 us against ~31 us).
    """
    q = np.asarray(quat_xyzw, dtype=float)
    if q.shape != (4,):
        return Rotation.from_quat(q).as_matrix()
    x, y, z, w = float(q[0]), float(q[1]), float(q[2]), float(q[3])
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if not norm > 0:  # zero, or NaN: scipy refuses both
        raise ValueError('Found zero norm quaternions in `quat`.')
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    return np.array([
        [x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw)],
        [2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw)],
        [2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2],
    ])


def quat_wxyz_to_matrix(q_wxyz: Any) -> Array:
    """Rotation matrix of one quaternion in (w, x, y, z) order (normalised), without scipy's
    per-call overhead: for per-sample loops such as the AHRS (~20 us -> ~2 us)."""
    w, x, y, z = q_wxyz.tolist() if isinstance(q_wxyz, np.ndarray) else (float(v) for v in q_wxyz)
    n = w * w + x * x + y * y + z * z
    s = 2.0 / n if n > 0 else 0.0
    return np.array([
        [1 - s * (y * y + z * z), s * (x * y - w * z), s * (x * z + w * y)],
        [s * (x * y + w * z), 1 - s * (x * x + z * z), s * (y * z - w * x)],
        [s * (x * z - w * y), s * (y * z + w * x), 1 - s * (x * x + y * y)],
    ])


def _matrix_to_quat_xyzw_one(R: Array) -> Array:
    """One rotation matrix to (x, y, z, w), w >= 0, by the largest of the trace and the diagonal
    (Shepperd's method, as scipy does per matrix) without scipy's per-call overhead: a node
    publishing every sample spends ~190 us per call in Rotation.from_matrix, ~5 us here."""
    m00, m01, m02 = float(R[0, 0]), float(R[0, 1]), float(R[0, 2])
    m10, m11, m12 = float(R[1, 0]), float(R[1, 1]), float(R[1, 2])
    m20, m21, m22 = float(R[2, 0]), float(R[2, 1]), float(R[2, 2])
    tr = m00 + m11 + m22
    biggest = max(tr, m00, m11, m22)
    if biggest == tr:
        x, y, z, w = m21 - m12, m02 - m20, m10 - m01, 1.0 + tr
    elif biggest == m00:
        x, y, z, w = 1.0 + m00 - m11 - m22, m01 + m10, m02 + m20, m21 - m12
    elif biggest == m11:
        x, y, z, w = m01 + m10, 1.0 - m00 + m11 - m22, m12 + m21, m02 - m20
    else:
        x, y, z, w = m02 + m20, m12 + m21, 1.0 - m00 - m11 + m22, m10 - m01
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if w < 0:
        n = -n
    return np.array([x / n, y / n, z / n, w / n])


def matrix_to_quat_xyzw(R: Array) -> Array:
    """Quaternion(s) in (x, y, z, w) order with w >= 0 (a canonical sign, for reproducibility)."""
    R = np.asarray(R, dtype=float)
    if R.shape == (3, 3) and np.all(np.isfinite(R)):
        return _matrix_to_quat_xyzw_one(R)
    q = Rotation.from_matrix(R).as_quat()
    q = np.asarray(q)
    flip = q[..., 3] < 0
    q[flip] = -q[flip]
    return q


def quat_wxyz_to_xyzw(quat_wxyz: Array) -> Array:
    q = np.asarray(quat_wxyz, dtype=float)
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def quat_xyzw_to_wxyz(quat_xyzw: Array) -> Array:
    q = np.asarray(quat_xyzw, dtype=float)
    return np.concatenate([q[..., 3:], q[..., :3]], axis=-1)


def is_valid_quat(quat: Array, tol: float = 1e-3) -> bool:
    """Finite and of unit norm within ``tol`` (any component order)."""
    q = np.asarray(quat, dtype=float)
    return bool(np.all(np.isfinite(q)) and abs(np.linalg.norm(q) - 1.0) < tol)


def rot_x(angle_rad: float) -> Array:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=float)


def rot_y(angle_rad: float) -> Array:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=float)


def rot_z(angle_rad: float) -> Array:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=float)


def rotvec_to_matrix(rotvec: Array) -> Array:
    """Rotation matrix (or stack) of rotation vectors (axis times angle, rad)."""
    return Rotation.from_rotvec(np.asarray(rotvec, dtype=float)).as_matrix()


def matrix_to_rotvec(R: Array) -> Array:
    """Rotation vector(s) (axis times angle, rad) of a matrix (or stack), the angle in [0, pi]."""
    return Rotation.from_matrix(np.asarray(R, dtype=float)).as_rotvec()


def angle_of(R: Array) -> Array:
    """Rotation angle in radians of a matrix (or stack), robust near 0 and pi."""
    R = np.asarray(R, dtype=float)
    return np.linalg.norm(Rotation.from_matrix(R).as_rotvec(), axis=-1)


def trace_angle(R: Array) -> Array:
    """Rotation angle in radians of a matrix (or stack) from its trace: ~80x faster than
    :func:`angle_of` on thousands of matrices (RANSAC hypotheses), but imprecise below ~1e-4 rad
    (arccos near 1); fine for comparing with thresholds of a degree or more."""
    tr = np.trace(np.asarray(R, dtype=float), axis1=-2, axis2=-1)
    return np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0))


def heading_tilt_error_deg(R_w_est: Array, R_w_true: Array) -> tuple[Array, Array, Array]:
    """Split the orientation error into heading and tilt, in degrees.

    The world-frame error ``E = R_w_est @ R_w_true^T`` is decomposed (swing-twist about the
    world's up axis) into ``E = Rz(heading) @ E_tilt``: the heading error is the rotation about
    up (signed, in (-180, 180]), the tilt error the angle of the remaining rotation, whose axis
    is horizontal. Returns (total, heading, tilt) arrays.
    """
    E = np.asarray(R_w_est, dtype=float) @ np.swapaxes(np.asarray(R_w_true, dtype=float), -1, -2)
    q = Rotation.from_matrix(E).as_quat()  # x, y, z, w
    q = np.atleast_2d(q)
    # Twist about z: the projection of the quaternion onto (0, 0, z, w).
    heading = 2.0 * np.arctan2(q[:, 2], q[:, 3])
    heading = (heading + np.pi) % (2.0 * np.pi) - np.pi
    twist_inv = Rotation.from_rotvec(np.stack([0 * heading, 0 * heading, -heading], axis=-1))
    tilt = (twist_inv * Rotation.from_quat(q)).magnitude()
    total = Rotation.from_quat(q).magnitude()
    shape = np.shape(E)[:-2]
    return (
        np.degrees(total).reshape(shape),
        np.degrees(heading).reshape(shape),
        np.degrees(tilt).reshape(shape),
    )


def camera_heading_pitch_roll_deg(R_enu_cam: Array) -> tuple[Array, Array, Array]:
    """What a person calls the camera's heading, pitch and roll, in degrees.

    heading: compass azimuth of the optical axis (z), clockwise from north, in [0, 360);
    pitch: elevation of the optical axis above the horizon;
    roll: rotation about the optical axis, 0 when the image x axis is horizontal, positive when
    the image turns clockwise as seen by the user (right side down).
    """
    R = np.asarray(R_enu_cam, dtype=float)
    z = R[..., :, 2]  # optical axis in ENU
    x = R[..., :, 0]  # image right in ENU
    heading = np.degrees(np.arctan2(z[..., 0], z[..., 1])) % 360.0
    pitch = np.degrees(np.arcsin(np.clip(z[..., 2], -1.0, 1.0)))
    # Roll: angle of the image x axis below the horizontal plane, measured about z.
    up = np.array([0.0, 0.0, 1.0])
    horiz_right = np.cross(z, up)  # right-hand horizontal vector perpendicular to the view
    norm = np.linalg.norm(horiz_right, axis=-1, keepdims=True)
    horiz_right = horiz_right / np.where(norm < 1e-9, 1.0, norm)
    cos_r = np.sum(x * horiz_right, axis=-1)
    # image down at zero roll (z x right), not world down: -x_z would be sin(roll) * cos(pitch)
    sin_r = np.sum(x * np.cross(z, horiz_right), axis=-1)
    roll = np.degrees(np.arctan2(sin_r, cos_r))
    return heading, pitch, roll


def interpolate_rotations(times: Array, R: Array, query_times: Array) -> tuple[Array, Array]:
    """Slerp a rotation sequence at query times.

    Returns (matrices at the valid queries, boolean mask of queries inside [times[0], times[-1]]).
    ``times`` must be strictly increasing (duplicates are dropped, keeping the first).
    """
    times = np.asarray(times, dtype=float)
    query_times = np.asarray(query_times, dtype=float)
    keep = np.concatenate([[True], np.diff(times) > 0])
    times, R = times[keep], np.asarray(R)[keep]
    inside = (query_times >= times[0]) & (query_times <= times[-1])
    if len(times) < 2:
        return np.repeat(R[:1], int(inside.sum()), axis=0), inside
    slerp = Slerp(times, Rotation.from_matrix(R))
    return slerp(query_times[inside]).as_matrix(), inside


def align_directions(src: Array, dst: Array, weights: Array | None = None) -> Array:
    """The rotation R minimising sum w_i |dst_i - R src_i|^2 for (n, 3) direction sets, n >= 2
    (Wahba's problem / Kabsch, Horn's absolute orientation, solved by SVD). Plain numpy: it
    runs several times per frame in the panorama tracker, where scipy's align_vectors costs
    more than the SVD itself."""
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    H = (dst if weights is None else dst * np.asarray(weights, float)[:, None]).T @ src
    U, _, Vt = np.linalg.svd(H)
    return _proper_product(U, Vt)



def nearest_rotation(M: Array) -> Array:
    """The rotation matrix nearest to a 3x3 matrix in the Frobenius norm (SVD): re-orthonormalises
    a drifting estimate, and applied to a sum of rotations it is their chordal L2 mean."""
    U, _, Vt = np.linalg.svd(np.asarray(M, float))
    return _proper_product(U, Vt)


def _proper_product(U: Array, Vt: Array) -> Array:
    """U diag(1, 1, sign det(U Vt)) Vt of an SVD's orthogonal factors: the rotation (det +1).

    The determinant of the orthogonal U Vt is +-1 to rounding, so its sign from the cofactor
    formula is LAPACK's; and multiplying by the diagonal of ones is exact, so scaling U's last
    column (or leaving it) and one product give the bytes of U @ D @ Vt - without np.linalg.det
    and np.diag, a third of the call in the panorama tracker, which fits twice per frame."""
    (a, b, c), (d, e, f), (g, h, i) = (U @ Vt).tolist()
    sign = np.sign(a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)) or 1.0
    if sign != 1.0:
        U = U.copy()
        U[:, 2] *= sign
    return U @ Vt


def align_about_axis(src: Array, dst: Array, axis: Array, weights: Array | None = None) -> float:
    """The angle psi (rad) minimising sum w_i |dst_i - R(axis, psi) src_i|^2 for (n, 3) vectors,
    n >= 1: the rotation about one known axis (closed form, the 1-DoF case of Wahba's problem).
    With the axis vertical it is the heading between two gravity-aligned direction sets."""
    src = np.asarray(src, float).reshape(-1, 3)
    dst = np.asarray(dst, float).reshape(-1, 3)
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    w = np.ones(len(src)) if weights is None else np.asarray(weights, float)
    sin_part = np.einsum('ij,ij->i', dst, np.cross(k, src))
    cos_part = np.einsum('ij,ij->i', dst, src) - (dst @ k) * (src @ k)
    return math.atan2(float(w @ sin_part), float(w @ cos_part))


def rotations_about_axis(axis: Array, angles: ArrayLike) -> Array:
    """(H, 3, 3) rotations by ``angles`` (rad) about one unit axis (Rodrigues, batched)."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    a = np.asarray(angles, float).reshape(-1)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return (np.eye(3)[None] + np.sin(a)[:, None, None] * K[None]
            + (1.0 - np.cos(a))[:, None, None] * (K @ K)[None])

# ----------------------------------------------------------------------------------------------
# Single rotations on hot paths. scipy's Rotation costs ~20-40 us per call for one rotation; the
# filters run >= 20,000 updates/s and the SLAM tracker several per frame, so exp/log of single
# rotations are the closed forms (Rodrigues).

_I3 = np.eye(3)
_I3.setflags(write=False)


def cross3(a: Array, b: Array) -> Array:
    """Cross product of two 3-vectors (numpy's ``cross`` costs ~10 us for single vectors)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


_NEXT = np.array([1, 2, 0])
_PREV = np.array([2, 0, 1])


def cross_rows(a: Array, b: Array) -> Array:
    """Row-wise cross products of (n, 3) (or broadcasting (1, 3)) arrays: the same products and
    differences as ``np.cross`` (a1 b2 - a2 b1, ...; the same values), without its axis handling,
    which costs several times the arithmetic on a few dozen rows. Written into a C-ordered array
    as np.cross's is (the column gathers come out column-major, and a sum over the rows of that
    layout adds in another order: different last bits)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    np.subtract(a.take(_NEXT, 1) * b.take(_PREV, 1), a.take(_PREV, 1) * b.take(_NEXT, 1), out=out)
    return out


def skew(v: Array) -> Array:
    """The cross-product matrix of a 3-vector: ``skew(a) @ b == cross(a, b)``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def so3_exp(v: Array) -> Array:
    """exp: so(3) 3-vector (rotation vector, rad) -> rotation matrix (Rodrigues)."""
    theta = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    K = skew(v)
    if theta < 1e-8:
        return _I3 + K
    return _I3 + (math.sin(theta) / theta) * K + ((1.0 - math.cos(theta)) / theta**2) * (K @ K)


def so3_log(R: Array) -> Array:
    """log: rotation matrix -> so(3) 3-vector (rad), robust near 0 and pi."""
    cos_t = min(1.0, max(-1.0, 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)))
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    theta = math.acos(cos_t)
    if theta < 1e-6:
        return 0.5 * w
    if math.pi - theta > 1e-4:
        return (theta / (2.0 * math.sin(theta))) * w
    # Near pi: the axis from the symmetric part.
    B = 0.5 * (R + R.T) - cos_t * np.eye(3)
    i = int(np.argmax(np.diag(B)))
    axis = B[:, i] / max(float(np.linalg.norm(B[:, i])), 1e-12)  # B = (1 - cos) a a^T
    if np.dot(axis, w) < 0:
        axis = -axis
    return theta * axis


# ----------------------------------------------------------------------------------------------
# Quaternions in (w, x, y, z) order, one at a time: the error-state filters (core/vio) keep their
# orientation as ``quat_wxyz`` and advance it per IMU sample. Measured (timeit, this machine,
# 2026-11-26): one eskf.predict_orientation step takes ~72 us with these closed forms and ~142 us
# with scipy's Rotation (from_rotvec ~28 us vs quat_wxyz_exp ~5 us; from_quat().as_matrix()
# ~23 us vs unit_quat_wxyz_to_matrix ~7 us), so they stay closed forms.

def quat_wxyz_mul(a: Array, b: Array) -> Array:
    """Hamilton product a * b of two quaternions in (w, x, y, z) order."""
    return np.array(quat_wxyz_mul_floats(a, b))


# The same quaternion algebra on Python floats, for per-sample and per-frame loops where numpy's
# per-call cost on 4-vectors is more than the arithmetic (the azimuth distortion's frame
# comparison: four products and two logarithms per frame, ~42 of ~80 us as arrays).
QuatFloats = tuple[float, float, float, float]


def quat_wxyz_mul_floats(a: Sequence[float] | Array, b: Sequence[float] | Array) -> QuatFloats:
    """:func:`quat_wxyz_mul` on (and to) Python floats."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw)


def quat_wxyz_conj_floats(q: Sequence[float] | Array) -> QuatFloats:
    """:func:`quat_wxyz_conj` on (and to) Python floats."""
    return (q[0], -q[1], -q[2], -q[3])


def quat_wxyz_log_along(q: Sequence[float], u: Sequence[float]) -> float:
    """The component along u of q's rotation vector (the shorter way round), ``quat_wxyz_log(q)
    @ u`` on Python floats."""
    w, x, y, z = q
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    n = math.sqrt(x * x + y * y + z * z)
    k = 2.0 if n < 1e-12 else 2.0 * math.atan2(n, w) / n
    return k * (x * u[0] + y * u[1] + z * u[2])


def quat_wxyz_of_rows(m00: float, m01: float, m02: float, m10: float, m11: float, m12: float,
                      m20: float, m21: float, m22: float) -> QuatFloats:
    """:func:`matrix_to_quat_wxyz` of a rotation matrix given row-major as Python floats."""
    tr = m00 + m11 + m22
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        w, x, y, z = 0.25 * s, (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s
    elif m00 > m11 and m00 > m22:
        s = 2.0 * math.sqrt(1.0 + m00 - m11 - m22)
        w, x, y, z = (m21 - m12) / s, 0.25 * s, (m01 + m10) / s, (m02 + m20) / s
    elif m11 > m22:
        s = 2.0 * math.sqrt(1.0 + m11 - m00 - m22)
        w, x, y, z = (m02 - m20) / s, (m01 + m10) / s, 0.25 * s, (m12 + m21) / s
    else:
        s = 2.0 * math.sqrt(1.0 + m22 - m00 - m11)
        w, x, y, z = (m10 - m01) / s, (m02 + m20) / s, (m12 + m21) / s, 0.25 * s
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if w < 0:
        n = -n
    return (w / n, x / n, y / n, z / n)


def quat_wxyz_exp(rotvec: Array) -> Array:
    """Quaternion (w, x, y, z) of a rotation vector; Fig. 7's q_y = (cos(|y|dt/2), sin(.) y/|y|)
    with y*dt = rotvec."""
    angle = math.sqrt(float(rotvec[0] ** 2 + rotvec[1] ** 2 + rotvec[2] ** 2))
    if angle < 1e-12:
        return np.array([1.0, 0.5 * rotvec[0], 0.5 * rotvec[1], 0.5 * rotvec[2]])
    s = math.sin(0.5 * angle) / angle
    return np.array([math.cos(0.5 * angle), s * rotvec[0], s * rotvec[1], s * rotvec[2]])


def quat_wxyz_log(q: Array) -> Array:
    """Rotation vector of a quaternion (w, x, y, z), taking the shorter way round."""
    w, v = float(q[0]), np.asarray(q[1:], dtype=float)
    if w < 0:
        w, v = -w, -v
    n = float(np.linalg.norm(v))
    if n < 1e-12:
        return 2.0 * v
    return 2.0 * math.atan2(n, w) / n * v


def quat_wxyz_conj(q: Array) -> Array:
    """Conjugate (the inverse of a unit quaternion) in (w, x, y, z) order."""
    return np.array(quat_wxyz_conj_floats(q))


def unit_quat_wxyz_to_matrix(q: Array) -> Array:
    """Rotation matrix of a unit quaternion (w, x, y, z), not normalised (the filters keep theirs
    unit; :func:`quat_wxyz_to_matrix` normalises, and so differs in the last bits)."""
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quat_wxyz(R: Array) -> Array:
    """Unit quaternion (w, x, y, z), w >= 0, of a rotation matrix (Shepperd's method, the trace
    branch first; :func:`matrix_to_quat_xyzw` picks the largest of trace and diagonal)."""
    return np.array(quat_wxyz_of_rows(*np.asarray(R, dtype=float).ravel().tolist()))
