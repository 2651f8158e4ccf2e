"""A throwaway PostgreSQL + PostGIS cluster for tests and benchmarks.

:class:`TemporaryCluster` runs ``initdb`` into a fresh temporary directory, starts the server
with ``pg_ctl`` on a unix socket in that directory (no TCP port, so parallel runs never
collide), enables PostGIS in the ``postgres`` database and gives its connection URL; ``stop``
ends the server and removes the directory. The binaries are Debian's (``apt-get install
postgresql postgis``: ``/usr/lib/postgresql/<version>/bin``) or any ``initdb`` on PATH.

PostgreSQL refuses to run as root: as root the server runs as the ``postgres`` system user
(created by the Debian package), and the directory is handed to it.

:func:`unavailable_reason` says why no cluster can be started here (None when one can), so a
test fixture can skip with that reason.
"""
from __future__ import annotations

import glob
import logging
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

from ..errors import ArTrackingError

logger = logging.getLogger(__name__)

#: The server's user when this process is root.
SERVER_USER = 'postgres'


class ClusterError(ArTrackingError):
    """The temporary cluster could not be started (one line)."""


def find_bindir() -> Path | None:
    """The directory of ``initdb``/``pg_ctl``: PATH first, then the newest Debian version."""
    on_path = shutil.which('initdb')
    if on_path and shutil.which('pg_ctl'):
        return Path(os.path.realpath(on_path)).parent
    found = sorted(glob.glob('/usr/lib/postgresql/*/bin/initdb'),
                   key=lambda p: int(Path(p).parent.parent.name) if Path(p).parent.parent.name.isdigit() else 0)
    return Path(found[-1]).parent if found else None


def _sharedir(bindir: Path) -> Path | None:
    """The share directory of this PostgreSQL (extensions live in its ``extension/``)."""
    pg_config = bindir / 'pg_config'
    if pg_config.exists():
        try:
            out = subprocess.run([str(pg_config), '--sharedir'], capture_output=True, text=True,
                                 timeout=10, check=True).stdout.strip()
            if out:
                return Path(out)
        except (OSError, subprocess.SubprocessError):
            pass
    version = bindir.parent.name  # Debian: /usr/lib/postgresql/<version>/bin
    candidate = Path('/usr/share/postgresql') / version
    return candidate if candidate.is_dir() else None


def unavailable_reason() -> str | None:
    """None if a PostGIS cluster can be started here, else why not (one line)."""
    bindir = find_bindir()
    if bindir is None:
        return 'PostgreSQL server binaries (initdb, pg_ctl) not found: apt-get install postgresql postgis'
    share = _sharedir(bindir)
    if share is None or not (share / 'extension' / 'postgis.control').exists():
        return f'PostGIS is not installed for the PostgreSQL in {bindir}: apt-get install postgis'
    if os.geteuid() == 0:
        try:
            import pwd

            pwd.getpwnam(SERVER_USER)
        except KeyError:
            return f'running as root and there is no {SERVER_USER!r} user to run the server as'
    try:
        import psycopg  # noqa: F401
    except ImportError:
        return 'psycopg is not installed (pip install "psycopg[binary]")'
    return None


class TemporaryCluster:
    """A PostgreSQL cluster in a temporary directory (see the module docstring).

    ``fast`` turns fsync off (tests); benchmarks keep the server's defaults."""

    def __init__(self, *, fast: bool = True, start_timeout_s: float = 60.0) -> None:
        self.fast = fast
        self.start_timeout_s = start_timeout_s
        self.root: Path | None = None
        self.bindir: Path | None = None
        self._as_root = os.geteuid() == 0
        self.running = False

    @property
    def socket_dir(self) -> Path:
        assert self.root is not None
        return self.root / 'socket'

    @property
    def url(self) -> str:
        """libpq URL of the ``postgres`` database on the unix socket."""
        return f'postgresql://{SERVER_USER}@/postgres?host={self.socket_dir}'

    def _run(self, args: list[str]) -> subprocess.CompletedProcess:
        kwargs: dict = {'capture_output': True, 'text': True, 'timeout': self.start_timeout_s}
        if self._as_root:
            kwargs.update(user=SERVER_USER, group=SERVER_USER)
        return subprocess.run(args, **kwargs)

    def start(self) -> 'TemporaryCluster':
        reason = unavailable_reason()
        if reason is not None:
            raise ClusterError(reason)
        self.bindir = find_bindir()
        assert self.bindir is not None
        self.root = Path(tempfile.mkdtemp(prefix='ar_tracking_pg_'))
        data, sock = self.root / 'data', self.socket_dir
        sock.mkdir()
        if self._as_root:
            for path in (self.root, sock):
                shutil.chown(path, SERVER_USER, SERVER_USER)
        try:
            out = self._run([str(self.bindir / 'initdb'), '-D', str(data), '-U', SERVER_USER, '-A', 'trust',
                             '-E', 'UTF8', '--locale=C', *(['--no-sync'] if self.fast else [])])
            if out.returncode != 0:
                raise ClusterError(f'initdb failed: {out.stderr.strip().splitlines()[-1:]}')
            opts = f"-c listen_addresses='' -k {sock} -c max_connections=100"
            if self.fast:
                opts += ' -c fsync=off -c synchronous_commit=off -c full_page_writes=off'
            out = self._run([str(self.bindir / 'pg_ctl'), '-D', str(data), '-o', opts,
                             '-l', str(self.root / 'server.log'), '-w', '-t', str(int(self.start_timeout_s)),
                             'start'])
            if out.returncode != 0:
                raise ClusterError(f'pg_ctl start failed: {self._log_tail()}')
            self.running = True
            import psycopg

            with psycopg.connect(self.url, autocommit=True) as conn:
                conn.execute('CREATE EXTENSION IF NOT EXISTS postgis')
        except (OSError, subprocess.SubprocessError) as exc:
            self.stop()
            raise ClusterError(f'cannot start a temporary PostgreSQL cluster ({exc})') from exc
        except BaseException:
            self.stop()
            raise
        logger.info('temporary PostgreSQL cluster on %s', sock)
        return self

    def _log_tail(self) -> str:
        try:
            lines = (self.root / 'server.log').read_text(errors='replace').strip().splitlines()  # type: ignore[operator]
            return lines[-1] if lines else 'no server log'
        except OSError:
            return 'no server log'

    def create_database(self, name: str) -> str:
        """A new database (from template1, with PostGIS enabled); its URL."""
        import psycopg
        from psycopg import sql

        with psycopg.connect(self.url, autocommit=True) as conn:
            conn.execute(sql.SQL('CREATE DATABASE {}').format(sql.Identifier(name)))
        url = self.url.replace('@/postgres?', f'@/{name}?')
        with psycopg.connect(url, autocommit=True) as conn:
            conn.execute('CREATE EXTENSION IF NOT EXISTS postgis')
        return url

    def stop(self) -> None:
        """Stop the server (immediately) and remove the directory."""
        if self.running and self.bindir is not None and self.root is not None:
            try:
                self._run([str(self.bindir / 'pg_ctl'), '-D', str(self.root / 'data'), '-m', 'immediate',
                           '-w', 'stop'])
            except (OSError, subprocess.SubprocessError) as exc:
                logger.warning('temporary PostgreSQL cluster did not stop cleanly (%s)', exc)
            self.running = False
        if self.root is not None:
            shutil.rmtree(self.root, ignore_errors=True)
            self.root = None

    def __enter__(self) -> 'TemporaryCluster':
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
