"""The AHRS core (VQF on stamped samples): equality with VQF, stamps, covariance, bad samples."""
from __future__ import annotations

import math

import numpy as np
import pytest

from ar_tracking.core.ahrs import Ahrs, AhrsConfig, AhrsError
from ar_tracking.core.imu_orientation import ImuCalibration
from ar_tracking.core.rotations import so3_exp, so3_log

G = 9.80665
FIELD_ENU = 48e-6 * np.array([0.0, math.cos(math.radians(64)), -math.sin(math.radians(64))])


def _motion(n: int, rate_hz: float = 100.0, seed: int = 0):
    """A body tumbling smoothly: true R_enu_body, gyro, accel, field (exact, no noise)."""
    rng = np.random.default_rng(seed)
    dt = 1.0 / rate_hz
    w_amp, w_f = rng.uniform(0.3, 1.5, 3), rng.uniform(0.05, 0.4, 3)
    R = np.eye(3)
    Rs, gyro = [], []
    for k in range(n):
        w = w_amp * np.sin(2 * math.pi * w_f * k * dt)
        Rs.append(R)
        gyro.append(w)
        R = R @ so3_exp(w * dt)
    Rs = np.array(Rs)
    accel = np.einsum('nji,j->ni', Rs, [0.0, 0.0, G])
    mag = np.einsum('nji,j->ni', Rs, FIELD_ENU)
    return Rs, np.array(gyro), accel, mag


def _angle_deg(Ra, Rb) -> float:
    return float(np.degrees(np.linalg.norm(so3_log(Ra.T @ Rb))))


def test_equals_vqf_on_uniform_samples():
    vqf = pytest.importorskip('vqf')
    _, gyro, accel, mag = _motion(1500)
    ref = vqf.VQF(0.01).updateBatch(gyro, accel, mag * 1e6)['quat9D']
    ahrs = Ahrs(AhrsConfig(sample_period_s=0.01))
    for k in range(len(gyro)):
        est = ahrs.update(k * 10_000_000, gyro[k], accel[k], mag[k], k * 10_000_000)
    w, x, y, z = ref[-1]
    assert est.R_enu_body[0, 0] == pytest.approx(1 - 2 * (y * y + z * z), abs=1e-9)
    assert est.R_enu_body[1, 0] == pytest.approx(2 * (x * y + w * z), abs=1e-9)


def test_tracks_a_tumbling_body_and_measures_the_rate_from_stamps():
    R_true, gyro, accel, mag = _motion(3000, seed=1)
    ahrs = Ahrs()  # sample period measured from the first stamp gaps
    errs = []
    for k in range(len(gyro)):
        est = ahrs.update(k * 10_000_000, gyro[k], accel[k], mag[k], k * 10_000_000)
        if est is not None and not isinstance(est, str):
            errs.append(_angle_deg(est.R_enu_body, R_true[k]))
    assert ahrs.sample_period_s == pytest.approx(0.01)
    assert len(errs) == len(gyro)  # a provisional filter answers while the rate is measured
    assert max(errs) < 2.0  # VQF itself is within 1.2 deg on this exact motion (its filters lag)


def test_jittered_stamps_integrate_each_sample_over_its_own_gap():
    """A sample that comes 25 ms after the previous one (a dropped sample in between) turns the
    estimate by rate * 25 ms, not by rate * Ts (6D, so only the gyro decides the heading)."""
    rate = 1.0  # rad/s about up
    ahrs = Ahrs(AhrsConfig(sample_period_s=0.01, use_mag=False))
    stamps = np.cumsum(np.r_[0, np.tile([10, 10, 25, 10, 5], 40)]) * 1_000_000
    for t in stamps:
        est = ahrs.update(int(t), [0.0, 0.0, rate], [0.0, 0.0, G])
    heading = math.atan2(est.R_enu_body[1, 0], est.R_enu_body[0, 0])
    # (the first sample is integrated over one nominal period, as VQF does)
    assert heading == pytest.approx(rate * ((stamps[-1] - stamps[0]) * 1e-9 + 0.01), abs=1e-3)


def test_calibration_and_declination_are_applied():
    cal = ImuCalibration(gyro_bias=[0.01, -0.02, 0.005], hard_iron_offset=[5e-6, -3e-6, 2e-6])
    ahrs = Ahrs(AhrsConfig(sample_period_s=0.01, declination_rad=math.radians(8.0)), cal)
    for k in range(200):
        est = ahrs.update(k * 10_000_000, cal.gyro_bias, [0.0, 0.0, G], FIELD_ENU + cal.hard_iron_offset, k * 10_000_000)
    # body y is magnetic north, 8 deg east of true north
    assert math.degrees(math.atan2(est.R_enu_body[0, 1], est.R_enu_body[1, 1])) == pytest.approx(8.0, abs=0.05)


def test_heading_variance_grows_without_the_field_and_tilt_variance_with_acceleration():
    ahrs = Ahrs(AhrsConfig(sample_period_s=0.01))
    still = [ahrs.update(k * 10_000_000, [0, 0, 0], [0, 0, G], FIELD_ENU, k * 10_000_000) for k in range(300)]
    blind = [ahrs.update((300 + k) * 10_000_000, [0, 0, 0], [0, 0, G]) for k in range(300)]
    shaken = [ahrs.update((600 + k) * 10_000_000, [0, 0, 0], [0, 0, G + 3.0 * math.sin(k)], FIELD_ENU,
                          (600 + k) * 10_000_000) for k in range(300)]
    assert blind[-1].heading_sigma_rad > blind[0].heading_sigma_rad > still[-1].heading_sigma_rad * 0.999
    assert not blind[-1].mag_used and still[-1].mag_used
    assert shaken[-1].tilt_sigma_rad > 1.5 * still[-1].tilt_sigma_rad
    for est in still + blind + shaken:
        assert np.all(np.isfinite(est.covariance)) and np.all(np.linalg.eigvalsh(est.covariance) > 0)


@pytest.mark.parametrize('gyro, accel, why', [
    ([math.nan, 0, 0], [0, 0, G], 'not finite'),
    ([0, 0, 0], [0, math.inf, G], 'not finite'),
    ([0, 0, 0], [0, 0, 0], 'zero norm'),
])
def test_bad_samples_are_refused_with_a_reason_and_leave_the_state(gyro, accel, why):
    ahrs = Ahrs(AhrsConfig(sample_period_s=0.01))
    good = ahrs.update(10_000_000, [0, 0, 0], [0, 0, G], FIELD_ENU, 10_000_000)
    reason = ahrs.update(20_000_000, gyro, accel, FIELD_ENU, 20_000_000)
    assert isinstance(reason, str) and why in reason
    after = ahrs.update(30_000_000, [0, 0, 0], [0, 0, G], FIELD_ENU, 30_000_000)
    assert _angle_deg(after.R_enu_body, good.R_enu_body) < 1e-6
    assert 'not newer' in ahrs.update(30_000_000, [0, 0, 0], [0, 0, G])


def test_a_non_finite_field_sample_means_a_6d_update():
    ahrs = Ahrs(AhrsConfig(sample_period_s=0.01))
    ahrs.update(10_000_000, [0, 0, 0], [0, 0, G], FIELD_ENU, 10_000_000)
    est = ahrs.update(20_000_000, [0, 0, 0], [0, 0, G], [math.nan, 0, 0], 20_000_000)
    assert not isinstance(est, str) and not est.mag_used


def test_rejects_unusable_settings():
    with pytest.raises(AhrsError):
        AhrsConfig(tau_acc_s=0.0)
    with pytest.raises(AhrsError):
        AhrsConfig(sample_period_s=math.nan)
