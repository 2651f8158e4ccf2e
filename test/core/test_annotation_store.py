"""The SQLite annotation store (Langlotz 2011 sec. 4.3): records, radius query, bad files."""
from __future__ import annotations

import math
import sqlite3
import threading

import numpy as np
import pytest

from annotation_synth import annotation
from ar_tracking.core.annotations import store as store_module
from ar_tracking.core.annotations.store import (SCHEMA_VERSION, Landmark, PanoramaInfo, SqliteAnnotationStore,
                                                StoreError, distance_m, open_store, validate_annotation,
                                                validate_landmark)

LAT, LON = 47.0458, 15.4251


def offset(lat: float, lon: float, north_m: float, east_m: float) -> tuple[float, float]:
    return (lat + math.degrees(north_m / 6_371_008.8),
            lon + math.degrees(east_m / (6_371_008.8 * math.cos(math.radians(lat)))))


def rec(seed: int = 0, side: int = 16, **kw):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=3)
    return annotation(rng.integers(0, 256, (side, side), dtype=np.uint8), d / np.linalg.norm(d), **kw)


def landmark(seed: int = 0, pano: str = 'p1', side: int = 16) -> Landmark:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=3)
    return Landmark(pano, rng.integers(0, 256, (side, side), dtype=np.uint8), d / np.linalg.norm(d))


def make_version_1(path) -> None:
    """Turn a fresh store file into what the version-1 program wrote: no landmarks table."""
    db = sqlite3.connect(path)
    db.execute('DROP TABLE landmarks')
    db.execute("UPDATE meta SET value = '1' WHERE key = 'version'")
    db.commit()
    db.close()


def meta_version(path) -> str:
    db = sqlite3.connect(path)
    try:
        return db.execute("SELECT value FROM meta WHERE key = 'version'").fetchone()[0]
    finally:
        db.close()


@pytest.fixture
def store(tmp_path):
    s = SqliteAnnotationStore(tmp_path / 'a.db', create=True)
    yield s
    s.close()


def test_round_trip_keeps_every_field(store):
    q = np.array([0.0, 0.0, math.sin(0.2), math.cos(0.2)])
    a = rec(1, side=32, text='Door', q=q)
    report = store.add([a])
    assert report.ids == [1] and not report.skipped
    (b,) = store.all()
    assert b.id == 1 and b.text == 'Door' and b.author == 'peter' and b.panorama_id == 'p1'
    assert np.array_equal(b.patch, a.patch) and b.patch.shape == (32, 32)
    assert np.allclose(b.direction, a.direction) and b.created_ns == a.created_ns
    assert np.allclose(b.panorama_in_world_quat_xyzw, q) and b.has_world_orientation()
    assert (b.latitude_deg, b.longitude_deg, b.altitude_m) == (a.latitude_deg, a.longitude_deg, a.altitude_m)
    assert len(a.patch.tobytes()) + len(a.text) < 2100  # about 2 kB a record (sec. 4.3)


def test_radius_query_is_an_rtree_index_query(store):
    recs = []
    for k, dist in enumerate([10.0, 45.0, 55.0, 500.0, 49.0]):
        lat, lon = offset(LAT, LON, dist * math.cos(k), dist * math.sin(k))
        recs.append(rec(k, text=f'at {dist:g} m', lat=lat, lon=lon))
    store.add(recs)
    found = sorted(a.text for a in store.near(LAT, LON, 50.0))
    assert found == ['at 10 m', 'at 45 m', 'at 49 m']
    for a in store.near(LAT, LON, 50.0):
        assert distance_m(LAT, LON, a.latitude_deg, a.longitude_deg) <= 50.0
    plan = ' '.join(str(r) for r in store._db.execute(
        'EXPLAIN QUERY PLAN SELECT id FROM annotations_rtree WHERE max_lat >= 1 AND min_lat <= 2 '
        'AND max_lon >= 1 AND min_lon <= 2').fetchall())
    assert 'VIRTUAL TABLE INDEX' in plan


