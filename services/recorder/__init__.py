"""Recorder service: captures the bus to MCAP (the recording issue)."""
