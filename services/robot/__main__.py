"""python -m services.robot --help"""

from services.robot.node import main

raise SystemExit(main())
