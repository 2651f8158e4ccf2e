"""The annotation store on PostgreSQL + PostGIS, for many authors and browsers on one server
(Langlotz 2011 sec. 3.2 and 4.3: annotations live on a server; a browsing device asks for
everything authored within 50 m of its GPS fix).

:class:`PostgisAnnotationStore` implements :class:`~ar_tracking.core.annotations.store.AnnotationStore`
with the same records and the same answers as the SQLite store:

- ``annotations``: one row per record, the position also as ``geography(Point, 4326)`` with a
  GiST index; ``near`` is ``ST_DWithin(geog, point, radius, false)``, the great-circle distance
  on PostGIS's mean-radius sphere (6,371,008.8 m, the radius the SQLite store's haversine check
  uses), so both backends return the same records; the index answers it (no table scan).
- ``landmarks``: one row per landmark, indexed by panorama id.
- ``meta``: schema name and version. :data:`MIGRATIONS` brings any older schema up to date in
  one transaction under an advisory lock (two programs opening a new database at once do not
  both create it); a database of a newer version is refused.

The tables live in a PostgreSQL schema of their own (``ar_tracking`` by default, ``?schema=NAME``
in the URL for another one), so one database can hold several stores next to other data.
Every write is one transaction; every statement is built from constants with values passed as
parameters (never formatted into SQL). The connection string comes from the caller (a node
parameter, a CLI option or ``AR_TRACKING_STORE_URL``), never from code; libpq's own variables
(``PGPASSWORD``, ``PGHOST``, ``~/.pgpass``) work as usual. Error lines name the server without
its password.

Errors are :class:`StoreError` with one line: server down, wrong credentials, no PostGIS, a query
that ran longer than ``query_timeout_s`` (the server cancels it).

One instance per thread or process (a psycopg connection is not shared between threads here).
"""
from __future__ import annotations

import logging
import math
import re
from typing import Any, Callable, Iterable, Sequence, TypeVar
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

import numpy as np

from ..core.annotations.store import (DEFAULT_RADIUS_M, PANORAMAS_VERSION, SCHEMA, SCHEMA_VERSION, AddReport,
                                      Annotation, AnnotationStore, Landmark, PanoramaInfo,
                                      SqliteAnnotationStore, StoreError, _panorama_row, panorama_from_row,
                                      validate_annotation, validate_landmark, validate_panorama)

logger = logging.getLogger(__name__)

#: The PostgreSQL schema (namespace) of the tables unless the URL says ``?schema=NAME``.
DEFAULT_PG_SCHEMA = 'ar_tracking'
_IDENTIFIER = re.compile(r'^[a-z_][a-z0-9_]{0,62}$')
#: Schema version -> the statements that bring the previous version to it. Version 1: annotations
#: with a geography column and its GiST index; version 2: landmarks (as the SQLite store).
MIGRATIONS: dict[int, tuple[str, ...]] = {
    1: (
        'CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)',
        '''CREATE TABLE annotations (
            id BIGSERIAL PRIMARY KEY, text TEXT NOT NULL, patch BYTEA NOT NULL,
            patch_side INTEGER NOT NULL, dx DOUBLE PRECISION NOT NULL, dy DOUBLE PRECISION NOT NULL,
            dz DOUBLE PRECISION NOT NULL, latitude DOUBLE PRECISION NOT NULL,
            longitude DOUBLE PRECISION NOT NULL, altitude DOUBLE PRECISION NOT NULL,
            geog geography(Point, 4326) NOT NULL, panorama_id TEXT NOT NULL, author TEXT NOT NULL,
            created_ns BIGINT NOT NULL, pano_qx DOUBLE PRECISION, pano_qy DOUBLE PRECISION,
            pano_qz DOUBLE PRECISION, pano_qw DOUBLE PRECISION)''',
        'CREATE INDEX annotations_geog ON annotations USING GIST (geog)',
    ),
    2: (
        '''CREATE TABLE landmarks (
            id BIGSERIAL PRIMARY KEY, panorama_id TEXT NOT NULL, patch BYTEA NOT NULL,
            patch_side INTEGER NOT NULL, dx DOUBLE PRECISION NOT NULL, dy DOUBLE PRECISION NOT NULL,
            dz DOUBLE PRECISION NOT NULL)''',
        'CREATE INDEX landmarks_panorama_id ON landmarks (panorama_id)',
    ),
    3: (
        '''CREATE TABLE panoramas (
            panorama_id TEXT PRIMARY KEY, qx DOUBLE PRECISION, qy DOUBLE PRECISION,
            qz DOUBLE PRECISION, qw DOUBLE PRECISION, cov BYTEA, up_x DOUBLE PRECISION,
            up_y DOUBLE PRECISION, up_z DOUBLE PRECISION, orientation_source TEXT NOT NULL,
            created_ns BIGINT NOT NULL)''',
    ),
}
assert max(MIGRATIONS) == SCHEMA_VERSION

