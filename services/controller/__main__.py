"""python -m services.controller --help"""

from services.controller.node import main

raise SystemExit(main())
