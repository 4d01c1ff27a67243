"""The client image carries what robots in containers need beyond PyPI's ROS wheels:
tf2_msgs (built by ``fleetctl build``) for TF, and PyAV for video."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from fleetctl.deploy.dockercli import image_exists, subprocess_runner
from fleetctl.deploy.images import image_tag

pytestmark = [
    pytest.mark.docker,
    pytest.mark.skipif(shutil.which("docker") is None, reason="needs docker"),
]

# A real rclpy round trip on /tf inside the image: the typesupport libraries load.
TF_ROUND_TRIP = """
import time, rclpy, av
from tf2_msgs.msg import TFMessage
from geometry_msgs.msg import TransformStamped
rclpy.init()
node = rclpy.create_node("tf_check")
got = []
node.create_subscription(TFMessage, "/tf", got.append, 10)
pub = node.create_publisher(TFMessage, "/tf", 10)
deadline = time.monotonic() + 20
while not got and time.monotonic() < deadline:
    t = TransformStamped()
    t.header.frame_id, t.child_frame_id = "odom", "base_link"
    pub.publish(TFMessage(transforms=[t]))
    rclpy.spin_once(node, timeout_sec=0.2)
print("tf", got[0].transforms[0].child_frame_id if got else "none", "h264",
      av.codec.Codec("libx264", "w").name)
"""


def test_the_client_image_round_trips_tf_and_encodes_h264(tmp_path: Path) -> None:
    image = image_tag("client")
    if not image_exists(subprocess_runner, image):
        pytest.fail(f"{image} missing: run `fleetctl build` first")
    script = tmp_path / "check.py"
    script.write_text(TF_ROUND_TRIP)
    script.chmod(0o644)
    res = subprocess.run(
        ["docker", "run", "--rm", "--network", "none", "-v", f"{script}:/tmp/check.py:ro",
         "--entrypoint", "/opt/fleetctl/bin/python3", image, "/tmp/check.py"],
        capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == ["tf", "base_link", "h264", "libx264"], res.stdout
