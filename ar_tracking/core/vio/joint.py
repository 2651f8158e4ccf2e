"""One joint error-state filter over orientation and position (15 error states), the
alternative to the two separate filters of Caarls et al. 2009, Fig. 7.

Why: the paper's two filters are separate - the position filter takes the orientation as given.
On real camera poses that loses two couplings that carry most of the remaining position error:

* **in the time update**, an orientation error tilts the specific force: the position filter
  integrates gravity leaking through the tilt (9.81 m/s^2 x 0.05 deg = 8.6 mm/s^2, as large as
  the accelerometer bias) without knowing it. Here dv' = -R [a]x dtheta - R db_a, so the
  orientation uncertainty flows into the velocity and position covariance, and a position
  innovation corrects the tilt (and the gyro bias) as well;
* **in the observation update**, a marker pose's position and orientation errors are strongly
  correlated (the rotation-translation ambiguity of a small marker group seen from a few metres:
  a sideways shift of the camera looks almost like a turn). The separate filters drop the
  off-diagonal blocks of the pose covariance; here the full 6x6 covariance is used, so the
  gyro-propagated orientation, more precise than a single pose's, tells how much of the pose's
  position error is the turn-like part.

Error state (IMU frame for the angle, world for the rest; true = estimate (+) error):
``x = (dtheta, db_g, dp, dv, db_a)``, q_true = q_hat * exp(dtheta). The real states and the
diagonal blocks keep the layout of :class:`.eskf.OrientationState` (6x6) and
:class:`.eskf.PositionState` (9x9); the joint covariance is those two blocks plus their 6x9
cross block.

The process model is that of Fig. 7 (the same real-state equations and noise terms as
:func:`.eskf.predict_orientation` / :func:`.eskf.predict_position`), plus the coupling
Phi_v,theta = -R_mid [a - b_a]x E^T dt, Phi_p,theta = Phi_v,theta dt / 2 (R_mid the orientation at
mid-step, E the rotation over the first half step).

Camera pose observation (Fig. 8's non-linear transformation, both parts at once): predicted
camera pose R_hat R_imu_cam, p_hat + R_hat t_imu_cam; innovation z = (p_m - p_cam_hat,
log(R_m R_cam_hat^T)) in the world (the marker pose covariance's convention); H = [[-R [t]x, 0,
I, 0, 0], [R, 0, 0, 0, 0]].
"""
from __future__ import annotations

import math

import numpy as np

from ..rotations import skew
from .eskf import (
    CHI2_3DOF_999,
    GRAVITY_M_S2,
    Array,
    FilterNoise,
    OrientationState,
    PositionState,
    UpdateResult,
    predict_orientation,
    predict_position,
    quat_exp,
    quat_log,
    quat_mul,
    quat_to_matrix,
    matrix_to_quat,
)


def joint_covariance(ori: OrientationState, pos: PositionState, cross: Array) -> Array:
    """The 15x15 covariance of (dtheta, db_g, dp, dv, db_a) from its blocks."""
    P = np.empty((15, 15))
    P[:6, :6] = ori.P
    P[6:, 6:] = pos.P
    P[:6, 6:] = cross
    P[6:, :6] = cross.T
    return P


def split_covariance(P: Array, ori: OrientationState, pos: PositionState) -> Array:
    """Write the diagonal blocks of a joint covariance back into the states; returns the cross
    block (6x9)."""
    P = 0.5 * (P + P.T)
    ori.P = P[:6, :6].copy()
    pos.P = P[6:, 6:].copy()
    return P[:6, 6:].copy()


