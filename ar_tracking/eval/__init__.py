"""ar_tracking evaluation: metrics, reports and benchmarks behind ``ar-tracking evaluate|bench``."""
from pathlib import Path

#: Real recordings beside the repository (../shared/data), used when present.
SHARED_DATA = Path(__file__).resolve().parents[3] / 'shared' / 'data'
