"""The annotation store (Langlotz 2011 sec. 3.2 and 4.3, Fig. 2).

An annotation is a small record (about 2 kB): its text, the image patch of its support area
(cut from the source panorama map), the unit vector from the camera to the anchor in the source
panorama frame (sec. 4.3, Fig. 5), the GPS position where it was authored, the source panorama
id, the author and the creation time. Optionally the source panorama's orientation in the world
(ENU), which the sensor prior of sec. 4.2 needs to predict where an annotation appears.

A landmark (:class:`Landmark`, about 300 bytes) is a distinctive textured patch of a source
panorama with its unit direction, but no text, position or author: it is never shown. The
re-detector matches landmarks like annotations to get more correspondences between the source and
the current panorama, for the global rotation and the parallax fit. They are stored per source
panorama and read back with the annotations' panorama ids.

A browsing device asks for "everything within 50 m of this fix" (sec. 4.3). :class:`AnnotationStore`
is the interface; :class:`SqliteAnnotationStore` implements it on one SQLite file: WAL journal
(readers never block the writer), every write in one transaction, and an R-tree (sqlite's rtree
module) over latitude/longitude so the radius query is an index query followed by an exact
great-circle check; landmarks live in their own table, indexed by panorama id. A
PostgreSQL/PostGIS backend would implement the same six methods (``add``, ``near``, ``all``,
``add_landmarks``, ``landmarks``, ``close``) with ``ST_DWithin`` on a geography column.

Errors are :class:`StoreError` with one line (missing, locked or corrupt files); an existing file
is never overwritten or re-initialised. Bad records (wrong patch size, NaN or zero vector, ...)
are skipped and reported, never stored. Schema version 2 added the landmarks table: a version-1
file opens as it is (it has no landmarks) and gets the table, in the same transaction, on its
first ``add_landmarks``. Schema version 3 added the panoramas table (:class:`PanoramaInfo`: the
source panorama's estimated orientation in the world, its covariance, its up direction and where
they came from), created the same way on the first :meth:`~AnnotationStore.put_panorama`.

A store is opened read-only (``read_only=True``, what the matcher does) without writing anything:
in a read-only directory, where SQLite cannot create the WAL's shared-memory file, it is opened
as an immutable file; a file the user may not read, a store another process holds locked, and a
read-only file opened for writing each get their own one-line StoreError.

The records, their validation and row conversion are in :mod:`.records` (re-exported here); this
module is the schema, the interface and the SQLite implementation.
"""
from __future__ import annotations

import abc
import contextlib
import logging
import math
import os
import sqlite3
from pathlib import Path
from typing import Callable, Iterable, Iterator, Sequence, TypeVar

import numpy as np
from numpy.typing import NDArray

# The records and their validation live in .records; every name is re-exported here (the stores,
# the nodes and the tools import them from this module).
from .records import (EARTH_RADIUS_M, AddReport, Annotation, Landmark, PanoramaInfo, _panorama_row, distance_m,
                      panorama_from_row, validate_annotation, validate_landmark, validate_panorama)
from .records import ORIENTATION_SOURCES as ORIENTATION_SOURCES, PATCH_SIDES as PATCH_SIDES
from ...errors import ArTrackingError

logger = logging.getLogger(__name__)

#: Search radius of sec. 4.3 ("all datasets created within proximity of 50 m").
DEFAULT_RADIUS_M = 50.0
SCHEMA = 'ar_tracking.annotations'
SCHEMA_VERSION = 3
#: The schema version that added the landmarks table.
LANDMARKS_VERSION = 2
#: The schema version that added the panoramas table.
PANORAMAS_VERSION = 3


class StoreError(ArTrackingError):
    """The store cannot be opened, read or written: one line for the user."""


