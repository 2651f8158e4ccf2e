"""Opening an annotation store by URL, and the retry schedule of a store that cannot be reached.

``open_store(url)`` takes ``sqlite:///path/notes.db`` (or a plain path: SQLite, the embedded
default) or ``postgresql://user@host:port/dbname[?schema=NAME]`` (PostGIS, a server many users
share). An empty URL reads ``AR_TRACKING_STORE_URL``. Passwords belong in libpq's
``PGPASSWORD``/``~/.pgpass`` or in the URL given at run time, never in code or committed files.

:class:`RetryBackoff` is what a node uses when the store is down or refuses its credentials: one
line, no annotations for now, and the next attempt after 1, 2, 4, ... up to ``max_s`` seconds.
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

from ..core.annotations.store import AnnotationStore, SqliteAnnotationStore, StoreError

#: Environment variable read when no store URL is given.
STORE_URL_ENV = 'AR_TRACKING_STORE_URL'


def resolve_url(url: str | Path | None) -> str:
    """The URL to open: ``url``, else ``$AR_TRACKING_STORE_URL``; a StoreError when neither is set."""
    text = str(url) if url not in (None, '') else os.environ.get(STORE_URL_ENV, '')
    if not text:
        raise StoreError(f'no annotation store given (a store URL or path, or {STORE_URL_ENV})')
    return text


def open_store(url: str | Path | None, *, create: bool = False, read_only: bool = False,
               timeout_s: float = 5.0, query_timeout_s: float = 5.0) -> AnnotationStore:
    """The store behind ``url`` (see the module docstring); errors are one-line StoreErrors."""
    text = resolve_url(url)
    if text.startswith(('postgresql://', 'postgres://')):
        from .postgis_store import PostgisAnnotationStore

        return PostgisAnnotationStore(text, create=create, read_only=read_only, timeout_s=timeout_s,
                                      query_timeout_s=query_timeout_s)
    if text.startswith('sqlite:///'):
        text = text[len('sqlite:///'):]
    elif re.match(r'^[A-Za-z][A-Za-z0-9+.-]*://', text):
        raise StoreError(f'{text.split("://", 1)[0]}://: unknown store URL scheme (sqlite:/// or postgresql://)')
    return SqliteAnnotationStore(text, create=create, timeout_s=timeout_s, read_only=read_only)


def describe(url: str | Path | None) -> str:
    """The store's name for a log line (no password)."""
    text = str(url or os.environ.get(STORE_URL_ENV, '') or '-')
    if text.startswith(('postgresql://', 'postgres://')):
        from .postgis_store import describe_url

        return describe_url(text)
    return text


@dataclass
class RetryBackoff:
    """Exponential back-off between attempts (times in seconds on any monotonic clock)."""

    initial_s: float = 1.0
    max_s: float = 60.0
    factor: float = 2.0
    failures: int = 0
    next_s: float | None = None

    def ready(self, now_s: float) -> bool:
        """May an attempt be made now?"""
        return self.next_s is None or now_s >= self.next_s

    def failed(self, now_s: float) -> float:
        """Book a failed attempt at ``now_s``; returns the wait until the next one."""
        wait = min(self.max_s, self.initial_s * self.factor ** self.failures)
        self.failures += 1
        self.next_s = now_s + wait
        return wait

    def succeeded(self) -> None:
        self.failures = 0
        self.next_s = None
