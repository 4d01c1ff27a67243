"""``fleetctl.wire`` does no I/O: it never imports asyncio, websockets or rclpy."""

from __future__ import annotations

import subprocess
import sys


def test_wire_imports_no_io_or_ros_modules() -> None:
    code = (
        "import sys\n"
        "import fleetctl.wire.codec, fleetctl.wire.control, fleetctl.wire.fragments\n"
        "import fleetctl.wire.schema, fleetctl.wire.samples, fleetctl.wire.compression\n"
        "import fleetctl.wire.whole_messages\n"
        "fleetctl.wire.control.encode_subscription('.*')\n"
        "print(sorted(m for m in ('asyncio', 'websockets', 'rclpy') if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60, check=True).stdout
    assert out.strip() == "[]"
