"""The world alignment's and the azimuth distortion's shortcuts give what the full computation
gives (core/world_alignment, core/panorama_azimuth): each test computes both and compares."""
from __future__ import annotations

import numpy as np

from ar_tracking.core.rotations import so3_exp
from ar_tracking.core.world_alignment import WorldAlignment, WorldAlignmentConfig, solve_due_after_ns


def test_the_field_solves_fall_where_the_full_period_test_puts_them() -> None:
    """add_field skips the period test for stamps before the next solve can be due; the solves
    must still fall at every stamp where the full test says one is due - with field samples
    before the first IMU sample, stamps that go back, gaps, and a long session's growing
    period."""
    config = WorldAlignmentConfig()
    wa = WorldAlignment(config)
    solved: list[int] = []

    def counted() -> tuple[np.ndarray, np.ndarray, float, float]:
        solved.append(wa._field_samples)
        return np.array([0.0, 1.0, 0.0]), np.zeros(3), 0.01, 0.0
    wa._solve_field = counted  # type: ignore[method-assign]
    rng = np.random.default_rng(3)
    R = so3_exp(np.array([0.1, 0.2, 0.3]))
    t = 5_000_000_000
    expected_solves = 0
    for k in range(30000):
        step = int(rng.choice([10_000_000, 10_000_000, 10_000_000, -30_000_000, 900_000_000], p=[0.7, 0.2, 0.05, 0.04, 0.01]))
        t += step
        solve_t, samples = wa._solve_t_ns, wa._field_samples + 1
        t_first = wa._t_first_ns if k < 50 else (t if wa._t_first_ns is None else wa._t_first_ns)
        due = (solve_t is None or samples < 8
               or t - solve_t >= solve_due_after_ns(config, wa._solve_period_ns, t, t_first))
        if k < 50:
            wa.add_field(t, R, np.array([0.0, 2e-5, -4e-5]))  # before the first IMU sample
        else:
            wa.add(t, R, np.array([0.0, 0.0, 9.8]), np.array([0.0, 2e-5, -4e-5]))
        expected_solves += due
        assert len(solved) == expected_solves, k
        assert wa._solve_t_ns == (t if due else solve_t)
    assert 150 < expected_solves < 2000


def test_a_frames_kept_azimuth_knots_equal_those_taken_again() -> None:
    """A frame keeps its azimuth's knots for the comparison that takes it as the older frame,
    while the azimuth axes stay the same object; with the axes made anew at every frame (the
    knots then taken again from the frame's forward axis) the filter must end the same, bit for
    bit - on a turning, wobbling camera whose up moves every 2 s (a comparison across a move takes the knots again)."""
    from ar_tracking.core.panorama_azimuth import AzimuthDistortion
    from ar_tracking.core.rotations import so3_log

    R_imu_cam = np.diag([1.0, -1.0, -1.0])
    level = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

    def run(fresh_axes: bool) -> AzimuthDistortion:
        rng = np.random.default_rng(4)
        est = AzimuthDistortion(R_imu_cam)
        if fresh_axes:
            axes_of = est._axes_of

            def fresh(up: np.ndarray):  # noqa: ANN202  (a copy: never the kept object)
                axes = axes_of(up)
                return None if axes is None else tuple(tuple(v) for v in axes)
            est._axes_of = fresh  # type: ignore[method-assign]
        n = 3000
        turn = np.cumsum(0.01 * (0.8 * np.sin(np.arange(n) * 0.004) + rng.normal(0, 0.05, n)))
        tilt = rng.normal(0, 0.02, (n, 3)).cumsum(axis=0) * 0.01
        R = [so3_exp(np.array([0.0, 0.0, turn[k]]) + tilt[k]) @ level for k in range(n)]
        up = np.array([0.0, 0.0, 1.0])
        for k in range(n):
            t_ns = k * 10_000_000 + 1
            w = np.zeros(3) if k == 0 else so3_log((R[k - 1] @ R_imu_cam.T).T @ (R[k] @ R_imu_cam.T)) / 0.01
            est.add_gyro(t_ns, w + rng.normal(0, 0.002, 3))
            if k % 200 == 0:
                up = np.array([0.0, 0.0, 1.0]) + rng.normal(0, 0.002, 3)
            if k % 3 == 0:
                est.add_visual(t_ns, so3_exp(np.array([0.0, 0.0, 0.004 * np.sin(turn[k])])) @ R[k], up)
        return est

    kept, again = run(False), run(True)
    assert kept.pairs > 900 and kept.pairs == again.pairs
    assert np.array_equal(kept.x, again.x) and np.array_equal(kept.P, again.P)
