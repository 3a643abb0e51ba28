"""One logging format for every service: time, service, level, message."""

from __future__ import annotations

import logging
import os


def setup_logging(service: str) -> logging.Logger:
    """Log to stderr at ``DAMMRL_LOG_LEVEL`` (default INFO)."""
    level = os.environ.get("DAMMRL_LOG_LEVEL", "INFO").upper()
    logging.basicConfig(
        level=level if level in logging.getLevelNamesMapping() else "INFO",
        format=f"%(asctime)s {service} %(levelname)s %(message)s",
    )
    return logging.getLogger(f"dammrl.{service}")
