"""The graph runner: lockstep output, determinism, bad bags, Ctrl-C, realtime mode."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip('rclpy')

from ar_tracking.eval.metrics import evaluate_bag  # noqa: E402
from ar_tracking.io.bags import BagReader, read_metadata  # noqa: E402
from ar_tracking.ros.runner import RUN_METADATA, GraphRunner, RunError  # noqa: E402
from bagfactory import write_turning_imu_bag  # noqa: E402

CLI = [sys.executable, '-m', 'ar_tracking.cli']


def messages(path: Path, topic: str) -> list[tuple[int, bytes]]:
    with BagReader(path) as bag:
        return [(m.log_time_ns, m.rawdata) for m in bag.messages([topic])]


def test_lockstep_run_records_outputs_and_ground_truth(tmp_path):
    bag = write_turning_imu_bag(tmp_path / 'in.mcap', seconds=2.0)
    params = tmp_path / 'compass.yaml'
    params.write_text('imu_magnetometer:\n  ros__parameters:\n    method: compass\n')
    result = GraphRunner(bag, tmp_path / 'out.mcap', params_files=[params]).run()
    # Without a camera the hybrid filter runs too and follows the AHRS (one output per sample
    # once visual_timeout_s, 0.2 s, has passed without a frame: 20 of the 200).
    assert result.nodes == ['imu_magnetometer', 'hybrid_orientation_filter']
    assert result.input_messages == 400 and not result.interrupted and result.lost_deliveries == 0
    with BagReader(result.out_path) as out:
        topics = out.topics
        assert topics['/imu/data'] == 'sensor_msgs/msg/Imu'
        for copied in ('/ground_truth/orientation', '/tf_static', '/imu/data_raw', '/imu/mag'):
            assert copied in topics
        assert out.message_count(['/imu/data']) == 200
        assert out.message_count(['/orientation/global']) == 180
    metrics = evaluate_bag(result.out_path)['orientation']['imu/data']
    # Noise-free sensors: eq. 3-4 is exact, so the only error is numerical.
    assert metrics['n'] == 200 and metrics['rmse_deg'] < 1e-3
    assert result.timings_ms['imu_magnetometer']


def test_two_lockstep_runs_are_byte_identical(tmp_path):
    bag = write_turning_imu_bag(tmp_path / 'in.mcap', seconds=1.0)
    a = GraphRunner(bag, tmp_path / 'a.mcap', executor='single').run().out_path
    b = GraphRunner(bag, tmp_path / 'b.mcap', executor='events').run().out_path
    assert a.read_bytes() == b.read_bytes()  # whole files: the flush points follow the log time
    assert messages(a, '/imu/data') == messages(b, '/imu/data')
    assert len(messages(a, '/imu/data')) == 100


def test_bad_messages_in_a_bag_are_skipped(tmp_path):
    bag = write_turning_imu_bag(tmp_path / 'in.mcap', seconds=1.0,
                                faults=['nan_accel', 'zero_mag', 'backwards', 'zero_stamp'])
    out = GraphRunner(bag, tmp_path / 'out.mcap').run().out_path
    from ar_tracking.io.bags import deserialize

    data = [deserialize(raw, 'sensor_msgs/msg/Imu') for _, raw in messages(out, '/imu/data')]
    assert 94 <= len(data) < 100  # the bad samples (and at most their partners) are gone
    for m in data:
        q = np.array([m.orientation.x, m.orientation.y, m.orientation.z, m.orientation.w])
        assert np.all(np.isfinite(q)) and abs(np.linalg.norm(q) - 1) < 1e-9
    # One IMU sample pairs with the neighbouring field sample (10 ms at 0.5 rad/s: 0.29 deg).
    assert evaluate_bag(out)['orientation']['imu/data']['max_deg'] < 0.3


def test_sqlite3_bag_and_output(tmp_path):
    bag = write_turning_imu_bag(tmp_path / 'in_db', seconds=0.5, storage='sqlite3')
    result = GraphRunner(bag, tmp_path / 'out_db', storage='sqlite3').run()
    with BagReader(result.out_path) as out:
        assert out.message_count(['/imu/data']) == 50


def test_bag_without_usable_topics_is_a_run_error(tmp_path):
    from ar_tracking.io.bags import BagWriter
    from bagfactory import truth_msg

    path = tmp_path / 'gt_only.mcap'
    with BagWriter(path) as w:
        w.write('/ground_truth/orientation', 1, truth_msg(1, np.eye(3)))
    with pytest.raises(RunError, match='no node can run'):
        GraphRunner(path, tmp_path / 'out.mcap').run()


def test_realtime_mode_paces_and_records(tmp_path):
    bag = write_turning_imu_bag(tmp_path / 'in.mcap', seconds=1.0)
    start = time.monotonic()
    result = GraphRunner(bag, tmp_path / 'out.mcap', rate=2.0).run()
    assert time.monotonic() - start >= 0.5  # 1 s of bag at 2x
    with BagReader(result.out_path) as out:
        # Live pacing drops what it cannot keep up with (a busy machine); most must get through.
        assert out.message_count(['/imu/data']) >= 50
        assert out.message_count(['/ground_truth/orientation']) == 100
    # the CPU of each node's own thread (it spun that node's callbacks)
    assert set(result.live_cpu_s) == set(result.live_inputs) and all(cpu > 0 for cpu in result.live_cpu_s.values())


def run_cli(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run(CLI + list(args), capture_output=True, text=True, timeout=timeout)


@pytest.mark.parametrize('content', [b'', b'not a bag at all' * 50, 'truncated'])
def test_cli_unreadable_bag_is_one_line_and_nonzero(tmp_path, content):
    path = tmp_path / 'broken.mcap'
    if content == 'truncated':  # cut inside its only chunk: nothing is recoverable
        from mcap.reader import make_reader

        good = write_turning_imu_bag(tmp_path / 'good.mcap', seconds=1.0)
        with open(good, 'rb') as f:
            chunk = make_reader(f).get_summary().chunk_indexes[0]
        path.write_bytes(good.read_bytes()[: chunk.chunk_start_offset + chunk.chunk_length // 2])
    else:
        path.write_bytes(content)
    proc = run_cli('run', str(path), '-o', str(tmp_path / 'out.mcap'), '-q')
    assert proc.returncode != 0
    assert 'Traceback' not in proc.stderr
    errors = [line for line in proc.stderr.splitlines() if 'error' in line.lower()]
    assert len(errors) == 1 and 'broken.mcap' in errors[0], proc.stderr


def test_cli_missing_bag(tmp_path):
    proc = run_cli('run', str(tmp_path / 'nope.mcap'))
    assert proc.returncode == 1 and 'no such bag' in proc.stderr and 'Traceback' not in proc.stderr


def test_ctrl_c_closes_the_output_bag(tmp_path):
    bag = write_turning_imu_bag(tmp_path / 'long.mcap', seconds=60.0)
    out = tmp_path / 'out.mcap'
    proc = subprocess.Popen(CLI + ['run', str(bag), '-o', str(out), '-q'], stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and (not out.exists() or out.stat().st_size < 20_000):
        time.sleep(0.1)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert 'Traceback' not in err
    with BagReader(out) as bag:
        n = bag.message_count(['/imu/data'])
        assert 0 < n < 6000
        assert len(list(bag.messages(['/imu/data']))) == n


@pytest.mark.parametrize('executor', ['events', 'processes'])
def test_undecodable_messages_end_the_run_with_one_error(tmp_path, executor):
    """Bytes that are not the declared type never reach a callback: the run stops, it does not
    hang (in one process, and with the nodes in processes of their own)."""
    from ar_tracking.io.bags import BagWriter
    from bagfactory import mag_msg

    path = tmp_path / 'garbage.mcap'
    with BagWriter(path) as w:
        for i in range(40):
            t = 1_700_000_000_000_000_000 + i * 10_000_000
            w.write('/imu/data_raw', t, b'\x00\x01\x00\x00garbage', msgtype='sensor_msgs/msg/Imu')
            w.write('/imu/mag', t, mag_msg(t, (0.0, 2e-5, -4e-5)))
    with pytest.raises(RunError, match='received none'):
        GraphRunner(path, tmp_path / 'out.mcap', step_timeout_s=0.5, executor=executor).run()
    with BagReader(tmp_path / 'out.mcap') as out:  # closed cleanly all the same
        assert out.message_count(['/imu/mag']) > 0


def test_concurrent_lockstep_runs_on_one_domain_do_not_hear_each_other(tmp_path):
    """Two runs at once, forced onto the same DDS domain: each output is still its own bag's."""
    fast = write_turning_imu_bag(tmp_path / 'a.mcap', seconds=3.0, yaw_rate_rad_s=0.5)
    slow = write_turning_imu_bag(tmp_path / 'b.mcap', seconds=3.0, yaw_rate_rad_s=-0.2)
    env = dict(os.environ, AR_TRACKING_DOMAIN_ID='77')
    procs = [subprocess.Popen(CLI + ['run', str(bag), '-o', str(tmp_path / f'{bag.stem}.out.mcap'), '-q'],
                              env=env, stderr=subprocess.PIPE, text=True) for bag in (fast, slow)]
    for p in procs:
        _, err = p.communicate(timeout=120)
        assert p.returncode == 0, err
    for bag in (fast, slow):
        out = tmp_path / f'{bag.stem}.out.mcap'
        assert len(messages(out, '/imu/data')) == 300
        # Noise-free samples: the AHRS is within hundredths of a degree; the other run's samples
        # (another turning rate) would put it degrees off.
        assert evaluate_bag(out)['orientation']['imu/data']['max_deg'] < 0.05


