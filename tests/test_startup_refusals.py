"""What ``busgate run``, ``check-config`` and ``demo`` refuse at start-up, and how: one line
naming what is wrong and what to do, no traceback. Real parts throughout: the CLI as a child
process, the simulator's ptys, pyserial's exclusive open (a ``flock``) for a held port, a plain
listening socket for an endpoint in use, file modes for a port this user may not open."""

from __future__ import annotations

import contextlib
import ctypes
import errno
import os
import socket
import tempfile
from collections.abc import Iterator
from importlib import metadata
from pathlib import Path

import pytest
import serial

from busgate.codecs import inspire_la as la
from busgate.errors import BusUnavailableError
from busgate.gateway.bus import port_access
from busgate.gateway.bus.port_access import UDEV_RULES, describe_open_error
from busgate.gateway.cli import main
from busgate.gateway.service.assembly import build_bus
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.schemas.config import SerialBus
from tests.gateway_process import GatewayProcess, run_busgate, serial_bus, write_config

ROOT = Path(__file__).resolve().parent.parent
BAUD = 921_600
IN_USE = "it is in use (another busgate demo or run?)"


@pytest.fixture
def simulator() -> Iterator[SerialSimulator]:
    simulator = SerialSimulator(la, [InspireLaDevice(1)], baudrate=BAUD).start()
    try:
        yield simulator
    finally:
        simulator.stop()


@pytest.fixture
def endpoint(free_port) -> str:
    return f"tcp/127.0.0.1:{free_port()}"


# -- the config -----------------------------------------------------------------------------


@pytest.mark.parametrize("through_a_link", [False, True], ids=["same name", "symlink"])
def test_two_buses_on_one_device_file_are_refused_naming_both(through_a_link, tmp_path,
                                                               endpoint, capsys) -> None:
    device = tmp_path / "ttyUSB0"
    device.touch()
    other = tmp_path / "hand" if through_a_link else device
    if through_a_link:
        other.symlink_to(device)
    config = write_config(tmp_path / "gw.toml", endpoint, serial_bus("uart0", str(device), "la1"),
                          serial_bus("uart1", str(other), "la2"))
    real = os.path.realpath(device)
    named = f" (as {device} and {other})" if through_a_link else ""
    refusal = (f"{config}: buses[1].port: buses 'uart0' and 'uart1' both open {real}{named}; "
               f"give each bus its own port")

    run = run_busgate("run", "--config", str(config))
    assert (run.returncode, run.stderr.splitlines()) == (2, [f"busgate run: error: {refusal}"])
    assert main(["check-config", str(config)]) == 1  # check-config: 1 for every refusal
    assert capsys.readouterr().err.splitlines() == [f"error: {refusal}"]


def test_a_config_that_is_not_utf8_is_one_line_naming_the_file(tmp_path, capsys) -> None:
    config = tmp_path / "gw.toml"
    config.write_bytes('[gateway]\nname = "gw1"  # café\n'.encode("latin-1"))
    refusal = f"{config} is not UTF-8 text (line 2 has the byte 0xe9): save it as UTF-8"

    run = run_busgate("run", "--config", str(config))
    assert (run.returncode, run.stderr.splitlines()) == (2, [f"busgate run: error: {refusal}"])
    assert main(["check-config", str(config)]) == 1
    assert capsys.readouterr().err.splitlines() == [f"error: {refusal}"]


def test_every_line_of_a_refusal_has_the_prefix(tmp_path, endpoint, capsys) -> None:
    """And names the file, as a compiler's lines do: the journal's reader may not know it."""
    bus = serial_bus("uart0", "/dev/ttyUSB0", "la1").replace("baudrate", "baudrat")
    config = write_config(tmp_path / "gw.toml", endpoint, bus + "poll_hz = 0\n")
    refusal = [f"{config}: buses[0].devices[0].poll_hz: Input should be greater than 0",
               f"{config}: buses[0]: unknown key `baudrat` (did you mean `baudrate`?)"]

    run = run_busgate("run", "--config", str(config))
    assert (run.returncode, run.stderr.splitlines()) == (
        2, [f"busgate run: error: {line}" for line in refusal])
    assert main(["check-config", str(config)]) == 1
    assert capsys.readouterr().err.splitlines() == [f"error: {line}" for line in refusal]


# -- zenoh ----------------------------------------------------------------------------------


@pytest.fixture
def held_address() -> Iterator[str]:
    """``127.0.0.1:PORT`` of a plain socket listening there: the address is in use."""
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        yield f"127.0.0.1:{holder.getsockname()[1]}"