def test_bad_records_are_skipped_and_reported(store):
    good = rec(0)
    wrong_size = annotation(np.zeros((15, 15), np.uint8), good.direction)
    nan_dir = annotation(good.patch, np.array([np.nan, 0.0, 1.0]))
    zero_dir = annotation(good.patch, np.zeros(3))
    bad_pos = annotation(good.patch, good.direction, lat=float('nan'))
    report = store.add([wrong_size, good, nan_dir, zero_dir, bad_pos])
    assert len(report.ids) == 1
    assert [i for i, _ in report.skipped] == [0, 2, 3, 4]
    assert 'patch' in report.skipped[0][1] and 'finite' in report.skipped[1][1]
    assert store.count() == 1


def test_corrupt_record_in_file_is_skipped_on_read(store):
    store.add([rec(0), rec(1)])
    store._db.execute('UPDATE annotations SET patch = ? WHERE id = 2', (b'short',))
    assert [a.id for a in store.all()] == [1]
    assert len(store.skipped) == 1 and 'record 2' in store.skipped[0]


def test_missing_file_is_an_error_and_not_created(tmp_path):
    path = tmp_path / 'nope.db'
    with pytest.raises(StoreError, match='no such annotation store'):
        SqliteAnnotationStore(path)
    assert not path.exists()


@pytest.mark.parametrize('content', [b'garbage' * 100, b''])
def test_corrupt_file_is_an_error_and_left_untouched(tmp_path, content):
    path = tmp_path / 'bad.db'
    path.write_bytes(content)
    for create in (False, True):
        with pytest.raises(StoreError, match='corrupt'):
            SqliteAnnotationStore(path, create=create)
    assert path.read_bytes() == content


def test_foreign_sqlite_file_is_refused_untouched(tmp_path):
    path = tmp_path / 'other.db'
    db = sqlite3.connect(path)
    db.execute('CREATE TABLE x (y)')
    db.commit()
    db.close()
    before = path.read_bytes()
    with pytest.raises(StoreError, match='not an annotation store|corrupt'):
        SqliteAnnotationStore(path, create=True)
    assert path.read_bytes() == before