def test_plan_skips_nodes_without_their_required_parameters():
    from ar_tracking.ros.runner import plan_nodes

    topics = ['/camera/image_raw', '/camera/camera_info', '/imu/data_raw', '/imu/mag']
    names, why = plan_nodes(topics, params=lambda name: {})
    assert 'marker_tracker' not in names and 'marker_map' in why['marker_tracker']
    assert 'visual_inertial_filter' not in names  # its markers/pose would come from marker_tracker
    assert {'imu_magnetometer', 'panorama_mapper', 'hybrid_orientation_filter'} <= set(names)
    names, _ = plan_nodes(topics, params=lambda name: {'marker_map': 'markers: []'} if name == 'marker_tracker' else {})
    assert {'marker_tracker', 'visual_inertial_filter'} <= set(names)


@pytest.mark.parametrize('rate', [float('inf'), float('nan'), -1.0])
def test_runner_rejects_a_rate_that_is_not_finite_and_non_negative(tmp_path, rate):
    with pytest.raises(RunError, match='--rate'):
        GraphRunner(tmp_path / 'unused.mcap', tmp_path / 'out.mcap', rate=rate).run()
    assert not (tmp_path / 'out.mcap').exists()


@pytest.mark.parametrize('command, rate', [('run', 'inf'), ('run', 'nan'), ('run', '-1'),
                                           ('replay', 'inf'), ('replay', '0'), ('replay', '-2')])
