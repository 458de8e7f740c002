"""``busgate check-config``: every example config passes with a budget line per bus; a broken
one names its key path and exits 1; a port missing here is only a warning; an oversubscribed
bus is reported with what to change; the budget's figures match wire times worked out by hand;
it says where each bus would run (bus workers).
"""

from __future__ import annotations

import errno
import os
import socket
import subprocess
import threading
from pathlib import Path

import can
import pytest

from busgate.gateway.bus.can_options import unnamed_options
from busgate.gateway.cli import main
from busgate.gateway.service import placement as placement_module
from busgate.gateway.service.budget import bus_budget
from busgate.schemas import files
from busgate.schemas.config import CanBus, SerialBus, load_config
from tests.conftest import unused_loopback_port
from tests.gateway_process import BUSGATE

DEPLOY = Path(__file__).resolve().parent.parent / "deploy" / "config"
EXAMPLES = sorted(DEPLOY.glob("*.toml"))
BAUD = 921_600


def write(tmp_path: Path, devices: list[str], *, port: str | None = None, baud: int = BAUD,
          extra: str = "") -> Path:
    """A config of one serial bus, on a port missing here by default (a warning: the gateway
    would retry until it appears)."""
    port = port or str(tmp_path / "ttyUSB0")
    text = (f'[gateway]\nname = "gw"\n[[buses]]\nname = "uart0"\ntransport = "serial"\n'
            f'port = "{port}"\nbaudrate = {baud}\n{extra}')
    text += "".join(f"[[buses.devices]]\n{device}\n" for device in devices)
    path = tmp_path / "gateway.toml"
    path.write_text(text)
    return path


def la_buses(tmp_path: Path, *ids: tuple[int, ...]) -> str:
    """``[[buses]]`` tables of serial buses ``uart0``, ``uart1`` … on ports missing here, each
    with the LA actuators of its ``ids``."""
    return "".join(
        f'[[buses]]\nname = "uart{n}"\ntransport = "serial"\nport = "{tmp_path}/tty{n}"\n'
        f'baudrate = {BAUD}\n' + "".join(f"[[buses.devices]]\n{la(i)}\n" for i in bus_ids)
        for n, bus_ids in enumerate(ids)
    )


def la(device_id: int, **fields: object) -> str:
    pairs = {"name": f'"la{device_id}"', "kind": '"inspire_la"', "id": device_id, **fields}
    return "\n".join(f"{key} = {value}" for key, value in pairs.items())


def test_there_are_examples_for_every_family_and_a_robot() -> None:
    names = {path.stem for path in EXAMPLES}
    assert {"inspire_la", "ds_servo", "zlac706_can", "zlac706_rs232", "robot"} <= names


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda path: path.stem)
def test_every_example_config_passes_with_a_budget_line_per_bus(path, capsys) -> None:
    assert main(["check-config", str(path)]) == 0
    out = capsys.readouterr().out
    config = load_config(path)
    for bus in config.buses:
        (line,) = [text for text in out.splitlines() if text.startswith(f"bus {bus.name}:")]
        assert "reserved" in line and line.endswith(": fits")
    assert "oversubscribed" not in out


