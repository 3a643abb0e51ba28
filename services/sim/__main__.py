"""python -m services.sim --help"""

from services.sim.node import main

raise SystemExit(main())
