"""PostgisAnnotationStore on a real throwaway server (the session's ``pg_cluster``), open_store by
URL, and the retry schedule. Skipped with the reason when PostgreSQL/PostGIS are not installed."""
from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from ar_tracking.core.annotations.store import (SCHEMA_VERSION, Annotation, Landmark, SqliteAnnotationStore,
                                                StoreError, distance_m)
from ar_tracking.io.stores import RetryBackoff, describe, open_store

pytest.importorskip('psycopg')

LAT0, LON0 = 47.0707, 15.4395


def record(rng: np.random.Generator, text: str = 'a', lat: float = LAT0, lon: float = LON0,
           pano: str = 'p1', author: str = 'me') -> Annotation:
    d = rng.normal(size=3)
    q = rng.normal(size=4)
    return Annotation(text=text, patch=rng.integers(0, 256, (16, 16), dtype=np.uint8),
                      direction=d / np.linalg.norm(d), latitude_deg=lat, longitude_deg=lon, altitude_m=350.0,
                      panorama_id=pano, author=author, created_ns=1_700_000_000_000_000_000,
                      panorama_in_world_quat_xyzw=q / np.linalg.norm(q))


def scattered(rng: np.random.Generator, n: int, radius_m: float) -> list[Annotation]:
    """n records within ``radius_m`` of (LAT0, LON0), uniform over the disc."""
    r = radius_m * np.sqrt(rng.random(n))
    phi = rng.random(n) * 2 * math.pi
    dlat = np.degrees(r * np.cos(phi) / 6_371_008.8)
    dlon = np.degrees(r * np.sin(phi) / 6_371_008.8) / math.cos(math.radians(LAT0))
    return [record(rng, f'n{i}', LAT0 + a, LON0 + b, pano=f'p{i % 7}') for i, (a, b) in enumerate(zip(dlat, dlon))]


def same(a: Annotation, b: Annotation) -> bool:
    return (a.text == b.text and a.author == b.author and a.panorama_id == b.panorama_id
            and np.array_equal(a.patch, b.patch) and np.allclose(a.direction, b.direction, atol=0)
            and a.latitude_deg == b.latitude_deg and a.longitude_deg == b.longitude_deg
            and a.created_ns == b.created_ns
            and np.allclose(a.panorama_in_world_quat_xyzw, b.panorama_in_world_quat_xyzw, atol=0, equal_nan=True))


def test_round_trip_and_landmarks(pg_store_url: str) -> None:
    rng = np.random.default_rng(0)
    items = [record(rng, f't{i}', pano=f'p{i % 2}') for i in range(5)]
    items.append(Annotation(**{**items[0].__dict__, 'text': 'no world', 'id': None,
                               'panorama_in_world_quat_xyzw': np.full(4, np.nan)}))
    with open_store(pg_store_url, create=True) as store:
        report = store.add(items)
        assert len(report.ids) == 6 and not report.skipped
        got = store.all()
        assert [a.id for a in got] == report.ids
        assert all(same(a, b) for a, b in zip(items, got))
        assert not got[-1].has_world_orientation()
        lms = [Landmark('p1', rng.integers(0, 256, (8, 8), dtype=np.uint8), np.array([0.0, 0.6, 0.8]))
               for _ in range(3)]
        assert len(store.add_landmarks(lms).ids) == 3
        assert len(store.landmarks(['p1', 'p0'])) == 3 and store.landmarks(['p0']) == []
        with pytest.raises(TypeError):
            store.landmarks('p1')
    # a second program opens the existing store read-only and sees the same
    with open_store(pg_store_url, read_only=True) as again:
        assert [a.text for a in again.all()] == [a.text for a in items]
        with pytest.raises(StoreError, match='read-only'):
            again.add(items[:1])


def test_near_matches_sqlite_and_uses_the_index(pg_store_url: str, tmp_path) -> None:
    rng = np.random.default_rng(1)
    items = scattered(rng, 600, 300.0)
    with open_store(pg_store_url, create=True) as pg, \
            open_store(f'sqlite:///{tmp_path / "s.db"}', create=True) as lite:
        pg.add(items)
        lite.add(items)
        for k in range(12):
            lat = LAT0 + rng.normal() * 0.001
            lon = LON0 + rng.normal() * 0.001
            radius = [50.0, 10.0, 120.0][k % 3]
            texts_pg = [a.text for a in pg.near(lat, lon, radius)]
            texts_lite = [a.text for a in lite.near(lat, lon, radius)]
            expected = [a.text for a in items
                        if float(distance_m(lat, lon, a.latitude_deg, a.longitude_deg)) <= radius]
            assert sorted(texts_pg) == sorted(expected) == sorted(texts_lite)
        assert pg.near(LAT0 + 1.0, LON0, 50.0) == []
        with pytest.raises(StoreError):
            pg.near(float('nan'), LON0)
        pg._db.execute('SET enable_seqscan = off')
        plan = pg._db.execute("EXPLAIN SELECT id FROM annotations WHERE "
                              "ST_DWithin(geog, ST_SetSRID(ST_MakePoint(15.4, 47.0), 4326)::geography, 50, false)"
                              ).fetchall()
        assert 'annotations_geog' in ' '.join(r[0] for r in plan)


