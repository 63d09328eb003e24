"""``python -m dc_sim``: run the simulated robot (see :func:`dc_sim.node.main`)."""

import sys

from dc_sim.node import main

sys.exit(main())
