"""``python -m dammrl`` is the ``dammrl`` command."""

from dammrl.cli import main

raise SystemExit(main())
