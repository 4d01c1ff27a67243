"""How soon a thread running Python hands the GIL to an event loop that wants it.

Python's default switch interval is 5 ms: a thread converting messages keeps the GIL that
long each time the loop's thread gives it up (every socket call, every wait). Both the
robot's client (its executor converts the slow topics, a Nav2 Path: 39 ms of Python) and
the relay (its Foxglove conversion thread) run such a thread beside their link's loop;
with 5 ms the robot's link read 11 ms RTTs on loopback and carried 2.2 MB/s, with 0.5 ms
48 MB/s (docs/benchmarks.md, "A realistic robot graph"; docs/foxglove.md, "Heavy topics").
A lone thread is never interrupted, so the setting costs nothing without one.
"""

from __future__ import annotations

import sys

GIL_SWITCH_INTERVAL_S = 0.0005


def tune_gil() -> None:
    """Lower the process's switch interval to :data:`GIL_SWITCH_INTERVAL_S` (a process
    that set a shorter one keeps it)."""
    if sys.getswitchinterval() > GIL_SWITCH_INTERVAL_S:
        sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
