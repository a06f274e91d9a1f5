"""Session-wide test setup: a private DDS domain per pytest run.

In-process graph tests use fixed topic names; two test runs on one machine (or a test run next to
`make run`) must not hear each other. The domain is chosen before any rclpy context is created.
"""

import os
import random

if "TAL_TEST_KEEP_DOMAIN" not in os.environ:
    os.environ["ROS_DOMAIN_ID"] = str(random.SystemRandom().randint(150, 230))
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

# Session fixtures shared by tal_perception's and tal_lab's tests (HyQ model, FEC evaluator, VFA selector).
pytest_plugins = ["perception_fixtures"]