HOSTILE = ["'); DROP TABLE annotations; --", "Robert'); DELETE FROM meta;--", '\\x27 OR 1=1 --',
           '%s %(x)s {} $1 ::geography', 'ünïcødé 注釈 \u202e', '"double" \'single\' `back`', '\n\t;']


def test_hostile_texts_are_data(pg_store_url: str) -> None:
    rng = np.random.default_rng(2)
    items = [record(rng, text=t, author=t, pano=t) for t in HOSTILE]
    nul = record(rng, text='nul\x00byte')
    with open_store(pg_store_url, create=True) as store:
        report = store.add(items + [nul])
        assert len(report.ids) == len(HOSTILE)
        assert report.skipped == [(len(HOSTILE), 'text contains a NUL character')]
        got = store.all()
        assert [(a.text, a.author, a.panorama_id) for a in got] == [(t, t, t) for t in HOSTILE]
        assert len(store.near(LAT0, LON0)) == len(HOSTILE)
        assert store.add_landmarks([Landmark(HOSTILE[0], items[0].patch, items[0].direction)]).ids
        assert len(store.landmarks(HOSTILE)) == 1
    # the hostile schema name is refused, not formatted into SQL
    with pytest.raises(StoreError, match='identifier'):
        open_store(pg_store_url + '_x%22%3B%20DROP', create=True)


def test_bad_records_skipped(pg_store_url: str) -> None:
    rng = np.random.default_rng(3)
    good = record(rng)
    bad = [Annotation(**{**good.__dict__, 'latitude_deg': 95.0}),
           Annotation(**{**good.__dict__, 'direction': np.array([np.nan, 0, 1])}),
           Annotation(**{**good.__dict__, 'text': '  '})]
    with open_store(pg_store_url, create=True) as store:
        report = store.add([good, *bad, 'not a record'])  # type: ignore[list-item]
        assert len(report.ids) == 1 and [i for i, _ in report.skipped] == [1, 2, 3, 4]
        assert store.count() == 1


def test_migration_from_version_1_and_newer_refused(pg_cluster, pg_store_url: str) -> None:
    import psycopg
    from ar_tracking.io.postgis_store import MIGRATIONS, split_url

    conninfo, schema = split_url(pg_store_url)
    with psycopg.connect(conninfo, autocommit=True) as conn:
        conn.execute(f'CREATE SCHEMA {schema}')
        conn.execute(f'SET search_path TO {schema}, public')
        for statement in MIGRATIONS[1]:
            conn.execute(statement)
        conn.execute("INSERT INTO meta VALUES ('schema', 'ar_tracking.annotations'), ('version', '1')")
    rng = np.random.default_rng(4)
    with open_store(pg_store_url, read_only=True) as ro:  # read-only: no landmarks, no migration
        assert ro.landmarks(['p1']) == [] and ro.all() == []
    with open_store(pg_store_url) as rw:  # read-write: migrated to the current version
        assert rw.add([record(rng)]).ids
        assert rw.add_landmarks([Landmark('p1', record(rng).patch, np.array([1.0, 0, 0]))]).ids
        version = rw._db.execute("SELECT value FROM meta WHERE key = 'version'").fetchone()[0]
        assert int(version) == SCHEMA_VERSION
        rw._db.execute("UPDATE meta SET value = '99' WHERE key = 'version'")
    with pytest.raises(StoreError, match='newer than this program'):
        open_store(pg_store_url)


def test_missing_store_and_foreign_schema(pg_store_url: str) -> None:
    with pytest.raises(StoreError, match='no annotation store'):
        open_store(pg_store_url)  # not create: an empty database is not a store


def test_server_down_and_wrong_credentials(pg_cluster, tmp_path) -> None:
    down = f'postgresql://someone:s3cret@/postgres?host={tmp_path}'
    with pytest.raises(StoreError) as info:
        open_store(down, timeout_s=1)
    text = str(info.value)
    assert 'cannot connect' in text and '\n' not in text and 's3cret' not in text
    assert 's3cret' not in describe(down)
    wrong_user = pg_cluster.url.replace('postgres@', 'nobody:s3cret@')
    with pytest.raises(StoreError, match='nobody') as info:
        open_store(wrong_user, timeout_s=1)
    assert 's3cret' not in str(info.value)


