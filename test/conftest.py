"""Shared test fixtures: private rclpy contexts, small bags, the shared real-data folder."""
from __future__ import annotations

import itertools
import os
import time
from pathlib import Path
from typing import Any, Callable, Iterator

import pytest

#: Real recordings (../shared/data beside the repository, or $AR_TRACKING_SHARED_DATA) when present.
SHARED_DATA = Path(os.environ.get('AR_TRACKING_SHARED_DATA')
                   or Path(__file__).resolve().parents[2] / 'shared' / 'data')

#: DDS domains of the private contexts: 1-99, a block of 33 per pytest-xdist worker, so that
#: two workers' tests never share a domain (with one count per process they did, and a latched
#: topic of one worker's test reached the other's); the runner's graphs use 101-200.
_WORKER = os.environ.get('PYTEST_XDIST_WORKER', 'gw0')
_BLOCK = int(_WORKER[2:]) % 3 if _WORKER[2:].isdigit() else 0
_domain_ids = (1 + 33 * _BLOCK + k % 33 for k in itertools.count(os.getpid() % 33))


@pytest.fixture
def ros_context() -> Iterator[Any]:
    """An initialised private rclpy Context on its own DDS domain, shut down afterwards."""
    rclpy = pytest.importorskip('rclpy')
    from rclpy.context import Context

    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    context = Context()
    rclpy.init(context=context, domain_id=next(_domain_ids))
    try:
        yield context
    finally:
        rclpy.try_shutdown(context=context)


def spin_until(executor: Any, predicate: Callable[[], bool], timeout_s: float = 10.0) -> bool:
    """Spin an executor until the predicate holds or the deadline passes; returns the predicate."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        executor.spin_once(timeout_sec=0.02)
    return predicate()


@pytest.fixture(scope='session')
def pg_cluster() -> Iterator[Any]:
    """A throwaway PostgreSQL + PostGIS cluster (initdb, pg_ctl, unix socket in a temp dir) for
    the whole session; skipped with the reason when the binaries are missing
    (./ar-tracking.sh test installs them as root: apt-get install postgresql postgis)."""
    from ar_tracking.io.pg_cluster import ClusterError, TemporaryCluster, unavailable_reason

    reason = unavailable_reason()
    if reason is not None:
        pytest.skip(reason)
    try:
        cluster = TemporaryCluster().start()
    except ClusterError as exc:
        pytest.skip(f'temporary PostgreSQL cluster did not start: {exc}')
    try:
        yield cluster
    finally:
        cluster.stop()


_pg_schemas = itertools.count()


@pytest.fixture
def pg_store_url(pg_cluster: Any) -> str:
    """A store URL in the session cluster with a schema of its own (a fresh, empty store)."""
    return f'{pg_cluster.url}&schema=t{os.getpid()}_{next(_pg_schemas)}'


_runner_domains = itertools.count(os.getpid() % 50)


@pytest.fixture(autouse=True)
def _lockstep_runs_lose_nothing(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Issue 18: every lockstep run of the suite loses and drops no delivery. Each in-process
    ``GraphRunner.run`` at rate 0 is checked when it returns; a test that provokes a loss on
    purpose says so with ``@pytest.mark.lossy``."""
    if request.node.get_closest_marker('lossy') is not None:
        yield
        return
    try:
        from ar_tracking.ros import runner as runner_module
    except ImportError:  # no rclpy: no runs to check
        yield
        return
    original = runner_module.GraphRunner.run
    bad: list[str] = []

    def checked_run(self: Any) -> Any:
        result = original(self)
        if self.rate == 0 and (result.lost_deliveries or result.dropped_deliveries):
            bad.append(f'{self.bag_path}: lost {result.lost}, dropped {result.dropped}')
        return result

    monkeypatch.setattr(runner_module.GraphRunner, 'run', checked_run)
    # Realtime graphs keep localhost discovery: each xdist worker's runs take their own half of
    # the runner's domains (101-150, 151-200), so two workers' live runs never share one.
    monkeypatch.setattr(runner_module, '_domain_id', lambda: 101 + 50 * (_BLOCK % 2) + next(_runner_domains) % 50)
    yield
    assert not bad, 'lockstep run lost or dropped deliveries: ' + '; '.join(bad)


#: The committed sample bags (bags/): annotations authored on the first, browsed on the second.
SAMPLE_BAGS = Path(__file__).resolve().parents[1] / 'bags'
SAMPLE_AUTHORING = SAMPLE_BAGS / 'rotation_sweep_authoring.mcap'
SAMPLE_BROWSING = SAMPLE_BAGS / 'rotation_sweep_browsing.mcap'


@pytest.fixture(scope='session')
def sample_authored(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Any]:
    """The simulated user's annotations on the authoring sample bag (author peter, panorama
    authoring-7): the store and annotate_bag's report. Tests only read the store."""
    from ar_tracking.annotate import annotate_bag
    from ar_tracking.eval.annotation_metrics import simulated_user_positions

    store = tmp_path_factory.mktemp('store') / 'annotations.db'
    report = annotate_bag(SAMPLE_AUTHORING, store, author='peter', panorama_id='authoring-7',
                          positions=simulated_user_positions(SAMPLE_AUTHORING))
    return store, report