def test_the_first_line_names_the_bases_and_the_ros_2_face(tmp_path, capsys) -> None:
    """What the gateway serves beyond its buses, or that it serves none of it."""
    assert main(["check-config", str(DEPLOY / "inspire_la.toml")]) == 0
    assert ", no base, no ROS 2 face, " in capsys.readouterr().out.splitlines()[0]
    text = (DEPLOY / "robot.toml").read_text() + '[ros2]\ndomain_id = 7\ndistro = "humble"\n'
    path = tmp_path / "robot.toml"
    path.write_text(text)
    assert main(["check-config", str(path)]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert ", base base (wheels wheel_left, wheel_right), ROS 2 node busgate_robot1 in domain 7 " \
           "(humble), " in first


def test_a_broken_config_names_each_key_path_and_exits_1(tmp_path, capsys) -> None:
    path = write(tmp_path, [la(1, poll_hz='"fast"'), la(2, follow_period_ms=5)], baud=100)
    assert main(["check-config", str(path)]) == 1
    captured = capsys.readouterr()
    errors = captured.err.splitlines()
    assert any(e.startswith(f"error: {path}: buses[0].baudrate:") and "1200" in e
               for e in errors)
    assert any(e.startswith(f"error: {path}: buses[0].devices[0].poll_hz:") for e in errors)
    assert any(e.startswith(f"error: {path}: buses[0].devices[1].follow_period_ms:")
               and "10" in e for e in errors)
    assert captured.out == ""


def test_a_misspelt_key_is_one_error_naming_the_key_it_means(tmp_path, capsys) -> None:
    path = write(tmp_path, [la(1).replace("kind", "knd")])
    assert main(["check-config", str(path)]) == 1
    assert capsys.readouterr().err.splitlines() == [
        f"error: {path}: buses[0].devices[0]: unknown key `knd` (did you mean `kind`?)"]


def test_an_unreadable_or_non_toml_file_is_an_error(tmp_path, capsys) -> None:
    assert main(["check-config", str(tmp_path / "absent.toml")]) == 1
    bad = tmp_path / "bad.toml"
    bad.write_text("[gateway\n")
    assert main(["check-config", str(bad)]) == 1
    errors = capsys.readouterr().err.splitlines()
    assert "cannot read" in errors[0] and "not valid TOML" in errors[1]


def test_a_gateway_no_client_can_reach_is_a_warning(tmp_path, capsys) -> None:
    """No [zenoh] listen, connect, scouting or file: valid (a file may add endpoints), and
    the gateway is reached by nobody."""
    assert main(["check-config", str(write(tmp_path, [la(1)]))]) == 0
    assert "warning: zenoh: the gateway listens on no endpoint and connects to none: no " \
           "client can reach it" in capsys.readouterr().out
    reached = write(tmp_path, [la(1)], extra="").read_text() + \
        '[zenoh]\nlisten = ["tcp/127.0.0.1:7447"]\n'
    (tmp_path / "reached.toml").write_text(reached)
    assert main(["check-config", str(tmp_path / "reached.toml")]) == 0
    assert "no client can reach it" not in capsys.readouterr().out


def test_a_port_missing_on_this_host_is_a_warning_not_an_error(tmp_path, capsys) -> None:
    path = write(tmp_path, [la(1)], port=str(tmp_path / "usb-nothing"))
    assert main(["check-config", str(path)]) == 0
    out = capsys.readouterr().out
    assert f"warning: buses[0].port: {tmp_path / 'usb-nothing'} does not exist" in out


def test_a_max_effort_no_command_of_the_kind_sets_is_a_warning(tmp_path, capsys) -> None:
    table = '[buses.devices.joint]\nunit = "m"\nscale = 5.0e-6\nmax_effort = 20.0'
    path = write(tmp_path, [f"{la(1)}\n{table}"])
    assert main(["check-config", str(path)]) == 0
    assert ("warning: buses[0].devices[0].joint.max_effort: la1: 20 N is ignored"
            in capsys.readouterr().out)


def test_a_file_that_cannot_be_a_config_is_one_error_and_nothing_waits(tmp_path,
                                                                        capsys) -> None:
    """/dev/zero was read without end (2.7 GB), a named pipe nobody writes to waited on for
    ever, a 3000-deep array raised RecursionError, an integer of 4301 digits Python's
    ValueError (its limit on turning digits into an int)."""
    fifo = tmp_path / "pipe.toml"
    os.mkfifo(fifo)
    deep = tmp_path / "deep.toml"
    deep.write_text("x = " + "[" * 3000 + "]" * 3000)
    big = tmp_path / "big.toml"
    big.write_text("# " + "x" * 1024 * 1024)
    digits = tmp_path / "digits.toml"
    digits.write_text('[gateway]\nname = 1' + "0" * 4300 + "\n")
    for path in ("/dev/zero", fifo, deep, big, tmp_path, digits):
        assert main(["check-config", str(path)]) == 1
    assert capsys.readouterr().err.splitlines() == [
        "error: /dev/zero is over 1 MiB: not a config",
        f"error: {fifo} is empty: a config names its gateway and buses",  # read as empty
        f"error: {deep} is not valid TOML: nested too deeply",
        f"error: {big} is over 1 MiB: not a config",
        f"error: cannot read {tmp_path}: Is a directory",
        f"error: {digits}: a number of thousands of digits: not a config",
    ]


def test_a_config_through_a_pipe_is_read_as_a_file(tmp_path, capsys) -> None:
    """``busgate run --config <(envsubst < gw.toml)``: the shell hands a pipe's path."""
    source = write(tmp_path, [la(1)])
    reading, writing = os.pipe()
    os.write(writing, source.read_bytes())
    os.close(writing)
    try:
        assert main(["check-config", f"/dev/fd/{reading}"]) == 0
    finally:
        os.close(reading)
    assert capsys.readouterr().out.startswith(f"/dev/fd/{reading}: valid; gateway gw,")


@pytest.mark.parametrize("head", [False, True], ids=["nothing sent", "a config sent, never ended"])
def test_a_config_whose_writer_stalls_is_refused_and_nothing_waits_for_ever(
        tmp_path, capsys, monkeypatch, head) -> None:
    """``check-config <(sleep 40)`` and ``run --config <(cat gw.toml; sleep 40)`` waited until
    the writer ended (for ever, for a writer stuck for good). The wait for more is shortened
    here from ``STALL_S``'s 10 s."""
    monkeypatch.setattr(files, "STALL_S", 0.2)
    reading, writing = os.pipe()
    os.write(writing, write(tmp_path, [la(1)]).read_bytes() if head else b"")
    statuses: list[int] = []
    checking = threading.Thread(
        target=lambda: statuses.append(main(["check-config", f"/dev/fd/{reading}"])))
    checking.start()
    checking.join(5)
    stuck = checking.is_alive()
    os.close(writing)  # a wait for the writer's end ends with it
    checking.join()
    os.close(reading)
    assert not stuck and statuses == [1]
    assert capsys.readouterr().err.splitlines() == [
        f"error: /dev/fd/{reading}: nothing more came for 0.2 s: whatever writes it is stuck; "
        "give a file, or a pipe that ends"]


@pytest.mark.parametrize(("port", "what"), [
    ("a-file", "a regular file"), (".", "a directory"), ("loop", "a loop of symbolic links"),
    ("/dev/null", "a mem device, no tty")])  # a device file, but no serial port: run retried
def test_a_port_that_is_no_device_file_is_a_warning_and_run_refuses_it(tmp_path, capsys, port,
                                                                       what) -> None:
    (tmp_path / "a-file").write_text("")
    (tmp_path / "loop").symlink_to(tmp_path / "loop")
    path = write(tmp_path, [la(1)], port=str(tmp_path / port))
    assert main(["check-config", str(path)]) == 2  # valid, but run refuses it on this host
    captured = capsys.readouterr()
    assert (f"warning: buses[0].port: {tmp_path / port} is {what}: a serial port is a device "
            "file") in captured.out
    assert captured.err == (f"{path}: valid, but busgate run on this host refuses to start with "
                            "it (1 of the warnings above)\n")
    assert main(["run", "--config", str(path)]) == 2
    assert capsys.readouterr().err.startswith(f"busgate run: error: bus uart0: {tmp_path / port}"
                                              f" is {what}")


def test_a_can_interface_python_can_does_not_have_is_a_warning_and_run_refuses_it(
        tmp_path, capsys) -> None:
    """``busgate run`` retried it for ever, every 0.1–2 s, as if an adapter might appear."""
    path = tmp_path / "gateway.toml"
    path.write_text('[gateway]\nname = "gw"\n[[buses]]\nname = "can0"\ntransport = "can"\n'
                    'interface = "nosuch"\nchannel = "can0"\n[[buses.devices]]\n'
                    'name = "wheel"\nkind = "zlac706"\nid = 1\n')
    assert main(["check-config", str(path)]) == 2
    refusal = "python-can has no interface 'nosuch' on this host (it has "
    assert f"warning: buses[0].interface: {refusal}" in capsys.readouterr().out
    assert main(["run", "--config", str(path)]) == 2
    assert capsys.readouterr().err.startswith(f"busgate run: error: bus can0: {refusal}")


@pytest.mark.parametrize(("content", "warned"), [
    (None, "no such file"),
    ("{ listen: ", "line 1, column 11: expected array, boolean, null, number, object, or string"),
    ("{}", None),
], ids=["missing", "malformed", "fine"])
def test_a_zenoh_config_file_missing_here_or_malformed_is_a_warning(tmp_path, capsys, content,
                                                                    warned) -> None:
    """``busgate run`` refuses both at start, which check-config said nothing of."""
    zenoh_file = tmp_path / "zenoh.json5"
    if content is not None:
        zenoh_file.write_text(content)
    path = write(tmp_path, [la(1)])
    path.write_text(path.read_text().replace(
        "[[buses]]", f'[zenoh]\nconfig_file = "{zenoh_file}"\n[[buses]]', 1))
    assert main(["check-config", str(path)]) == (2 if warned else 0)
    out = capsys.readouterr().out
    expected = (f"warning: zenoh.config_file: {zenoh_file}: {warned}" if warned else None)
    assert [line for line in out.splitlines() if "zenoh.config_file" in line] == (
        [f"{expected}; busgate run refuses to start so"] if warned else [])


def test_a_listener_the_zenoh_files_links_leave_out_is_a_warning(tmp_path, capsys) -> None:
    """docs/running.md's config with the deploy file: check-config said valid, and run stopped
    with zenoh's 'Unsupported protocol: tcp'."""
    deploy = Path(__file__).parents[1] / "deploy" / "zenoh" / "busgate.json5"
    path = write(tmp_path, [la(1)])
    path.write_text(path.read_text().replace("[[buses]]", (
        f'[zenoh]\nlisten = ["tcp/127.0.0.1:7447"]\nconfig_file = "{deploy}"\n[[buses]]'), 1))
    assert main(["check-config", str(path)]) == 2
    [line] = [line for line in capsys.readouterr().out.splitlines() if "config_file" in line]
    assert line == (
        f"warning: zenoh.config_file: {deploy}: zenoh endpoint 'tcp/127.0.0.1:7447': the zenoh "
        "config file allows only tls links (transport/link/protocols); give a tls/ endpoint, "
        "or leave listen out to listen where the file says; busgate run refuses to start so")


def test_a_unix_socket_listener_at_a_file_is_a_warning_without_a_zenoh_file_too(
        tmp_path, capsys) -> None:
    """Warned of only under a ``config_file``: in ``listen`` alone, check-config said valid
    and ``busgate run`` refused to start. The file is left as it was."""
    victim = tmp_path / "victim.txt"
    victim.write_text("kept")
    path = write(tmp_path, [la(1)])
    path.write_text(path.read_text().replace(
        "[[buses]]", f'[zenoh]\nlisten = ["unixsock-stream/{victim}"]\n[[buses]]', 1))
    assert main(["check-config", str(path)]) == 2
    [line] = [line for line in capsys.readouterr().out.splitlines() if "zenoh:" in line]
    assert line == (
        f"warning: zenoh: cannot listen on unixsock-stream/{victim}: {victim} exists and is not "
        "a socket (zenoh would delete it to listen there): name a path of its own; busgate run "
        "refuses to start so")
    assert victim.read_text() == "kept"


@pytest.mark.parametrize(("listen", "config_file", "warned"), [
    ("tcp/0.0.0.0:7447", False, True),
    ("tcp/192.168.1.5:7447", False, True),
    ("tcp/127.0.0.1:7447", False, False),
    ("tcp/[::1]:7447", False, False),
    ("tcp/0.0.0.0:7447", True, False),  # the operator's own file: TLS, passwords, ACL
])
def test_a_listener_other_hosts_reach_with_nothing_to_keep_them_out_is_a_warning(
        tmp_path, capsys, listen, config_file, warned) -> None:
    zenoh_file = tmp_path / "zenoh.json5"
    zenoh_file.write_text("{}")
    path = write(tmp_path, [la(1)])
    table = f'[zenoh]\nlisten = ["{listen}"]\n' + (
        f'config_file = "{zenoh_file}"\n' if config_file else "")
    path.write_text(path.read_text().replace("[[buses]]", table + "[[buses]]", 1))
    assert main(["check-config", str(path)]) == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if "zenoh.listen" in line]
    assert lines == ([f"warning: zenoh.listen[0]: {listen} can be reached from other hosts, and "
                      "no zenoh.config_file gives it TLS, passwords or access control: whoever "
                      "reaches it moves every device "
                      "(docs/running.md#threat-model-who-can-move-what)"] if warned else [])


