"""The simulator's shared parts: the IMU sensor model, the scenario dispatch, the import graph."""
from __future__ import annotations

import ast
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ar_tracking.io.bags import BagWriter
from ar_tracking.sim import bagmaker, handheld_desk as hd, rotation_sweep as rs
from ar_tracking.sim.imu import imu_samples, specific_force_cam
from ar_tracking.sim.scenario import BagRequest

SIM_DIR = Path(bagmaker.__file__).parent
G = 9.80665


def _imu_args(**kw):
    args = dict(R_imu_cam=rs.R_IMU_CAM, gyro_bias_rad_s=np.zeros(3), accel_bias_m_s2=np.zeros(3),
                gyro_noise_rad_s=0.0, accel_noise_m_s2=0.0)
    args.update(kw)
    return args


def test_phone_at_rest_reads_gravity_up_the_screen_and_no_rate():
    """A level phone camera looking north (screen vertical): the IMU's y axis (up the screen)
    reads +g, the others 0; the gyro reads the bias only."""
    R = np.repeat(rs.R0_ENU_CAM[None], 5, axis=0)
    f_cam = specific_force_cam(R, np.zeros((5, 3)), G)
    bias = np.array([0.01, -0.02, 0.03])
    gyro, accel = imu_samples(np.zeros((5, 3)), f_cam, rng=np.random.default_rng(0),
                              **_imu_args(gyro_bias_rad_s=bias))
    assert np.allclose(accel, [0.0, G, 0.0], atol=1e-12)
    assert np.allclose(gyro, bias, atol=1e-15)


def test_rates_and_forces_are_rotated_into_the_imu_frame():
    rng = np.random.default_rng(3)
    R = Rotation.random(20, random_state=4).as_matrix()
    omega_cam, a_world = rng.normal(size=(20, 3)), rng.normal(size=(20, 3))
    f_cam = specific_force_cam(R, a_world, G)
    expected_f_cam = np.einsum('nji,nj->ni', R, a_world + [0.0, 0.0, G])
    assert np.allclose(f_cam, expected_f_cam, atol=1e-12)
    scale = np.array([1.01, 0.99, 1.005])
    gyro, accel = imu_samples(omega_cam, f_cam, rng=rng, **_imu_args(accel_scale=scale))
    assert np.allclose(gyro, omega_cam @ rs.R_IMU_CAM.T, atol=1e-15)
    assert np.allclose(accel, (f_cam @ rs.R_IMU_CAM.T) * scale, atol=1e-12)


def test_noise_is_drawn_gyro_first_then_accelerometer():
    """The draw order is part of the contract: rotation_sweep draws its magnetometer noise from
    the same stream afterwards, so reordering would change every bag."""
    n = 50
    gyro, accel = imu_samples(np.zeros((n, 3)), np.zeros((n, 3)), rng=np.random.default_rng(9),
                              **_imu_args(gyro_noise_rad_s=0.1, accel_noise_m_s2=0.2))
    ref = np.random.default_rng(9)
    assert np.array_equal(gyro, ref.normal(0.0, 0.1, (n, 3)))
    assert np.array_equal(accel, ref.normal(0.0, 0.2, (n, 3)))


def test_drift_adds_to_the_gyro_bias():
    n = 4
    drift = np.arange(12, dtype=float).reshape(n, 3)
    gyro, _ = imu_samples(np.zeros((n, 3)), np.zeros((n, 3)), rng=np.random.default_rng(0),
                          **_imu_args(gyro_bias_rad_s=np.ones(3), gyro_drift_rad_s=drift))
    assert np.array_equal(gyro, drift + 1.0)


def test_desk_phone_held_still_reads_about_one_g():
    """handheld_desk is still for its first 0.3 s: |accel| is g (plus biases and noise)."""
    gyro, accel = hd.simulate_imu(2, np.arange(0.0, 0.25, 0.01))
    assert abs(np.linalg.norm(accel.mean(axis=0)) - G) < 0.15
    assert np.all(np.abs(gyro.mean(axis=0)) < 0.03)


