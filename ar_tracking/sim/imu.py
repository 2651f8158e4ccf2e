"""The IMU simulator shared by the scenarios: true camera motion -> gyro and accelerometer samples.

A strapdown IMU rigidly mounted on the camera (rotation ``R_imu_cam``, no lever arm) measures

* gyro  = s_g * (R_imu_cam omega_cam) + b_g (+ drift(t)) + n_g (rad/s),
* accel = s * (R_imu_cam R_world_cam^T (a_world + g e_z)) + b_a + n_a (m/s^2, specific force:
  a device at rest reads +g upwards),

with white noise ``n ~ N(0, sigma^2)`` per axis, drawn from ``rng`` in this order: gyro, then
accelerometer (a scenario that draws more from the same stream, e.g. the magnetometer of
rotation_sweep, draws after). This is the measurement model the filters invert (Langlotz et al.
2011, section 5; Caarls et al. 2009, section 2.5). Scenarios supply the true kinematics (closed
form or finite differences of their closed-form motion) and their error model: constant biases,
a bias drift, accelerometer and gyro scale errors. robot_arcs and robot_arcs_real keep their own
``simulate_imu`` for now (world-frame angular rate, bias random walks, a lever arm).
"""
from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def imu_samples(omega_cam: Array, specific_force_cam: Array, *, rng: np.random.Generator,
                R_imu_cam: Array, gyro_bias_rad_s: Array, accel_bias_m_s2: Array,
                gyro_noise_rad_s: float, accel_noise_m_s2: float,
                gyro_drift_rad_s: Array | None = None,
                accel_scale: Array | None = None,
                gyro_scale: Array | None = None) -> tuple[Array, Array]:
    """(gyro (N, 3) rad/s, accel (N, 3) m/s^2) in the IMU frame.

    ``omega_cam`` (N, 3): true angular rates in the camera frame; ``specific_force_cam`` (N, 3):
    the true ``R_world_cam^T (a_world + g e_z)`` (see :func:`specific_force_cam`).
    ``gyro_drift_rad_s`` (N, 3) is added to the constant gyro bias; ``accel_scale`` (3,)
    multiplies the specific force per IMU axis before the bias, ``gyro_scale`` (3,) the rate.
    """
    n = len(omega_cam)
    gyro = omega_cam @ R_imu_cam.T
    if gyro_scale is not None:
        gyro = gyro * gyro_scale
    gyro = gyro + gyro_bias_rad_s
    if gyro_drift_rad_s is not None:
        gyro += gyro_drift_rad_s
    gyro += rng.normal(0.0, gyro_noise_rad_s, (n, 3))
    f_imu = specific_force_cam @ R_imu_cam.T
    if accel_scale is not None:
        f_imu = f_imu * accel_scale
    accel = f_imu + accel_bias_m_s2
    accel += rng.normal(0.0, accel_noise_m_s2, (n, 3))
    return gyro, accel


def specific_force_cam(R_world_cam: Array, accel_world: Array, gravity_m_s2: float) -> Array:
    """``R_world_cam^T (a_world + g e_z)`` (N, 3): what an ideal accelerometer on the camera
    reads, in the camera frame (``R_world_cam`` (N, 3, 3), ``accel_world`` (N, 3) without
    gravity)."""
    f_world = accel_world + np.array([0.0, 0.0, gravity_m_s2])
    return np.einsum('nij,nj->ni', np.ascontiguousarray(np.swapaxes(R_world_cam, 1, 2)), f_world)