def checked(tmp_path: Path, capsys, tables: str, about: str) -> tuple[int, list[str]]:
    """check-config's status on an LA config with ``tables`` (TOML) before its buses, and
    the lines it printed that speak ``about`` something."""
    path = write(tmp_path, [la(1)])
    path.write_text(path.read_text().replace("[[buses]]", f"{tables}\n[[buses]]", 1))
    status = main(["check-config", str(path)])
    return status, [line for line in capsys.readouterr().out.splitlines() if about in line]


NO_TLS_FILES = ("needs a private key and a certificate, and it has no transport/link/tls/"
                "listen_private_key and no transport/link/tls/listen_certificate: set them in a "
                "zenoh config file (docs/running.md#access-control-passwords-and-tls)")


@pytest.mark.parametrize(("listen", "refused"), [
    ("tls/127.0.0.1:27801", f"a tls listener {NO_TLS_FILES}"),  # zenoh: Missing TLS private key
    ("quic/127.0.0.1:27801", f"a quic listener {NO_TLS_FILES}"),
    ("tcp/no-such-host.invalid:27801", "its host no-such-host.invalid does not resolve here "
                                       "(Name or service not known)"),
    ("tcp/" + "a" * 64 + ".invalid:27801", f"its host {'a' * 64}.invalid is no host name"),
    ("tcp/127.0.0.1:27801#iface=nonexistent0",
     "this host has no network interface 'nonexistent0' (iface)"),
    ("unixsock-stream/{tmp}/" + "s" * 100, "a Unix socket's path is at most 107 bytes: name a "
                                           "shorter one"),
    ("unixsock-stream//nonexistent/dir/gw.sock", "its folder /nonexistent/dir does not exist"),
    ("tls/127.0.0.1:27801#listen_private_key_file=/k.pem;listen_certificate_file=/c.pem", None),
    ("tcp/localhost:27801", None),
    ("tcp/127.0.0.1:27801#iface=lo", None),
    ("unixsock-stream/{tmp}/gw.sock", None),
], ids=["tls", "quic", "unresolved", "a label over 63", "no such iface", "long unix path",
        "no unix folder", "tls files on the endpoint", "localhost", "iface lo", "unix socket"])
