"""Authoring on the sample authoring bag, re-detection in the graph on the browsing bag, and the
annotation measures (Langlotz 2011 sec. 3.2, 4.3, 6.1): a committed-bag regression."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from ar_tracking.annotate import annotate_bag
from ar_tracking.core.annotations.landmarks import LandmarkConfig
from ar_tracking.core.annotations.store import SqliteAnnotationStore, StoreError
from ar_tracking.core.panorama.cylinder import CylinderGeometry
from ar_tracking.core.rotations import quat_xyzw_to_matrix
from ar_tracking.eval.annotation_metrics import evaluate_annotations

BAGS = Path(__file__).resolve().parents[1] / 'bags'
AUTHORING = BAGS / 'rotation_sweep_authoring.mcap'
BROWSING = BAGS / 'rotation_sweep_browsing.mcap'


@pytest.fixture(scope='module')
def authored(tmp_path_factory):
    store = tmp_path_factory.mktemp('store') / 'annotations.db'
    report = annotate_bag(AUTHORING, store, author='peter')
    return store, report


def test_annotate_stores_every_ground_truth_anchor(authored):
    store, report = authored
    assert report.lost_frames == 0 and not report.skipped and len(report.stored) == 6
    with SqliteAnnotationStore(store) as s:
        recs = s.near(report.latitude_deg, report.longitude_deg, 50.0)
        assert len(recs) == 6 and s.integrity_ok()
    geo = CylinderGeometry()
    for a in recs:
        assert a.patch.shape == (16, 16) and a.author == 'peter' and a.has_world_orientation()
        assert abs(np.linalg.norm(a.direction) - 1) < 1e-9
        u, v = geo.project(a.direction)
        assert 0 <= u < 2048 and 0 <= v < 512
    assert len({a.panorama_id for a in recs}) == 1
    # Landmarks of the same panorama: the requested number above the horizon, none at an
    # anchor, then the support landmarks, each next to an anchor.
    with SqliteAnnotationStore(store) as s:
        lms = s.landmarks([recs[0].panorama_id])
    assert report.landmarks == len(lms) and 24 < len(lms) <= 24 + LandmarkConfig.support_count * 6
    R_enu_pano = quat_xyzw_to_matrix(recs[0].panorama_in_world_quat_xyzw)
    dirs = np.array([lm.direction for lm in lms])
    anchors = np.array([a.direction for a in recs])
    assert np.all(dirs[:24] @ R_enu_pano[2] > 0)
    assert np.max(dirs[:24] @ anchors.T) < np.cos(np.radians(2.0))
    su, sv = geo.project(dirs[24:])
    au, av = geo.project(anchors)
    du = np.abs((su[:, None] - au[None] + 1024) % 2048 - 1024)
    cfg = LandmarkConfig()
    assert np.all(((du <= cfg.support_u_px + 0.5) & (np.abs(sv[:, None] - av[None]) <= cfg.support_v_px + 0.5)).any(axis=1))


def test_annotate_refuses_a_corrupt_store_without_touching_it(tmp_path):
    bad = tmp_path / 'bad.db'
    bad.write_bytes(b'not a database' * 10)
    with pytest.raises(StoreError, match='corrupt'):
        annotate_bag(AUTHORING, bad)
    assert bad.read_bytes() == b'not a database' * 10


def test_redetection_in_the_browsing_bag(authored, tmp_path):
    pytest.importorskip('rclpy')
    from ar_tracking.ros.runner import GRAPH_NODES, GraphRunner

    store, _ = authored
    graph = dict(GRAPH_NODES)
    graph['annotation_matcher'] = 'ar_tracking.nodes.annotation_matcher:AnnotationMatcherNode'
    params = tmp_path / 'p.yaml'
    params.write_text(yaml.safe_dump({'annotation_matcher': {'ros__parameters': {'store_path': str(store)}}}))
    out = tmp_path / 'out.mcap'
    result = GraphRunner(BROWSING, out, params_files=[BROWSING.with_name(BROWSING.stem + '.params.yaml'), params],
                         graph=graph, nodes=['imu_magnetometer', 'panorama_mapper', 'hybrid_orientation_filter',
                                             'annotation_matcher']).run()
    assert 'annotation_matcher' in result.nodes
    m = evaluate_annotations(out)
    assert m is not None and m['n'] == 6
    assert m['redetection_rate'] >= 0.8 and m['wrong_rate'] <= 0.2
    assert m['time_to_first_s'] is not None and m['time_to_first_s'] < 20.0
    assert evaluate_annotations(AUTHORING) is None  # no markers: not this area
    from ar_tracking.eval.annotation_figures import annotation_figure
    png = annotation_figure(out, tmp_path / 'fig4.png')
    assert png is not None and png.stat().st_size > 10_000
    from ar_tracking.eval.report import write_report
    html = write_report(out, tmp_path / 'report.html').read_text()
    assert 'Annotations placed in the panorama' in html and 'Panorama map built' in html