def predict_joint(ori: OrientationState, pos: PositionState, cross: Array, gyro: Array, accel: Array,
                  dt: float, noise: FilterNoise, gravity_m_s2: float = GRAVITY_M_S2,
                  accel_step_cov: Array | None = None) -> tuple[Array, Array, Array]:
    """One time update of the real states (as Fig. 7: the orientation with the bias-corrected
    rate, the position with the specific force rotated at mid-step) and of the joint covariance.

    Returns (cross block after the step, bias-corrected rate w, world acceleration). The diagonal
    blocks' process noise is exactly that of the separate filters; only the couplings are new.
    """
    q_prev = ori.quat_wxyz
    P0 = joint_covariance(ori, pos, cross)
    # Real states and the process noise of each block: the separate filters' own updates, run
    # on zero covariances (their output covariance is then exactly Q).
    ori.P = np.zeros((6, 6))
    w = predict_orientation(ori, gyro, dt, noise)
    Q_o = ori.P
    R_mid = quat_to_matrix(quat_mul(q_prev, quat_exp(0.5 * dt * w)))
    a_body = accel - pos.accel_bias
    pos.P = np.zeros((9, 9))
    a_world = predict_position(pos, R_mid, accel, dt, noise, gravity_m_s2, accel_step_cov)
    Q_p = pos.P
    I3 = np.eye(3)
    Phi = np.eye(15)
    Phi[:3, :3] = quat_to_matrix(quat_exp(w * dt)).T
    Phi[:3, 3:6] = -dt * I3
    Phi[6:9, 9:12] = dt * I3
    Phi[6:9, 12:] = -0.5 * dt * dt * R_mid
    Phi[9:12, 12:] = -dt * R_mid
    # the force is rotated at mid-step: R_mid(true) = R_mid exp(E^T dtheta), E = exp(w dt / 2)
    Ra = R_mid @ skew(a_body) @ quat_to_matrix(quat_exp(0.5 * dt * w)).T
    Phi[9:12, :3] = -dt * Ra
    Phi[6:9, :3] = -0.5 * dt * dt * Ra
    P = Phi @ P0 @ Phi.T
    P[:6, :6] += Q_o
    P[6:, 6:] += Q_p
    return split_covariance(P, ori, pos), w, a_world


def pose_jacobian(R_world_imu: Array, t_imu_cam: Array) -> Array:
    """H (6x15) of the camera pose (position, then rotation in the world) with respect to the
    error state: the lever arm turns an orientation error into a camera position error."""
    H = np.zeros((6, 15))
    H[:3, :3] = -R_world_imu @ skew(t_imu_cam)
    H[:3, 6:9] = np.eye(3)
    H[3:, :3] = R_world_imu
    return H


def pose_observation(ori: OrientationState, pos: PositionState, R_imu_cam: Array, t_imu_cam: Array,
                     R_meas_world_cam: Array, p_meas_world_cam: Array) -> tuple[Array, Array]:
    """Innovation z (6: position, then rotation in the world) of a camera pose and its H (6x15)."""
    R = ori.R
    R_cam = R @ R_imu_cam
    p_cam = pos.p + R @ t_imu_cam
    z = np.empty(6)
    z[:3] = p_meas_world_cam - p_cam
    z[3:] = quat_log(matrix_to_quat(R_meas_world_cam @ R_cam.T))
    return z, pose_jacobian(R, t_imu_cam)


def update_joint(ori: OrientationState, pos: PositionState, cross: Array, R_imu_cam: Array, t_imu_cam: Array,
                 R_meas_world_cam: Array, p_meas_world_cam: Array, R_meas: Array,
                 gate: float | None = CHI2_3DOF_999, apply: bool = True) -> tuple[UpdateResult, Array]:
    """Kalman update of all 15 error states with one camera pose (6x6 covariance ``R_meas`` in
    ROS order: position, rotation about the world axes), then the transfer into the real states
    (Fig. 8: q+ = q- * exp(dtheta), the rest added); the error state is zero again.

    The gate tests the position part and the orientation part of the innovation separately
    against ``gate`` (each 3 degrees of freedom, as the separate filters did), so that the one
    parameter keeps its meaning; the reported distance is the larger of the two. Returns the
    result and the new cross block."""
    z, H = pose_observation(ori, pos, R_imu_cam, t_imu_cam, R_meas_world_cam, p_meas_world_cam)
    P = joint_covariance(ori, pos, cross)
    S = H @ P @ H.T + R_meas
    S = 0.5 * (S + S.T)
    try:
        d2 = max(float(z[:3] @ np.linalg.solve(S[:3, :3], z[:3])), float(z[3:] @ np.linalg.solve(S[3:, 3:], z[3:])))
        Sinv = np.linalg.inv(S)
    except np.linalg.LinAlgError:
        return UpdateResult(False, math.inf), cross
    if not math.isfinite(d2) or (gate is not None and d2 > gate):
        return UpdateResult(False, d2), cross
    if not apply:
        return UpdateResult(True, d2), cross
    K = P @ H.T @ Sinv
    x = K @ z
    IKH = np.eye(15) - K @ H
    P_new = IKH @ P @ IKH.T + K @ R_meas @ K.T   # Joseph form: stays positive definite
    q = quat_mul(ori.quat_wxyz, quat_exp(x[:3]))
    ori.quat_wxyz = q / np.linalg.norm(q)
    ori.gyro_bias = ori.gyro_bias + x[3:6]
    pos.p = pos.p + x[6:9]
    pos.v = pos.v + x[9:12]
    pos.accel_bias = pos.accel_bias + x[12:]
    return UpdateResult(True, d2), split_covariance(P_new, ori, pos)