def test_a_listener_zenoh_cannot_listen_on_here_is_a_warning_and_run_refuses_it(
        tmp_path, capsys, listen, refused) -> None:
    """check-config said valid (exit 0) and ``busgate run`` refused to start (exit 2)."""
    listen = listen.format(tmp=tmp_path)
    status, lines = checked(tmp_path, capsys, f'[zenoh]\nlisten = ["{listen}"]', "cannot listen")
    assert status == (2 if refused else 0)
    assert lines == ([f"warning: zenoh.listen[0]: cannot listen on {listen}: {refused}; busgate "
                      "run refuses to start so"] if refused else [])


@pytest.mark.parametrize("protocol", ["tcp", "udp"])
def test_a_listen_port_in_use_now_is_a_warning_as_a_locked_serial_port_is(
        tmp_path, capsys, protocol) -> None:
    """An audit: check-config said valid with no word and ``busgate run`` then refused to
    start ("it is in use"). A warning, exit 0: its holder may be the gateway being checked."""
    listen = f"{protocol}/127.0.0.1:{unused_loopback_port()}"
    tables = f'[zenoh]\nlisten = ["{listen}"]'
    sort = socket.SOCK_DGRAM if protocol == "udp" else socket.SOCK_STREAM
    with socket.socket(socket.AF_INET, sort) as holder:
        holder.bind(("127.0.0.1", int(listen.rpartition(":")[2])))
        if protocol == "tcp":
            holder.listen()
        assert checked(tmp_path, capsys, tables, "in use") == (0, [
            f"warning: zenoh.listen[0]: {listen} is in use on this host now (another busgate "
            "demo or run, or this gateway itself?): busgate run refuses to start while it is"])
    assert checked(tmp_path, capsys, tables, "in use") == (0, [])  # free again: no word


