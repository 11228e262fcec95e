"""Connecting to a Ray cluster: an address where nothing listens fails at once with a
SlamError that says what to do (Ray itself retries for minutes)."""

import socket
import time

import pytest

from slam.errors import SlamError
from slam.tools.ray_session import check_reachable, host_port


def test_host_port_of_cluster_addresses():
    assert host_port("10.0.0.5:6379") == ("10.0.0.5", 6379)
    assert host_port("ray://head.example:10001") == ("head.example", 10001)
    assert host_port("[::1]:6379") == ("::1", 6379)
    assert host_port("auto") is None and host_port("local") is None


def test_an_address_where_nothing_listens_fails_at_once():
    with socket.socket() as s:  # a port that was free a moment ago, now closed
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.monotonic()
    with pytest.raises(SlamError, match=f"nothing answers .*127.0.0.1:{port}.*ray start --head"):
        check_reachable(f"127.0.0.1:{port}", "run without --ray")
    assert time.monotonic() - t0 < 10


def test_a_listening_address_passes():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        check_reachable(f"127.0.0.1:{s.getsockname()[1]}", "run without --ray")
        check_reachable("auto", "run without --ray")  # Ray resolves it: not checked here
