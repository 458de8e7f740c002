"""Building a ``zenoh.Config`` from busgate's few zenoh settings.

One of the three modules allowed to import ``zenoh``: the bridge (``bridge.py``, the daemon's
session), the client tools (``client_cli.py``, ``busgate send`` and ``busgate watch``) and this
helper, which both use so that a gateway and a client read the same settings the same way.
Everything else in busgate stays free of zenoh.

Rules: a full zenoh config file (ACL, TLS, auth …) is the base and busgate's settings are laid
over it. ``mode`` and multicast scouting are always set (multicast off unless asked for: a
service talks to the endpoints it is given, never to whoever answers on the LAN). ``listen``
and ``connect`` are set when given, so endpoints written in the file survive an empty list;
with neither ``listen`` nor a file, a session listens nowhere (zenoh's default would be every
interface, with no authentication): it reaches others only through ``connect``.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import zenoh

MODES = ("peer", "client", "router")


def session_config(
    *,
    mode: str = "peer",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    multicast_scouting: bool = False,
    config_file: str | Path | None = None,
) -> zenoh.Config:
    """A zenoh config: ``config_file`` (if any) underneath, the given settings on top.

    Raises ``ValueError`` for an unknown mode; zenoh itself rejects a malformed file or endpoint.
    """
    if mode not in MODES:
        raise ValueError(f"zenoh mode must be one of {', '.join(MODES)}, not {mode!r}")
    config = zenoh.Config.from_file(str(config_file)) if config_file else zenoh.Config()
    config.insert_json5("mode", json.dumps(mode))
    config.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast_scouting)))
    if listen or not config_file:  # zenoh's own default listens on every interface
        config.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return config