@pytest.mark.parametrize(("tls", "refused"), [
    ("", "a tls listener " + NO_TLS_FILES),
    ('listen_private_key: "/k.pem"', "a tls listener needs a private key and a certificate, "
     "and it has no transport/link/tls/listen_certificate: set them in a zenoh config file "
     "(docs/running.md#access-control-passwords-and-tls)"),
    ('listen_private_key: "/k.pem", listen_certificate: "/c.pem"', None),
], ids=["neither", "no certificate", "both"])
def test_a_tls_listener_is_refused_only_when_the_zenoh_file_gives_no_key_or_certificate(
        tmp_path, capsys, tls, refused) -> None:
    zenoh_file = tmp_path / "zenoh.json5"
    zenoh_file.write_text(f"{{ transport: {{ link: {{ tls: {{ {tls} }} }} }} }}")
    zenoh = f'[zenoh]\nlisten = ["tls/127.0.0.1:27801"]\nconfig_file = "{zenoh_file}"'
    status, lines = checked(tmp_path, capsys, zenoh, "cannot listen")
    assert status == (2 if refused else 0)
    assert lines == ([f"warning: zenoh.listen[0]: cannot listen on tls/127.0.0.1:27801: "
                      f"{refused}; busgate run refuses to start so"] if refused else [])


@pytest.mark.parametrize(("host", "refused"), [
    ("no-such-host.invalid", True), ("localhost", False), ("127.0.0.1", False)])
def test_a_metrics_host_that_does_not_resolve_is_a_warning_and_run_refuses_it(
        tmp_path, capsys, host, refused) -> None:
    status, lines = checked(tmp_path, capsys, f'[metrics]\nlisten = "{host}:27802"',
                            "metrics.listen")
    assert status == (2 if refused else 0)
    assert lines == ([f"warning: metrics.listen: {host}:27802: its host {host} does not resolve "
                      "here (Name or service not known); busgate run refuses to start so"]
                     if refused else [])


def test_a_recorder_folder_this_user_cannot_write_is_a_warning(tmp_path, capsys) -> None:
    (tmp_path / "a-file").write_text("")
    path = write(tmp_path, [la(1)])
    plain = path.read_text()
    for folder, warned in ((tmp_path / "a-file" / "incidents", True),
                           (tmp_path / "new" / "incidents", False)):
        path.write_text(plain.replace("[[buses]]", f'[recorder]\ndir = "{folder}"\n[[buses]]'))
        assert main(["check-config", str(path)]) == (2 if warned else 0)
        out = capsys.readouterr().out
        assert f"flight recorder (60 s) into {folder}" in out.splitlines()[0]
        assert (f"warning: recorder.dir: {tmp_path / 'a-file'} is not a directory; busgate run "
                "refuses to start so" in out) is warned
    assert not (tmp_path / "new").exists()  # checked, not made


def test_a_can_channel_missing_on_this_host_is_a_warning(tmp_path, capsys) -> None:
    path = tmp_path / "can.toml"
    path.write_text(
        '[gateway]\nname = "gw"\n[[buses]]\nname = "can9"\ntransport = "can"\n'
        'interface = "socketcan"\nchannel = "nosuchcan9"\n'
        '[[buses.devices]]\nname = "wheel"\nkind = "zlac706"\nid = 1\n'
    )
    assert main(["check-config", str(path)]) == 0
    assert "warning: buses[0].channel: nosuchcan9 does not exist" in capsys.readouterr().out


def can_config(tmp_path: Path, interface: str, options: str) -> Path:
    path = tmp_path / "can.toml"
    path.write_text(
        '[gateway]\nname = "gw"\n[[buses]]\nname = "can9"\ntransport = "can"\n'
        f'interface = "{interface}"\nchannel = "nosuchcan9"\noptions = {{ {options} }}\n'
        '[[buses.devices]]\nname = "wheel"\nkind = "zlac706"\nid = 1\n'
    )
    return path