def test_truncated_store_is_reported(tmp_path):
    path = tmp_path / 't.db'
    with SqliteAnnotationStore(path, create=True) as s:
        s.add([rec(k) for k in range(50)])
    data = path.read_bytes()
    path.write_bytes(data[:len(data) // 3])
    with pytest.raises(StoreError):
        with SqliteAnnotationStore(path) as s:
            s.all()


def test_locked_store_gives_one_line_error(tmp_path):
    path = tmp_path / 'l.db'
    SqliteAnnotationStore(path, create=True).close()
    other = sqlite3.connect(path, isolation_level=None)
    other.execute('BEGIN EXCLUSIVE')
    try:
        with SqliteAnnotationStore(path, timeout_s=0.1) as s:
            with pytest.raises(StoreError, match='locked') as info:
                s.add([rec(0)])
            assert '\n' not in str(info.value)
    finally:
        other.execute('ROLLBACK')
        other.close()
    with SqliteAnnotationStore(path) as s:
        assert s.add([rec(0)]).ids == [1]


def test_concurrent_readers_and_writer_do_not_corrupt(tmp_path):
    path = tmp_path / 'c.db'
    SqliteAnnotationStore(path, create=True).close()
    batches, size = 30, 5
    seen: list[list[int]] = [[], []]
    errors: list[BaseException] = []
    done = threading.Event()

    def writer():
        try:
            with SqliteAnnotationStore(path, timeout_s=10) as s:
                for b in range(batches):
                    s.add([rec(b * size + k) for k in range(size)])
        except BaseException as exc:  # noqa: BLE001
            errors.append(exc)
        finally:
            done.set()

    def reader(k):
        try:
            with SqliteAnnotationStore(path, timeout_s=10, read_only=True) as s:
                while not done.is_set():
                    seen[k].append(len(s.near(47.0, 15.0, 50.0)))
                seen[k].append(len(s.near(47.0, 15.0, 50.0)))
        except BaseException as exc:  # noqa: BLE001
            errors.append(exc)

    threads = [threading.Thread(target=writer)] + [threading.Thread(target=reader, args=(k,)) for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert not errors, errors
    for counts in seen:
        assert counts and all(c % size == 0 for c in counts)  # whole transactions only
        assert counts == sorted(counts) and counts[-1] == batches * size
    with SqliteAnnotationStore(path) as s:
        assert s.count() == batches * size and s.integrity_ok()


def test_open_store_urls(tmp_path):
    with open_store(f'sqlite:///{tmp_path / "u.db"}', create=True) as s:
        assert s.count() == 0
    with pytest.raises(StoreError, match='PostgreSQL'):
        open_store('postgresql://host/db')


def test_invalid_query_position_is_an_error(store):
    with pytest.raises(StoreError):
        store.near(float('nan'), 15.0)


def test_new_store_has_the_landmarks_table(tmp_path):
    path = tmp_path / 'n.db'
    SqliteAnnotationStore(path, create=True).close()
    assert meta_version(path) == str(SCHEMA_VERSION)
    db = sqlite3.connect(path)
    names = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE tbl_name = 'landmarks'")}
    db.close()
    assert names == {'landmarks', 'landmarks_panorama_id'}


def test_landmarks_round_trip_per_panorama(store):
    a = [landmark(k, 'pa', side=8 * (k % 4 + 1)) for k in range(3)]
    b = [landmark(10 + k, 'pb') for k in range(2)]
    report = store.add_landmarks([a[0], b[0], a[1], b[1], a[2]])
    assert report.ids == [1, 2, 3, 4, 5] and not report.skipped
    got = store.landmarks(['pa'])
    assert [lm.id for lm in got] == [1, 3, 5] and {lm.panorama_id for lm in got} == {'pa'}
    for want, lm in zip(a, got):
        assert lm.patch.dtype == np.uint8 and np.array_equal(lm.patch, want.patch)
        assert np.array_equal(lm.direction, want.direction)
    assert [lm.id for lm in store.landmarks(['pb', 'pa', 'pb'])] == [1, 2, 3, 4, 5]
    assert store.landmarks(['nope']) == [] and store.landmarks([]) == []
    assert store.count() == 0 and store.all() == []  # landmarks are not annotations


def test_landmarks_query_accepts_many_panorama_ids(store):
    store._db.setlimit(sqlite3.SQLITE_LIMIT_VARIABLE_NUMBER, 999)  # sqlite's old default
    n = 1500  # more ids than one statement may bind
    store.add_landmarks([landmark(0, f'p{n - 1}'), landmark(1, 'p0')])
    ids = [f'p{k}' for k in range(n)]
    assert [lm.panorama_id for lm in store.landmarks(iter(ids))] == [f'p{n - 1}', 'p0']
    with pytest.raises(TypeError, match='one string'):
        store.landmarks('p0')


def test_invalid_landmarks_are_skipped_and_reported(store):
    good = landmark(0)
    wrong_size = Landmark('p1', np.zeros((15, 15), np.uint8), good.direction)
    nan_dir = Landmark('p1', good.patch, np.array([np.nan, 0.0, 1.0]))
    long_dir = Landmark('p1', good.patch, 2 * good.direction)
    no_pano = Landmark('', good.patch, good.direction)
    report = store.add_landmarks([wrong_size, good, nan_dir, long_dir, no_pano, landmark(1)])
    assert report.ids == [1, 2]
    reasons = dict(report.skipped)
    assert sorted(reasons) == [0, 2, 3, 4]
    assert 'patch' in reasons[0] and 'finite' in reasons[2] and 'unit' in reasons[3]
    assert 'panorama_id' in reasons[4]
    assert [lm.id for lm in store.landmarks(['p1'])] == [1, 2]
    # the patch and direction checks are the annotations' ones
    for lm in (wrong_size, nan_dir, long_dir):
        assert validate_landmark(lm) == validate_annotation(annotation(lm.patch, lm.direction))
    assert validate_landmark(rec(0)) is not None  # an annotation is not a landmark


def test_only_invalid_landmarks_write_nothing(store):
    report = store.add_landmarks([Landmark('p1', np.zeros((16, 16), np.uint8), np.array([0.0, 0.0, 1.0]))])
    assert report.ids == [] and report.skipped == [(0, 'patch has no texture')]
    assert store.landmarks(['p1']) == []


def test_version_1_store_opens_and_upgrades_on_add_landmarks(tmp_path):
    path = tmp_path / 'v1.db'
    with SqliteAnnotationStore(path, create=True) as s:
        s.add([rec(0), rec(1)])
    make_version_1(path)
    with SqliteAnnotationStore(path) as s:
        assert s.landmarks(['p1']) == [] and not s.skipped
        assert [a.id for a in s.all()] == [1, 2]
        assert meta_version(path) == '1'  # opening and reading do not upgrade
        assert s.add_landmarks([landmark(0), landmark(1, 'p2')]).ids == [1, 2]
        assert meta_version(path) == '2'
        assert [lm.id for lm in s.landmarks(['p1', 'p2'])] == [1, 2]
        assert s.add([rec(2)]).ids == [3] and s.integrity_ok()
    with SqliteAnnotationStore(path) as s:
        assert [lm.panorama_id for lm in s.landmarks(['p1', 'p2'])] == ['p1', 'p2']
        assert s.count() == 3
        plan = ' '.join(str(r) for r in s._db.execute(
            "EXPLAIN QUERY PLAN SELECT id FROM landmarks WHERE panorama_id IN ('p1')").fetchall())
        assert 'landmarks_panorama_id' in plan


def test_read_only_handle_never_upgrades_a_version_1_store(tmp_path):
    path = tmp_path / 'ro.db'
    with SqliteAnnotationStore(path, create=True) as s:
        s.add([rec(0)])
    make_version_1(path)
    with SqliteAnnotationStore(path, read_only=True) as s:
        assert s.landmarks(['p1']) == [] and len(s.all()) == 1
        with pytest.raises(StoreError) as info:
            s.add_landmarks([landmark(0)])
        assert '\n' not in str(info.value)
    assert meta_version(path) == '1'
    db = sqlite3.connect(path)
    assert db.execute("SELECT name FROM sqlite_master WHERE name LIKE 'landmarks%'").fetchall() == []
    db.close()


def test_newer_store_version_is_refused(tmp_path):
    path = tmp_path / 'v99.db'
    SqliteAnnotationStore(path, create=True).close()
    db = sqlite3.connect(path)
    db.execute("UPDATE meta SET value = '99' WHERE key = 'version'")
    db.commit()
    db.close()
    with pytest.raises(StoreError, match='version 99 is newer'):
        SqliteAnnotationStore(path)


def test_corrupt_landmark_row_is_skipped_on_read(tmp_path):
    path = tmp_path / 'cl.db'
    with SqliteAnnotationStore(path, create=True) as s:
        assert s.add_landmarks([landmark(k) for k in range(3)]).ids == [1, 2, 3]
    db = sqlite3.connect(path)
    db.execute('UPDATE landmarks SET patch = ? WHERE id = 2', (b'\x00' * 100,))
    db.execute('UPDATE landmarks SET dx = 5.0 WHERE id = 3')
    db.commit()
    db.close()
    with SqliteAnnotationStore(path) as s:
        assert [lm.id for lm in s.landmarks(['p1'])] == [1]
        assert len(s.skipped) == 2
        assert 'landmark 2' in s.skipped[0] and '100 bytes' in s.skipped[0]
        assert 'landmark 3' in s.skipped[1] and 'unit' in s.skipped[1]
        s.all()
        assert s.skipped == []  # the list is of the last query


def test_integrity_ok_after_adding_landmarks(store):
    store.add([rec(0), rec(1)])
    store.add_landmarks([landmark(k, f'p{k % 2}') for k in range(20)])
    assert store.integrity_ok() and store.count() == 2
    assert len(store.landmarks(['p0', 'p1'])) == 20


# -- panoramas table (version 3), deletion, read-only stores -------------------------------------

def panorama(pid: str = 'p1') -> PanoramaInfo:
    q = np.array([0.1, -0.2, 0.3, 0.9])
    return PanoramaInfo(pid, q / np.linalg.norm(q), np.diag([1e-5, 2e-5, 3e-4]), np.array([0.0, -1.0, 0.0]),
                        'estimated', 123)


def test_panorama_record_round_trip_and_replace(store):
    store.put_panorama(panorama('p1'))
    got = store.panoramas(['p1', 'p2'])
    assert list(got) == ['p1']
    p = got['p1']
    assert np.allclose(p.covariance_enu, np.diag([1e-5, 2e-5, 3e-4])) and p.orientation_source == 'estimated'
    assert np.allclose(p.up, [0, -1, 0]) and p.has_world_orientation()
    assert math.isclose(p.heading_sigma_rad(), math.sqrt(3e-4))
    store.put_panorama(PanoramaInfo('p1', orientation_source='none'))  # replaced, unknowns stay NULL
    p = store.panoramas(['p1'])['p1']
    assert not p.has_world_orientation() and np.all(np.isnan(p.covariance_enu)) and np.all(np.isnan(p.up))


def test_bad_panorama_record_is_refused(store):
    with pytest.raises(StoreError, match='orientation_source'):
        store.put_panorama(PanoramaInfo('p1', orientation_source='guess'))
    with pytest.raises(StoreError, match='unit quaternion'):
        store.put_panorama(PanoramaInfo('p1', np.array([0.0, 0.0, 0.0, 2.0]), orientation_source='estimated'))


def test_version_2_store_gets_the_panoramas_table_on_first_put(tmp_path):
    path = tmp_path / 'v2.db'
    with SqliteAnnotationStore(path, create=True) as s:
        s.add([rec(1)])
    db = sqlite3.connect(path)
    db.execute('DROP TABLE panoramas')
    db.execute("UPDATE meta SET value = '2' WHERE key = 'version'")
    db.commit()
    db.close()
    with SqliteAnnotationStore(path, read_only=True) as s:
        assert s.panoramas(['p1']) == {} and len(s.all()) == 1
    assert meta_version(path) == '2'
    with SqliteAnnotationStore(path) as s:
        s.put_panorama(panorama())
        assert 'p1' in s.panoramas(['p1'])
    assert meta_version(path) == '3'


def test_delete_panorama_removes_its_records_only(store):
    store.add([rec(1, pano='p1'), rec(2, pano='p1'), rec(3, pano='p2')])
    store.add_landmarks([landmark(1, 'p1'), landmark(2, 'p2')])
    store.put_panorama(panorama('p1'))
    assert [a.panorama_id for a in store.annotations_of('p1')] == ['p1', 'p1']
    assert store.delete_panorama('p1') == 2
    assert [a.panorama_id for a in store.all()] == ['p2']
    assert [lm.panorama_id for lm in store.landmarks(['p1', 'p2'])] == ['p2']
    assert store.panoramas(['p1']) == {} and store.integrity_ok()
    assert store.near(47.0, 15.0, 50.0)[0].panorama_id == 'p2'  # the R-tree rows went too


def _no_write_access(monkeypatch, what):
    """The tests run as root, for whom every file is writable: os.access answers as for a user."""
    real = store_module.os.access

    def access(path, mode, *a, **kw):
        if str(path) == str(what) and mode & store_module.os.W_OK:
            return False
        return real(path, mode, *a, **kw)
    monkeypatch.setattr(store_module.os, 'access', access)


def test_store_in_read_only_directory_is_browsed_without_wal_files(tmp_path, monkeypatch):
    d = tmp_path / 'ro'
    d.mkdir()
    with SqliteAnnotationStore(d / 'a.db', create=True) as s:
        s.add([rec(1)])
    assert not (d / 'a.db-wal').exists()
    _no_write_access(monkeypatch, d)
    with SqliteAnnotationStore(d / 'a.db', read_only=True) as s:
        assert len(s.all()) == 1
    assert sorted(p.name for p in d.iterdir()) == ['a.db']  # nothing created beside it
    with pytest.raises(StoreError, match='read-only directory'):
        SqliteAnnotationStore(d / 'a.db')


def test_read_only_file_opened_for_writing_says_read_only(tmp_path, monkeypatch):
    path = tmp_path / 'a.db'
    SqliteAnnotationStore(path, create=True).close()
    _no_write_access(monkeypatch, path)
    with pytest.raises(StoreError, match='read-only') as err:
        SqliteAnnotationStore(path)
    assert '\n' not in str(err.value) and 'not an annotation store' not in str(err.value)
    with SqliteAnnotationStore(path, read_only=True) as s:  # browsing still works
        assert s.count() == 0
