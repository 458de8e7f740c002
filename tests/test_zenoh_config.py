"""``session_config`` (``busgate.schemas.zenoh_session``): busgate's few zenoh settings laid
over zenoh's, with safe defaults."""

from __future__ import annotations

import json
import re
import socket

import pytest

from busgate.schemas.zenoh_session import session_config


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


def test_an_endpoint_of_a_protocol_the_files_links_leave_out_is_refused(tmp_path) -> None:
    file = tmp_path / "zenoh.json5"
    file.write_text('{ transport: { link: { protocols: ["tls"] } } }')
    with pytest.raises(ValueError, match=re.escape(
            "'tcp/127.0.0.1:7451': the zenoh config file allows only tls links")):
        session_config(mode="peer", listen=["tcp/127.0.0.1:7451"], config_file=file)
    with pytest.raises(ValueError, match=re.escape("'tcp/127.0.0.1:7452'")):
        session_config(mode="client", connect=["tcp/127.0.0.1:7452"], config_file=file)
    config = session_config(mode="peer", listen=["tls/127.0.0.1:7451"], config_file=file)
    assert setting(config, "listen/endpoints") == ["tls/127.0.0.1:7451"]


def test_a_unix_socket_is_never_taken_from_a_file_or_a_process(tmp_path) -> None:
    """zenoh deletes what is at a listener's path, and its ``.lock`` beside it when it stops:
    a file, a socket something listens on, and a lock that is not zenoh's are refused, left
    as they were; a socket left behind by a process that ended is taken."""
    keep = tmp_path / "keep.conf"
    keep.write_text("precious")
    with pytest.raises(ValueError, match=r"keep\.conf exists and is not a socket"):
        session_config(mode="router", listen=[f"unixsock-stream/{keep}"])
    file = tmp_path / "zenoh.json5"  # the same from a config file's endpoints
    file.write_text(json.dumps({"listen": {"endpoints": [f"unixsock-stream/{keep}#x=1"]}}))
    with pytest.raises(ValueError, match=r"keep\.conf exists and is not a socket"):
        session_config(mode="peer", config_file=file)
    assert keep.read_text() == "precious"

    path = tmp_path / "gw.sock"
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as listening:
        listening.bind(str(path))
        listening.listen()
        with pytest.raises(ValueError, match="a process listens on"):
            session_config(mode="router", listen=[f"unixsock-stream/{path}"])
    # closed: a socket nobody listens on, as a killed process leaves it, with zenoh's lock
    (tmp_path / "gw.sock.lock").touch()
    config = session_config(mode="router", listen=[f"unixsock-stream/{path}"])
    assert setting(config, "listen/endpoints") == [f"unixsock-stream/{path}"]
    (tmp_path / "gw.sock.lock").write_text("not zenoh's")
    with pytest.raises(ValueError, match=r"gw\.sock\.lock is not zenoh.s lock"):
        session_config(mode="router", listen=[f"unixsock-stream/{path}"])


def test_only_the_sessions_own_modes_endpoints_are_checked(tmp_path) -> None:
    """A config file a router shares with its clients (TLS, passwords) lists its endpoints by
    mode: a client does not listen on the router's socket, so it is not refused for it."""
    path = tmp_path / "router.sock"
    file = tmp_path / "shared.json5"
    file.write_text(json.dumps({"listen": {"endpoints": {
        "router": [f"unixsock-stream/{path}"], "peer": [], "client": []}}}))
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as router:
        router.bind(str(path))
        router.listen()
        session_config(mode="client", config_file=file)  # taken
        with pytest.raises(ValueError, match="a process listens on"):
            session_config(mode="router", config_file=file)


def test_an_unknown_mode_is_refused() -> None:
    with pytest.raises(ValueError, match="mode"):
        session_config(mode="bridge")


def test_scripts_of_earlier_releases_still_import_the_settings_from_the_client() -> None:
    """They moved below the daemon and the SDK (``busgate.schemas.zenoh_session``); the
    SDK's old module names the same functions."""
    from busgate.client import zenoh_config
    from busgate.schemas import zenoh_session

    for name in zenoh_config.__all__:
        assert getattr(zenoh_config, name) is getattr(zenoh_session, name)
    assert set(zenoh_config.__all__) >= {"session_config", "zenoh_reason", "session_refusal"}