@pytest.mark.parametrize('name', bagmaker.SCENARIOS)
def test_every_scenario_is_dispatched_to_a_scenario_bag(name):
    scn = bagmaker.REGISTRY[name]
    assert scn.name == name
    for method in ('write_bag', 'write_sidecars', 'summary'):
        assert callable(getattr(scn, method))
    assert name in scn.summary(BagRequest(seed=7, duration_s=2.0))
    assert 'seed 7' in scn.summary(BagRequest(seed=7, duration_s=2.0))


def test_a_bag_error_becomes_a_sim_error(tmp_path, monkeypatch):
    """make_bag turns the writer's error into the one-line SimError, whatever the scenario."""
    from ar_tracking.io.bags import BagError

    def broken(self, bag, req, progress):
        raise BagError('disk full')

    monkeypatch.setattr(type(bagmaker.REGISTRY['handheld_desk']), 'write_bag', broken)
    with pytest.raises(bagmaker.SimError, match='disk full'):
        bagmaker.make_bag('handheld_desk', tmp_path / 'x.mcap', duration_s=1.0)


def test_handheld_desk_scenario_bag_writes_what_write_handheld_desk_bag_writes(tmp_path):
    req = BagRequest(seed=1, duration_s=1.0, image_format='compressed')
    with BagWriter(tmp_path / 'a.mcap') as bag:
        hd.SCENARIO.write_bag(bag, req, None)
    with BagWriter(tmp_path / 'b.mcap') as bag:
        hd.write_handheld_desk_bag(bag, 1, 1.0, 'compressed')
    assert (tmp_path / 'a.mcap').read_bytes() == (tmp_path / 'b.mcap').read_bytes()


def _sim_imports() -> dict[str, set[str]]:
    """Module -> the sim modules it imports (at module level or inside functions)."""
    mods = {p.stem for p in SIM_DIR.glob('*.py')}
    graph: dict[str, set[str]] = {}
    for p in SIM_DIR.glob('*.py'):
        deps: set[str] = set()
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level == 1:
                deps |= {node.module.split('.')[0]} if node.module else {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom) and (node.module or '').startswith('ar_tracking.sim.'):
                deps.add(node.module.split('.')[2])
        graph[p.stem] = deps & mods
    return graph


def test_nothing_bagmaker_imports_imports_bagmaker_back():
    """The dispatcher <-> scenario cycle is gone: bagmaker is not reachable from its imports."""
    graph = _sim_imports()
    seen, todo = set(), list(graph['bagmaker'])
    while todo:
        m = todo.pop()
        if m not in seen:
            seen.add(m)
            todo.extend(graph[m])
    assert 'bagmaker' not in seen
    assert {'scenario', 'messages', 'handheld_desk', 'rotation_sweep_bag'} <= seen


def test_scene_modules_form_layers():
    """model and rng import no other sim module; the concern modules never import a scenario."""
    graph = _sim_imports()
    assert graph['model'] == set() and graph['rng'] == set() and graph['imu'] == set()
    scenarios = {'bagmaker', 'handheld_desk', 'rotation_sweep', 'rotation_sweep_bag', 'robot_arcs',
                 'robot_arcs_real', 'visual_orientation', 'world'}
    for concern in ('camera', 'desk_textures', 'layout', 'lighting', 'render', 'street_textures',
                    'textures', 'messages', 'scenario', 'phone_sensors'):
        assert not graph[concern] & scenarios, concern


def test_world_still_offers_the_street_scene():
    from ar_tracking.sim import world

    for name in ('build_world', 'make_lighting', 'render_panorama', 'FrameRenderer', 'PinholeCamera',
                 'rng_stream'):
        assert hasattr(world, name), name
    assert math.isclose(world.EYE_HEIGHT_M, 1.5)