def browse_sample(bag: Path, store: Path, out: Path) -> Path:
    """The orientation graph and annotation_matcher (store ``store``) run on ``bag``, lockstep."""
    import yaml

    from ar_tracking.ros.runner import GRAPH_NODES, GraphRunner

    graph = dict(GRAPH_NODES)
    graph['annotation_matcher'] = 'ar_tracking.nodes.annotation_matcher:AnnotationMatcherNode'
    params = out.with_suffix('.yaml')
    params.write_text(yaml.safe_dump({'annotation_matcher': {'ros__parameters': {'store_path': str(store)}}}))
    result = GraphRunner(bag, out, params_files=[bag.with_name(bag.stem + '.params.yaml'), params],
                         graph=graph, nodes=['imu_magnetometer', 'panorama_mapper', 'hybrid_orientation_filter',
                                             'annotation_matcher']).run()
    assert 'annotation_matcher' in result.nodes
    # (as a session fixture it runs outside the per-test check below: checked here)
    assert not (result.lost_deliveries or result.dropped_deliveries)
    return out


@pytest.fixture(scope='session')
def sample_browsed(sample_authored: tuple[Path, Any], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The output bag of :func:`browse_sample` on the browsing sample bag with the authored store."""
    pytest.importorskip('rclpy')
    return browse_sample(SAMPLE_BROWSING, sample_authored[0], tmp_path_factory.mktemp('browse') / 'out.mcap')


#: pytest-xdist (-n 2): the modules whose tests share an expensive module- or session-scoped
#: fixture (a simulated bag, a graph run), by group. A group runs on one worker, so that its
#: fixtures are built once and not once per worker; the groups are handed out first, the
#: other tests one by one after them. (xdist's own ``--dist loadgroup`` does not work with
#: pytest 9.2: it renames the items' nodeids, which pytest 9.2 no longer lets it do.)
XDIST_GROUPS = {
    'test/test_end_to_end.py': 'end_to_end',
    'test/test_annotations_end_to_end.py': 'sample_annotations',  # sample_authored, sample_browsed
    'test/eval/test_annotation_replay.py': 'sample_annotations',
    'test/test_slam_end_to_end.py': 'slam_end_to_end',
    'test/eval/test_vi_metrics.py': 'vi_metrics',
    'test/sim/test_rotation_sweep.py': 'rotation_sweep',
    'test/sim/test_photo_world.py': 'photo_world',
    'test/core/test_panorama_rolling_shutter.py': 'panorama_rolling_shutter',
    'test/core/test_panorama_core.py': 'panorama_core',
    'test/core/test_panorama_overlap.py': 'panorama_overlap',
    'test/core/test_time_offset.py': 'time_offset',  # _camera_track, cached per process
    'test/eval/test_bench.py': 'bench',  # the benches' seed-1 bag: its simulated view built once
    'test/eval/test_bench_hybrid.py': 'bench',
    'test/eval/test_report.py': 'report',
    'test/io/test_replay.py': 'replay',
    'test/ros/test_panorama_mapper_node.py': 'panorama_mapper_node',
    'test/ros/test_keyframe_slam_mapper_node.py': 'keyframe_slam_mapper_node',
}

#: Long tests outside the groups: first in the collection, so that none of them is the last
#: test of a worker while the other worker is done (xdist hands tests out in this order).
LONG_TESTS = (
    'test/test_lint.py::test_mypy_on_the_cores_finds_nothing',
    'test/eval/test_bench_hybrid.py::test_broad_trial_is_scored_for_every_estimator',
    'test/eval/test_bench_hybrid.py::test_sim_bench_runs_on_a_short_bag',
    'test/eval/test_bench_annotations.py::test_make_bag_lighting_argument',
    'test/core/slam/test_slam_robustness.py::test_relocalises_after_a_long_gap_in_another_place',
    'test/eval/test_bench.py::test_quiet_bench_prints_its_json_and_no_node_logs',
    'test/ros/test_ros_citizen.py::test_graph_as_separate_processes_tf_at_camera_rate_and_live_parameter',
)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """LONG_TESTS first (a stable sort: the rest keeps its order)."""
    items.sort(key=lambda item: not item.nodeid.startswith(LONG_TESTS))


def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """xdist's load scheduling (the default with -n), with the groups of XDIST_GROUPS."""
    if config.getvalue('dist') != 'load':
        return None
    from xdist.scheduler import LoadScopeScheduling

    class GroupedLoadScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return XDIST_GROUPS.get(nodeid.split('::', 1)[0], nodeid)

    return GroupedLoadScheduling(config, log)


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line('markers', 'lossy: the test provokes lost or dropped lockstep deliveries on purpose')
