"""Ray for the commands that spread work over processes (``slam bench --ray``, ``slam run
--workers``): the package imported with a clear error where it is missing, and a session on a
local instance or an existing cluster, shut down after use if it was started here."""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from slam.errors import SlamError

log = logging.getLogger(__name__)


def import_ray(without: str = "run without --ray for local processes") -> Any:
    """The ``ray`` module; a :class:`SlamError` saying how to install it (or do ``without``)
    where it is missing."""
    try:
        import ray
    except ImportError as exc:
        raise SlamError(
            "--ray needs the Ray package, which is not installed: pip install 'rgbd-slam[ray]' "
            f"(or pip install ray), or {without}"
        ) from exc
    return ray


@contextmanager
def ray_session(address: str | None, cpus: int, local_hint: str) -> Iterator[Any]:
    """Ray, initialised on a local instance of ``cpus`` CPUs (``address`` None) or on the
    cluster at ``address``, unless this process already initialised it; shut down on exit if
    started here. ``local_hint``: how the user gets a local instance instead (error messages)."""
    ray = import_ray()
    started = not ray.is_initialized()
    if started:
        if address is None:
            ray.init(num_cpus=cpus, include_dashboard=False, log_to_driver=False)
        else:
            check_reachable(address, local_hint)
            try:
                ray.init(address=address, log_to_driver=False)
            except (ConnectionError, RuntimeError, ValueError) as exc:
                raise SlamError(
                    f"cannot connect to the Ray cluster at {address!r}: {str(exc).rstrip('.')}; "
                    f"start one with `ray start --head`, or {local_hint}{_auth_hint()}"
                ) from exc
    log.info("Ray: %s", ray.cluster_resources())
    try:
        yield ray
    finally:
        if started:
            ray.shutdown()


def host_port(address: str) -> tuple[str, int] | None:
    """``(host, port)`` of a cluster address (``host:port`` or ``ray://host:port``); None for
    what names no port (``auto``, ``local``: Ray resolves those itself)."""
    rest = address.removeprefix("ray://")
    host, sep, port = rest.rpartition(":")
    if not sep or not host or not port.isdigit():
        return None
    return host.strip("[]"), int(port)


def check_reachable(address: str, local_hint: str, timeout_s: float = 5.0) -> None:
    """Fail at once, with a :class:`SlamError`, when nothing accepts a TCP connection at the
    cluster address (Ray itself retries for minutes before giving up)."""
    hp = host_port(address)
    if hp is None:
        return
    try:
        with socket.create_connection(hp, timeout=timeout_s):
            pass
    except OSError as exc:
        raise SlamError(
            f"nothing answers at the Ray cluster address {address!r} ({exc}); check the host "
            f"and port (`ray status` on the head node prints them), start a cluster with "
            f"`ray start --head`, or {local_hint}"
        ) from exc


def _auth_hint() -> str:
    if os.environ.get("RAY_AUTH_MODE"):
        return ""
    return (
        ". If the cluster uses token authentication (`ray start --head` enables it from Ray "
        "2.59), set RAY_AUTH_MODE=token in this shell; the token is read from RAY_AUTH_TOKEN or "
        "~/.ray/auth_token"
    )
