"""``busgate demo`` as a new user runs it: a child process serving every simulated device on
a zenoh endpoint of its own; a real client session moves an actuator, sees every device of
every kind online (and, with ``--ros2``, their joint states in ROS 2), and the demo stops
cleanly on SIGTERM; a second demo on the same endpoint
is refused in one line."""

from __future__ import annotations

import json
import socket
import subprocess
import sys

import pytest
import zenoh

from busgate.codecs.ros2 import messages, rmw_zenoh
from busgate.errors import ConfigError
from busgate.gateway.cli import demo as demo_cli
from busgate.gateway.cli import main
from busgate.gateway.cli.demo import DEMO_BUSES, demo_config
from busgate.schemas.families import PROTOCOLS
from busgate.schemas.zenoh_session import session_config
from tests.gateway_process import TIMEOUT_S, DemoProcess

ALL_DEVICES = {"la1", "la2", "la3", "servo1", "servo2", "wheel", "wheel_l", "wheel_r",
               "drive"}


@pytest.fixture
def demo(free_port):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    process = DemoProcess(endpoint, "--dashboard-listen", "127.0.0.1:0", "--ros2")
    client = zenoh.open(session_config(connect=[endpoint]))
    try:
        yield process, client, endpoint
    finally:
        client.close()
        process.terminate()


def get(client: zenoh.Session, key: str, payload: str = "") -> dict:
    [reply] = [json.loads(r.ok.payload.to_bytes()) for r in client.get(key, payload=payload,
                                                                      timeout=5.0) if r.ok]
    return reply


def test_the_demo_serves_every_device_and_an_actuator_moves(wait_for, demo) -> None:
    process, client, endpoint = demo
    assert f"busgate send la1 '{{\"op\":\"move\",\"position\":1500}}' --connect {endpoint}" \
        in process.hints
    assert f"busgate watch demo --connect {endpoint}" in process.hints

    def online() -> set[str]:
        info = get(client, "busgate/demo/info")
        return {device["name"] for bus in info["buses"] for device in bus["devices"]
                if (device["state"] or {}).get("online")}

    wait_for(lambda: online() == ALL_DEVICES)
    protocols = {bus["protocol"] for bus in get(client, "busgate/demo/info")["buses"]}
    assert protocols == {"inspire_la", "ds_servo", "zlac706_can", "zlac706_rs232"}

    # --ros2: the demo is a ROS 2 node too, and says how to reach it
    assert ("ROS 2 (rmw_zenoh, domain 0): node /busgate_demo, joint states on "
            "/robot_joint_states, commands on /robot_joint_commands") in process.hints
    assert f'connect/endpoints=["{endpoint}"]' in process.hints
    joint_states: list[dict | None] = []
    ros_states = client.declare_subscriber(
        rmw_zenoh.data_key(0, "/robot_joint_states", "sensor_msgs/msg/JointState", "jazzy"),
        lambda sample: joint_states.append(
            messages.decode("sensor_msgs/msg/JointState", sample.payload.to_bytes())))
    wait_for(lambda: joint_states)
    ros_states.undeclare()
    assert joint_states[-1] is not None and len(joint_states[-1]["name"]) == len(ALL_DEVICES)

    positions: list[int] = []
    subscriber = client.declare_subscriber(
        "busgate/demo/dev/la1/state",
        lambda sample: positions.append(json.loads(sample.payload.to_bytes())["position"]))
    wait_for(lambda: positions)
    reply = get(client, "busgate/demo/dev/la1/cmd", '{"op":"move","position":1500}')
    assert reply["ok"] and reply["state"]["target"] == 1500
    wait_for(lambda: positions[-1] == 1500)
    assert positions[0] != 1500, "la1 started elsewhere and moved"
    subscriber.undeclare()
    assert process.terminate() == 0


