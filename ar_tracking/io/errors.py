"""The io subpackage's error: one class that every bag reader and writer raises.

Its own module so that the bag modules (:mod:`~ar_tracking.io.bags` and the unfinished-MCAP
recovery in :mod:`~ar_tracking.io.mcap_recovery`) share it without importing each other;
:mod:`ar_tracking.io.bags` re-exports it.
"""
from __future__ import annotations

from ..errors import ArTrackingError


class BagError(ArTrackingError):
    """A bag cannot be opened, read or written. The message is one line meant for the user."""