def test_query_timeout_is_one_line(pg_cluster, pg_store_url: str) -> None:
    import psycopg
    from ar_tracking.io.postgis_store import split_url

    rng = np.random.default_rng(5)
    with open_store(pg_store_url, create=True) as store:
        store.add([record(rng)])
    conninfo, schema = split_url(pg_store_url)
    with psycopg.connect(conninfo) as blocker:  # holds a lock the query has to wait for
        blocker.execute(f'LOCK TABLE {schema}.annotations IN ACCESS EXCLUSIVE MODE')
        with open_store(pg_store_url, read_only=True, query_timeout_s=0.2) as store:
            with pytest.raises(StoreError, match='timed out'):
                store.near(LAT0, LON0)
        blocker.rollback()


def test_concurrent_writers_and_readers(pg_store_url: str) -> None:
    """4 authors and 4 browsers at once: nothing lost, nothing duplicated, every read consistent."""
    writers, readers, batches, per_batch = 4, 4, 25, 3
    open_store(pg_store_url, create=True).close()
    done = threading.Event()
    errors: list[str] = []
    problems: list[str] = []

    def write(w: int) -> None:
        rng = np.random.default_rng(100 + w)
        try:
            with open_store(pg_store_url) as store:
                for b in range(batches):
                    store.add([record(rng, f'w{w}-{b}-{k}', *scatter(rng)) for k in range(per_batch)])
        except Exception as exc:  # noqa: BLE001 - reported by the assertion below
            errors.append(f'writer {w}: {exc}')

    def scatter(rng: np.random.Generator) -> tuple[float, float]:
        return LAT0 + rng.uniform(-1, 1) * 2e-4, LON0 + rng.uniform(-1, 1) * 2e-4  # within ~30 m

    def read(r: int) -> None:
        seen = 0
        try:
            with open_store(pg_store_url, read_only=True) as store:
                while not done.is_set():
                    got = store.near(LAT0, LON0, 50.0) if r % 2 else store.all()
                    ids = [a.id for a in got]
                    if len(ids) != len(set(ids)):
                        problems.append(f'reader {r}: duplicated ids')
                    if len(ids) < seen or len(ids) % per_batch:  # a batch is all or nothing
                        problems.append(f'reader {r}: {len(ids)} after {seen}')
                    seen = len(ids)
        except Exception as exc:  # noqa: BLE001
            errors.append(f'reader {r}: {exc}')

    threads = [threading.Thread(target=read, args=(r,)) for r in range(readers)]
    for t in threads:
        t.start()
    wthreads = [threading.Thread(target=write, args=(w,)) for w in range(writers)]
    for t in wthreads:
        t.start()
    for t in wthreads:
        t.join(30)
    done.set()
    for t in threads:
        t.join(30)
    assert errors == [] and problems == []
    with open_store(pg_store_url, read_only=True) as store:
        texts = [a.text for a in store.all()]
    expected = {f'w{w}-{b}-{k}' for w in range(writers) for b in range(batches) for k in range(per_batch)}
    assert len(texts) == len(expected) and set(texts) == expected


def test_open_store_urls(tmp_path, monkeypatch) -> None:
    path = tmp_path / 'a.db'
    with open_store(f'sqlite:///{path}', create=True) as s:
        assert isinstance(s, SqliteAnnotationStore)
    with open_store(str(path)) as s:
        assert isinstance(s, SqliteAnnotationStore)
    monkeypatch.setenv('AR_TRACKING_STORE_URL', f'sqlite:///{path}')
    with open_store('') as s:
        assert isinstance(s, SqliteAnnotationStore)
    monkeypatch.delenv('AR_TRACKING_STORE_URL')
    with pytest.raises(StoreError, match='no annotation store given'):
        open_store(None)
    with pytest.raises(StoreError, match='unknown store URL scheme'):
        open_store('mysql://x/y')
    assert describe('postgresql://u:pw@h:5432/db?password=pw2') == 'postgresql://u@h:5432/db'


def test_retry_backoff() -> None:
    b = RetryBackoff(initial_s=1.0, max_s=5.0)
    assert b.ready(0.0)
    assert [b.failed(t) for t in (0.0, 1.0, 3.0, 7.0, 12.0)] == [1.0, 2.0, 4.0, 5.0, 5.0]
    assert not b.ready(16.9) and b.ready(17.0)
    b.succeeded()
    assert b.ready(0.0) and b.failed(0.0) == 1.0


def test_annotate_cli_with_a_server_that_is_down_is_one_line(tmp_path, capsys) -> None:
    from pathlib import Path

    from ar_tracking.cli import main

    bag = Path(__file__).resolve().parents[2] / 'bags' / 'rotation_sweep_authoring.mcap'
    positions = tmp_path / 'positions.txt'
    positions.write_text('door,1000,250\n')
    code = main(['annotate', str(bag), '--positions', str(positions),
                 '--store', f'postgresql://author:pw@/notes?host={tmp_path}&connect_timeout=1'])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and len(err) == 1 and 'cannot connect' in err[0] and ':pw@' not in err[0]