def test_a_can_option_python_can_s_bus_names_no_parameter_for_is_a_warning(tmp_path,
                                                                          capsys) -> None:
    """A misspelt option passed in silence (the bus class's ``**kwargs`` takes it); the class's
    own parameters, ``can.BusABC``'s (``can_filters``) and ``can.Bus``'s are named."""
    path = can_config(tmp_path, "socketcan", "bogus_option = 1, receive_own_messages = false, "
                      "can_filters = [{ can_id = 1, can_mask = 0x7FF }], ignore_config = true")
    assert main(["check-config", str(path)]) == 0  # a warning only: it is passed on
    assert [line for line in capsys.readouterr().out.splitlines() if ".options." in line] == [
        "warning: buses[0].options.bogus_option: python-can's socketcan bus names no such "
        "parameter: check its spelling (it is passed on all the same)"]


def test_can_options_python_can_takes_by_no_parameter_name_are_not_warned_of() -> None:
    """A pcan bus's ``fd`` (read from its ``**kwargs``) and a bit timing's keys (python-can's
    own, for every interface) were told to be checked for their spelling."""
    options = ["fd", "data_bitrate", "f_clock", "brp", "tseg1", "tseg2", "sjw", "auto_reset",
               "bogus"]
    assert unnamed_options("pcan", options) == ["bogus"]


def test_can_options_of_a_bus_class_that_cannot_be_loaded_here_are_not_warned_of(
        tmp_path, capsys, monkeypatch) -> None:
    monkeypatch.setitem(can.interfaces.BACKENDS, "broken", ("busgate_no_such_module", "Bus"))
    monkeypatch.setattr(can.interfaces, "VALID_INTERFACES",
                        can.interfaces.VALID_INTERFACES | {"broken"})
    path = can_config(tmp_path, "broken", "bogus_option = 1")
    assert main(["check-config", str(path)]) == 0
    assert ".options." not in capsys.readouterr().out


@pytest.mark.parametrize("workers, line", [
    ("1", "workers on this host: none, every bus in the gateway's process"),
    ("2", "workers on this host: 0: uart0; 1: uart1, uart2; in the gateway's process: can0"),
])
def test_it_says_which_buses_each_worker_would_run(tmp_path, capsys, workers, line) -> None:
    serial = la_buses(tmp_path, (1, 2, 3), (4,), (5,))  # the busiest has a worker to itself
    path = tmp_path / "gateway.toml"
    path.write_text(
        f'[gateway]\nname = "gw"\nworkers = {workers}\n{serial}'
        '[[buses]]\nname = "can0"\ntransport = "can"\ninterface = "virtual"\nchannel = "c"\n'
        '[[buses.devices]]\nname = "wheel"\nkind = "zlac706"\nid = 1\n'  # stays: one process
    )
    assert main(["check-config", str(path)]) == 0
    assert capsys.readouterr().out.splitlines()[1] == line


def test_more_workers_than_the_cores_this_host_gives_are_a_warning(tmp_path, capsys,
                                                                  monkeypatch) -> None:
    path = tmp_path / "gateway.toml"
    path.write_text('[gateway]\nname = "gw"\nworkers = 2\n' + la_buses(tmp_path, (1,), (2,)))
    for cores, warned in ((2, False), (1, True)):
        monkeypatch.setattr(placement_module, "usable_cores", lambda c=cores: c)
        assert main(["check-config", str(path)]) == 0
        warning = ('warning: gateway.workers: 2 workers on this host\'s 1 core(s) take turns on '
                   'them; "auto" makes one a core')
        assert (warning in capsys.readouterr().out.splitlines()) is warned


def test_by_default_the_buses_go_to_a_worker_per_core(tmp_path, capsys) -> None:
    path = tmp_path / "gateway.toml"
    path.write_text('[gateway]\nname = "gw"\n' + la_buses(tmp_path, (1,), (2,)))
    assert main(["check-config", str(path)]) == 0
    cores = len(os.sched_getaffinity(0))
    assert capsys.readouterr().out.splitlines()[1] == (
        "workers on this host: 0: uart0; 1: uart1" if cores > 1
        else "workers on this host: none, every bus in the gateway's process")


