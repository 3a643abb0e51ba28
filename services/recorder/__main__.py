"""python -m services.recorder --help"""

from services.recorder.node import main

raise SystemExit(main())