@pytest.fixture
def existing_port() -> Iterator[str]:
    """A port that exists (a pty nobody serves), so that nothing is said of it: what is
    refused comes first."""
    controller, port = os.openpty()
    try:
        yield os.ttyname(port)
    finally:
        os.close(port)
        os.close(controller)


def test_a_zenoh_endpoint_in_use_is_refused_in_one_line(held_address, existing_port,
                                                        tmp_path) -> None:
    endpoint = f"tcp/{held_address}"
    config = write_config(tmp_path / "gw.toml", endpoint, serial_bus("uart0", existing_port, "la1"))
    results = {"run": run_busgate("run", "--config", str(config)),
               "demo": run_busgate("demo", "--listen", endpoint)}
    beside = {"run": "", "demo": " A second one runs beside it with --listen "
                                 "tcp/127.0.0.1:<another port>"}
    for command, result in results.items():
        refusal = (f"busgate {command}: error: zenoh cannot listen on {endpoint}: "
                   f"{IN_USE[:-1]}{beside[command]})")
        assert (result.returncode, result.stderr.splitlines()) == (2, [refusal]), command
        assert result.stdout == ""


def test_a_metrics_endpoint_in_use_is_refused_before_any_bus_opens(held_address, simulator,
                                                                   tmp_path, endpoint) -> None:
    config = write_config(tmp_path / "gw.toml", endpoint,
                          serial_bus("uart0", simulator.port, "la1"), metrics=held_address)
    run = run_busgate("run", "--config", str(config))
    assert run.returncode == 2 and "Traceback" not in run.stderr
    assert run.stderr.splitlines()[-1] == (f"busgate run: error: metrics cannot listen on "
                                           f"{held_address}: Address already in use (another "
                                           f"busgate demo or run?)")
    assert " up on " not in run.stderr


# -- ports ----------------------------------------------------------------------------------


def test_a_port_another_process_holds_is_refused_naming_it(simulator, tmp_path, endpoint,
                                                            capsys) -> None:
    config = write_config(tmp_path / "gw.toml", endpoint,
                          serial_bus("uart0", simulator.port, "la1"))
    with serial.Serial(simulator.port, BAUD, exclusive=True):  # as another gateway holds it
        run = run_busgate("run", "--config", str(config))
        assert main(["check-config", str(config)]) == 0  # a warning: the holder may be the
        out = capsys.readouterr().out                   # very gateway being checked
    held = f"{simulator.port} is locked by another process (pid {os.getpid()}: "
    [line] = run.stderr.splitlines()
    assert run.returncode == 2
    assert line.startswith(f"busgate run: error: bus uart0: {held}")
    assert line.endswith("stop that process (another busgate run or demo? a serial terminal?) "
                         "or give this bus another port")
    assert f"warning: buses[0].port: {held}" in out


def test_a_missing_port_still_starts_retries_and_comes_up(simulator, tmp_path,
                                                          endpoint) -> None:
    unplugged = tmp_path / "usb-hand"
    config = write_config(tmp_path / "gw.toml", endpoint,
                          serial_bus("uart0", simulator.port, "la1"),
                          serial_bus("uart1", str(unplugged), "la2"))
    gateway = GatewayProcess(config)
    try:
        gateway.wait_for(f"bus uart1: {unplugged} does not exist on this host")
        assert gateway.wait_for(" serving ").endswith("gateway gw1 serving 2 buses, 1 up")
        with SerialSimulator(la, [InspireLaDevice(1)], baudrate=BAUD) as plugged:
            unplugged.symlink_to(plugged.port)  # the adapter is plugged in
            gateway.wait_for("bus uart1 up on")
            assert gateway.stop() == 0
    finally:
        gateway.stop()


def _without_root_file_access() -> None:
    """In the child, before exec: drop CAP_DAC_OVERRIDE and CAP_DAC_READ_SEARCH from the
    capability bounding set, so that root, too, is held to a file's mode bits."""
    libc = ctypes.CDLL(None, use_errno=True)
    pr_capbset_drop, cap_dac_override, cap_dac_read_search = 24, 1, 2
    for capability in (cap_dac_override, cap_dac_read_search):
        if libc.prctl(pr_capbset_drop, capability, 0, 0, 0) != 0:
            raise OSError(ctypes.get_errno(), "prctl(PR_CAPBSET_DROP)")


