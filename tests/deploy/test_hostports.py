"""The host-port check before ``fleetctl up``: real sockets hold the ports."""

from __future__ import annotations

import socket
from collections.abc import Iterator, Sequence

import pytest

from fleetctl.deploy import hostports
from fleetctl.deploy.dockercli import Completed
from fleetctl.deploy.hostports import PublishedPort
from fleetctl.errors import ConflictError


@pytest.fixture()
def taken_tcp() -> Iterator[int]:
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        yield listener.getsockname()[1]


@pytest.fixture()
def taken_udp() -> Iterator[int]:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        yield sock.getsockname()[1]


def test_published_ports_reads_fleetctls_short_form() -> None:
    document = {"services": {
        "server": {"ports": ["0.0.0.0:8443:8443/tcp", "[::1]:51820:51820/udp"]},
        "relay-1": {"ports": ["127.0.0.1:8444:9443"]},
        "robot-a": {},
    }}
    assert hostports.published_ports(document) == [
        PublishedPort("server", "0.0.0.0", 8443, "tcp"),
        PublishedPort("server", "[::1]", 51820, "udp"),
        PublishedPort("relay-1", "127.0.0.1", 8444, "tcp"),
    ]


def test_a_taken_tcp_port_names_the_port_and_the_setting(taken_tcp: int) -> None:
    port = PublishedPort("server", "127.0.0.1", taken_tcp, "tcp")
    with pytest.raises(ConflictError) as caught:
        hostports.require_free([port], set())
    message = str(caught.value)
    assert f"127.0.0.1:{taken_tcp}/tcp (server) is in use by another program" in message
    assert "--https-port" in message and "https_port in fleet.yaml" in message


def test_a_taken_udp_port_points_at_wireguard_port(taken_udp: int) -> None:
    port = PublishedPort("server", "127.0.0.1", taken_udp, "udp")
    with pytest.raises(ConflictError, match=rf"{taken_udp}/udp .*wireguard_port in fleet.yaml"):
        hostports.require_free([port], set())


def test_every_taken_port_is_named_at_once(taken_tcp: int, taken_udp: int) -> None:
    ports = [PublishedPort("server", "127.0.0.1", taken_tcp, "tcp"),
             PublishedPort("server", "127.0.0.1", taken_udp, "udp")]
    with pytest.raises(ConflictError) as caught:
        hostports.require_free(ports, set())
    assert f"{taken_tcp}/tcp" in str(caught.value) and f"{taken_udp}/udp" in str(caught.value)


def test_a_port_the_fleet_itself_publishes_is_not_in_the_way(taken_tcp: int) -> None:
    hostports.require_free([PublishedPort("server", "127.0.0.1", taken_tcp, "tcp")],
                           {(taken_tcp, "tcp")})


def test_free_ports_pass(taken_tcp: int) -> None:
    # The same number over UDP is free: the protocols are separate port spaces.
    hostports.require_free([PublishedPort("server", "127.0.0.1", taken_tcp, "udp")], set())


def test_an_address_that_is_not_this_hosts_is_named() -> None:
    # 192.0.2.0/24 is TEST-NET-1: never an address of this machine; bind fails locally.
    port = PublishedPort("server", "192.0.2.1", 8443, "tcp")
    with pytest.raises(ConflictError, match=r"not one of this host's .*--bind"):
        hostports.require_free([port], set())


def test_held_by_fleet_counts_the_containers_whose_compose_file_is_ours() -> None:
    calls: list[list[str]] = []

    def runner(argv: Sequence[str], stdin: bytes | None, capture: bool) -> Completed:
        calls.append(list(argv))
        out = ("/f/.compose/docker-compose.yml\t0.0.0.0:8443->8443/tcp, "
               "[::]:8443->8443/tcp, 0.0.0.0:51820->51820/udp\n"
               "/moved/.compose/docker-compose.yml\t127.0.0.1:9000->8443/tcp\n"
               "/other/.compose/docker-compose.yml\t0.0.0.0:7000->8443/tcp\n\n")
        return Completed(tuple(argv), 0, out, "")

    held = hostports.held_by_fleet(runner, "proj", lambda f: not f.startswith("/other/"))
    assert held == {(8443, "tcp"), (51820, "udp"), (9000, "tcp")}
    assert "label=com.docker.compose.project=proj" in calls[0]


def test_held_by_fleet_is_empty_when_docker_ps_fails() -> None:
    def runner(argv: Sequence[str], stdin: bytes | None, capture: bool) -> Completed:
        return Completed(tuple(argv), 1, "", "Cannot connect to the Docker daemon")

    assert hostports.held_by_fleet(runner, "p", lambda f: True) == set()
