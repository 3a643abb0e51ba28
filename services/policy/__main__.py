"""python -m services.policy --help"""

from services.policy.node import main

raise SystemExit(main())
