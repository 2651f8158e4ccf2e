"""``ar-tracking bench --areas store``: the annotation store's radius query and its behaviour
under many authors and browsers at once (issue 22; DESIGN.md sec. 8 area ``store``).

``near_ms_p95`` (per backend): 100,000 annotations spread uniformly over a 4 km x 4 km city
centre (about 50 in every 50 m circle, Langlotz 2011 sec. 4.3's query), 500 queries at random
positions of that area; the time of ``store.near(lat, lon, 50)`` including the records read
back as :class:`Annotation` objects. Target <= 10 ms.

``concurrent`` (PostGIS): 8 writer and 8 reader processes against one server for 30 s. Writers
add batches of 1-4 annotations (each batch within 5 m of one point: one of 8 busy spots one time
in ten, else anywhere in the 4 km square) and remember what the store acknowledged; each reader
asks again and again for everything within 50 m of its busy spot and checks each answer (no
record twice, a record once seen never disappears, a batch that lies inside the circle whole). Afterwards every acknowledged record must be in the
store exactly once: ``lost`` (acknowledged, not stored), ``duplicated`` (stored twice), ``errors``
(any exception in a writer or reader) are all 0 when the store is right.

The PostGIS server is ``$AR_TRACKING_BENCH_PG_URL`` when set (its schemas ``bench_near`` and
``bench_concurrent`` are replaced), else a throwaway cluster (io/pg_cluster.py, the server's
default durability settings); without PostgreSQL/PostGIS that part reports why it was skipped.
"""
from __future__ import annotations

import logging
import math
import multiprocessing
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..core.annotations.store import Annotation

logger = logging.getLogger(__name__)

LAT0, LON0 = 47.0707, 15.4395  # a city centre
EARTH_RADIUS_M = 6_371_008.8
PG_URL_ENV = 'AR_TRACKING_BENCH_PG_URL'


def offset_deg(north_m: np.ndarray, east_m: np.ndarray, lat0: float = LAT0) -> tuple[np.ndarray, np.ndarray]:
    """Latitude/longitude offsets (degrees) of local north/east offsets (metres)."""
    return (np.degrees(north_m / EARTH_RADIUS_M),
            np.degrees(east_m / EARTH_RADIUS_M) / math.cos(math.radians(lat0)))


def synthetic_annotations(n: int, seed: int, half_side_m: float, prefix: str = 'a',
                          lat0: float = LAT0, lon0: float = LON0) -> list[Annotation]:
    """``n`` valid records (random 16x16 patches, unit directions) uniform over a square of
    side 2 * ``half_side_m`` around (lat0, lon0)."""
    rng = np.random.default_rng(seed)
    north, east = rng.uniform(-half_side_m, half_side_m, (2, n))
    dlat, dlon = offset_deg(north, east, lat0)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    patches = rng.integers(0, 256, (n, 16, 16), dtype=np.uint8)
    return [Annotation(text=f'{prefix}{i}', patch=patches[i], direction=d[i], latitude_deg=lat0 + float(dlat[i]),
                       longitude_deg=lon0 + float(dlon[i]), altitude_m=350.0, panorama_id=f'{prefix}p{i // 20}',
                       author='bench', created_ns=i) for i in range(n)]


def _fill(store: Any, records: list[Annotation], chunk: int = 5000) -> float:
    start = time.perf_counter()
    for k in range(0, len(records), chunk):
        report = store.add(records[k:k + chunk])
        if report.skipped:
            raise RuntimeError(f'bench records skipped: {report.skipped[:3]}')
    return time.perf_counter() - start


def _near_times(store: Any, n_queries: int, half_side_m: float, seed: int) -> tuple[list[float], list[int]]:
    rng = np.random.default_rng(seed)
    north, east = rng.uniform(-half_side_m, half_side_m, (2, n_queries))
    dlat, dlon = offset_deg(north, east)
    times, found = [], []
    for a, b in zip(dlat, dlon):
        start = time.perf_counter()
        got = store.near(LAT0 + float(a), LON0 + float(b), 50.0)
        times.append((time.perf_counter() - start) * 1e3)
        found.append(len(got))
    return times, found


def _summary(times: list[float], found: list[int], fill_s: float, n: int) -> dict[str, Any]:
    arr = np.asarray(times)
    return {'annotations': n, 'queries': len(times), 'fill_s': round(fill_s, 2),
            'near_ms_p50': round(float(np.percentile(arr, 50)), 3),
            'near_ms_p95': round(float(np.percentile(arr, 95)), 3),
            'near_ms_max': round(float(arr.max()), 3),
            'found_mean': round(float(np.mean(found)), 1)}


