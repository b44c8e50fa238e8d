"""A local Ray of the job's own, on loopback unless the user asks for another interface.

Ray's processes (GCS, raylet, workers, the dashboard and runtime-env agents, the
metrics exporter) serve unauthenticated RPC and HTTP: its job agent runs any command it
is sent. On Linux a plain ``ray.init()`` binds them to every interface (``::``,
``0.0.0.0``) or to the host's address, so anyone on the network could run code as the
user. A local ``mine submit`` therefore starts Ray single-host on 127.0.0.1: the node
address is loopback (``_node_ip_address``), the dashboard is off and its host is
loopback, and Ray's single-host mode (``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0``, its
default on Windows and macOS) keeps Ray from swapping 127.0.0.1 for the host's address
and binds every server to the node address. ``run.bind_host`` (``mine submit --host``)
names another interface for a user who wants one; ``0.0.0.0`` means Ray's own choice.
Such a bind is said out loud: ``exposure_line`` is the one line ``mine submit`` prints on
standard error, naming the interface and where the setting came from (``bind_origin``).

The mode is read when ``ray`` is first imported, so it is set before that; a process
that imported Ray earlier in cluster mode gets a ConfigError rather than open ports.
Joining a cluster (``--address``) uses the cluster's own settings (infra/README.md).
"""

from __future__ import annotations

import ipaddress
import os
from typing import Any

from mining.config import parse_override
from mining.errors import ConfigError

LOOPBACK = "127.0.0.1"  # ours: the default of run.bind_host
SINGLE_HOST_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"  # Ray: "0" = no multi-node cluster, localhost addresses kept
ANY_INTERFACE = "0.0.0.0"


def _is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        raise ConfigError(f"run.bind_host must be an IP address (e.g. {LOOPBACK}), got {host!r}") from None


def bind_origin(host_flag: str | None, sets: list[str], config: str | None) -> str:
    """Where ``run.bind_host`` came from, in the words of the command line: the ``--host``
    flag, else the last ``--set`` that names it (``run.bind_host=…`` or ``run={bind_host=…}``),
    else the job file, else the default."""
    if host_flag:
        return "the --host flag"
    named = [s for s in sets if "bind_host" in (parse_override(s).get("run") or {})]
    if named:
        return f"--set {named[-1]}"
    return f"the job file {config}" if config else "the default run.bind_host"


def exposure_line(bind_host: str, origin: str) -> str | None:
    """The one warning of a bind beyond loopback (None on loopback): the interface, where
    the setting came from, and what it exposes."""
    if _is_loopback(bind_host):
        return None
    where = "every interface" if ipaddress.ip_address(bind_host).is_unspecified else "a non-loopback interface"
    return (f"mine submit: Ray will listen on {bind_host} ({where}; run.bind_host from {origin}): Ray's ports run "
            "code unauthenticated for anyone who can reach them; use it only on a network you trust")


def prepare_local_ray(bind_host: str = LOOPBACK) -> bool:
    """Check ``bind_host`` and, when it is loopback, put Ray in single-host mode (before
    ``import ray`` where possible); returns whether it is loopback."""
    loopback = _is_loopback(bind_host)
    if loopback:
        os.environ[SINGLE_HOST_ENV] = "0"  # inherited by every Ray process started from here
    return loopback


def init_local_ray(num_cpus: int | None, bind_host: str = LOOPBACK, **init_kwargs: Any) -> str:
    """Start a local Ray (``ray.init(address="local")``) bound to ``bind_host``; returns the node address.

    ``init_kwargs`` go to ``ray.init`` (e.g. ``runtime_env``). Raises ConfigError when
    ``bind_host`` is loopback and Ray would not stay on it.
    """
    loopback = prepare_local_ray(bind_host)
    import ray

    kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False}
    if bind_host != ANY_INTERFACE:
        kwargs |= {"_node_ip_address": bind_host, "dashboard_host": bind_host}
    ray.init(address="local", num_cpus=num_cpus, **(kwargs | init_kwargs))
    node = ray.util.get_node_ip_address()
    if loopback and not _is_loopback(node):
        ray.shutdown()
        raise ConfigError(f"Ray would listen on {node}, not {bind_host}: this process imported Ray before "
                          f"{SINGLE_HOST_ENV}=0 was set; set it in the environment, or run `mine submit` "
                          "in a process of its own")
    return node