#: Columns in the order of SqliteAnnotationStore's rows, so that one reader turns both into records.
_ANNOTATION_COLUMNS = ('id, text, patch, patch_side, dx, dy, dz, latitude, longitude, altitude, '
                       'panorama_id, author, created_ns, pano_qx, pano_qy, pano_qz, pano_qw')
_INSERT_ANNOTATION = (
    'INSERT INTO annotations (text, patch, patch_side, dx, dy, dz, latitude, longitude, altitude, geog, '
    'panorama_id, author, created_ns, pano_qx, pano_qy, pano_qz, pano_qw) VALUES '
    '(%s, %s, %s, %s, %s, %s, %s, %s, %s, ST_SetSRID(ST_MakePoint(%s, %s), 4326)::geography, '
    '%s, %s, %s, %s, %s, %s, %s) RETURNING id')
_NEAR = (f'SELECT {_ANNOTATION_COLUMNS} FROM annotations '
         'WHERE ST_DWithin(geog, ST_SetSRID(ST_MakePoint(%s, %s), 4326)::geography, %s, false) ORDER BY id')
_ADVISORY_KEY = 'ar_tracking.annotations.migrate'
_T = TypeVar('_T')


def is_postgres_url(url: str) -> bool:
    return str(url).startswith(('postgresql://', 'postgres://'))


def split_url(url: str) -> tuple[str, str]:
    """(libpq URL without our ``schema`` query parameter, the PostgreSQL schema name)."""
    parts = urlsplit(url)
    query = parse_qsl(parts.query, keep_blank_values=True)
    schema = DEFAULT_PG_SCHEMA
    rest = []
    for key, value in query:
        if key == 'schema':
            schema = value
        else:
            rest.append((key, value))
    if not _IDENTIFIER.match(schema):
        raise StoreError(f'schema {schema!r} in the store URL is not a plain lower-case identifier')
    return urlunsplit(parts._replace(query=urlencode(rest))), schema


def describe_url(url: str) -> str:
    """The URL without its password, for error lines and logs."""
    try:
        parts = urlsplit(str(url))
    except ValueError:
        return 'postgresql://?'
    netloc = parts.netloc
    if '@' in netloc:
        user, host = netloc.rsplit('@', 1)
        netloc = f'{user.split(":", 1)[0]}@{host}'
    query = [(k, v) for k, v in parse_qsl(parts.query, keep_blank_values=True) if k != 'password']
    return urlunsplit(parts._replace(netloc=netloc, query=urlencode(query, safe='/')))


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _nul_problem(*texts: str) -> str | None:
    """PostgreSQL text cannot hold NUL characters: such a record is skipped with this reason."""
    return 'text contains a NUL character' if any('\x00' in t for t in texts) else None


