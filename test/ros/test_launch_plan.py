"""The launch files' decisions (ar_tracking.ros.launch_plan; launch itself is not on the pip path)."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

from ar_tracking.ros.launch_plan import plan, sidecar_params
from ar_tracking.ros.params import ParamsError

REPO = Path(__file__).resolve().parents[2]
CONFIG = str(REPO / 'config')


def _by_name(specs):
    return {s.executable: s for s in specs}


def _merged(spec):
    out = {}
    for p in spec.parameters:
        if isinstance(p, dict):
            out.update(p)
    return out


def test_without_params_the_bag_calibration_is_used(tmp_path):
    bag = tmp_path / 'phone.mcap'
    bag.write_bytes(b'')
    assert sidecar_params(str(bag)) == ''
    (tmp_path / 'phone.params.yaml').write_text(
        'imu_magnetometer:\n  ros__parameters:\n    hard_iron_offset: [1.0e-6, 2.0e-6, 3.0e-6]\n')
    nodes = _by_name(plan('orientation', str(bag), CONFIG))
    assert list(nodes) == ['bag_replay', 'imu_magnetometer', 'panorama_mapper', 'hybrid_orientation_filter']
    assert _merged(nodes['imu_magnetometer'])['hard_iron_offset'] == [1.0e-6, 2.0e-6, 3.0e-6]
    assert 'hard_iron_offset' not in _merged(nodes['panorama_mapper'])
    assert _merged(nodes['hybrid_orientation_filter'])['use_sim_time'] is True
    assert nodes['imu_magnetometer'].parameters[0].endswith('config/imu_magnetometer.yaml')


def test_a_namespace_gets_its_own_clock_and_namespaced_sections(tmp_path):
    params = tmp_path / 'p.yaml'
    params.write_text('/**:\n  ros__parameters:\n    declination_rad: 0.1\n'
                      '/r1/imu_magnetometer:\n  ros__parameters:\n    declination_rad: 0.2\n')
    nodes = _by_name(plan('orientation', 'x.mcap', CONFIG, namespace='r1', params=str(params), rate='2', loop='true'))
    replay = _merged(nodes['bag_replay'])
    assert replay['clock_topic'] == 'clock' and replay['rate'] == 2.0 and replay['loop'] is True
    for name, spec in nodes.items():
        assert spec.namespace == 'r1'
        if name != 'bag_replay':
            assert spec.remappings == [('/clock', 'clock')]
    assert _merged(nodes['imu_magnetometer'])['declination_rad'] == 0.2   # its namespaced section
    assert _merged(nodes['hybrid_orientation_filter'])['declination_rad'] == 0.1  # /**

    plain = _by_name(plan('slam', 'x.mcap', CONFIG, use_sim_time='false'))
    assert list(plain) == ['bag_replay', 'keyframe_slam_mapper']
    assert _merged(plain['bag_replay'])['clock_topic'] == '/clock' and not plain['keyframe_slam_mapper'].remappings
    assert _merged(plain['keyframe_slam_mapper'])['use_sim_time'] is False
    shared = _by_name(plan('slam', 'x.mcap', CONFIG, namespace='r2', own_clock='false'))
    assert _merged(shared['bag_replay'])['clock_topic'] == '/clock'


def test_bad_params_file_and_graph_are_one_line_errors(tmp_path):
    with pytest.raises(ParamsError, match='no such params file'):
        plan('orientation', 'x.mcap', CONFIG, params=str(tmp_path / 'missing.yaml'))
    with pytest.raises(ValueError, match='unknown graph'):
        plan('everything', 'x.mcap', CONFIG)


@pytest.mark.parametrize('name', ['ar_tracking.launch.py', 'slam.launch.py'])
def test_launch_files_declare_the_arguments(name):
    tree = ast.parse((REPO / 'launch' / name).read_text())
    declared = {c.args[0].value for c in ast.walk(tree)
                if isinstance(c, ast.Call) and getattr(c.func, 'id', '') == 'DeclareLaunchArgument'}
    assert {'bag', 'namespace', 'params', 'use_sim_time', 'rate', 'loop', 'own_clock'} <= declared