def test_a_bus_with_a_bases_wheel_stays_in_the_gateways_process(tmp_path, capsys) -> None:
    wheels = "".join(
        f'[[buses.devices]]\nname = "wheel_{side}"\nkind = "zlac706"\nid = {i}\n'
        f'[buses.devices.joint]\nunit = "rad"\nscale = {sign}6.283185307179586e-4\n'
        for i, (side, sign) in enumerate((("l", ""), ("r", "-")), start=1)
    )
    path = tmp_path / "gateway.toml"
    path.write_text(
        '[gateway]\nname = "gw"\nworkers = 4\n'
        + la_buses(tmp_path, (1,), (2,))
        + '[[buses]]\nname = "can0"\ntransport = "can"\ninterface = "socketcan"\nchannel = "can0"\n'
        + wheels
        + '[[bases]]\nname = "base"\nkind = "diff_drive"\nleft = "wheel_l"\nright = "wheel_r"\n'
        'wheel_radius_m = 0.0825\ntrack_m = 0.4\nmax_linear_mps = 1.0\nmax_angular_radps = 2.0\n'
        'max_linear_accel = 0.8\nmax_angular_accel = 3.0\n'
    )
    assert main(["check-config", str(path)]) == 0
    assert capsys.readouterr().out.splitlines()[1] == (
        "workers on this host: 0: uart0; 1: uart1; in the gateway's process: can0"
    ), "four asked for, two buses a worker may run: two workers"


def test_an_oversubscribed_bus_is_reported_with_what_to_change(tmp_path, capsys) -> None:
    path = write(tmp_path, [la(i, poll_hz=100) for i in range(1, 16)])
    assert main(["check-config", str(path)]) == 0  # a warning: it runs, with stale telemetry
    out = capsys.readouterr().out
    assert "OVERSUBSCRIBED" in out
    (warning,) = [line for line in out.splitlines() if line.startswith("warning: buses[0]:")]
    assert "lower poll_hz" in warning and "reply_margin_ms" in warning


def test_a_poll_that_cannot_fit_between_follow_ticks_is_reported(tmp_path, capsys) -> None:
    # 15 DS servos in one SYNC WRITE at 9600 baud: the frame alone takes most of 10 ms.
    servos = [f'name = "s{i}"\nkind = "ds_servo"\nid = {i}\npoll_hz = 0.1\n'
              f"follow_period_ms = 10" for i in range(1, 16)]
    path = write(tmp_path, servos, baud=9600)
    assert main(["check-config", str(path)]) == 0
    out = capsys.readouterr().out
    assert "left between follow ticks every 10 ms" in out and "raise follow_period_ms" in out


def test_budget_figures_match_hand_computed_wire_times() -> None:
    # One LA at 921600 baud: a status poll is 8 bytes out and 22 back (manual 3.4); its
    # worst case adds the stated 800 µs reply time and the 2 ms margin, then the 1 ms gap.
    # A follow frame without reply (0x19) is 9 bytes. 10 bits a byte.
    bus = SerialBus.model_validate({
        "name": "uart0", "transport": "serial", "port": "/dev/null", "baudrate": BAUD,
        "devices": [{"name": "la1", "kind": "inspire_la", "id": 1, "poll_hz": 10,
                     "follow_period_ms": 20}],
    })
    budget = bus_budget(bus)
    bit = 10 / BAUD
    poll_wire, poll_worst = 30 * bit, 30 * bit + 0.0008 + 0.002
    assert budget.polling.frames == 10
    assert budget.polling.wire_s == pytest.approx(10 * poll_wire)
    assert budget.polling.reserved_s == pytest.approx(10 * (poll_worst + 0.001))
    assert budget.follow.frames == 50
    assert budget.follow.wire_s == pytest.approx(50 * 9 * bit)
    assert budget.follow.reserved_s == pytest.approx(50 * (9 * bit + 0.001))
    assert budget.heartbeats.frames == 0
    assert budget.wire_share == pytest.approx(10 * poll_wire + 50 * 9 * bit)
    assert budget.tick_free_s == pytest.approx(0.020 - 9 * bit - 0.001)
    assert budget.longest_poll_s == pytest.approx(poll_worst + 0.001)  # slack: the gap
    assert not budget.oversubscribed and budget.warnings() == []


def test_la_streams_of_one_period_share_one_frame_per_tick() -> None:
    devices = [{"name": f"la{i}", "kind": "inspire_la", "id": i, "follow_period_ms": 10}
               for i in range(1, 18)]
    bus = SerialBus.model_validate({"name": "uart0", "transport": "serial", "port": "/dev/null",
                                    "baudrate": BAUD, "devices": devices})
    # 17 actuators: one 0xF3 frame carries 15, a second one the other 2: two frames a tick.
    assert bus_budget(bus).follow.frames == pytest.approx(200)


def test_a_zlac706_position_joint_with_limits_has_its_budget_and_the_config_is_valid(
        tmp_path, capsys) -> None:
    """Its budget's sample is a speed, which a limited position joint refuses (where it
    would turn to is not known): an outside audit saw ``check-config`` and ``run`` stop on
    it, the only way to give a ZLAC706 position limits."""
    path = tmp_path / "gateway.toml"
    path.write_text(
        '[gateway]\nname = "gw"\n[[buses]]\nname = "can0"\ntransport = "can"\n'
        'interface = "socketcan"\nchannel = "can0"\n[[buses.devices]]\nname = "wp"\n'
        'kind = "zlac706"\nid = 1\n[buses.devices.joint]\ntype = "position"\nunit = "rad"\n'
        'scale = 6.283185307179586e-4\nmin = -3.0\nmax = 3.0\nmax_velocity = 5.0\n')
    assert main(["check-config", str(path)]) == 0, capsys.readouterr()
    assert capsys.readouterr().out.startswith(f"{path}: valid")