class AnnotationStore(abc.ABC):
    """What the matcher and the authoring tool need from a store (SQLite, PostGIS, ...)."""

    #: Reasons of the stored records that could not be read back by the last query.
    skipped: list[str]

    @abc.abstractmethod
    def add(self, annotations: Iterable[Annotation]) -> AddReport:
        """Store the valid records in one transaction; skip and report the others."""

    @abc.abstractmethod
    def near(self, latitude_deg: float, longitude_deg: float,
             radius_m: float = DEFAULT_RADIUS_M) -> list[Annotation]:
        """Every record authored within ``radius_m`` of the position (an index query)."""

    @abc.abstractmethod
    def all(self) -> list[Annotation]:
        """Every record (used when GPS is poor)."""

    @abc.abstractmethod
    def add_landmarks(self, landmarks: Iterable[Landmark]) -> AddReport:
        """Store the valid landmarks in one transaction; skip, report and log the others."""

    @abc.abstractmethod
    def landmarks(self, panorama_ids: Iterable[str]) -> list[Landmark]:
        """Every stored landmark of these source panoramas, ordered by id. Landmarks that cannot
        be read back are skipped and listed in :attr:`skipped`."""

    @abc.abstractmethod
    def put_panorama(self, info: PanoramaInfo) -> None:
        """Store (or replace) what is known of a source panorama as a whole."""

    @abc.abstractmethod
    def panoramas(self, panorama_ids: Iterable[str]) -> dict[str, PanoramaInfo]:
        """The stored panorama records of these ids (ids without one are left out)."""

    @abc.abstractmethod
    def annotations_of(self, panorama_id: str) -> list[Annotation]:
        """Every record of one source panorama, ordered by id."""

    @abc.abstractmethod
    def delete_panorama(self, panorama_id: str) -> int:
        """Remove a source panorama's annotations, landmarks and record in one transaction;
        returns how many annotations were removed."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the connection."""

    def __enter__(self) -> 'AnnotationStore':
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


_SQLITE_MAGIC = b'SQLite format 3\x00'
#: The landmarks table and its index; idempotent, so they also upgrade a version-1 file.
_LANDMARKS_DDL = (
    'CREATE TABLE IF NOT EXISTS landmarks (id INTEGER PRIMARY KEY, panorama_id TEXT NOT NULL, '
    'patch BLOB NOT NULL, patch_side INTEGER NOT NULL, dx REAL NOT NULL, dy REAL NOT NULL, '
    'dz REAL NOT NULL)',
    'CREATE INDEX IF NOT EXISTS landmarks_panorama_id ON landmarks (panorama_id)',
)
#: The panoramas table; idempotent, so it also upgrades a version-1/2 file.
_PANORAMAS_DDL = (
    'CREATE TABLE IF NOT EXISTS panoramas (panorama_id TEXT PRIMARY KEY, qx REAL, qy REAL, qz REAL, '
    'qw REAL, cov BLOB, up_x REAL, up_y REAL, up_z REAL, orientation_source TEXT NOT NULL, '
    'created_ns INTEGER NOT NULL)',
)
#: Panorama ids per landmark query (below sqlite's limit on bound parameters).
_IDS_PER_QUERY = 500
_T = TypeVar('_T')