def bench_near(workdir: Path, pg_url: str | None, n: int = 100_000, n_queries: int = 500,
               half_side_m: float = 2000.0) -> dict[str, Any]:
    """near_ms_p50/p95 per backend on ``n`` annotations (see the module docstring)."""
    from ..io.stores import open_store

    records = synthetic_annotations(n, seed=1, half_side_m=half_side_m)
    out: dict[str, Any] = {}
    db = workdir / 'bench_store.db'
    for suffix in ('', '-wal', '-shm'):
        Path(f'{db}{suffix}').unlink(missing_ok=True)
    with open_store(f'sqlite:///{db}', create=True) as store:
        fill_s = _fill(store, records)
        _near_times(store, 20, half_side_m, seed=99)  # warm the page cache
        times, found = _near_times(store, n_queries, half_side_m, seed=2)
    out['sqlite'] = _summary(times, found, fill_s, n)
    if pg_url is None:
        return out
    url = _fresh_schema(pg_url, 'bench_near')
    with open_store(url, create=True) as store:
        fill_s = _fill(store, records)
        store._db.execute('ANALYZE annotations')  # type: ignore[attr-defined]
        _near_times(store, 20, half_side_m, seed=99)
        times, found = _near_times(store, n_queries, half_side_m, seed=2)
    out['postgis'] = _summary(times, found, fill_s, n)
    return out


def _fresh_schema(pg_url: str, schema: str) -> str:
    """``pg_url`` with ``schema``, dropped first (a bench starts empty)."""
    import psycopg
    from psycopg import sql

    from ..io.postgis_store import split_url

    conninfo, _ = split_url(pg_url)
    with psycopg.connect(conninfo, autocommit=True) as conn:
        conn.execute(sql.SQL('DROP SCHEMA IF EXISTS {} CASCADE').format(sql.Identifier(schema)))
    return f'{pg_url}{"&" if "?" in pg_url else "?"}schema={schema}'


# -- concurrency ------------------------------------------------------------------------------

#: Busy spots of the concurrency run (north, east offsets in metres); reader r watches spot r % 8.
BUSY_SPOTS_M = [(-1500.0 + 400.0 * i, 1200.0 - 350.0 * i) for i in range(8)]
_SPOT_HALF_SIDE_M = 2000.0


def _spot(north_m: float, east_m: float) -> tuple[float, float]:
    dlat, dlon = offset_deg(np.array(north_m), np.array(east_m))
    return LAT0 + float(dlat), LON0 + float(dlon)


def _start(barrier: Any, duration_s: float) -> float:
    """Wait until every process is connected; the time this one stops."""
    barrier.wait(300.0)
    return time.time() + duration_s


def _writer(url: str, w: int, barrier: Any, duration_s: float, queue: Any) -> None:
    from ..io.stores import open_store

    rng = np.random.default_rng(1000 + w)
    acknowledged: list[str] = []
    errors: list[str] = []
    batches = 0
    try:
        with open_store(url) as store:
            stop_at = _start(barrier, duration_s)
            seq = 0
            while time.time() < stop_at:
                k = int(rng.integers(1, 5))
                if rng.random() < 0.1:
                    north, east = BUSY_SPOTS_M[int(rng.integers(len(BUSY_SPOTS_M)))]
                    north, east = north + rng.uniform(-30, 30), east + rng.uniform(-30, 30)
                else:
                    north, east = rng.uniform(-_SPOT_HALF_SIDE_M, _SPOT_HALF_SIDE_M, 2)
                lat, lon = _spot(north, east)
                batch = synthetic_annotations(k, seed=int(rng.integers(1 << 31)), half_side_m=3.0,
                                              prefix=f'w{w}-{seq}-{k}-', lat0=lat, lon0=lon)
                try:
                    report = store.add(batch)
                    if len(report.ids) != k:
                        errors.append(f'writer {w}: {len(report.ids)} of {k} acknowledged')
                    acknowledged += [a.text for a in batch]
                    batches += 1
                except Exception as exc:  # noqa: BLE001 - counted
                    errors.append(f'writer {w}: {type(exc).__name__}: {exc}')
                seq += 1
    except Exception as exc:  # noqa: BLE001
        errors.append(f'writer {w}: {type(exc).__name__}: {exc}')
    queue.put(('writer', w, acknowledged, errors, batches, []))


