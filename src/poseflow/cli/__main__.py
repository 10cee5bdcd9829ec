"""``python -m poseflow.cli``."""

import sys

from poseflow.cli import main

sys.exit(main())
