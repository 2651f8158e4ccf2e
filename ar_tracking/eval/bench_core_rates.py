"""Samples per second of the orientation cores on one core (``orientation.*_updates_per_s``)."""
from __future__ import annotations

import time

import numpy as np


def bench_core_rates(samples: int = 20000, seed: int = 0) -> dict[str, float]:
    """Samples per second of the orientation cores on one core: the AHRS (imu_magnetometer),
    the eq. 3-4 compass, and the hybrid's cores per IMU sample at 100 Hz IMU / 30 Hz camera:
    the world alignment (one IMU sample with its field, an estimate every third sample) and the
    panorama's azimuth distortion (the gyro sample; every third sample a frame of a camera
    turning at 0.5 rad/s, compared and corrected). ``hybrid_alignment_updates_per_s`` and
    ``hybrid_distortion_updates_per_s`` time each of the two on the same workload alone (after
    the hybrid's own timing, which they leave unchanged)."""
    from ..core.ahrs import Ahrs, AhrsConfig
    from ..core.imu_orientation import FieldModel, GravityFieldOrientation
    from ..core.panorama_azimuth import AzimuthDistortion
    from ..core.rotations import so3_exp
    from ..core.world_alignment import WorldAlignment

    rng = np.random.default_rng(seed)
    gyro = rng.normal(0.0, 0.3, (samples, 3))
    accel = rng.normal([0.0, 0.0, 9.81], 0.3, size=(samples, 3))
    mag = rng.normal([0.0, 2.1e-5, -4.3e-5], 3e-7, size=(samples, 3))
    R = [so3_exp(v) for v in rng.normal(0.0, 1.0, (samples, 3))]

    ahrs = Ahrs(AhrsConfig(sample_period_s=0.01))
    start = time.perf_counter()
    for k in range(samples):
        ahrs.update(k * 10_000_000 + 1, gyro[k], accel[k], mag[k], k * 10_000_000 + 1)
    ahrs_rate = samples / (time.perf_counter() - start)

    compass = GravityFieldOrientation(model=FieldModel(field_t=48e-6, dip_rad=1.117))
    start = time.perf_counter()
    for k in range(samples):
        compass.estimate(accel[k], mag[k])
    compass_rate = samples / (time.perf_counter() - start)

    # The phone's mount (imu -> camera_optical) and a camera turning about up at 0.5 rad/s,
    # looking horizontally: the gyro reads that turn in the imu frame.
    R_imu_cam = np.diag([1.0, -1.0, -1.0])
    up = np.array([0.0, 0.0, 1.0])
    level = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # optical axis along +y
    turn_imu = R_imu_cam @ level.T @ (0.5 * up)
    frames = [so3_exp(0.5 * 0.01 * k * up) @ level for k in range(0, samples, 3)]
    def hybrid(align: WorldAlignment | None, stretch: AzimuthDistortion | None) -> float:
        """Samples per second of the workload for the given cores (None: left out)."""
        start = time.perf_counter()
        for k in range(samples):
            t_ns = k * 10_000_000 + 1
            if align is not None:
                align.add(t_ns, R[k], accel[k], mag[k], gyro[k])
            if stretch is not None:
                stretch.add_gyro(t_ns, turn_imu + 0.01 * gyro[k])
            if k % 3 == 0:
                if align is not None:
                    align.estimate()
                if stretch is not None:
                    stretch.add_visual(t_ns, frames[k // 3], up)
                    stretch.correct(frames[k // 3], up)
        return samples / (time.perf_counter() - start)

    stretch = AzimuthDistortion(R_imu_cam)
    hybrid_rate = hybrid(WorldAlignment(), stretch)
    # The breakdown: the same workload for each core alone (the loop's own cost in both).
    align_rate = hybrid(WorldAlignment(), None)
    stretch_rate = hybrid(None, AzimuthDistortion(R_imu_cam))
    return {'ahrs_updates_per_s': round(ahrs_rate, 1), 'imu_magnetometer_compass_updates_per_s': round(compass_rate, 1),
            'hybrid_updates_per_s': round(hybrid_rate, 1), 'hybrid_azimuth_pairs': stretch.pairs, 'samples': samples,
            'hybrid_alignment_updates_per_s': round(align_rate, 1),
            'hybrid_distortion_updates_per_s': round(stretch_rate, 1)}