def test_a_second_demo_on_the_same_endpoint_is_refused_in_one_line(demo) -> None:
    _, _, endpoint = demo
    second = subprocess.run([sys.executable, "-m", "busgate.gateway.cli", "demo", "--listen",
                             endpoint], capture_output=True, text=True, timeout=TIMEOUT_S)
    refusal = (f"busgate demo: error: zenoh cannot listen on {endpoint}: it is in use (another "
               "busgate demo or run? A second one runs beside it with --listen "
               "tcp/127.0.0.1:<another port>)")
    assert (second.returncode, second.stderr.splitlines(), second.stdout) == (2, [refusal], "")


def test_the_demo_config_is_validated_like_any_config() -> None:
    links = {bus.name: {"transport": "can", "interface": "virtual", "channel": bus.name}
             if PROTOCOLS[bus.protocol].can else
             {"transport": "serial", "port": f"/dev/{bus.name}", "baudrate": bus.rate}
             for bus in DEMO_BUSES}
    config = demo_config(links, listen="tcp/127.0.0.1:7447", metrics_listen="127.0.0.1:9108")
    assert config.metrics is not None and config.metrics.listen == "127.0.0.1:9108"
    for metrics_listen in ("9108", "127.0.0.1:0"):
        with pytest.raises(ConfigError) as refused:
            demo_config(links, listen="tcp/127.0.0.1:7447", metrics_listen=metrics_listen)
        assert refused.value.path == "metrics.listen"


@pytest.mark.parametrize("name", ["a/b", "", "x" * 65, "gw*"])
def test_a_gateway_name_that_is_none_is_refused_naming_the_flag(name, capsys) -> None:
    """Before anything starts; the config's refusal named its key (``gateway.name``) and
    pydantic's pattern."""
    with pytest.raises(SystemExit) as exited:
        main(["demo", f"--name={name}", "--no-dashboard"])
    assert exited.value.code == 2
    assert capsys.readouterr().err.endswith(
        f"argument --name: not a gateway name: {name[:80]!r} (1-64 of A-Z a-z 0-9 _ -)\n")


def test_a_demo_joining_a_router_names_its_gateway_in_the_send_it_suggests(monkeypatch) -> None:
    """A fleet's demos share device names: the hint's bare ``la1`` named every gateway's."""
    monkeypatch.setattr(demo_cli, "_program", lambda: "busgate")
    links = {bus.name: {"transport": "can", "interface": "virtual", "channel": bus.name,
                        "bitrate": 500_000}
             if PROTOCOLS[bus.protocol].can else
             {"transport": "serial", "port": f"/dev/{bus.name}", "baudrate": bus.rate}
             for bus in DEMO_BUSES}
    config = demo_config(links, listen="", connect="tcp/127.0.0.1:7448", name="gw2")
    assert ("busgate send gw2/la1 '{\"op\":\"move\",\"position\":1500}' --connect "
            "tcp/127.0.0.1:7448") in demo_cli._hints(config, links, None)


def test_a_dashboard_port_in_use_stops_the_demo_at_once_saying_what_else_to_do(free_port) -> None:
    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    try:
        port = taken.getsockname()[1]
        done = subprocess.run([sys.executable, "-m", "busgate.gateway.cli", "demo", "--listen",
                               f"tcp/127.0.0.1:{free_port()}", "--dashboard-listen",
                               f"127.0.0.1:{port}"], capture_output=True, text=True,
                              timeout=TIMEOUT_S)
    finally:
        taken.close()
    assert done.returncode == 2 and done.stdout == "", done
    assert done.stderr.splitlines() == [  # at once: no gateway came up first
        f"busgate demo: error: the dashboard cannot listen on 127.0.0.1:{port}: Address already "
        "in use (another busgate demo? A second one runs beside it with --listen "
        "tcp/127.0.0.1:<another port> --dashboard-listen 127.0.0.1:0, or --no-dashboard)"]


