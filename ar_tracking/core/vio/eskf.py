"""The two error-state Kalman filters of Caarls et al. 2009, sec. 2.5, Fig. 7 (prediction) and
Fig. 8 (observation update).

The *real* states (orientation quaternion ``quat_wxyz`` = R_world_imu, gyro bias, position,
velocity, accelerometer bias) are kept apart from the *error* states the filters estimate. The
IMU is treated as an input of the time update ("a computationally cheaper model in which the
inertia sensors are treated as an input", sec. 2.5): each sample advances the real states with
the process model of Fig. 7, and the filters only propagate the covariance of a zero error. A
camera measurement is turned into an error observation by a non-linear transformation (Fig. 8:
``z = q_hat^-1 * q_m`` for orientation, ``z = p_m - p_hat`` for position), applied with the
standard Kalman update, and the estimated error is transferred into the real states at once, so
that the error state is zero again ("x++ = 0").

Deviation from the figure, and why: the orientation error is the 3-vector of the small error
rotation (twice the vector part of the error quaternion) instead of the 4-element error
quaternion with an extra process noise on its scalar part (sigma_q0). The two are the same to
first order; the 3-vector keeps the covariance non-singular without that extra noise. The
process-noise blocks of Fig. 7 are therefore written in angle units (the figure's 1/4 and 1/12
factors for the half-angle become 1 and 1/3). The filters are separate, as in the paper: the
position filter takes the orientation as given (R_k) and does not model its error.

Units: rad, rad/s, m, m/s, m/s^2; time steps in seconds. Gravity points down the world z axis
(ENU, REP-103): the accelerometer measures the specific force f = R^T (a - g), g = (0, 0, -9.80665).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..rotations import (matrix_to_quat_wxyz, quat_wxyz_conj, quat_wxyz_exp, quat_wxyz_log, quat_wxyz_mul,
                         unit_quat_wxyz_to_matrix)

Array = NDArray[np.float64]

GRAVITY_M_S2 = 9.80665
I3 = np.eye(3)
#: chi-square 99.9 % quantile for 3 degrees of freedom: the default innovation gate.
CHI2_3DOF_999 = 16.266


# --- quaternion helpers (w, x, y, z) ------------------------------------------------------
# core.rotations' quaternion section (closed forms: ~72 us per predict_orientation step against
# ~142 us with scipy's Rotation, measured there) under the filters' short names; joint.py,
# rollback.py and the tests import them from here.
quat_mul = quat_wxyz_mul
quat_exp = quat_wxyz_exp
quat_log = quat_wxyz_log
quat_conj = quat_wxyz_conj
quat_to_matrix = unit_quat_wxyz_to_matrix
matrix_to_quat = matrix_to_quat_wxyz


# --- parameters ---------------------------------------------------------------------------

@dataclass(frozen=True)
class FilterNoise:
    """Noise of the process models of Fig. 7 (1-sigma; per-sample values are per IMU sample).

    The names follow the figure: sigma_z,w / sigma_z,a (sensor noise, used through Gamma),
    sigma_dw / sigma_da (unknown change of angular velocity / acceleration caused by the user's
    motion, a white-noise density), sigma_db,w / sigma_db,a (bias random walk densities).
    """

    gyro_noise_rad_s: float = 0.006          # sigma_z,w per sample, rad/s
    angular_rate_change_rad_s: float = 0.01  # sigma_dw, rad/s/sqrt(s)
    gyro_bias_walk_rad_s: float = 2e-4       # sigma_db,w, rad/s/sqrt(s)
    accel_noise_m_s2: float = 0.02           # sigma_z,a per sample, m/s^2
    accel_change_m_s2: float = 0.03          # sigma_da, m/s^2/sqrt(s)
    accel_bias_walk_m_s2: float = 2e-3       # sigma_db,a, m/s^2/sqrt(s)


@dataclass(frozen=True)
class InitialUncertainty:
    """1-sigma of the states at initialisation from the first camera pose."""

    velocity_m_s: float = 1.0
    gyro_bias_rad_s: float = 0.02
    accel_bias_m_s2: float = 0.2


# --- the states ---------------------------------------------------------------------------

@dataclass
class OrientationState:
    """Real orientation states and the covariance of the orientation error filter (Fig. 7 top).

    ``quat_wxyz`` rotates IMU-frame vectors into the world frame; the error ``dtheta`` is in the
    IMU frame (q_true = q_hat * exp(dtheta)); ``P`` is the 6x6 covariance of (dtheta, db_g).
    """

    quat_wxyz: Array
    gyro_bias: Array
    P: Array

    def copy(self) -> 'OrientationState':
        return OrientationState(self.quat_wxyz.copy(), self.gyro_bias.copy(), self.P.copy())

    @property
    def R(self) -> Array:
        return quat_to_matrix(self.quat_wxyz)


@dataclass
class PositionState:
    """Real position states and the covariance of the position error filter (Fig. 7 bottom):
    position and velocity of the IMU in the world frame, accelerometer bias in the IMU frame;
    ``P`` is the 9x9 covariance of (dp, dv, db_a)."""

    p: Array
    v: Array
    accel_bias: Array
    P: Array

    def copy(self) -> 'PositionState':
        return PositionState(self.p.copy(), self.v.copy(), self.accel_bias.copy(), self.P.copy())


# --- time update (Fig. 7) -----------------------------------------------------------------

def predict_orientation(s: OrientationState, gyro: Array, dt: float, noise: FilterNoise) -> Array:
    """Advance the real orientation with the bias-corrected rate and propagate P (in place).

    Fig. 7: w = w_g - b_g, q_k = q_(k-1) * q_w, b_g,k = b_g,(k-1);
    P_(k+1) = Phi P Phi^T + Gamma sigma_z,w^2 Gamma^T + Q_dw + Q_db. Returns the rate w used.
    """
    w = gyro - s.gyro_bias
    dq = quat_exp(w * dt)
    q = quat_mul(s.quat_wxyz, dq)
    s.quat_wxyz = q / math.sqrt(float(q @ q))
    Rw = quat_to_matrix(dq)
    P = s.P
    # Phi = [[Rw^T, -I dt], [0, I]] (error in the new body frame; bias error enters with -dt).
    A = Rw.T
    P_tt = A @ P[:3, :3] @ A.T
    P_tb = A @ P[:3, 3:]
    P_bb = P[3:, 3:]
    P_tt = P_tt - dt * (P_tb + P_tb.T) + dt * dt * P_bb
    P_tb = P_tb - dt * P_bb
    sz2 = noise.gyro_noise_rad_s ** 2
    sdw2 = noise.angular_rate_change_rad_s ** 2
    sdb2 = noise.gyro_bias_walk_rad_s ** 2
    q_tt = sz2 * dt * dt + sdw2 * dt + sdb2 * dt ** 3 / 3.0
    q_tb = -sdb2 * dt * dt / 2.0
    q_bb = sdb2 * dt
    out = np.empty((6, 6))
    out[:3, :3] = P_tt + q_tt * I3
    out[:3, 3:] = P_tb + q_tb * I3
    out[3:, :3] = out[:3, 3:].T
    out[3:, 3:] = P_bb + q_bb * I3
    s.P = out
    return w


def predict_position(s: PositionState, R_world_imu: Array, accel: Array, dt: float,
                     noise: FilterNoise, gravity_m_s2: float = GRAVITY_M_S2,
                     accel_step_cov: Array | None = None) -> Array:
    """Advance position/velocity with the specific force and propagate P (in place).

    Fig. 7: v_k = v_(k-1) + (R_k a_k - g) dt, p_k = p_(k-1) + (v_(k-1) + v_k) dt / 2,
    b_a,k = b_a,(k-1); Phi = [[I, I dt, -R dt^2/2], [0, I, -R dt], [0, 0, I]],
    Gamma = [R dt^2/2, R dt, 0], Q_da and Q_db as in the figure (with R in the bias coupling,
    because b_a is kept in the IMU frame). Returns the world acceleration used.

    ``accel_step_cov`` (3x3, world frame, (m/s^2)^2) is the uncertainty of the step's mean
    acceleration itself - the integration error of the sampled input, see
    :func:`sampling_error_cov` - entered through Gamma = [dt^2/2, dt, 0] like the sensor noise.
    """
    a_world = R_world_imu @ (accel - s.accel_bias)
    a_world[2] -= gravity_m_s2
    v_new = s.v + a_world * dt
    s.p = s.p + 0.5 * (s.v + v_new) * dt
    s.v = v_new
    R = R_world_imu
    h = 0.5 * dt * dt
    Phi = np.eye(9)
    Phi[:3, 3:6] = dt * I3
    Phi[:3, 6:] = -h * R
    Phi[3:6, 6:] = -dt * R
    out = Phi @ s.P @ Phi.T
    sa2 = noise.accel_noise_m_s2 ** 2
    sda2 = noise.accel_change_m_s2 ** 2
    sdb2 = noise.accel_bias_walk_m_s2 ** 2
    dt2, dt3 = dt * dt, dt ** 3
    # Gamma sigma_z,a^2 Gamma^T + Q_da + Q_db (position/velocity blocks are rotation-free).
    qpp = sa2 * h * h + sda2 * dt3 / 3.0 + sdb2 * dt ** 5 / 20.0
    qpv = sa2 * h * dt + sda2 * dt2 / 2.0 + sdb2 * dt ** 4 / 8.0
    qvv = sa2 * dt2 + sda2 * dt + sdb2 * dt3 / 3.0
    out[:3, :3] += qpp * I3
    out[:3, 3:6] += qpv * I3
    out[3:6, :3] += qpv * I3
    out[3:6, 3:6] += qvv * I3
    qpb = -sdb2 * dt3 / 6.0 * R
    qvb = -sdb2 * dt2 / 2.0 * R
    out[:3, 6:] += qpb
    out[6:, :3] += qpb.T
    out[3:6, 6:] += qvb
    out[6:, 3:6] += qvb.T
    out[6:, 6:] += sdb2 * dt * I3
    if accel_step_cov is not None:
        out[:3, :3] += h * h * accel_step_cov
        out[:3, 3:6] += h * dt * accel_step_cov
        out[3:6, :3] += h * dt * accel_step_cov
        out[3:6, 3:6] += dt2 * accel_step_cov
    s.P = out
    return a_world


def sampling_error_cov(delta_world: Array) -> Array:
    """Covariance of the error of the trapezoid mean of a sampled input over one step, from the
    change of that input between the step's two samples (world frame).

    The time update takes the mean of the two samples as the input over the step. That is exact
    for an input that changes linearly between samples, but not when it changes abruptly in
    between: a tool that starts or stops turning fast steps its angular acceleration, and the
    IMU, turned with a lever arm, sees a step of alpha x r in its specific force (several m/s^2
    at 100 Hz). With the step at an unknown, uniformly distributed instant inside the interval,
    the mean the filter uses is wrong by (1/2 - u) * delta, u ~ U(0, 1): variance
    delta delta^T / 12. Where the input is smooth delta is small and so is this term; where it
    jumps the filter now knows that its velocity is less certain, and the next camera poses pull
    it back instead of being weighed against a confident but wrong prediction.
    """
    d = np.asarray(delta_world, dtype=float).reshape(3)
    return np.outer(d, d) / 12.0


# --- observation update (Fig. 8) ----------------------------------------------------------

@dataclass(frozen=True)
class UpdateResult:
    """Outcome of one observation update: accepted or not, and the squared Mahalanobis
    distance of the innovation (what the gate compares)."""

    accepted: bool
    mahalanobis2: float


def orientation_innovation(s: OrientationState, quat_meas_wxyz: Array, R_meas_body: Array) -> tuple[Array, Array]:
    """Error observation z = 2 vec(q_hat^-1 * q_m) (Fig. 8) and its covariance S = P_tt + R."""
    z = quat_log(quat_mul(quat_conj(s.quat_wxyz), quat_meas_wxyz))
    S = s.P[:3, :3] + R_meas_body
    return z, S


def update_orientation(s: OrientationState, quat_meas_wxyz: Array, R_meas_body: Array,
                       gate: float | None = CHI2_3DOF_999, apply: bool = True) -> UpdateResult:
    """Kalman update of (dtheta, db_g) with H = [I 0], then transfer to the real states:
    q+ = q- * dq+, b_g+ = b_g- + db+ (Fig. 8); the error state is zero again."""
    z, S = orientation_innovation(s, quat_meas_wxyz, R_meas_body)
    result, x, P = _gated_update(s.P, z, S, gate, apply)
    if x is not None:
        s.P = P
        q = quat_mul(s.quat_wxyz, quat_exp(x[:3]))
        s.quat_wxyz = q / np.linalg.norm(q)
        s.gyro_bias = s.gyro_bias + x[3:]
    return result


def position_innovation(s: PositionState, p_meas: Array, R_meas: Array) -> tuple[Array, Array]:
    """Error observation z = p_t - p_hat (Fig. 8) and S = P_pp + R."""
    return p_meas - s.p, s.P[:3, :3] + R_meas


def update_position(s: PositionState, p_meas: Array, R_meas: Array,
                    gate: float | None = CHI2_3DOF_999, apply: bool = True) -> UpdateResult:
    """Kalman update of (dp, dv, db_a) with H = [I 0 0], then transfer: p+ = p- + dp, etc."""
    z, S = position_innovation(s, p_meas, R_meas)
    result, x, P = _gated_update(s.P, z, S, gate, apply)
    if x is not None:
        s.P = P
        s.p = s.p + x[:3]
        s.v = s.v + x[3:6]
        s.accel_bias = s.accel_bias + x[6:]
    return result


def _gated_update(P: Array, z: Array, S: Array, gate: float | None,
                  apply: bool) -> tuple[UpdateResult, Array | None, Array]:
    """The shared Kalman step of both filters, H = [I 0 ...]: Mahalanobis gate on the
    innovation z (covariance S), then the error-state estimate x and the updated covariance.
    x is None when the measurement is rejected or only tested (apply=False)."""
    Sinv = np.linalg.inv(S)
    d2 = float(z @ Sinv @ z)
    if not math.isfinite(d2) or (gate is not None and d2 > gate):
        return UpdateResult(False, d2), None, P
    if not apply:
        return UpdateResult(True, d2), None, P
    K = P[:, :3] @ Sinv
    P_new = P - K @ S @ K.T
    return UpdateResult(True, d2), K @ z, 0.5 * (P_new + P_new.T)
