"""ar_tracking evaluation: metrics, reports and benchmarks behind ``ar-tracking evaluate|bench``."""
import os
from pathlib import Path

#: Real recordings beside the repository (../shared/data), used when present; the environment
#: variable AR_TRACKING_SHARED_DATA points elsewhere (e.g. a git worktree outside the checkout).
SHARED_DATA = Path(os.environ.get('AR_TRACKING_SHARED_DATA')
                   or Path(__file__).resolve().parents[3] / 'shared' / 'data')
