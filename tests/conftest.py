"""Test-session environment: ROS traffic stays on this machine, in a domain of its own."""

from __future__ import annotations

import os
import random
import tempfile
from pathlib import Path

# Set before any test module imports rclpy, so every context of this session uses them.
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(1, 100)))
os.environ.setdefault("ROS_LOG_DIR", tempfile.mkdtemp(prefix="dc-test-roslog-"))
os.environ.setdefault("RCUTILS_COLORIZED_OUTPUT", "0")

REPO = Path(__file__).resolve().parent.parent