def _reader(url: str, r: int, barrier: Any, duration_s: float, queue: Any) -> None:
    from ..io.stores import open_store

    from ..core.annotations.store import distance_m

    errors: list[str] = []
    times: list[float] = []
    seen_ids: set[int] = set()
    lat0, lon0 = _spot(*BUSY_SPOTS_M[r % len(BUSY_SPOTS_M)])
    try:
        with open_store(url, read_only=True) as store:
            stop_at = _start(barrier, duration_s)
            while time.time() < stop_at:
                t0 = time.perf_counter()
                try:
                    got = store.near(lat0, lon0, 50.0)
                except Exception as exc:  # noqa: BLE001 - counted
                    errors.append(f'reader {r}: {type(exc).__name__}: {exc}')
                    continue
                times.append((time.perf_counter() - t0) * 1e3)
                ids = [a.id for a in got]
                texts = [a.text for a in got]
                if len(set(ids)) != len(ids) or len(set(texts)) != len(texts):
                    errors.append(f'reader {r}: a record twice in one answer')
                now_ids = set(ids)
                if not seen_ids <= now_ids:
                    errors.append(f'reader {r}: {len(seen_ids - now_ids)} records seen before are gone')
                seen_ids = now_ids
                # a batch well inside the circle (all its records within 5 m of the first) is whole
                batches: dict[str, list[Annotation]] = {}
                for a in got:
                    w, seq, k, _ = a.text.split('-', 3)
                    batches.setdefault(f'{w}-{seq}-{k}', []).append(a)
                for key, members in batches.items():
                    inside = float(distance_m(lat0, lon0, members[0].latitude_deg, members[0].longitude_deg)) < 40.0
                    if inside and len(members) != int(key.rsplit('-', 1)[1]):
                        errors.append(f'reader {r}: batch {key} seen with {len(members)} records')
    except Exception as exc:  # noqa: BLE001
        errors.append(f'reader {r}: {type(exc).__name__}: {exc}')
    queue.put(('reader', r, [], errors, len(times), times))


def bench_concurrent(pg_url: str, writers: int = 8, readers: int = 8, duration_s: float = 30.0) -> dict[str, Any]:
    """``writers`` + ``readers`` processes on one PostGIS store for ``duration_s`` (see the module
    docstring): lost, duplicated, errors, and the radius query's latency under that load."""
    from ..io.stores import open_store

    url = _fresh_schema(pg_url, 'bench_concurrent')
    open_store(url, create=True).close()
    ctx = multiprocessing.get_context('spawn')
    queue = ctx.Queue()
    barrier = ctx.Barrier(writers + readers)  # the clock starts when every process is connected
    procs = [ctx.Process(target=_writer, args=(url, w, barrier, duration_s, queue)) for w in range(writers)]
    procs += [ctx.Process(target=_reader, args=(url, r, barrier, duration_s, queue)) for r in range(readers)]
    for p in procs:
        p.start()
    results = []
    deadline = time.time() + 300.0 + duration_s + 120.0
    while len(results) < len(procs) and time.time() < deadline:
        try:
            results.append(queue.get(timeout=5.0))
        except Exception:  # queue.Empty: a process may have died
            if not any(p.is_alive() for p in procs):
                break
    for p in procs:
        p.join(10.0)
    errors = [e for res in results for e in res[3]]
    missing = len(procs) - len(results)
    if missing:
        errors.append(f'{missing} processes did not report')
    acknowledged = [t for res in results if res[0] == 'writer' for t in res[2]]
    with open_store(url, read_only=True) as store:
        stored = [a.text for a in store.all()]
    counts: dict[str, int] = {}
    for t in stored:
        counts[t] = counts.get(t, 0) + 1
    lost = sum(1 for t in acknowledged if t not in counts)
    duplicated = sum(c - 1 for c in counts.values() if c > 1)
    times = np.asarray([t for res in results if res[0] == 'reader' for t in res[5]] or [float('nan')])
    queries = int(sum(res[4] for res in results if res[0] == 'reader'))
    return {
        'writers': writers, 'readers': readers, 'duration_s': duration_s,
        'acknowledged': len(acknowledged), 'stored': len(stored),
        'batches': int(sum(res[4] for res in results if res[0] == 'writer')),
        'queries': queries,
        'lost': lost, 'duplicated': duplicated, 'errors': len(errors),
        'error_examples': errors[:5],
        'near_ms_p95_under_load': None if queries == 0 else round(float(np.nanpercentile(times, 95)), 3),
        'near_ms_p50_under_load': None if queries == 0 else round(float(np.nanpercentile(times, 50)), 3),
    }


def bench_store(workdir: Path, n: int = 100_000, concurrent_s: float = 30.0) -> dict[str, Any]:
    """The ``store`` area: near_ms_p95 per backend and the concurrency run (module docstring)."""
    workdir.mkdir(parents=True, exist_ok=True)
    out: dict[str, Any] = {}
    cluster = None
    pg_url = os.environ.get(PG_URL_ENV) or None
    if pg_url is None:
        from ..io.pg_cluster import ClusterError, TemporaryCluster, unavailable_reason

        reason = unavailable_reason()
        if reason is None:
            try:
                cluster = TemporaryCluster(fast=False).start()
                pg_url = cluster.url
            except ClusterError as exc:
                reason = str(exc)
        if reason is not None:
            out['postgis_skipped'] = reason
    try:
        near = bench_near(workdir, pg_url, n=n)
        out['near_ms_p95'] = {backend: r['near_ms_p95'] for backend, r in near.items()}
        out['near'] = near
        if pg_url is not None:
            out['concurrent'] = bench_concurrent(pg_url, duration_s=concurrent_s)
    finally:
        if cluster is not None:
            cluster.stop()
    return out
