"""Why a publish entry has no publisher: the graph's topics it may have meant."""

from __future__ import annotations

from fleetctl.client.topichints import candidates, no_publisher_reason

SCAN = "sensor_msgs/msg/LaserScan"
GRAPH = [("/husky1/scan", [SCAN]), ("/scan_raw", ["sensor_msgs/msg/PointCloud2"]),
         ("/rosout", ["rcl_interfaces/msg/Log"]), ("/front/scan_filtered", [SCAN])]


def reason(topic: str, type_name: str = SCAN, graph: list[tuple[str, list[str]]] = GRAPH,
           other_nodes: int = 3) -> str:
    return no_publisher_reason(topic, type_name, 30.2, graph, other_nodes, 77,
                               "rmw_fastrtps_cpp")


def test_a_namespaced_driver_is_named_first_then_close_names_of_its_type_first() -> None:
    assert candidates("/scan", SCAN, GRAPH) == ["/husky1/scan", "/scan_raw"]
    assert reason("/scan") == (
        "/scan: no publisher in 30 s, so nothing of it is sent; the ROS graph has "
        "/husky1/scan (sensor_msgs/msg/LaserScan), /scan_raw (sensor_msgs/msg/PointCloud2): "
        "a namespaced or remapped driver? set this entry's topic to the one it publishes")


def test_the_type_elsewhere_is_named_when_no_name_is_close() -> None:
    assert reason("/laser", graph=[("/front/scan_filtered", [SCAN])]) == (
        "/laser: no publisher in 30 s, so nothing of it is sent; sensor_msgs/msg/LaserScan "
        "is published on /front/scan_filtered: set this entry's topic to the one it should "
        "send")


def test_no_other_node_points_at_the_domain_and_rmw() -> None:
    said = reason("/scan", graph=[("/rosout", ["rcl_interfaces/msg/Log"])], other_nodes=0)
    assert said.endswith("the client sees no other node at all: are the robot's nodes in "
                         "ROS_DOMAIN_ID=77 with rmw_fastrtps_cpp (and the same "
                         "ROS_AUTOMATIC_DISCOVERY_RANGE / ROS_LOCALHOST_ONLY)?")


def test_nothing_like_it_asks_for_the_driver() -> None:
    assert reason("/imu/data", "sensor_msgs/msg/Imu").endswith("; is its driver running?")
