"""python -m services.intent --help"""

from services.intent.node import main

raise SystemExit(main())