class PostgisAnnotationStore(AnnotationStore):
    """PostgreSQL/PostGIS implementation (see the module docstring).

    ``create``: create the tables (and PostGIS, when this user may) in a database that has none;
    otherwise a database without a store is an error. ``read_only``: never write (no migration
    either; a version-1 store simply has no landmarks). ``timeout_s`` bounds the connection,
    ``query_timeout_s`` every statement (0: no limit)."""

    def __init__(self, url: str, *, create: bool = False, timeout_s: float = 5.0, read_only: bool = False,
                 query_timeout_s: float = 5.0) -> None:
        try:
            import psycopg
        except ImportError as exc:  # pragma: no cover - psycopg is in install_requires
            raise StoreError('PostgreSQL stores need psycopg: pip install "psycopg[binary]"') from exc
        self._psycopg = psycopg
        self.skipped: list[str] = []
        self.read_only = read_only
        self.path = describe_url(url)  # the name in error lines (as SqliteAnnotationStore.path)
        conninfo, self.pg_schema = split_url(str(url))
        try:
            self._db = psycopg.connect(conninfo, autocommit=True, connect_timeout=max(1, math.ceil(timeout_s)),
                                       application_name='ar_tracking')
        except psycopg.Error as exc:
            raise StoreError(f'{self.path}: cannot connect to the annotation store ({_first_line(exc)})') from exc
        try:
            # Parameters, not formatting: the schema name and the timeout are values here.
            self._db.execute("SELECT set_config('search_path', %s, false), set_config('statement_timeout', %s, false)",
                             (f'{self.pg_schema}, public', f'{int(query_timeout_s * 1000)}'))
            self._open(create)
        except psycopg.Error as exc:
            self._db.close()
            raise self._error(exc, 'cannot open') from exc
        except StoreError:
            self._db.close()
            raise

    # -- opening and migrations --------------------------------------------------------------

    def _version(self) -> int | None:
        """The stored schema version, None when the database has no store in our schema."""
        if self._db.execute("SELECT to_regclass('meta')").fetchone()[0] is None:
            return None
        rows = dict(self._db.execute('SELECT key, value FROM meta').fetchall())
        if rows.get('schema') != SCHEMA:
            raise StoreError(f'{self.path}: schema {self.pg_schema}.meta is not an annotation store '
                             f'({rows.get("schema")!r}); left untouched')
        return int(rows.get('version', '0'))

    def _open(self, create: bool) -> None:
        version = self._version()
        if version is not None and version > SCHEMA_VERSION:
            raise StoreError(f'{self.path}: annotation store version {version} is newer than this program ({SCHEMA_VERSION})')
        if version is None and not create:
            raise StoreError(f'{self.path}: no annotation store in schema {self.pg_schema!r} '
                             '(ar-tracking annotate creates one)')
        if self.read_only or version == SCHEMA_VERSION:
            self._has_landmarks = (version or 0) >= 2
            return
        self._ensure_postgis()
        from psycopg import sql

        with self._db.transaction():
            self._db.execute('SELECT pg_advisory_xact_lock(hashtext(%s))', (_ADVISORY_KEY,))
            self._db.execute(sql.SQL('CREATE SCHEMA IF NOT EXISTS {}').format(sql.Identifier(self.pg_schema)))
            version = self._version() or 0  # again, under the lock: another program may have migrated
            for target in range(version + 1, SCHEMA_VERSION + 1):
                for statement in MIGRATIONS[target]:
                    self._db.execute(statement)
                if target == 1:
                    self._db.execute('INSERT INTO meta VALUES (%s, %s), (%s, %s)',
                                     ('schema', SCHEMA, 'version', '1'))
                else:
                    self._db.execute("UPDATE meta SET value = %s WHERE key = 'version'", (str(target),))
                logger.info('%s: annotation store schema %s at version %d', self.path, self.pg_schema, target)
        self._has_landmarks = True

    def _ensure_postgis(self) -> None:
        if self._db.execute("SELECT 1 FROM pg_extension WHERE extname = 'postgis'").fetchone():
            return
        try:
            self._db.execute('CREATE EXTENSION IF NOT EXISTS postgis')
        except self._psycopg.Error as exc:
            raise StoreError(f'{self.path}: the database has no PostGIS and this user cannot add it '
                             f'({_first_line(exc)}); a superuser runs CREATE EXTENSION postgis') from exc

    def _error(self, exc: Exception, what: str) -> StoreError:
        errors = self._psycopg.errors
        if isinstance(exc, errors.QueryCanceled):
            return StoreError(f'{self.path}: query timed out ({_first_line(exc)})')
        if isinstance(exc, self._psycopg.OperationalError):
            return StoreError(f'{self.path}: connection to the annotation store lost ({_first_line(exc)})')
        return StoreError(f'{self.path}: {what} ({_first_line(exc)})')

    # -- interface -------------------------------------------------------------------------

    def add(self, annotations: Iterable[Annotation]) -> AddReport:
        report = AddReport()
        rows = []
        for i, a in enumerate(annotations):
            reason = validate_annotation(a) if isinstance(a, Annotation) else f'not an Annotation ({type(a).__name__})'
            reason = reason or _nul_problem(a.text, a.author, a.panorama_id)
            if reason is not None:
                report.skipped.append((i, reason))
                logger.warning('annotation %d (%r) skipped: %s', i, getattr(a, 'text', ''), reason)
                continue
            d = np.asarray(a.direction, float)
            q = [float(v) for v in np.asarray(a.panorama_in_world_quat_xyzw, float)] \
                if a.has_world_orientation() else [None] * 4
            lat, lon = float(a.latitude_deg), float(a.longitude_deg)
            rows.append((a.text, np.ascontiguousarray(a.patch).tobytes(), a.patch_side,
                         float(d[0]), float(d[1]), float(d[2]), lat, lon, float(a.altitude_m), lon, lat,
                         a.panorama_id, a.author, int(a.created_ns), *q))
        if rows:
            report.ids = self._insert(_INSERT_ANNOTATION, rows)
        return report

    def add_landmarks(self, landmarks: Iterable[Landmark]) -> AddReport:
        report = AddReport()
        rows = []
        for i, lm in enumerate(landmarks):
            reason = validate_landmark(lm) or _nul_problem(lm.panorama_id)
            if reason is not None:
                report.skipped.append((i, reason))
                logger.warning('landmark %d (panorama %r) skipped: %s', i, getattr(lm, 'panorama_id', ''), reason)
                continue
            d = np.asarray(lm.direction, float)
            rows.append((lm.panorama_id, np.ascontiguousarray(lm.patch).tobytes(), lm.patch_side,
                         float(d[0]), float(d[1]), float(d[2])))
        if rows:
            report.ids = self._insert('INSERT INTO landmarks (panorama_id, patch, patch_side, dx, dy, dz) '
                                      'VALUES (%s, %s, %s, %s, %s, %s) RETURNING id', rows)
        return report

    def near(self, latitude_deg: float, longitude_deg: float,
             radius_m: float = DEFAULT_RADIUS_M) -> list[Annotation]:
        if not (math.isfinite(latitude_deg) and math.isfinite(longitude_deg) and math.isfinite(radius_m)
                and radius_m >= 0 and -90 <= latitude_deg <= 90 and -180 <= longitude_deg <= 180):
            raise StoreError(f'invalid query position ({latitude_deg}, {longitude_deg}) or radius {radius_m}')
        rows = self._fetch(_NEAR, (float(longitude_deg), float(latitude_deg), float(radius_m)))
        return self._collect(rows, SqliteAnnotationStore._from_row, 'record')

    def all(self) -> list[Annotation]:
        return self._collect(self._fetch(f'SELECT {_ANNOTATION_COLUMNS} FROM annotations ORDER BY id', ()),
                             SqliteAnnotationStore._from_row, 'record')

    def landmarks(self, panorama_ids: Iterable[str]) -> list[Landmark]:
        if isinstance(panorama_ids, str):
            raise TypeError('panorama_ids must be an iterable of panorama ids, not one string')
        ids = [str(p) for p in dict.fromkeys(panorama_ids)]
        if not ids or not self._has_landmarks:
            self.skipped = []
            return []
        rows = self._fetch('SELECT id, panorama_id, patch, patch_side, dx, dy, dz FROM landmarks '
                           'WHERE panorama_id = ANY(%s) ORDER BY id', (ids,))
        return self._collect(rows, SqliteAnnotationStore._landmark_from_row, 'landmark')

    def put_panorama(self, info: PanoramaInfo) -> None:
        reason = validate_panorama(info) or _nul_problem(info.panorama_id)
        if reason is not None:
            raise StoreError(f'panorama {getattr(info, "panorama_id", "")!r} not stored: {reason}')
        if self.read_only:
            raise StoreError(f'{self.path}: the annotation store is open read-only')
        try:
            with self._db.transaction():
                self._db.execute(
                    'INSERT INTO panoramas (panorama_id, qx, qy, qz, qw, cov, up_x, up_y, up_z, '
                    'orientation_source, created_ns) VALUES (%s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s) '
                    'ON CONFLICT (panorama_id) DO UPDATE SET qx = EXCLUDED.qx, qy = EXCLUDED.qy, '
                    'qz = EXCLUDED.qz, qw = EXCLUDED.qw, cov = EXCLUDED.cov, up_x = EXCLUDED.up_x, '
                    'up_y = EXCLUDED.up_y, up_z = EXCLUDED.up_z, '
                    'orientation_source = EXCLUDED.orientation_source, created_ns = EXCLUDED.created_ns',
                    _panorama_row(info))
        except self._psycopg.Error as exc:
            raise self._error(exc, 'cannot write') from exc

    def panoramas(self, panorama_ids: Iterable[str]) -> dict[str, PanoramaInfo]:
        if isinstance(panorama_ids, str):
            raise TypeError('panorama_ids must be an iterable of panorama ids, not one string')
        ids = [str(p) for p in dict.fromkeys(panorama_ids)]
        if not ids or (self._version() or 0) < PANORAMAS_VERSION:
            return {}
        rows = self._fetch('SELECT panorama_id, qx, qy, qz, qw, cov, up_x, up_y, up_z, orientation_source, '
                           'created_ns FROM panoramas WHERE panorama_id = ANY(%s)', (ids,))
        return {p.panorama_id: p for p in self._collect(rows, panorama_from_row, 'panorama')}

    def annotations_of(self, panorama_id: str) -> list[Annotation]:
        return self._collect(self._fetch(f'SELECT {_ANNOTATION_COLUMNS} FROM annotations WHERE panorama_id = %s '
                                         'ORDER BY id', (panorama_id,)), SqliteAnnotationStore._from_row, 'record')

    def delete_panorama(self, panorama_id: str) -> int:
        if self.read_only:
            raise StoreError(f'{self.path}: the annotation store is open read-only')
        try:
            with self._db.transaction():
                n = self._db.execute('DELETE FROM annotations WHERE panorama_id = %s', (panorama_id,)).rowcount
                self._db.execute('DELETE FROM landmarks WHERE panorama_id = %s', (panorama_id,))
                self._db.execute('DELETE FROM panoramas WHERE panorama_id = %s', (panorama_id,))
        except self._psycopg.Error as exc:
            raise self._error(exc, 'cannot write') from exc
        return int(n)

    def count(self) -> int:
        return int(self._fetch('SELECT COUNT(*) FROM annotations', ())[0][0])

    def close(self) -> None:
        db = getattr(self, '_db', None)
        if db is not None:
            db.close()
            self._db = None  # type: ignore[assignment]

    # -- helpers ---------------------------------------------------------------------------

    def _insert(self, statement: str, rows: Sequence[tuple]) -> list[int]:
        """All rows in one transaction; their ids in input order."""
        if self.read_only:
            raise StoreError(f'{self.path}: the annotation store is open read-only')
        ids: list[int] = []
        try:
            with self._db.transaction(), self._db.cursor() as cur:
                cur.executemany(statement, rows, returning=True)
                while True:
                    ids.append(int(cur.fetchone()[0]))  # type: ignore[index]
                    if not cur.nextset():
                        break
        except self._psycopg.Error as exc:
            raise self._error(exc, 'cannot write') from exc
        return ids

    def _fetch(self, statement: str, args: Sequence[object]) -> list[tuple]:
        """Rows in PostgreSQL's binary format (patches and numbers arrive as they are stored,
        without text parsing: half the client time of the radius query)."""
        try:
            with self._db.cursor(binary=True) as cur:
                return cur.execute(statement, args).fetchall()
        except self._psycopg.Error as exc:
            raise self._error(exc, 'cannot read') from exc

    def _collect(self, rows: Iterable[tuple], from_row: Callable[[tuple], tuple[Any, str]], kind: str) -> list[Any]:
        """The records ``from_row`` can read back; the others are listed in :attr:`skipped`."""
        self.skipped = []
        out = []
        for row in rows:
            item, reason = from_row(row)
            if item is None:
                self.skipped.append(f'{kind} {row[0]}: {reason}')
                logger.warning('%s: %s %s skipped: %s', self.path, kind, row[0], reason)
            else:
                out.append(item)
        return out