def test_can_heartbeats_count_against_the_bus() -> None:
    # Two 8-byte heartbeat frames per node and interval: 135 bits each at worst-case stuffing.
    bus = CanBus.model_validate({
        "name": "can0", "transport": "can", "interface": "socketcan", "channel": "can0",
        "devices": [{"name": f"w{i}", "kind": "zlac706", "id": i, "heartbeat_ms": 100}
                    for i in (1, 2)],
    })
    budget = bus_budget(bus)
    heartbeats = budget.heartbeats
    assert heartbeats.frames == pytest.approx(40)
    assert heartbeats.wire_s == pytest.approx(40 * 135 / 500_000) == heartbeats.reserved_s
    # Heartbeats are the telemetry: an online node is never polled, so nothing is reserved
    # for polls (its offline probes are not the steady state).
    assert budget.polling.frames == 0 and budget.longest_poll_s == 0


def test_a_reader_that_leaves_early_ends_it_quietly(tmp_path) -> None:
    """``busgate check-config robot.toml | head -1``: the rest of its lines find no reader;
    it ends, status 1, without a BrokenPipeError traceback on stderr."""
    config = write(tmp_path, [la(1), la(2), la(3)])
    reading, writing = os.pipe()
    os.close(reading)  # the reader is gone before the first line
    with os.fdopen(writing, "w") as nobody:
        done = subprocess.run([*BUSGATE, "check-config", str(config)], stdout=nobody,
                              stderr=subprocess.PIPE, text=True, timeout=60, check=False)
    assert (done.returncode, done.stderr) == (1, "")


def test_an_output_that_finds_no_room_is_told_in_one_line(tmp_path) -> None:
    """``busgate check-config robot.toml > /dev/full``: the write fails (no space), and that is
    said in one line, status 1, not a traceback (an audit: every command that prints)."""
    config = write(tmp_path, [la(1)])
    with open("/dev/full", "w") as full:
        done = subprocess.run([*BUSGATE, "check-config", str(config)], stdout=full,
                              stderr=subprocess.PIPE, text=True, timeout=60, check=False)
    assert (done.returncode, done.stderr) == (
        1, "busgate check-config: error: cannot write its output: No space left on device\n")


def test_a_bus_whose_commands_never_fit_between_follow_ticks_says_so() -> None:
    """Actuators streaming every 20 ms leave room for a status read with the default reply
    margin, none with 50 ms: their polls stop, and every command waits out the streams until
    it is answered busy. The warning says both."""
    def streaming(margin_ms: int) -> SerialBus:
        return SerialBus.model_validate({
            "name": "uart0", "transport": "serial", "port": "/dev/null", "baudrate": BAUD,
            "reply_margin_ms": margin_ms,
            "devices": [{"name": "la1", "kind": "inspire_la", "id": 1, "follow_period_ms": 20}],
        })
    assert bus_budget(streaming(2)).warnings() == []
    (warning,) = bus_budget(streaming(50)).warnings()
    assert "so polls stop while every device streams, and commands wait" in warning
    assert "each is answered busy after 2 s" in warning
    assert "reply_margin_ms (now 50 ms)" in warning


def test_commands_that_never_fit_between_ticks_are_warned_of_where_nothing_is_polled() -> None:
    """A ZLAC706 on CAN is never polled (its heartbeats are its telemetry): the room its
    ticks leave is judged for a command (its init's write) alone."""
    bus = CanBus.model_validate({
        "name": "can0", "transport": "can", "interface": "socketcan", "channel": "can0",
        "reply_margin_ms": 10, "bitrate": 125_000,
        "devices": [{"name": "w1", "kind": "zlac706", "id": 1, "heartbeat_ms": 20,
                     "follow_period_ms": 15}],
    })
    budget = bus_budget(bus)
    assert budget.longest_poll_s == 0 and budget.reserved_share < 1.0
    (warning,) = budget.warnings()
    assert warning.startswith("follow ticks every 15 ms leave at most ")
    assert "so commands wait while every device streams" in warning


def test_a_listen_probe_of_an_address_family_this_host_has_not_is_no_crash(monkeypatch) -> None:
    """A review: with IPv6 off, making the probe's socket raised EAFNOSUPPORT out of
    check-config; such a port is not in use."""
    from busgate.gateway.cli import check_config

    def no_ipv6(family, *args):
        raise OSError(errno.EAFNOSUPPORT, "Address family not supported by protocol")

    monkeypatch.setattr(check_config.socket, "socket", no_ipv6)
    assert check_config._in_use("tcp/[::1]:7447") is False
