"""The camera-IMU time offset from the gyro against the visual rotation (core.time_offset)."""
from __future__ import annotations

import functools

import numpy as np
import pytest

from ar_tracking.core.rotations import so3_exp
from ar_tracking.core.time_offset import ImuClock, TimeOffsetConfig, TimeOffsetEstimator
from conftest import SHARED_DATA

R_IMU_CAM = np.diag([1.0, -1.0, -1.0])
T0 = 1_700_000_000_000_000_000


def _motion(t: np.ndarray) -> np.ndarray:
    """Camera rate (camera axes, rad/s): pans that start and stop plus a tremor."""
    return np.stack([0.05 * np.sin(2 * np.pi * 2.3 * t),
                     0.6 * np.sin(2 * np.pi * 0.25 * t) ** 3 + 0.03 * np.sin(2 * np.pi * 4.1 * t),
                     0.04 * np.cos(2 * np.pi * 1.7 * t)], axis=-1)


@functools.lru_cache(maxsize=None)
def _camera_track(duration_s: float, seed: int, still: bool, late_first_s: float, late_by_s: float
                  ) -> tuple[np.ndarray, np.ndarray, dict[int, np.ndarray], dict]:
    """The slow part of :func:`_feed` (~3 s for 12 s: 10^5 fine steps), which does not depend on
    the offset: the fine times, the camera rate, the frames (fine step -> R_cam, with their
    noise) and the state of the noise generator after them (the gyro's noise is drawn next).
    Cached: the tests feed the same 12 s of motion with six different offsets (read-only)."""
    rng = np.random.default_rng(seed)
    fine = np.arange(0.0, duration_s, 1e-4)
    rate = np.zeros((len(fine), 3)) if still else _motion(fine)
    R = np.eye(3)
    frames = {}
    frame_every = int(round(1 / 30 / 1e-4))
    late = int(round(late_by_s / 1e-4))
    for k, w in enumerate(rate):
        shown = k - late if fine[k] - late_by_s < late_first_s else k  # the frame stamped then
        if shown >= 0 and shown % frame_every == 0:
            frames[shown] = R @ so3_exp(rng.normal(0.0, 3e-4, 3))  # ~0.02 deg of tracker noise
        R = R @ so3_exp(w * 1e-4)
    return fine, rate, frames, rng.bit_generator.state


def _feed(est_or_clock, offset_s: float, duration_s: float = 12.0, seed: int = 0, still: bool = False,
          gyro_bias=(0.01, -0.02, 0.005), late_first_s: float = 0.0, late_by_s: float = 0.0) -> None:
    """Gyro at 200 Hz stamped on the IMU clock (truth + offset), with noise and a bias; frames at
    30 Hz on the camera clock, integrated exactly from the same rate (fine steps), with noise;
    the frames of the first ``late_first_s`` show the orientation ``late_by_s`` after their
    stamp (a tracker that has not yet estimated its rolling shutter's readout)."""
    fine, rate, frames, state = _camera_track(duration_s, seed, still, late_first_s, late_by_s)
    rng = np.random.Generator(np.random.PCG64())
    rng.bit_generator.state = state  # where the frames' noise left default_rng(seed)
    events = []
    for k in range(0, len(fine), 50):  # 200 Hz
        w_imu = R_IMU_CAM @ rate[k] + np.asarray(gyro_bias) + rng.normal(0.0, 0.003, 3)
        events.append((T0 + int(round((fine[k] + offset_s) * 1e9)), 0, w_imu))
    events += [(T0 + int(round(fine[k] * 1e9)), 1, Rk) for k, Rk in frames.items()]
    for t_ns, kind, value in sorted(events, key=lambda e: (e[0], e[1])):
        if isinstance(est_or_clock, ImuClock):
            if kind == 0:
                est_or_clock.add((t_ns, 'sample'), value)
            else:
                est_or_clock.add_visual(t_ns, value)
        elif kind == 0:
            est_or_clock.add_gyro(t_ns, value)
        else:
            est_or_clock.add_visual(t_ns, value)


@pytest.mark.parametrize('offset_ms', [-30.0, 0.0, 7.0, 45.0])
def test_the_offset_is_found_with_an_honest_sigma(offset_ms):
    est = TimeOffsetEstimator(R_IMU_CAM, TimeOffsetConfig(skip_first_s=0.0))  # settled from its first frame
    _feed(est, offset_ms * 1e-3)
    found = est.estimate()
    assert found is not None
    offset, sigma = found
    assert abs(offset * 1e3 - offset_ms) < 0.5
    assert 0.0 < sigma * 1e3 < 1.0
    assert abs(offset * 1e3 - offset_ms) < 5 * sigma * 1e3 + 0.05
    assert est.offset_s == pytest.approx(offset)


def test_no_rotation_no_offset_and_out_of_range_is_not_found():
    still = TimeOffsetEstimator(R_IMU_CAM)
    _feed(still, 0.01, still=True)
    assert still.offset_s is None
    narrow = TimeOffsetEstimator(R_IMU_CAM, TimeOffsetConfig(max_offset_s=0.02))
    _feed(narrow, 0.05)
    assert narrow.estimate() is None and narrow.offset_s is None


