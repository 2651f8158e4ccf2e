"""Authoring on the sample authoring bag, re-detection in the graph on the browsing bag, and the
annotation measures (Langlotz 2011 sec. 3.2, 4.3, 6.1): a committed-bag regression. No ground
truth in the estimator path: the same bags without any /ground_truth/* topic give the same
stored records and the same placements."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import shutil

from ar_tracking.annotate import Position, annotate_bag
from ar_tracking.core.annotations.landmarks import LandmarkConfig
from ar_tracking.core.annotations.store import SqliteAnnotationStore, StoreError
from ar_tracking.core.panorama.cylinder import CylinderGeometry
from ar_tracking.core.rotations import quat_xyzw_to_matrix
from ar_tracking.eval.annotation_metrics import evaluate_annotations, simulated_user_positions
from ar_tracking.io.bags import BagReader, BagWriter
from conftest import SAMPLE_AUTHORING, SAMPLE_BROWSING, browse_sample

AUTHORING, BROWSING = SAMPLE_AUTHORING, SAMPLE_BROWSING


PANO_ID = 'authoring-7'


def strip_truth(bag: Path, out: Path) -> Path:
    """A copy of ``bag`` without any /ground_truth/* topic (and its calibration sidecar)."""
    with BagReader(bag) as r, BagWriter(out) as w:
        for m in r.messages([t for t in r.topics if not t.startswith('/ground_truth/')]):
            w.write(m.topic, m.log_time_ns, m.rawdata, m.msgtype)
    shutil.copyfile(bag.with_name(bag.stem + '.params.yaml'), out.with_name(out.stem + '.params.yaml'))
    with BagReader(out) as r:
        assert not [t for t in r.topics if 'ground_truth' in t]
    return out


@pytest.fixture(scope='module')
def authored(sample_authored):
    return sample_authored


@pytest.fixture(scope='module')
def authored_without_truth(authored, tmp_path_factory):
    """The same authoring from a copy of the bag without ground truth; the positions are the rows
    the simulated user gave the first time (what a user would type)."""
    _, first = authored
    d = tmp_path_factory.mktemp('notruth')
    bag = strip_truth(AUTHORING, d / 'authoring.mcap')
    rows = simulated_user_positions(AUTHORING)(first.first_stamp_ns)
    store = d / 'annotations.db'
    report = annotate_bag(bag, store, author='peter', panorama_id=PANO_ID, positions=rows)
    return store, report, rows


def test_annotate_stores_every_anchor_with_the_estimated_orientation(authored):
    store, report = authored
    assert report.lost_frames == 0 and not report.skipped and len(report.stored) == 6
    assert report.orientation_source == 'world_alignment' and 0 < report.heading_sigma_deg < 3.0
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
    with SqliteAnnotationStore(store) as s:
        info = s.panoramas([PANO_ID])[PANO_ID]
    assert info.orientation_source == 'estimated' and info.heading_sigma_rad() > 0
    R = quat_xyzw_to_matrix(recs[0].panorama_in_world_quat_xyzw)
    assert np.allclose(info.up, R[2])  # the estimated up is the panorama's ENU z
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


def test_stored_records_do_not_depend_on_the_ground_truth(authored, authored_without_truth):
    store, report = authored
    store2, report2, rows = authored_without_truth
    assert report2.stored and len(report2.stored) == len(report.stored)
    assert all(r.form == 'azel' for r in rows)
    with SqliteAnnotationStore(store) as a, SqliteAnnotationStore(store2) as b:
        ra, rb = a.all(), b.all()
        assert [x.text for x in ra] == [x.text for x in rb]
        for x, y in zip(ra, rb):
            assert np.array_equal(x.patch, y.patch) and np.array_equal(x.direction, y.direction)
            assert np.array_equal(x.panorama_in_world_quat_xyzw, y.panorama_in_world_quat_xyzw)
        la, lb = a.landmarks([PANO_ID]), b.landmarks([PANO_ID])
        assert len(la) == len(lb) and all(np.array_equal(x.patch, y.patch) for x, y in zip(la, lb))
        pa, pb = a.panoramas([PANO_ID])[PANO_ID], b.panoramas([PANO_ID])[PANO_ID]
        assert np.array_equal(pa.covariance_enu, pb.covariance_enu) and np.array_equal(pa.up, pb.up)


def test_annotating_twice_does_not_duplicate_and_replace_authors_again(authored, tmp_path):
    store = tmp_path / 'twice.db'
    shutil.copyfile(authored[0], store)
    rows = [Position('Tower', 0.0, 5.0, 'azel')]
    again = annotate_bag(AUTHORING, store, panorama_id=PANO_ID, positions=simulated_user_positions(AUTHORING))
    assert again.stored == [] and again.duplicates == 6 and again.landmarks == 0
    with SqliteAnnotationStore(store) as s:
        n_lm = len(s.landmarks([PANO_ID]))
        assert s.count() == 6
    fresh = annotate_bag(AUTHORING, store, panorama_id=PANO_ID, positions=rows, replace=True)
    assert fresh.replaced == 6 and len(fresh.stored) == 1 and fresh.landmarks > 0
    with SqliteAnnotationStore(store) as s:
        assert [a.text for a in s.all()] == ['Tower'] and len(s.landmarks([PANO_ID])) <= n_lm


def test_annotate_refuses_a_corrupt_store_without_touching_it(tmp_path):
    bad = tmp_path / 'bad.db'
    bad.write_bytes(b'not a database' * 10)
    with pytest.raises(StoreError, match='corrupt'):
        annotate_bag(AUTHORING, bad, positions=[])
    assert bad.read_bytes() == b'not a database' * 10


@pytest.fixture(scope='module')
def browsed(sample_browsed):
    return sample_browsed


def _arrays(bag: Path) -> list:
    with BagReader(bag) as r:
        return [[(mk.header.stamp.sec, mk.header.stamp.nanosec, mk.ns, mk.text, mk.pose.position.x,
                  mk.pose.position.y, mk.pose.position.z) for mk in msg.markers]
                for _, msg in r.read_all('/annotations/markers')]


def test_placements_do_not_depend_on_the_ground_truth(browsed, authored_without_truth, tmp_path):
    pytest.importorskip('rclpy')
    bag = strip_truth(BROWSING, tmp_path / 'browsing.mcap')
    out = browse_sample(bag, authored_without_truth[0], tmp_path / 'out.mcap')
    a, b = _arrays(browsed), _arrays(out)
    assert a and a == b


def test_redetection_in_the_browsing_bag(browsed, tmp_path):
    out = browsed
    m = evaluate_annotations(out)
    assert m is not None and m['n'] == 6
    assert m['redetection_rate'] >= 0.8 and m['wrong_rate'] <= 0.2
    assert m['time_to_first_s'] is not None and 0.0 <= m['time_to_first_s'] < 20.0
    assert m['wrong_label_time_share'] is not None and m['wrong_label_time_share'] <= 0.01
    assert m['label_time_s'] > 0
    assert evaluate_annotations(AUTHORING) is None  # no markers: not this area
    from ar_tracking.eval.annotation_figures import annotation_figure
    png = annotation_figure(out, tmp_path / 'fig4.png')
    assert png is not None and png.stat().st_size > 10_000
    from ar_tracking.eval.report import write_report
    html = write_report(out, tmp_path / 'report.html').read_text()
    assert 'Annotations placed in the panorama' in html and 'Panorama map built' in html