def test_a_port_this_user_may_not_open_is_reported_with_what_to_do(endpoint) -> None:
    as_someone_else = {"preexec_fn": _without_root_file_access} if os.geteuid() == 0 else {}
    controller, follower = os.openpty()
    port = os.ttyname(follower)  # a device file, as a port is, that nobody may open
    os.chmod(port, 0o000)
    with tempfile.TemporaryDirectory() as folder, contextlib.ExitStack() as fds:
        fds.callback(os.close, controller)
        fds.callback(os.close, follower)
        config = write_config(Path(folder) / "gw.toml", endpoint,
                              serial_bus("uart0", str(port), "la1"))
        check = run_busgate("check-config", str(config), **as_someone_else)
        gateway = GatewayProcess(config, **as_someone_else)
        try:
            logged = gateway.wait_for("permission denied")
            # It starts all the same and retries: a udev rule may yet give the port to it.
            assert gateway.wait_for(" serving ").endswith("serving 1 bus, 0 up")
        finally:
            assert gateway.stop() == 0
    assert check.returncode == 0, check.stderr
    [warning] = [line for line in check.stdout.splitlines() if line.startswith("warning: buses[0]:")
                 or line.startswith("warning: buses[0].port")]
    denied = f"{port}: permission denied for user "
    assert warning.startswith(f"warning: buses[0].port: {denied}")
    assert logged.startswith(f"WARNING busgate: bus uart0: {denied}")
    for text in (warning, logged):
        assert "to the dialout group (sudo usermod -aG dialout" in text
        assert f"or install {UDEV_RULES}" in text


def test_the_udev_rules_the_messages_name_exist() -> None:
    assert (ROOT / UDEV_RULES).is_file()


def test_describe_open_error_tells_each_trouble_from_what_the_open_raised(simulator,
                                                                          tmp_path) -> None:
    absent = str(tmp_path / "ttyUSB9")
    with pytest.raises(serial.SerialException) as gone:
        serial.Serial(absent, BAUD, exclusive=True)
    assert describe_open_error(absent, gone.value).startswith(
        f"{absent} does not exist on this host (is the adapter plugged in?)")

    bus = SerialBus.model_validate({"name": "uart0", "transport": "serial",
                                    "port": simulator.port, "baudrate": BAUD,
                                    "devices": [{"name": "la1", "kind": "inspire_la"}]})
    owner = build_bus(bus).owner
    with serial.Serial(simulator.port, BAUD, exclusive=True):
        with pytest.raises(BusUnavailableError) as held:
            owner.open()  # the serial owner's own error, raised from pyserial's
        assert describe_open_error(simulator.port, held.value).startswith(
            f"{simulator.port} is locked by another process (pid {os.getpid()}: ")

    denied = PermissionError(errno.EACCES, "Permission denied", "/dev/ttyUSB0")
    text = describe_open_error("/dev/ttyUSB0", denied)
    assert text.startswith("/dev/ttyUSB0: permission denied for user ")
    assert "dialout group" in text and UDEV_RULES in text
    # EPERM whatever the mode: a device cgroup's (the unit's DeviceAllow= lines), by driver
    cgroup = PermissionError(errno.EPERM, "Operation not permitted", "/dev/ttySC0")
    text = describe_open_error(str(tmp_path / "ttySC0"), cgroup)
    assert "not permitted, whatever its mode" in text and "dialout" not in text
    assert 'DeviceAllow=char-<its driver in /proc/devices> rw' in text  # no such file here
    broken = OSError(errno.EIO, "Input/output error")
    assert describe_open_error("/dev/ttyUSB0", broken) == \
        "cannot open /dev/ttyUSB0: Input/output error"


def test_a_port_the_kernel_does_not_permit_is_told_its_drivers_deviceallow_name(
        tmp_path, monkeypatch) -> None:
    """Drivers share major numbers (4: ``tty`` and ``ttyS``): the longest name the device
    file's own starts with is its (/dev/null, major 1, stands in for a port here)."""
    devices = tmp_path / "devices"
    devices.write_text("Character devices:\n  1 mem\n  1 n\n  1 nul\n  4 ttyS\n\n"
                       "Block devices:\n  1 null\n")
    monkeypatch.setattr(port_access, "PROC_DEVICES", devices)
    assert describe_open_error("/dev/null", PermissionError(errno.EPERM, "x")).endswith(
        '"DeviceAllow=char-nul rw")')


# -- the command line -----------------------------------------------------------------------


def test_version_prints_the_installed_version(capsys) -> None:
    with pytest.raises(SystemExit) as exited:
        main(["--version"])
    assert exited.value.code == 0
    assert capsys.readouterr().out == f"busgate {metadata.version('busgate')}\n"


def test_no_command_lists_the_commands_and_exits_2(capsys) -> None:
    assert main([]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    for command in ("run", "check-config", "demo", "send", "watch", "sim"):
        assert f"\n    {command} " in captured.err or f"\n    {command}\n" in captured.err
