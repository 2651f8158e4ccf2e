"""ar_tracking."""