class SqliteAnnotationStore(AnnotationStore):
    """SQLite implementation (see the module docstring). One instance per thread/process."""

    def __init__(self, path: str | Path, *, create: bool = False, timeout_s: float = 5.0,
                 read_only: bool = False) -> None:
        self.path = Path(path)
        self.skipped = []
        exists = self.path.exists()
        if not exists and not create:
            raise StoreError(f'{self.path}: no such annotation store')
        if exists:
            self._check_header()
        elif not self.path.parent.is_dir():
            raise StoreError(f'{self.path}: directory {self.path.parent} does not exist')
        if exists and not read_only and not os.access(self.path, os.W_OK):
            raise StoreError(f'{self.path}: the annotation store is read-only (no write permission); '
                             'it can be browsed, not written')
        if exists and not read_only and not os.access(self.path.parent, os.W_OK | os.X_OK):
            raise StoreError(f'{self.path}: the annotation store is in a read-only directory '
                             f'({self.path.parent}); it can be browsed, not written')
        mode = 'ro' if read_only else ('rwc' if create and not exists else 'rw')
        # A reader in a directory it cannot write cannot create the WAL's -shm file: with no
        # -wal file beside it nobody can be writing, so the file is opened as immutable.
        immutable = (read_only and exists and not os.access(self.path.parent, os.W_OK)
                     and not Path(str(self.path) + '-wal').exists())
        uri = f'file:{self.path}?mode={mode}' + ('&immutable=1' if immutable else '')
        try:
            self._db = sqlite3.connect(uri, uri=True, timeout=timeout_s, isolation_level=None)
        except sqlite3.Error as exc:
            raise StoreError(f'{self.path}: cannot open the annotation store ({exc})') from exc
        try:
            if exists:
                self._check_schema()
            else:
                self._create_schema()
            if not read_only:
                self._db.execute('PRAGMA journal_mode=WAL')
                self._db.execute('PRAGMA synchronous=NORMAL')
        except sqlite3.Error as exc:
            self._db.close()
            raise self._error(exc, 'cannot open') from exc
        except StoreError:
            self._db.close()
            raise

    # -- opening ---------------------------------------------------------------------------

    def _check_header(self) -> None:
        try:
            with open(self.path, 'rb') as f:
                head = f.read(16)
        except OSError as exc:
            raise StoreError(f'{self.path}: cannot read the annotation store ({exc.strerror})') from exc
        if head != _SQLITE_MAGIC:
            raise StoreError(f'{self.path}: corrupt annotation store (not an SQLite database); left untouched')

    def _create_schema(self) -> None:
        db = self._db
        db.execute('BEGIN IMMEDIATE')
        try:
            db.execute('CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)')
            db.executemany('INSERT INTO meta VALUES (?, ?)',
                           [('schema', SCHEMA), ('version', str(SCHEMA_VERSION))])
            db.execute('''CREATE TABLE annotations (
                id INTEGER PRIMARY KEY, text TEXT NOT NULL, patch BLOB NOT NULL,
                patch_side INTEGER NOT NULL, dx REAL NOT NULL, dy REAL NOT NULL, dz REAL NOT NULL,
                latitude REAL NOT NULL, longitude REAL NOT NULL, altitude REAL NOT NULL,
                panorama_id TEXT NOT NULL, author TEXT NOT NULL, created_ns INTEGER NOT NULL,
                pano_qx REAL, pano_qy REAL, pano_qz REAL, pano_qw REAL)''')
            db.execute('CREATE VIRTUAL TABLE annotations_rtree USING rtree('
                       'id, min_lat, max_lat, min_lon, max_lon)')
            for sql in _LANDMARKS_DDL + _PANORAMAS_DDL:
                db.execute(sql)
            db.execute('COMMIT')
        except BaseException:
            db.execute('ROLLBACK')
            raise

    def _check_schema(self) -> None:
        try:
            rows = dict(self._db.execute('SELECT key, value FROM meta').fetchall())
        except sqlite3.OperationalError as exc:
            raise self._error(exc, 'cannot read') from exc
        except sqlite3.DatabaseError as exc:
            raise self._error(exc, 'not an annotation store') from exc
        if rows.get('schema') != SCHEMA:
            raise StoreError(f'{self.path}: not an annotation store (schema {rows.get("schema")!r}); left untouched')
        if int(rows.get('version', '0')) > SCHEMA_VERSION:
            raise StoreError(f'{self.path}: annotation store version {rows["version"]} is newer than this program ({SCHEMA_VERSION})')

    def _error(self, exc: sqlite3.Error, what: str) -> StoreError:
        text = str(exc)
        if 'locked' in text or 'busy' in text:
            return StoreError(f'{self.path}: annotation store is locked by another process ({text})')
        if 'readonly' in text or 'read-only' in text:
            return StoreError(f'{self.path}: the annotation store is read-only ({text}); it can be browsed, not written')
        if 'unable to open' in text:
            return StoreError(f'{self.path}: cannot open the annotation store ({text}; check the file '
                              'and directory permissions)')
        if isinstance(exc, sqlite3.DatabaseError) and ('malformed' in text or 'not a database' in text
                                                       or 'no such table' in text):
            return StoreError(f'{self.path}: corrupt annotation store ({text}); left untouched')
        return StoreError(f'{self.path}: {what} ({text})')

    # -- interface -------------------------------------------------------------------------

    def add(self, annotations: Iterable[Annotation]) -> AddReport:
        report = AddReport()
        rows = []
        for i, a in enumerate(annotations):
            reason = validate_annotation(a)
            if reason is not None:
                report.skipped.append((i, reason))
                logger.warning('annotation %d (%r) skipped: %s', i, getattr(a, 'text', ''), reason)
                continue
            d = np.asarray(a.direction, float)
            q_row: list[float | None] = ([float(v) for v in np.asarray(a.panorama_in_world_quat_xyzw, float)]
                                         if a.has_world_orientation() else [None] * 4)
            rows.append((a.text, np.ascontiguousarray(a.patch).tobytes(), a.patch_side,
                         float(d[0]), float(d[1]), float(d[2]), float(a.latitude_deg),
                         float(a.longitude_deg), float(a.altitude_m), a.panorama_id, a.author,
                         int(a.created_ns), *q_row))
        if not rows:
            return report
        ids = []
        with self._write_transaction() as db:
            for row in rows:
                cur = db.execute('INSERT INTO annotations (text, patch, patch_side, dx, dy, dz, '
                                 'latitude, longitude, altitude, panorama_id, author, created_ns, '
                                 'pano_qx, pano_qy, pano_qz, pano_qw) '
                                 'VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)', row)
                assert cur.lastrowid is not None  # set by every INSERT
                rid = int(cur.lastrowid)
                db.execute('INSERT INTO annotations_rtree VALUES (?, ?, ?, ?, ?)',
                           (rid, row[6], row[6], row[7], row[7]))
                ids.append(rid)
        report.ids = ids
        return report

    def add_landmarks(self, landmarks: Iterable[Landmark]) -> AddReport:
        report = AddReport()
        rows = []
        for i, lm in enumerate(landmarks):
            reason = validate_landmark(lm)
            if reason is not None:
                report.skipped.append((i, reason))
                logger.warning('landmark %d (panorama %r) skipped: %s', i,
                               getattr(lm, 'panorama_id', ''), reason)
                continue
            d = np.asarray(lm.direction, float)
            rows.append((lm.panorama_id, np.ascontiguousarray(lm.patch).tobytes(), lm.patch_side,
                         float(d[0]), float(d[1]), float(d[2])))
        if not rows:
            return report
        ids = []
        with self._write_transaction() as db:
            self._ensure_landmarks_table(db)
            for row in rows:
                cur = db.execute('INSERT INTO landmarks (panorama_id, patch, patch_side, dx, dy, dz) '
                                 'VALUES (?, ?, ?, ?, ?, ?)', row)
                assert cur.lastrowid is not None  # set by every INSERT
                ids.append(int(cur.lastrowid))
        report.ids = ids
        return report

    def landmarks(self, panorama_ids: Iterable[str]) -> list[Landmark]:
        if isinstance(panorama_ids, str):
            raise TypeError('panorama_ids must be an iterable of panorama ids, not one string')
        ids = list(dict.fromkeys(panorama_ids))
        rows = self._landmark_rows(ids) if ids else []
        return self._collect(sorted(rows, key=lambda row: row[0]), self._landmark_from_row, 'landmark')

    def near(self, latitude_deg: float, longitude_deg: float,
             radius_m: float = DEFAULT_RADIUS_M) -> list[Annotation]:
        if not (math.isfinite(latitude_deg) and math.isfinite(longitude_deg) and radius_m >= 0):
            raise StoreError(f'invalid query position ({latitude_deg}, {longitude_deg}) or radius {radius_m}')
        dlat = math.degrees(radius_m / EARTH_RADIUS_M) * 1.01 + 1e-6
        coslat = max(math.cos(math.radians(latitude_deg)), 1e-6)
        dlon = min(180.0, dlat / coslat)
        # R-tree boxes overlapping the query box; the rtree stores 32-bit floats, rounded
        # outwards, so the exact distance check below decides.
        sql = ('SELECT a.* FROM annotations_rtree r JOIN annotations a ON a.id = r.id '
               'WHERE r.max_lat >= ? AND r.min_lat <= ? AND r.max_lon >= ? AND r.min_lon <= ? '
               'ORDER BY a.id')
        rows = self._query(sql, (latitude_deg - dlat, latitude_deg + dlat,
                                 longitude_deg - dlon, longitude_deg + dlon))
        if not rows:
            return rows
        d = distance_m(latitude_deg, longitude_deg, np.array([a.latitude_deg for a in rows]),
                       np.array([a.longitude_deg for a in rows]))  # one vectorised check
        return [a for a, d_m in zip(rows, d) if d_m <= radius_m]

    def all(self) -> list[Annotation]:
        return self._query('SELECT * FROM annotations ORDER BY id', ())

    def put_panorama(self, info: PanoramaInfo) -> None:
        reason = validate_panorama(info)
        if reason is not None:
            raise StoreError(f'panorama {getattr(info, "panorama_id", "")!r} not stored: {reason}')
        with self._write_transaction() as db:
            self._ensure_panoramas_table(db)
            db.execute('INSERT OR REPLACE INTO panoramas (panorama_id, qx, qy, qz, qw, cov, up_x, up_y, '
                       'up_z, orientation_source, created_ns) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)',
                       _panorama_row(info))

    def panoramas(self, panorama_ids: Iterable[str]) -> dict[str, PanoramaInfo]:
        if isinstance(panorama_ids, str):
            raise TypeError('panorama_ids must be an iterable of panorama ids, not one string')
        ids = list(dict.fromkeys(panorama_ids))
        try:
            if not ids or self._db.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND "
                                           "name = 'panoramas'").fetchone() is None:
                return {}
            rows = []
            for k in range(0, len(ids), _IDS_PER_QUERY):
                chunk = ids[k:k + _IDS_PER_QUERY]
                rows += self._db.execute('SELECT panorama_id, qx, qy, qz, qw, cov, up_x, up_y, up_z, '
                                         'orientation_source, created_ns FROM panoramas WHERE panorama_id '
                                         f'IN ({", ".join("?" * len(chunk))})', chunk).fetchall()
        except sqlite3.Error as exc:
            raise self._error(exc, 'cannot read') from exc
        return {p.panorama_id: p for p in self._collect(rows, panorama_from_row, 'panorama')}

    def annotations_of(self, panorama_id: str) -> list[Annotation]:
        return self._query('SELECT * FROM annotations WHERE panorama_id = ? ORDER BY id', (panorama_id,))

    def delete_panorama(self, panorama_id: str) -> int:
        with self._write_transaction() as db:
            ids = [r[0] for r in db.execute('SELECT id FROM annotations WHERE panorama_id = ?', (panorama_id,))]
            db.executemany('DELETE FROM annotations_rtree WHERE id = ?', [(i,) for i in ids])
            db.execute('DELETE FROM annotations WHERE panorama_id = ?', (panorama_id,))
            tables = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
            if 'landmarks' in tables:
                db.execute('DELETE FROM landmarks WHERE panorama_id = ?', (panorama_id,))
            if 'panoramas' in tables:
                db.execute('DELETE FROM panoramas WHERE panorama_id = ?', (panorama_id,))
        return len(ids)

    def count(self) -> int:
        try:
            return int(self._db.execute('SELECT COUNT(*) FROM annotations').fetchone()[0])
        except sqlite3.Error as exc:
            raise self._error(exc, 'cannot read') from exc

    def integrity_ok(self) -> bool:
        """sqlite's integrity check of the file (also of the R-tree)."""
        try:
            ok = self._db.execute('PRAGMA integrity_check').fetchone()[0] == 'ok'
            n_tree = self._db.execute('SELECT COUNT(*) FROM annotations_rtree').fetchone()[0]
            return ok and n_tree == self.count()
        except sqlite3.Error:
            return False

    def close(self) -> None:
        db = getattr(self, '_db', None)
        if db is not None:
            db.close()
            self._db = None  # type: ignore[assignment]

    # -- writing ---------------------------------------------------------------------------

    @contextlib.contextmanager
    def _write_transaction(self) -> Iterator[sqlite3.Connection]:
        """One write transaction (BEGIN IMMEDIATE ... COMMIT, rolled back on any error); sqlite
        errors become a one-line StoreError."""
        db = self._db
        try:
            db.execute('BEGIN IMMEDIATE')
            try:
                yield db
                db.execute('COMMIT')
            except BaseException:
                if db.in_transaction:
                    db.execute('ROLLBACK')
                raise
        except sqlite3.Error as exc:
            raise self._error(exc, 'cannot write') from exc

    @staticmethod
    def _ensure_landmarks_table(db: sqlite3.Connection) -> None:
        """Inside the caller's write transaction: create the landmarks table and index if missing
        (a version-1 file) and record the version that has them. A no-op on newer files."""
        for sql in _LANDMARKS_DDL:
            db.execute(sql)
        db.execute("UPDATE meta SET value = ? WHERE key = 'version' AND CAST(value AS INTEGER) < ?",
                   (str(LANDMARKS_VERSION), LANDMARKS_VERSION))

    @staticmethod
    def _ensure_panoramas_table(db: sqlite3.Connection) -> None:
        """As :meth:`_ensure_landmarks_table`, for the panoramas table (version 3)."""
        for sql in _LANDMARKS_DDL + _PANORAMAS_DDL:
            db.execute(sql)
        db.execute("UPDATE meta SET value = ? WHERE key = 'version' AND CAST(value AS INTEGER) < ?",
                   (str(PANORAMAS_VERSION), PANORAMAS_VERSION))

    # -- reading ---------------------------------------------------------------------------

    def _query(self, sql: str, args: Sequence[object]) -> list[Annotation]:
        try:
            rows = self._db.execute(sql, args).fetchall()
        except sqlite3.Error as exc:
            raise self._error(exc, 'cannot read') from exc
        return self._collect(rows, self._from_row, 'record')

    def _landmark_rows(self, panorama_ids: Sequence[str]) -> list[tuple]:
        """The landmark rows of these panoramas, from one read snapshot; none on a version-1 file
        (no landmarks table)."""
        db = self._db
        rows: list[tuple] = []
        try:
            db.execute('BEGIN')  # one snapshot for every chunk
            try:
                if db.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'landmarks'"
                              ).fetchone() is None:
                    return []
                for k in range(0, len(panorama_ids), _IDS_PER_QUERY):
                    chunk = panorama_ids[k:k + _IDS_PER_QUERY]
                    marks = ', '.join('?' * len(chunk))
                    rows += db.execute('SELECT id, panorama_id, patch, patch_side, dx, dy, dz '
                                       f'FROM landmarks WHERE panorama_id IN ({marks}) ORDER BY id', chunk).fetchall()
            finally:
                if db.in_transaction:
                    db.execute('ROLLBACK')
        except sqlite3.Error as exc:
            raise self._error(exc, 'cannot read') from exc
        return rows

    def _collect(self, rows: Iterable[tuple], from_row: Callable[[tuple], tuple[_T | None, str]],
                 kind: str) -> list[_T]:
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

    @staticmethod
    def _patch_from_blob(blob: bytes, side: int) -> tuple[NDArray[np.uint8] | None, str]:
        patch = np.frombuffer(blob, np.uint8)
        if patch.size != side * side:
            return None, f'patch has {patch.size} bytes, expected {side}x{side}'
        return patch.reshape(side, side).copy(), ''

    @classmethod
    def _landmark_from_row(cls, row: tuple) -> tuple[Landmark | None, str]:
        rid, pano, blob, side, dx, dy, dz = row
        try:
            patch, reason = cls._patch_from_blob(blob, side)
            if patch is None:
                return None, reason
            lm = Landmark(panorama_id=pano, patch=patch, direction=np.array([dx, dy, dz], float),
                          id=int(rid))
        except (TypeError, ValueError) as exc:
            return None, str(exc)
        problem = validate_landmark(lm)
        return (None, problem) if problem else (lm, '')

    @classmethod
    def _from_row(cls, row: tuple) -> tuple[Annotation | None, str]:
        (rid, text, blob, side, dx, dy, dz, lat, lon, alt, pano, author, created,
         qx, qy, qz, qw) = row
        try:
            patch, reason = cls._patch_from_blob(blob, side)
            if patch is None:
                return None, reason
            q = np.array([np.nan] * 4 if qw is None else [qx, qy, qz, qw], float)
            a = Annotation(text=text, patch=patch,
                           direction=np.array([dx, dy, dz], float), latitude_deg=float(lat),
                           longitude_deg=float(lon), altitude_m=float(alt), panorama_id=pano,
                           author=author, created_ns=int(created), panorama_in_world_quat_xyzw=q,
                           id=int(rid))
        except (TypeError, ValueError) as exc:
            return None, str(exc)
        problem = validate_annotation(a)
        return (None, problem) if problem else (a, '')


def open_store(url: str | Path, *, create: bool = False, timeout_s: float = 5.0) -> AnnotationStore:
    """A store from a path or URL: ``sqlite:///path`` or a plain path (SQLite). PostgreSQL/PostGIS
    stores live outside the core (psycopg): :func:`ar_tracking.io.stores.open_store` opens both."""
    text = str(url)
    if text.startswith(('postgresql://', 'postgres://')):
        raise StoreError('PostgreSQL/PostGIS stores open with ar_tracking.io.stores.open_store (the core opens SQLite only)')
    if text.startswith('sqlite:///'):
        text = text[len('sqlite:///'):]
    return SqliteAnnotationStore(text, create=create, timeout_s=timeout_s)
