"""``python -m dammrl.cli`` is the ``dammrl`` command, like ``python -m dammrl``."""

from dammrl.cli import main

raise SystemExit(main())
