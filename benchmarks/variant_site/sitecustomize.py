"""Every Python process started with this folder on its path applies the bus variant named
by ``DAMMRL_BENCH_VARIANT`` (``bus_variants.py``) at start-up: how ``flood.py --variant``
reaches the services ``dammrl up`` starts. For benchmarks only."""

import os
import sys

if variant := os.environ.get("DAMMRL_BENCH_VARIANT"):
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    from bus_variants import apply

    apply(variant)