def test_the_hints_name_the_busgate_started_by_its_absolute_path(monkeypatch, tmp_path) -> None:
    """``.venv/bin/busgate demo`` (the README's) prints hints that work in a second terminal,
    which opens in another directory; a ``busgate`` that PATH finds is named plainly."""
    program = tmp_path / ".venv" / "bin" / "busgate"
    program.parent.mkdir(parents=True)
    program.write_text("#!/bin/sh\n")
    program.chmod(0o755)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", [".venv/bin/busgate", "demo"])
    monkeypatch.setenv("PATH", str(tmp_path / "elsewhere"))
    assert demo_cli._program() == str(program)
    monkeypatch.setenv("PATH", str(program.parent))
    assert demo_cli._program() == "busgate"


@pytest.mark.parametrize("where", ["proc", "a directory"])
def test_a_wire_record_that_cannot_be_written_is_refused_in_one_line(
    where, tmp_path, free_port
) -> None:
    """``--record /proc`` (a folder that takes no files) and a directory named as a bus's
    record are refused naming the file, the simulators started before it stopped: the demo
    exits at once (one left running would keep it from exiting)."""
    if where == "proc":
        folder, record = "/proc", "/proc/uart0.jsonl"  # the first bus's
    else:
        (tmp_path / "can0.jsonl").mkdir()  # a later bus's: uart0's and uart1's simulators run
        folder, record = str(tmp_path), str(tmp_path / "can0.jsonl")
    done = subprocess.run([sys.executable, "-m", "busgate.gateway.cli", "demo", "--listen",
                           f"tcp/127.0.0.1:{free_port()}", "--no-dashboard", "--record", folder],
                          capture_output=True, text=True, timeout=TIMEOUT_S)
    reason = "No such file or directory" if where == "proc" else "Is a directory"
    assert (done.returncode, done.stdout, done.stderr.splitlines()) == (
        2, "", [f"busgate demo: error: cannot write the wire record {record}: {reason}"])


def test_a_dashboard_on_zenohs_own_port_is_refused_before_anything_starts(free_port) -> None:
    """Its socket is bound, not listening, until it serves: zenoh took the same port, and
    the dashboard failed after the gateway came up, with two tracebacks (an audit)."""
    port = free_port()
    done = subprocess.run([sys.executable, "-m", "busgate.gateway.cli", "demo", "--listen",
                           f"tcp/127.0.0.1:{port}", "--dashboard-listen", f"127.0.0.1:{port}"],
                          capture_output=True, text=True, timeout=TIMEOUT_S)
    assert (done.returncode, done.stdout, done.stderr.splitlines()) == (2, "", [
        f"busgate demo: error: --dashboard-listen 127.0.0.1:{port} is the port zenoh listens on "
        f"(tcp/127.0.0.1:{port}): give the dashboard another"])


@pytest.mark.parametrize("dashboard", [["--dashboard-listen", "127.0.0.1:8081"],
                                       ["--dashboard-allow-host", "robot.local"]])
def test_no_dashboard_with_the_dashboards_options_is_refused(capsys, dashboard) -> None:
    """They were ignored in silence (an audit)."""
    assert main(["demo", "--listen", "tcp/127.0.0.1:1", "--no-dashboard", *dashboard]) == 2
    assert capsys.readouterr().err == (
        "busgate demo: error: --no-dashboard serves none: --dashboard-listen and "
        "--dashboard-allow-host would be ignored; give one or the other\n")


def test_listen_and_connect_together_are_refused(capsys) -> None:
    """A demo that joins a router listens on nothing: --listen was ignored in silence."""
    with pytest.raises(SystemExit) as exited:
        main(["demo", "--listen", "tcp/127.0.0.1:1", "--connect", "tcp/127.0.0.1:2"])
    assert exited.value.code == 2
    assert capsys.readouterr().err.endswith(
        "busgate demo: error: argument --connect: not allowed with argument --listen\n")
