"""A local Ray of the job's own, on loopback unless the user asks for another interface.

Ray's processes (GCS, raylet, workers, the dashboard and runtime-env agents, the
metrics exporter) serve unauthenticated RPC and HTTP: its job agent runs any command it
is sent. On Linux Ray binds them to every interface (``::``, ``0.0.0.0``) or to the
host's address whenever its node address is not 127.0.0.1, so anyone on the network could run code as the
user. A local ``mine submit`` therefore starts Ray single-host on 127.0.0.1: the node
address is loopback (``_node_ip_address``), the dashboard is off and its host is
loopback, and Ray's single-host mode (``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0``, its
default on Windows and macOS) keeps Ray from swapping 127.0.0.1 for the host's address
and binds every server to the node address.

``run.bind_host`` (``mine submit --host``) can only be what Ray honours. Measured with Ray
2.58 (listening sockets of every process of the session, from /proc/net/tcp{,6}): a node
address of 127.0.0.1 keeps every port on 127.0.0.1 (and ::1 becomes 127.0.0.1), but any
other address — 127.0.0.2, a LAN address, ``::`` — makes the GCS, the raylet, the driver
and the workers listen on ``::``, every interface. So the rule (``check_bind_host``):
127.0.0.1, or every interface asked for by name (``0.0.0.0`` or ``::``), which
``exposure_line`` announces on standard error naming where the setting came from
(``bind_origin``); any other address is refused before anything is written, since Ray
would not keep to it.

The mode is read when ``ray`` is first imported, so it is set before that; a process
that imported Ray earlier in cluster mode gets a ConfigError rather than open ports.
Joining a cluster (``--address``) uses the cluster's own settings (infra/README.md).
"""

from __future__ import annotations

import ipaddress
import os
import sys
from typing import Any

from mining.config import parse_override
from mining.errors import ConfigError

LOOPBACK = "127.0.0.1"  # ours: the default of run.bind_host
SINGLE_HOST_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"  # Ray: "0" = no multi-node cluster, localhost addresses kept
EVERY_INTERFACE = ("0.0.0.0", "::")  # the two ways to ask for every interface by name


def check_bind_host(host: str, origin: str = "the job config") -> bool:
    """Whether ``host`` asks for every interface (False: 127.0.0.1); ConfigError, naming
    ``origin``, for any address Ray would not keep to (the module's docstring)."""
    if host == LOOPBACK or host in EVERY_INTERFACE:
        return host != LOOPBACK
    try:
        ip = ipaddress.ip_address(host)
        why = (f"Ray would listen on {LOOPBACK} instead" if ip == ipaddress.ip_address("::1")
               else "Ray would listen on every interface for it, not on it alone")
    except ValueError:
        why = "it is not an IP address"
    raise ConfigError(f"run.bind_host {host!r} (from {origin}): {why}; Ray keeps to {LOOPBACK} only, so use "
                      f"{LOOPBACK}, or ask for every interface by name with 0.0.0.0") from None


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
    """The one warning of a bind to every interface (None on 127.0.0.1): that it is every
    interface, where the setting came from, and what it exposes."""
    if not check_bind_host(bind_host, origin):
        return None
    return (f"mine submit: Ray will listen on every interface (run.bind_host {bind_host} from {origin}): Ray's "
            "ports run code unauthenticated for anyone who can reach them; use it only on a network you trust")


def prepare_local_ray(bind_host: str = LOOPBACK, origin: str = "the job config") -> bool:
    """Check ``bind_host`` (``check_bind_host``) and, on 127.0.0.1, put Ray in single-host mode
    (before ``import ray`` where possible); returns whether it is 127.0.0.1."""
    loopback = not check_bind_host(bind_host, origin)
    if loopback and os.environ.get(SINGLE_HOST_ENV) != "0":
        if "ray" in sys.modules:  # Ray read the mode at import: say so on every host, not only a networked one
            raise ConfigError(f"Ray was imported before {SINGLE_HOST_ENV}=0 was set, so it would not keep to "
                              f"{bind_host}; set it in the environment, or run `mine submit` in a process of its own")
        os.environ[SINGLE_HOST_ENV] = "0"  # inherited by every Ray process started from here
    return loopback


def init_local_ray(num_cpus: int | None, bind_host: str = LOOPBACK, **init_kwargs: Any) -> str:
    """Start a local Ray (``ray.init(address="local")``) bound to ``bind_host``; returns the node address.

    ``init_kwargs`` go to ``ray.init`` (e.g. ``runtime_env``). Raises ConfigError when
    ``bind_host`` is loopback and Ray would not stay on it.
    """
    loopback = prepare_local_ray(bind_host)
    import ray

    # The dashboard is off; were it turned on, it stays on loopback either way.
    kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False, "dashboard_host": LOOPBACK}
    if loopback:  # else Ray's own choice: the host's address as the node's, every port on `::`
        kwargs["_node_ip_address"] = LOOPBACK
    ray.init(address="local", num_cpus=num_cpus, **(kwargs | init_kwargs))
    node = ray.util.get_node_ip_address()
    if loopback and node != LOOPBACK:
        ray.shutdown()
        raise ConfigError(f"Ray would listen on {node}, not {bind_host}: this process imported Ray before "
                          f"{SINGLE_HOST_ENV}=0 was set; set it in the environment, or run `mine submit` "
                          "in a process of its own")
    return node
