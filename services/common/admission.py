"""The gate of a service's subscriptions: what Zenoh's callback lets into the service.

Rates are Zenoh's business (per-link ingress downsampling, ``schemas.keys.LIMITS``):
the messages arrive here already bounded per peer. Here, before the payload is copied
(a length test): the key's size limit; a larger payload is dropped and counted (Health).
"""

from __future__ import annotations

import threading
from collections import Counter

from schemas.keys import limits_of

MAX_KEYS = 256
"""Keys counted apart; beyond, refusals share one count (random keys cannot grow it)."""
SHARED = "<other keys>"


class Admission:
    """Per-key size limits for one session's subscriptions (thread-safe)."""

    def __init__(self, namespace: str) -> None:
        self.namespace = namespace
        self.refused: Counter[str] = Counter()  # "<key>: larger than N bytes" -> count
        self._lock = threading.Lock()

    def admit(self, key_expr: str, size: int) -> bool:
        """Whether a payload of ``size`` bytes on ``key_expr`` may enter (else counted)."""
        limit = limits_of(self.namespace, key_expr).max_bytes
        if size <= limit:
            return True
        why = f"{key_expr}: larger than {limit} bytes"
        with self._lock:
            if len(self.refused) >= MAX_KEYS and why not in self.refused:
                why = f"{SHARED}: larger than allowed"
            self.refused[why] += 1
        return False