def _offset_with_visual_fault(duration_s: float, seed: int, fault) -> float | None:
    """The estimate for a 12 ms offset when frame k is reported as ``fault(k, R_true)``."""
    est = TimeOffsetEstimator(R_IMU_CAM)
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration_s, 1 / 200)
    rate = _motion(t)
    R, frames = np.eye(3), []
    for k in range(len(t)):
        if k % 7 == 0:
            frames.append((T0 + int(t[k] * 1e9), 1, fault(k, R)))
        R = R @ so3_exp(0.5 * (rate[k] + rate[min(k + 1, len(t) - 1)]) / 200)  # trapezoid: no lag
    gyro = [(T0 + int((t[k] + 0.012) * 1e9), 0, R_IMU_CAM @ rate[k] + rng.normal(0, 0.002, 3)) for k in range(len(t))]
    for t_ns, kind, value in sorted(gyro + frames, key=lambda e: (e[0], e[1])):
        (est.add_gyro if kind == 0 else est.add_visual)(t_ns, value)
    return est.offset_s


def test_a_jump_of_the_visual_estimate_is_left_out():
    glitch = so3_exp(np.array([0.0, 0.3, 0.0]))
    offset = _offset_with_visual_fault(8.0, 1, lambda k, R: R @ glitch if k == 7 * 300 else R)  # one bad frame
    assert offset is not None and abs(offset - 0.012) < 0.002


def test_imu_clock_hands_back_the_first_samples_once_when_the_offset_settles():
    clock = ImuClock(0, TimeOffsetEstimator(R_IMU_CAM))
    handed: list = []
    original = clock.add

    def add(sample, omega):
        settled = original(sample, omega)
        if settled:
            handed.append(clock.take_kept())
        return settled

    clock.add = add  # type: ignore[method-assign]
    _feed(clock, 0.02)
    assert len(handed) == 1 and len(handed[0]) > 100  # the first seconds, once
    assert all(s[1] == 'sample' for s in handed[0])
    assert abs(clock.offset_ns - 20_000_000) < 1_000_000
    assert clock.take_kept() is None

    forgotten = ImuClock(5_000_000, TimeOffsetEstimator(R_IMU_CAM))
    forgotten.forget_kept()  # the tracker was lost: nothing before is re-paired
    assert forgotten.add((T0, 'sample'), np.zeros(3)) is False
    assert forgotten.take_kept() is None and forgotten.offset_ns == 5_000_000
    forgotten.restart()  # a bag loop: the new session's first seconds are kept again
    forgotten.add((T0, 'sample'), np.zeros(3))
    assert forgotten.take_kept() == [(T0, 'sample')]

    fixed = ImuClock(-8_000_000, None)  # estimation off: the known offset, nothing kept
    assert fixed.add((T0, 'sample'), np.zeros(3)) is False and fixed.offset_ns == -8_000_000


def test_the_gyro_buffer_stays_bounded_without_frames_and_after_the_tracker_stops():
    est = TimeOffsetEstimator(R_IMU_CAM)
    for k in range(200 * 120):  # two minutes of gyro, no camera
        est.add_gyro(T0 + k * 5_000_000, np.array([0.0, 0.1, 0.0]))
    assert len(est._gyro_t) < 1000
    est = TimeOffsetEstimator(R_IMU_CAM)
    _feed(est, 0.01, duration_s=3.5)  # frames for a while ...
    blocks = est.blocks
    for k in range(200 * 60):  # ... then the tracker stops for a minute
        est.add_gyro(T0 + int(3.6e9) + k * 5_000_000, np.array([0.0, 0.1, 0.0]))
    assert len(est._gyro_t) < 1000 and not est._pairs
    assert est.blocks == blocks + 1  # the pairs that waited made a short block


def test_a_lasting_jump_of_the_tracker_does_not_spoil_the_bias_of_its_block():
    jump = so3_exp(np.array([0.0, 0.2, 0.0]))  # a relocalisation: the reference moves for good
    offset = _offset_with_visual_fault(12.0, 2, lambda k, R: jump @ R if k >= 7 * 150 else R)
    assert offset is not None and abs(offset - 0.012) < 0.002


@pytest.mark.skipif(not (SHARED_DATA / 'euroc_imu_april_detections' / 'imu0.csv').is_file(),
                    reason='EuRoC imu_april detections not present in ../shared/data')
def test_a_real_hardware_synchronised_camera_imu_pair():
    """EuRoC imu_april (real VI-Sensor, one hardware clock): about 0 ms, and a shift of the IMU
    stamps is found to a fraction of a ms."""
    from ar_tracking.eval.bench_time_offset import bench_time_offset

    result = bench_time_offset(shifts_ms=(0.0, 25.0, -40.0))
    assert result['frames'] > 1000
    for shift in (0.0, 25.0, -40.0):
        found = result[f'shift_{shift:+g}ms']
        assert abs(found['offset_ms'] - shift) < 1.0 and found['sigma_ms'] < 0.5, (shift, found)


def test_the_trackers_first_second_is_left_out():
    """A tracker that shows the orientation 13 ms after each stamp for its first second (half a
    26 ms readout it has not yet estimated), then at its stamps: with that second the offset is
    pulled towards 13 ms, without it (the default) it is the device's."""
    found = {}
    for skip in (0.0, 1.0):
        est = TimeOffsetEstimator(R_IMU_CAM, TimeOffsetConfig(skip_first_s=skip))
        _feed(est, 0.005, duration_s=4.0, late_first_s=1.0, late_by_s=0.013)
        found[skip] = est.estimate()[0] * 1e3
    assert abs(found[1.0] - 5.0) < 0.75 and found[0.0] - 5.0 > 2.5, found