def test_cli_bad_rate_is_one_line_and_exit_1(tmp_path, command, rate):
    bag = write_turning_imu_bag(tmp_path / 'in.mcap', seconds=0.2)
    args = [command, str(bag), f'--rate={rate}'] + (['-o', str(tmp_path / 'out.mcap')] if command == 'run' else [])
    proc = run_cli(*args, timeout=60)
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.strip().splitlines() == [proc.stderr.strip()] and '--rate' in proc.stderr
    assert 'Traceback' not in proc.stderr
    assert not (tmp_path / 'out.mcap').exists()


def test_sigkill_leaves_an_output_that_opens_and_scores(tmp_path):
    """A kill no handler sees (SIGKILL, out of memory): the flushed chunks stay readable, and
    evaluate scores them with one line saying the bag was recovered."""
    bag = write_turning_imu_bag(tmp_path / 'long.mcap', seconds=60.0)
    out = tmp_path / 'out.mcap'
    proc = subprocess.Popen(CLI + ['run', str(bag), '-o', str(out), '-q'],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and (not out.exists() or out.stat().st_size < 50_000):
        time.sleep(0.05)
    proc.kill()
    proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    with BagReader(out) as recovered:
        assert recovered.recovered is not None  # no summary: the run was killed, not finished
        n = recovered.message_count(['/imu/data'])
        assert 0 < n < 6000
        assert len(list(recovered.messages(['/imu/data']))) == n
        assert {'/imu/data', '/ground_truth/orientation', '/imu/data_raw'} <= set(recovered.topics)
    metrics = evaluate_bag(out)['orientation']['imu/data']
    assert metrics['n'] == n and metrics['rmse_deg'] < 5.0  # every recovered estimate scored
    proc = run_cli('evaluate', str(out), '--json', '--compact')
    assert proc.returncode == 0, proc.stderr
    assert [line for line in proc.stderr.splitlines() if line.startswith(f'{out}: recovered')]


def _burst_graph(burst: int) -> dict:
    """A node that publishes ``burst`` messages per IMU sample, and three that listen with a
    depth-1 history (latest value), the sensor depth (5) and keep-all."""
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String

    from ar_tracking.ros.node_base import SENSOR_QOS, TrackingNode

    class BurstSource(TrackingNode):
        INPUTS = {'imu/data_raw': 'sensor_msgs/msg/Imu'}
        OUTPUTS = {'burst': 'std_msgs/msg/String'}

        def __init__(self, **kwargs):
            super().__init__('burst_source', **kwargs)
            self.pub = self.advertise(String, 'burst')
            self.subscribe(__import__('sensor_msgs.msg', fromlist=['Imu']).Imu, 'imu/data_raw', self.on_imu)

        def on_imu(self, msg):
            for i in range(burst):
                self.pub.publish(String(data=str(i)))

    def sink(name: str, qos):
        class Sink(TrackingNode):
            INPUTS = {'burst': 'std_msgs/msg/String'}
            OUTPUTS: dict = {}
            received: list = []

            def __init__(self, **kwargs):
                super().__init__(name, **kwargs)
                self.subscribe(String, 'burst', type(self).received.append, qos)
        Sink.received = []
        return Sink

    keep_all = QoSProfile(depth=1, history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
    latest = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)
    return {'burst_source': BurstSource, 'latest': sink('latest', latest),
            'queue5': sink('queue5', SENSOR_QOS), 'every': sink('every', keep_all)}


@pytest.mark.lossy  # a burst of 7 into depth 5 drops on purpose: the accounting is the test
@pytest.mark.parametrize('burst, executor', [(3, 'single'), (7, 'single'), (7, 'events')])
def test_lockstep_counts_what_a_history_depth_drops_instead_of_waiting(tmp_path, burst, executor):
    """A burst larger than a subscription's depth is booked at publish time (superseded for a
    depth-1 latest-value subscription, dropped for a deeper queue), never waited for."""
    bag = write_turning_imu_bag(tmp_path / 'in.mcap', seconds=0.2)
    graph = _burst_graph(burst)
    runner = GraphRunner(bag, tmp_path / 'out.mcap', graph=graph, step_timeout_s=5.0, executor=executor)
    result = runner.run()
    steps = 20
    assert result.lost_deliveries == 0 and result.lost == {}
    assert runner._ledger.corrections == 0  # DDS dropped exactly what the ledger booked
    assert len(graph['every'].received) == steps * burst
    assert len(graph['latest'].received) == steps  # the last of each burst
    assert [m.data for m in graph['latest'].received] == [str(burst - 1)] * steps
    assert len(graph['queue5'].received) == steps * min(burst, 5)
    assert result.superseded == {'latest': {'/burst': steps * (burst - 1)}}
    assert result.dropped == ({'queue5': {'/burst': steps * (burst - 5)}} if burst > 5 else {})
    with BagReader(result.out_path) as out:  # the recorder keeps every message of a burst
        assert out.message_count(['/burst']) == steps * burst


def test_cli_summary_reports_superseded_deliveries(tmp_path, monkeypatch):
    import json

    from ar_tracking import cli
    from ar_tracking.ros import runner as runner_module

    bag = write_turning_imu_bag(tmp_path / 'in.mcap', seconds=0.1)
    monkeypatch.setattr(runner_module, 'GRAPH_NODES', _burst_graph(3))
    original = runner_module.GraphRunner.__init__

    def with_burst_graph(self, *args, **kwargs):
        original(self, *args, **kwargs)
        self.graph = runner_module.GRAPH_NODES
    monkeypatch.setattr(runner_module.GraphRunner, '__init__', with_burst_graph)
    printed = []
    monkeypatch.setattr('builtins.print', lambda *a, **k: printed.append(' '.join(map(str, a))))
    assert cli.main(['run', str(bag), '-o', str(tmp_path / 'out.mcap'), '--json', '-q']) == 0
    summary = json.loads(printed[-1])
    assert summary['superseded'] == {'latest': {'/burst': 20}} and summary['superseded_deliveries'] == 20
    assert summary['lost_deliveries'] == 0 and summary['dropped'] == {} and summary['lost'] == {}


ROTATION_BAG_TOPICS = ['/camera/camera_info', '/camera/image_raw/compressed', '/gps/fix', '/imu/data_raw',
                       '/imu/mag', '/ground_truth/orientation', '/ground_truth/pose']
DESK_BAG_TOPICS = ['/camera/camera_info', '/camera/image_raw', '/ground_truth/pose', '/imu/data_raw', '/tf_static']


def test_auto_graph_leaves_slam_out_of_a_rotate_in_place_bag():
    from ar_tracking.ros.runner import choose_nodes, plan_nodes

    wanted, ruled_out = choose_nodes(ROTATION_BAG_TOPICS)
    assert 'keyframe_slam_mapper' not in wanted and '/imu/mag' in ruled_out['keyframe_slam_mapper']
    names, _ = plan_nodes(ROTATION_BAG_TOPICS, wanted, params=lambda name: {})
    assert names == ['imu_magnetometer', 'panorama_mapper', 'hybrid_orientation_filter']
    wanted, ruled_out = choose_nodes(DESK_BAG_TOPICS)  # a hand-held camera without magnetometer
    assert ruled_out == {}
    assert 'keyframe_slam_mapper' in plan_nodes(DESK_BAG_TOPICS, wanted, params=lambda name: {})[0]


@pytest.mark.parametrize('named, expected', [
    ('slam', ['keyframe_slam_mapper']),
    ('all', ['imu_magnetometer', 'panorama_mapper', 'hybrid_orientation_filter', 'keyframe_slam_mapper']),
    ('orientation', ['imu_magnetometer', 'panorama_mapper', 'hybrid_orientation_filter']),
    ('markers', []),  # marker_tracker needs its marker map
])
def test_named_graphs_and_explicit_nodes_override_the_rule(named, expected):
    from ar_tracking.ros.runner import choose_nodes, plan_nodes

    wanted, ruled_out = choose_nodes(ROTATION_BAG_TOPICS, named_graph=named)
    assert ruled_out == {}
    assert plan_nodes(ROTATION_BAG_TOPICS, wanted, params=lambda name: {})[0] == expected
    assert choose_nodes(ROTATION_BAG_TOPICS, nodes=['keyframe_slam_mapper'], named_graph='orientation')[0] == [
        'keyframe_slam_mapper']
    with pytest.raises(RunError, match='unknown graph'):
        choose_nodes(ROTATION_BAG_TOPICS, named_graph='everything')


def test_cli_graph_choices_are_the_runners():
    from ar_tracking.cli import build_parser
    from ar_tracking.ros.runner import GRAPH_CHOICES

    run = build_parser()._subparsers._group_actions[0].choices['run']
    graph = next(a for a in run._actions if a.dest == 'graph')
    assert tuple(graph.choices) == GRAPH_CHOICES and graph.default == 'auto'


def test_auto_graph_says_why_at_info_level(tmp_path, caplog):
    bag = write_turning_imu_bag(tmp_path / 'in.mcap', seconds=0.2)  # has /imu/mag
    with caplog.at_level('INFO', logger='ar_tracking.ros.runner'):
        result = GraphRunner(bag, tmp_path / 'out.mcap').run()
    assert 'keyframe_slam_mapper' not in result.nodes
    assert '/imu/mag' in result.not_started['keyframe_slam_mapper']
    not_started = [r for r in caplog.records if 'not started' in r.getMessage()]
    assert any(r.getMessage().startswith('keyframe_slam_mapper not started: the bag has /imu/mag') for r in not_started)
    assert not_started and all(r.levelname == 'INFO' for r in not_started)
    caplog.clear()
    with caplog.at_level('INFO', logger='ar_tracking.ros.runner'):  # asked for by name: a warning
        GraphRunner(bag, tmp_path / 'out2.mcap', nodes=['imu_magnetometer', 'panorama_mapper']).run()
    assert [r.levelname for r in caplog.records if 'panorama_mapper not started' in r.getMessage()] == ['WARNING']


def test_runner_hands_the_bags_tf_static_to_nodes_that_take_it(tmp_path, caplog):
    """No tf2_msgs on the pip-only path: the runner reads /tf_static itself and calls
    on_static_transforms before the first message, on every node that has the method."""
    from sensor_msgs.msg import Imu

    from ar_tracking.ros.node_base import TrackingNode
    from bagfactory import R_IMU_CAM

    calls: list = []

    def fake(name: str, method: str | None):
        class Fake(TrackingNode):
            INPUTS = {'imu/data_raw': 'sensor_msgs/msg/Imu'}
            OUTPUTS: dict = {}

            def __init__(self, **kwargs):
                super().__init__(name, **kwargs)
                self.subscribe(Imu, 'imu/data_raw', lambda msg: calls.append((name, 'message')))

        if method == 'records':
            Fake.on_static_transforms = lambda self, transforms: calls.append((name, list(transforms)))
        elif method == 'raises':
            def broken(self, transforms):
                raise ValueError('no camera frame here')
            Fake.on_static_transforms = broken
        return Fake

    bag = write_turning_imu_bag(tmp_path / 'in.mcap', seconds=0.1)
    graph = {'taker': fake('taker', 'records'), 'ignorer': fake('ignorer', None), 'breaker': fake('breaker', 'raises')}
    with caplog.at_level('WARNING', logger='ar_tracking.ros.runner'):
        result = GraphRunner(bag, tmp_path / 'out.mcap', graph=graph).run()
    assert result.input_messages == 10 and result.lost_deliveries == 0
    given = [c for c in calls if c[1] != 'message']
    assert len(given) == 1 and given[0][0] == 'taker'
    assert calls.index(given[0]) == 0  # before any message
    (tf,) = given[0][1]
    assert (tf.parent, tf.child) == ('imu', 'camera_optical')
    np.testing.assert_allclose(tf.rotation, R_IMU_CAM, atol=1e-12)
    np.testing.assert_allclose(tf.translation, np.zeros(3))
    assert sum(1 for c in calls if c == ('breaker', 'message')) == 10  # the failing node runs on
    assert any('breaker: cannot use /tf_static' in r.getMessage() for r in caplog.records)


def _live_graph(slow_sleep_s: float = 0.05, die: bool = False) -> dict:
    """The orientation nodes of an IMU bag plus a deliberately slow node on the IMU topic (and,
    with ``die``, one whose timer raises once it has received three field samples: its thread
    dies while the bag plays)."""
    import time as _time

    from rclpy.clock import Clock, ClockType
    from sensor_msgs.msg import Imu, MagneticField

    from ar_tracking.ros.node_base import TrackingNode
    from ar_tracking.ros.runner import GRAPH_NODES

    class SlowNode(TrackingNode):
        INPUTS = {'imu/data_raw': 'sensor_msgs/msg/Imu'}
        OUTPUTS: dict = {}

        def __init__(self, **kwargs):
            super().__init__('slow', **kwargs)
            self.subscribe(Imu, 'imu/data_raw', lambda msg: _time.sleep(slow_sleep_s))

    graph = {name: GRAPH_NODES[name] for name in ('imu_magnetometer', 'hybrid_orientation_filter')}
    graph['slow'] = SlowNode
    if die:
        class DyingNode(TrackingNode):
            INPUTS = {'imu/mag': 'sensor_msgs/msg/MagneticField'}
            OUTPUTS: dict = {}

            def __init__(self, **kwargs):
                super().__init__('dying', **kwargs)
                self.received = 0
                self.subscribe(MagneticField, 'imu/mag', self.count)
                self.create_timer(0.05, self.fail, clock=Clock(clock_type=ClockType.STEADY_TIME))

            def count(self, msg):
                self.received += 1

            def fail(self):
                # Not before the bag plays: a timer that fired at a fixed time after start-up
                # was already due when the node threads started on a loaded machine, and the
                # node died before the player had published (and recorded) anything. The
                # third field sample comes after two whole steps of the bag (truth included).
                if self.received >= 3:
                    raise RuntimeError('sensor driver lost')

        graph['dying'] = DyingNode
    return graph


def test_realtime_slow_node_does_not_stall_the_imu_path(tmp_path):
    """Each node spins on its own thread: a node that takes 100 ms per IMU sample (20 Hz at 2x:
    40 samples/s) drops most of its inputs - counted and reported - while imu_magnetometer and
    the hybrid filter on the same IMU stream process every one (on one shared executor the
    slow callback held them up and they dropped most too); orientation/global latency is
    measured. A low sample rate keeps the fast nodes far from their limit on a busy machine."""
    bag = write_turning_imu_bag(tmp_path / 'in.mcap', seconds=3.0, rate_hz=20.0)
    result = GraphRunner(bag, tmp_path / 'out.mcap', rate=2.0, graph=_live_graph(slow_sleep_s=0.1)).run()
    assert result.failed_nodes == {} and not result.interrupted
    inputs = result.live_inputs
    assert inputs['imu_magnetometer'] == {'/imu/data_raw': (60, 60), '/imu/mag': (60, 60)}
    assert inputs['hybrid_orientation_filter']['/imu/data'] == (60, 60)
    assert result.live_dropped['imu_magnetometer'] == 0
    assert result.live_dropped['hybrid_orientation_filter'] == 0
    published, processed = inputs['slow']['/imu/data_raw']
    assert published == 60 and processed < 60
    assert result.live_dropped['slow'] == 60 - processed > 0
    summary = result.live_summary()
    assert summary['dropped']['slow'] == 60 - processed
    # (the hybrid follows imu/data once 0.2 s passed without a camera frame: 56 of the 60)
    assert summary['latency_n'] == 56 and 0 < summary['latency_ms_p50'] <= summary['latency_ms_p95']
    with BagReader(result.out_path) as out:
        assert out.message_count(['/orientation/global']) == 56


def test_realtime_dead_node_is_reported_and_the_cli_exits_non_zero(tmp_path, monkeypatch):
    import json

    from ar_tracking import cli
    from ar_tracking.ros import runner as runner_module

    bag = write_turning_imu_bag(tmp_path / 'in.mcap', seconds=3.0, rate_hz=20.0)
    graph = _live_graph(slow_sleep_s=0.0, die=True)
    result = GraphRunner(bag, tmp_path / 'out.mcap', rate=2.0, graph=graph).run()
    assert result.failed_nodes == {'dying': 'RuntimeError: sensor driver lost'}
    with BagReader(result.out_path) as out:  # the output closes cleanly with what was recorded
        assert out.message_count(['/ground_truth/orientation']) > 0

    monkeypatch.setattr(runner_module, 'GRAPH_NODES', graph)
    original = runner_module.GraphRunner.__init__

    def with_graph(self, *args, **kwargs):
        original(self, *args, **kwargs)
        self.graph = graph
    monkeypatch.setattr(runner_module.GraphRunner, '__init__', with_graph)
    printed = []
    monkeypatch.setattr('builtins.print', lambda *a, **k: printed.append(' '.join(map(str, a))))
    code = cli.main(['run', str(bag), '-o', str(tmp_path / 'cli.mcap'), '--rate', '2', '--json', '-q'])
    assert code == 1
    assert any('node dying died: RuntimeError: sensor driver lost' in line for line in printed)
    summary = json.loads(next(line for line in printed if line.startswith('{')))
    assert summary['failed_nodes'] == {'dying': 'RuntimeError: sensor driver lost'}
    assert set(summary['live']['dropped']) == {'imu_magnetometer', 'hybrid_orientation_filter', 'slow', 'dying'}


def test_node_that_raises_while_starting_is_one_error(tmp_path):
    from ar_tracking.ros.node_base import TrackingNode

    class Broken(TrackingNode):
        INPUTS = {'imu/data_raw': 'sensor_msgs/msg/Imu'}
        OUTPUTS: dict = {}

        def __init__(self, **kwargs):
            raise ValueError('parameter gain: must be positive')

    bag = write_turning_imu_bag(tmp_path / 'in.mcap', seconds=0.2)
    with pytest.raises(RunError, match=r'broken: cannot start \(parameter gain: must be positive\)'):
        GraphRunner(bag, tmp_path / 'out.mcap', rate=2.0, graph={'broken': Broken}).run()


def test_header_stamp_is_read_from_cdr_bytes():
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import CompressedImage, Imu

    from ar_tracking.ros.runner import header_stamp_ns

    for msg in (Imu(), CompressedImage(format='jpeg', data=b'\xff\xd8')):
        msg.header.stamp.sec, msg.header.stamp.nanosec = 1_700_000_123, 456_789_012
        msg.header.frame_id = 'camera_optical'
        assert header_stamp_ns(serialize_message(msg)) == 1_700_000_123_456_789_012
    assert header_stamp_ns(b'\x00\x01') is None


def _process_graph(extra: str) -> dict:
    from ar_tracking.ros.runner import GRAPH_NODES

    graph = {name: GRAPH_NODES[name] for name in ('imu_magnetometer', 'hybrid_orientation_filter')}
    graph[extra] = f'live_test_nodes:{"SlowNode" if extra == "slow" else "DyingNode"}'
    return graph


def test_realtime_nodes_in_processes_of_their_own(tmp_path):
    """--executor processes: every node in its own process (as ros2 launch starts them). The
    slow node's drops are counted from its process, the IMU path keeps every sample, the
    outputs reach the recorder and the latency is measured across processes."""
    bag = write_turning_imu_bag(tmp_path / 'in.mcap', seconds=3.0, rate_hz=20.0)
    result = GraphRunner(bag, tmp_path / 'out.mcap', rate=1.0, graph=_process_graph('slow'),
                         executor='processes').run()
    assert result.failed_nodes == {} and not result.interrupted
    inputs = result.live_inputs
    assert inputs['imu_magnetometer'] == {'/imu/data_raw': (60, 60), '/imu/mag': (60, 60)}
    assert inputs['hybrid_orientation_filter']['/imu/data'] == (60, 60)
    published, processed = inputs['slow']['/imu/data_raw']
    assert published == 60 and 0 < processed < 60
    assert result.live_dropped['slow'] == 60 - processed
    assert result.live_summary()['latency_n'] == 56  # after the hybrid's 0.2 s start-up hold
    with BagReader(result.out_path) as out:
        assert out.message_count(['/orientation/global']) == 56


def test_a_node_process_that_dies_is_reported_by_name(tmp_path):
    bag = write_turning_imu_bag(tmp_path / 'in.mcap', seconds=4.0, rate_hz=20.0)
    result = GraphRunner(bag, tmp_path / 'out.mcap', rate=1.0, graph=_process_graph('dying'),
                         executor='processes').run()
    assert result.failed_nodes == {'dying': 'RuntimeError: sensor driver lost'}
    with BagReader(result.out_path) as out:
        assert out.message_count(['/ground_truth/orientation']) > 0


def test_node_processes_stop_upstream_first(tmp_path):
    """At the end of a live run a node still working off a backlog (300 ms per sample) keeps
    publishing with gaps longer than a downstream node's drain wait: the downstream node is
    stopped only once the upstream one has drained and reported, so it takes every sample."""
    bag = write_turning_imu_bag(tmp_path / 'in.mcap', seconds=2.0, rate_hz=5.0)
    graph = {'relay': 'live_test_nodes:LaggingRelay', 'counter': 'live_test_nodes:RelayCounter'}
    result = GraphRunner(bag, tmp_path / 'out.mcap', rate=1.0, graph=graph, executor='processes').run()
    assert result.failed_nodes == {} and not result.interrupted
    n = result.live_inputs['relay']['/imu/data_raw'][0]
    assert n >= 9
    assert result.live_inputs['relay']['/imu/data_raw'] == (n, n)
    assert result.live_inputs['counter']['/relay/imu'] == (n, n)
    # each process's CPU (its imports and DDS included), reported with its counts
    assert set(result.live_cpu_s) == {'relay', 'counter'} and all(cpu > 0.1 for cpu in result.live_cpu_s.values())
    assert result.live_summary()['cpu_s'].keys() == {'relay', 'counter'}


@pytest.mark.parametrize('executor', ['processes', 'single'])
def test_a_best_effort_publisher_is_recorded(tmp_path, executor):
    """A node that publishes best effort (as sensor drivers do) is recorded: the recorder takes
    the reliability the publisher offers. Before, a reliable recorder never matched it: a node
    process waited out its 60 s start timeout, and nothing of its output was recorded."""
    bag = write_turning_imu_bag(tmp_path / 'in.mcap', seconds=1.0, rate_hz=20.0)
    graph = {'relay': 'live_test_nodes:BestEffortRelay'}
    started = time.monotonic()
    rate = 0.0 if executor == 'single' else 2.0
    result = GraphRunner(bag, tmp_path / 'out.mcap', rate=rate, graph=graph, executor=executor).run()
    assert time.monotonic() - started < 45.0  # the start timeout is 60 s
    assert result.failed_nodes == {} and not result.interrupted
    with BagReader(result.out_path) as out:
        assert out.message_count(['/relay/imu']) >= 15  # best effort on one machine: ~all of 20


def test_lockstep_over_node_processes_equals_one_process(tmp_path):
    """Lockstep with every node in a process of its own (``--executor processes`` without
    ``--rate``; the runner carries the messages over pipes): the same output bag, byte for byte,
    as the one-process lockstep, a node downstream of two others included, and a burst into a
    depth-1 subscription booked as superseded in the same way."""
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import Imu

    bag = write_turning_imu_bag(tmp_path / 'in.mcap', seconds=1.0, rate_hz=50.0)
    graph = {'relay': 'live_test_nodes:Relay', 'triple': 'live_test_nodes:TripleRelay',
             'latest': 'live_test_nodes:LatestField'}
    tapped: dict[str, list[bytes]] = {'one': [], 'many': []}

    def taps(run: str):  # an output tap (the Foxglove view's hook) sees every recorded output
        return [lambda topic, msgtype: tapped[run].append]
    one = GraphRunner(bag, tmp_path / 'one.mcap', graph=graph, output_taps=taps('one')).run()
    many = GraphRunner(bag, tmp_path / 'many.mcap', graph=graph, executor='processes',
                       output_taps=taps('many')).run()
    with BagReader(bag) as inp:
        fields = inp.message_count(['/imu/mag'])
    assert fields >= 40 and many.lost_deliveries == 0 and many.failed_nodes == {}
    assert many.superseded == one.superseded == {'latest': {'/relay/mag': 2 * fields}}
    assert many.input_messages == one.input_messages and many.output_messages == one.output_messages > 4 * fields
    assert (tmp_path / 'many.mcap').read_bytes() == (tmp_path / 'one.mcap').read_bytes()
    assert len(tapped['many']) == many.output_messages and sorted(tapped['many']) == sorted(tapped['one'])
    with BagReader(tmp_path / 'many.mcap') as out:
        ws = [deserialize_message(m.rawdata, Imu).orientation.w for m in out.messages(['/joined/imu'])]
    assert len(ws) >= 40 and set(ws) <= {-1.0, 2.0} and ws[-1] == 2.0  # the last of each burst
    assert set(many.timings_ms) == {'relay', 'triple', 'latest'}


def test_lockstep_over_node_processes_refuses_a_cycle_and_reports_a_dead_node(tmp_path):
    bag = write_turning_imu_bag(tmp_path / 'in.mcap', seconds=0.5)
    cycle = {'relay': 'live_test_nodes:Relay', 'echo': 'live_test_nodes:Echo'}
    with pytest.raises(RunError, match='cycle'):
        GraphRunner(bag, tmp_path / 'cycle.mcap', graph=cycle, executor='processes').run()
    dying = {'relay': 'live_test_nodes:Relay', 'dying': 'live_test_nodes:DyingNode'}
    with pytest.raises(RunError, match='dying died: RuntimeError: sensor driver lost'):
        GraphRunner(bag, tmp_path / 'dying.mcap', graph=dying, executor='processes').run()
    # closed cleanly, with the steps every node had finished (none here: the dying node's first
    # batch held them all)
    assert read_metadata(tmp_path / 'dying.mcap', RUN_METADATA)['clock'] == 'lockstep'
    with BagReader(tmp_path / 'dying.mcap') as out:
        assert out.recovered is None
