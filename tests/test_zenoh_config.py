"""``session_config``: busgate's few zenoh settings laid over zenoh's, with safe defaults."""

from __future__ import annotations

import json

import pytest

from busgate.client.zenoh_config import session_config


def setting(config, key: str):
    return json.loads(config.get_json(key))


def test_without_listen_or_a_file_a_session_listens_nowhere() -> None:
    """zenoh's default for a peer is tcp/[::]:<any port>: every interface, no password."""
    config = session_config(mode="peer", connect=["tcp/127.0.0.1:7447"])
    assert setting(config, "listen/endpoints") == []
    assert setting(config, "scouting/multicast/enabled") is False


def test_listen_and_connect_are_taken_as_given() -> None:
    config = session_config(mode="router", listen=["tcp/127.0.0.1:7448"],
                            connect=["tcp/127.0.0.1:7449"])
    assert setting(config, "mode") == "router"
    assert setting(config, "listen/endpoints") == ["tcp/127.0.0.1:7448"]
    assert setting(config, "connect/endpoints") == ["tcp/127.0.0.1:7449"]


def test_a_files_endpoints_survive_an_empty_listen(tmp_path) -> None:
    file = tmp_path / "zenoh.json5"
    file.write_text('{ listen: { endpoints: ["tcp/127.0.0.1:7450"] } }')
    config = session_config(mode="peer", config_file=file)
    assert setting(config, "listen/endpoints") == ["tcp/127.0.0.1:7450"]


def test_an_unknown_mode_is_refused() -> None:
    with pytest.raises(ValueError, match="mode"):
        session_config(mode="bridge")
