"""Plumbing of the hybrid benchmark on short data (speed is measured by the bench, not here)."""
from __future__ import annotations

import functools

import numpy as np
import pytest

from ar_tracking.core.rotations import rot_z
from ar_tracking.eval import bench_hybrid as bh
from conftest import SHARED_DATA


def level_facing(heading_rad: float, n: int = 3000):
    """Static IMU samples (ENU body = rot_z(-heading)) with the field of a dip of 64 deg."""
    R_enu_body = rot_z(-heading_rad)
    field_enu = np.array([0.0, 21.0, -43.0])  # uT
    accel = np.tile(R_enu_body.T @ [0.0, 0.0, 9.81], (n, 1))
    mag = np.tile(R_enu_body.T @ field_enu, (n, 1))
    return R_enu_body, np.zeros((n, 3)), accel, mag


@pytest.mark.parametrize('runner', [bh.run_vqf, bh.run_madgwick, bh.run_madgwick_ahrs, bh.run_ahrs])
def test_peers_are_converted_to_enu(runner):
    R_true, gyro, accel, mag = level_facing(0.6)
    R = runner(gyro, accel, mag, 100.0)
    stats = bh.heading_stats(R[-100:], np.repeat(R_true[None], 100, axis=0))
    assert stats['heading_rmse_deg'] < 1.0, stats


def test_heading_stats_removes_the_offset_only_when_asked():
    R_true = np.repeat(np.eye(3)[None], 10, axis=0)
    R_est = np.repeat(rot_z(np.radians(5.0))[None], 10, axis=0)
    assert bh.heading_stats(R_est, R_true)['heading_rmse_deg'] == pytest.approx(5.0, abs=1e-3)
    assert bh.heading_stats(R_est, R_true, remove_offset=True)['heading_rmse_deg'] == pytest.approx(0.0, abs=1e-3)


def test_core_rates_are_measured():
    rates = bh.bench_core_rates(samples=300)
    assert rates['ahrs_updates_per_s'] > 0 and rates['hybrid_updates_per_s'] > 0
    assert rates['imu_magnetometer_compass_updates_per_s'] > 0
    # the hybrid's rate includes the azimuth distortion's comparisons (not only its gyro chain)
    assert rates['hybrid_azimuth_pairs'] > 50


def test_sim_bench_runs_on_a_short_bag(tmp_path, monkeypatch):
    # the core rates on 300 samples, not 20,000 (their measure: test_core_rates_are_measured)
    monkeypatch.setattr(bh, 'bench_core_rates', functools.partial(bh.bench_core_rates, samples=300))
    result = bh.bench_hybrid(tmp_path, duration_s=5.0, real=False)
    assert result['hybrid_updates_per_s'] > 0 and result['ahrs_updates_per_s'] > 0
    assert set(result['peers']) == {'hybrid', 'imu_magnetometer', 'vqf', 'madgwick'}
    assert all(result['peers'][k]['n'] > 100 for k in result['peers'])
    assert all(0.0 <= result['peers'][k]['heading_rmse_deg'] < 90.0 for k in result['peers'])  # 5 s: plumbing only


@pytest.mark.skipif(not (SHARED_DATA / 'broad').is_dir(), reason='BROAD data not present')
def test_broad_trial_is_scored_for_every_estimator():
    result = bh.bench_broad(SHARED_DATA / 'broad', max_trials=1)
    (trial,) = result.values()
    assert set(trial) == set(bh.REAL_ESTIMATORS)
    scored = {k: v for k, v in trial.items() if 'error' not in v}
    assert {'ahrs', 'vqf', 'compass_eq34'} <= set(scored)
    assert all(v['n'] > 1000 for v in scored.values())
    # imu_magnetometer's AHRS is VQF on stamped samples: the same figures on uniform samples
    assert trial['ahrs']['heading_rmse_deg'] == pytest.approx(trial['vqf']['heading_rmse_deg'], abs=1e-3)
    assert trial['compass_eq34']['tilt_rmse_deg'] > 3 * trial['ahrs']['tilt_rmse_deg']


@pytest.mark.skipif(not (SHARED_DATA / 'repoimu_ahrs_excerpt').is_dir(), reason='RepoIMU excerpt not present')
def test_repoimu_excerpt_is_scored_after_a_constant_rotation():
    (trial,) = bh.bench_repoimu().values()
    assert trial['ahrs']['n'] > 8000
    assert trial['ahrs']['heading_rmse_deg'] < 2.0 and trial['ahrs']['tilt_rmse_deg'] < 1.5
    assert trial['ahrs']['aligned_by_deg'] > 1.0  # the truth's frame is relative


def test_a_bench_reuses_a_simulated_bag_only_from_this_simulator_revision(tmp_path, caplog):
    """A bag made by an earlier simulator (same seed, other bytes) is made again, not reused."""
    from ar_tracking.eval.bench_bag import reusable_sweep_bag
    from ar_tracking.io.bags import BagReader, BagWriter
    from ar_tracking.sim.bagmaker import make_bag
    from ar_tracking.sim.rotation_sweep_bag import SIM_METADATA

    assert not reusable_sweep_bag(tmp_path / 'none.mcap')
    # seed 1, the benches' seed: the simulator's view of it is cached from the bench tests of
    # this xdist group (conftest XDIST_GROUPS 'bench'), not built again
    hard = make_bag('rotation_sweep', tmp_path / 'hard.mcap', seed=1, duration_s=1.0)
    kind = make_bag('rotation_sweep', tmp_path / 'kind.mcap', seed=1, duration_s=1.0, profile='kind')
    assert reusable_sweep_bag(hard) and reusable_sweep_bag(kind)  # kind bags are frozen
    (tmp_path / 'empty.mcap').touch()  # a bench killed as it started making the bag
    cut = tmp_path / 'cut.mcap'  # ... or while it wrote it
    cut.write_bytes(hard.read_bytes()[:hard.stat().st_size // 2])
    assert not reusable_sweep_bag(tmp_path / 'empty.mcap') and not reusable_sweep_bag(cut)
    old = tmp_path / 'old.mcap'  # the hard bag as the simulator before revisions wrote it
    with BagReader(hard) as src, BagWriter(old) as dst:
        dst.add_metadata(SIM_METADATA, {'scenario': 'rotation_sweep', 'profile': 'hard', 'seed': '1',
                                        'session': 'authoring'})
        for m in src.messages(['/imu/data_raw']):
            dst.write(m.topic, m.log_time_ns, src.deserialize(m))
    with caplog.at_level('INFO', logger='ar_tracking.eval.bench'):
        assert not reusable_sweep_bag(old)
    assert 'made by an earlier simulator' in caplog.text
