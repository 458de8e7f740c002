"""The configuration file: what it accepts, what it refuses, and how it names the key."""

from __future__ import annotations

import codecs
import copy
from pathlib import Path

import pytest

from busgate.errors import ConfigError
from busgate.schemas.config import (
    CanBus,
    CanFilter,
    CanOptions,
    SerialBus,
    load_config,
    parse_config,
)

ROOT = Path(__file__).resolve().parent.parent

EXAMPLE = """
[gateway]
name = "gw1"

[zenoh]
mode = "peer"
listen = ["tcp/127.0.0.1:7447"]

[[buses]]
name = "uart0"
transport = "serial"
port = "/dev/serial/by-id/usb-FTDI_x"
baudrate = 921600

[[buses.devices]]
name = "la1"
kind = "inspire_la"
id = 1
poll_hz = 20
follow_period_ms = 20

[[buses]]
name = "can0"
transport = "can"
interface = "socketcan"
channel = "can0"

[[buses.devices]]
name = "wheel"
kind = "zlac706"
id = 3
heartbeat_ms = 100
"""

BASE = {
    "gateway": {"name": "gw1"},
    "buses": [{"name": "uart0", "transport": "serial", "port": "/dev/ttyUSB0",
               "baudrate": 921600,
               "devices": [{"name": "la1", "kind": "inspire_la", "id": 1}]}],
}


def refused(change) -> ConfigError:
    data = copy.deepcopy(BASE)
    change(data)
    with pytest.raises(ConfigError) as caught:
        parse_config(data)
    return caught.value


def test_the_issue_example_loads_with_defaults(tmp_path) -> None:
    path = tmp_path / "gw.toml"
    path.write_text(EXAMPLE)
    config = load_config(path)
    uart, can = config.buses
    assert isinstance(uart, SerialBus) and isinstance(can, CanBus)
    assert config.gateway.prefix == "busgate" and config.zenoh.multicast_scouting is False
    assert uart.protocol == "inspire_la" and uart.gap_s == 0.001
    assert can.protocol == "zlac706_can" and can.bitrate == 500_000
    assert uart.devices[0].poll_hz == 20 and can.devices[0].follow_period_ms == 20


def test_the_flight_recorder_is_off_unless_its_table_is_there() -> None:
    assert parse_config(BASE).recorder is None
    recorder = parse_config({**BASE, "recorder": {}}).recorder
    assert recorder is not None
    assert (recorder.seconds, recorder.dir) == (60, "/var/lib/busgate/incidents")


@pytest.mark.parametrize(("change", "path"), [
    ({"seconds": 0}, "recorder.seconds"), ({"seconds": 601}, "recorder.seconds"),
    ({"seconds": "60"}, "recorder.seconds"), ({"dir": "incidents"}, "recorder.dir"),
    ({"dir": ""}, "recorder.dir"), ({"dir": "/var/\x00lib"}, "recorder.dir"),
    ({"max_total_mb": 0}, "recorder.max_total_mb"), ({"size": 1}, "recorder.size"),
])
def test_a_recorder_setting_out_of_bounds_is_refused_naming_it(change, path) -> None:
    error = refused(lambda d: d.update(recorder=change))
    assert error.path == path


def test_buses_are_split_across_a_worker_per_core_unless_told_and_a_bad_value_is_refused() -> None:
    assert parse_config(BASE).gateway.workers == "auto"
    auto = parse_config({**BASE, "gateway": {"name": "gw1", "workers": "auto"}})
    assert auto.gateway.workers == "auto"
    for count in (1, 64):
        config = parse_config({**BASE, "gateway": {"name": "gw1", "workers": count}})
        assert config.gateway.workers == count
    for bad, spelt in ((0, "0"), (65, "65"), (-1, "-1"), (2.0, "2.0"), ("AUTO", '"AUTO"'),
                       ("2", '"2"'), (True, "true"), (None, "null"), ([], "[]")):
        error = refused(lambda d, b=bad: d["gateway"].update(workers=b))
        assert error.path == "gateway.workers"
        assert str(error) == (
            f'gateway.workers: "auto" or a whole number of processes from 1 to 64, not {spelt}'
        )


def test_follow_period_outside_10_to_50_ms_is_refused_with_its_key_path() -> None:
    for period in (9.9, 50.1):
        error = refused(lambda d, p=period: d["buses"][0]["devices"][0].update(follow_period_ms=p))
        assert error.path == "buses[0].devices[0].follow_period_ms"


@pytest.mark.parametrize("value", [float("nan"), float("inf"), float("-inf")])
def test_a_number_that_is_no_number_is_refused_as_one(value) -> None:
    """NaN was refused for the bound it failed ("less than or equal to 1000")."""
    for change, path in (
        (lambda d: d["buses"][0]["devices"][0].update(poll_hz=value),
         "buses[0].devices[0].poll_hz"),
        (lambda d: d["buses"][0].update(min_gap_ms=value), "buses[0].min_gap_ms"),
        (lambda d: d.update(recorder={"seconds": value}), "recorder.seconds"),
    ):
        assert str(refused(change)) == f"{path}: Input should be a finite number"


def test_gap_below_the_protocol_minimum_is_refused() -> None:
    error = refused(lambda d: d["buses"][0].update(min_gap_ms=0.5))
    assert error.path == "buses[0].min_gap_ms" and "at least 1 ms" in str(error)


def test_an_la_bus_at_a_baud_rate_no_actuator_runs_at_is_refused() -> None:
    """An LA runs at the four rates of its register 12 only; 9600 was taken, and the bus then
    read nothing but garbage."""
    error = refused(lambda d: d["buses"][0].update(baudrate=9600))
    assert error.path == "buses[0].baudrate"
    assert str(error) == ("buses[0].baudrate: inspire_la runs at 19200, 57600, 115200, 921600 "
                          "only, not 9600")
    for rate in (19200, 57600, 115200):
        parse_config({**BASE, "buses": [{**BASE["buses"][0], "baudrate": rate}]})


def test_ids_are_checked_per_protocol_and_per_bus() -> None:
    error = refused(lambda d: d["buses"][0]["devices"][0].update(id=255))
    assert error.path == "buses[0].devices[0].id" and "1–254" in str(error)
    error = refused(lambda d: d["buses"][0]["devices"].append(
        {"name": "la2", "kind": "inspire_la", "id": 1}))
    assert error.path == "buses[0].devices[1].id"


@pytest.mark.parametrize(("change", "line"), [
    ({"gateway": {"name": "a/b"}}, "gateway.name: must be 1-64 of A-Z a-z 0-9 _ -, not 'a/b'"),
    ({"gateway": {"name": "clients"}},  # a client named "alive" would be taken for it
     "gateway.name: 'clients' is where clients hold their liveliness tokens "
     "(<prefix>/clients/<id>): name the gateway otherwise"),
    ({"metrics": {"listen": "garbage"}},
     "metrics.listen: must be HOST:PORT (e.g. 127.0.0.1:9100), not 'garbage'"),
    ({"recorder": {"dir": "incidents"}}, "recorder.dir: must be an absolute path, not 'incidents'"),
])  # fmt: skip
def test_a_value_of_the_wrong_form_is_told_the_form_it_takes(change, line) -> None:
    """pydantic said "String should match pattern '^[^:\\s]+:\\d{1,5}$'"."""
    document = {"gateway": {"name": "gw"}, "buses": []} | change
    with pytest.raises(ConfigError) as refused:
        parse_config(document)
    assert line in str(refused.value).splitlines()


def test_a_transport_that_is_none_is_named_with_the_ones_there_are() -> None:
    """pydantic said "Input tag 'Serial' found using 'transport' does not match any of the
    expected tags"."""
    bus = {"name": "uart0", "transport": "Serial", "port": "/dev/ttyUSB0", "devices": []}
    with pytest.raises(ConfigError) as refused:
        parse_config({"gateway": {"name": "gw"}, "buses": [bus]})
    assert str(refused.value) == "buses[0].transport: must be serial or can, not 'Serial'"


def test_one_kind_per_bus_and_kinds_on_their_transport() -> None:
    error = refused(lambda d: d["buses"][0]["devices"].append(
        {"name": "s1", "kind": "ds_servo", "id": 2}))
    assert error.path == "buses[0].devices"
    error = refused(lambda d: d["buses"].append(
        {"name": "can0", "transport": "can", "interface": "virtual", "channel": "x",
         "devices": [{"name": "la9", "kind": "inspire_la", "id": 1}]}))
    assert error.path == "buses[1].devices[0].kind"


def test_names_are_unique_and_key_expression_safe() -> None:
    error = refused(lambda d: d["buses"][0]["devices"][0].update(name="la/1"))
    assert error.path == "buses[0].devices[0].name"
    error = refused(lambda d: d["buses"].append(copy.deepcopy(d["buses"][0])))
    assert "used twice" in str(error)


def _second_bus(name: str, **link: str) -> dict:
    transport = "serial" if "port" in link else "can"
    kind = "ds_servo" if transport == "serial" else "zlac706"
    rate = {"baudrate": 115200} if transport == "serial" else {"interface": "slcan"}
    return {"name": name, "transport": transport, **rate, **link,
            "devices": [{"name": f"{name}_1", "kind": kind, "id": 1}]}


@pytest.mark.parametrize(("port", "said"), [("ttyUSB0", " (/dev/ttyUSB0?)"),
                                            ("dev/ttyUSB0", " (/dev/ttyUSB0?)"), ("./x", "")])
def test_a_relative_port_is_refused_naming_the_path_it_likely_means(port, said) -> None:
    """It was the working directory's: ``/`` under systemd, where ``ttyUSB0`` never is."""
    error = refused(lambda d: d["buses"][0].update(port=port))
    assert error.path == "buses[0].port"
    assert str(error) == f"buses[0].port: a port is a path from /{said}, not {port!r}"


def test_one_bus_per_device_file_however_it_is_named(tmp_path) -> None:
    error = refused(lambda d: d["buses"].append(_second_bus("uart1", port="/dev/ttyUSB0")))
    assert error.path == "buses[1].port"
    assert str(error) == ("buses[1].port: buses 'uart0' and 'uart1' both open /dev/ttyUSB0; "
                          "give each bus its own port")
    link = tmp_path / "hand"
    link.symlink_to("/dev/ttyUSB0")  # as a udev rule makes it
    error = refused(lambda d: d["buses"].append(_second_bus("uart1", port=str(link))))
    assert f"both open /dev/ttyUSB0 (as /dev/ttyUSB0 and {link})" in str(error)
    error = refused(lambda d: d["buses"].append(_second_bus("can0", channel=str(link))))
    assert error.path == "buses[1].channel"  # an slcan adapter is a tty too
    error = refused(lambda d: d["buses"].append(
        _second_bus("can0", channel="/dev/ttyUSB0@115200")))  # its baud rate after the tty
    assert str(error) == ("buses[1].channel: buses 'uart0' and 'can0' both open /dev/ttyUSB0; "
                          "give each bus its own channel")


def test_socketcan_channels_and_distinct_ports_are_not_device_files_in_common() -> None:
    data = copy.deepcopy(BASE)
    data["buses"] += [_second_bus("uart1", port="/dev/ttyUSB1"),
                      {**_second_bus("can0", channel="can0"), "interface": "socketcan"}]
    assert len(parse_config(data).buses) == 3


def test_one_bus_per_socketcan_channel() -> None:
    """Two buses on one channel would each take the other's replies for its own devices'
    (an outside audit found two ZLAC706 of id 1 on can0 taken as valid)."""
    can0 = {**_second_bus("can0", channel="can0"), "interface": "socketcan"}
    twin = {**can0, "name": "can1", "devices": [{"name": "w2", "kind": "zlac706", "id": 1}]}
    error = refused(lambda d: d["buses"].extend([can0, twin]))
    assert str(error) == ("buses[2].channel: buses 'can0' and 'can1' both open socketcan "
                          "channel can0; give each bus its own channel")
    data = copy.deepcopy(BASE)
    data["buses"] += [can0, {**twin, "interface": "virtual"}]  # another interface's can0
    assert len(parse_config(data).buses) == 3


def test_unknown_keys_and_wrong_types_are_refused_not_ignored() -> None:
    assert refused(lambda d: d["buses"][0].update(baud=9600)).path == "buses[0].baud"
    assert refused(lambda d: d["buses"][0].update(baudrate="fast")).path == "buses[0].baudrate"


def _misspell(table: dict, key: str, typo: str) -> None:
    table[typo] = table.pop(key)


@pytest.mark.parametrize(("zenoh", "metrics", "message"), [
    ({"listen": ["tcp/127.0.0.1:70000"]}, None,
     "zenoh.listen[0]: port '70000' is no port: from 1 to 65535"),
    ({"connect": ["tcp/127.0.0.1:0"]}, None, "zenoh.connect[0]: port '0' is no port: from 1 to "
                                             "65535"),
    ({"listen": ["tcp/127.0.0.1:0"]}, None, "zenoh.listen[0]: port 0 is one zenoh picks and tells "
                                            "nobody: name the port clients connect to"),
    ({"listen": ["tcp/"]}, None, "zenoh.listen[0]: it names no port: write host:port "
                                 "(tcp/127.0.0.1:7447)"),
    ({"listen": ["tcp/[::1:7447"]}, None, "zenoh.listen[0]: host '[::1' is no host: an IPv6 "
                                          "address goes in brackets (tcp/[::1]:7447)"),
    ({"connect": ["tcp/::1:7447"]}, None, "zenoh.connect[0]: host '::1' is no host: an IPv6 "
                                          "address goes in brackets (tcp/[::1]:7447)"),
    ({"connect": ["tcp/[::1]"]}, None, "zenoh.connect[0]: port '1]' is no port: from 1 to "
                                       "65535"),  # its port first: the host is no '[:'

    ({"listen": ["tcp/127.0.0.1:7447", "tcp/127.0.0.1:7447"]}, None,
     "zenoh: listen: tcp/127.0.0.1:7447 is given twice"),
    ({"listen": ["tcp/0.0.0.0:7447", "tcp/127.0.0.1:7447"]}, None,  # run found it "in use"
     "zenoh: listen: tcp/0.0.0.0:7447 and tcp/127.0.0.1:7447 take the same port"),
    ({"mode": "client"}, None, 'zenoh: connect: a gateway in mode "client" reaches others '
                               'through a router: name its endpoint (connect = '
                               '["tcp/192.168.1.2:7447"])'),
    ({"listen": ["tcp/127.0.0.1:9108"]}, "127.0.0.1:9108",
     "metrics.listen: 127.0.0.1:9108 is the zenoh listener tcp/127.0.0.1:9108's port"),
    ({"listen": ["tcp/0.0.0.0:9108"]}, "127.0.0.1:9108",
     "metrics.listen: 127.0.0.1:9108 is the zenoh listener tcp/0.0.0.0:9108's port"),
    ({}, "127.0.0.1:0", "metrics.listen: port 0 is one the system picks and tells nobody: name "
                        "the port Prometheus scrapes"),  # logged as metrics on …:0/metrics
], ids=["port over 65535", "connect to port 0", "listen on port 0", "no port",
        "one bracket of an IPv6 host", "an IPv6 host without brackets", "an IPv6 host alone",
        "listen twice",
        "one port listened on twice", "client with no router", "metrics on zenoh's port",
        "zenoh on every address", "metrics on port 0"])
def test_a_zenoh_setting_that_could_never_open_is_refused_before_anything_opens(
        zenoh, metrics, message) -> None:
    """Each passed check-config and failed at run, where zenoh's refusal named nothing."""
    error = refused(lambda d: d.update(zenoh=zenoh, **({"metrics": {"listen": metrics}}
                                                        if metrics else {})))
    assert str(error) == message


def test_zenoh_settings_that_can_open_are_taken() -> None:
    for zenoh, metrics in (
        ({"listen": ["tcp/127.0.0.1:7447", "udp/127.0.0.1:9108"]}, "127.0.0.1:9108"),
        ({"listen": ["tcp/127.0.0.1:7447"]}, "127.0.0.2:7447"),
        ({"mode": "client", "connect": ["tcp/[::1]:7447?prio=1"]}, None),
        ({"mode": "client", "config_file": "/etc/busgate/zenoh.json5"}, None),
        ({"listen": ["unixsock-stream//run/busgate/gw.sock"]}, None),
    ):
        data = {**BASE, "zenoh": zenoh, **({"metrics": {"listen": metrics}} if metrics else {})}
        assert parse_config(data).zenoh.listen == zenoh.get("listen", [])


@pytest.mark.parametrize(("change", "message"), [
    (lambda d: _misspell(d["buses"][0], "baudrate", "baudrat"),
     "buses[0]: unknown key `baudrat` (did you mean `baudrate`?)"),
    (lambda d: _misspell(d["buses"][0]["devices"][0], "kind", "knd"),
     "buses[0].devices[0]: unknown key `knd` (did you mean `kind`?)"),
    (lambda d: d["buses"].append(_second_bus("can0", chanel="can0")),
     "buses[1]: unknown key `chanel` (did you mean `channel`?)"),
    (lambda d: _misspell(d, "buses", "bsues"), "unknown key `bsues` (did you mean `buses`?)"),
    (lambda d: d.update(recorder={"size": 1}),
     "recorder: unknown key `size` (allowed: `seconds`, `dir`, `max_total_mb`)"),
    (lambda d: d["buses"][0].update(xyz=1), "buses[0]: unknown key `xyz`"),
    (lambda d: d["buses"][0].pop("transport"),
     "buses[0]: `transport` is missing: serial or can (which kind of table)"),
    (lambda d: _misspell(d["buses"][0], "port", "xyz"),
     "buses[0].port: Field required\nbuses[0]: unknown key `xyz`"),
])
def test_an_unknown_key_is_one_line_naming_the_key_it_most_likely_misspells(change,
                                                                              message) -> None:
    """The key it misspells is not reported missing as well; a key with no close match is
    named alone, with its table's keys when they are few; another missing key stays."""
    assert str(refused(change)) == message


def test_unreadable_and_malformed_files(tmp_path) -> None:
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[gateway\nname=1")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(bad)
    latin1 = tmp_path / "latin1.toml"
    latin1.write_bytes('[gateway]\nname = "gw1"\n# Grüße\n'.encode("latin-1"))
    with pytest.raises(ConfigError) as caught:
        load_config(latin1)
    assert str(caught.value) == (f"{latin1} is not UTF-8 text (line 3 has the byte 0xfc): save "
                                 "it as UTF-8")
    for blank in ("", "\n  \n"):
        empty = tmp_path / "empty.toml"
        empty.write_text(blank)
        with pytest.raises(ConfigError) as caught:
            load_config(empty)
        assert str(caught.value) == f"{empty} is empty: a config names its gateway and buses"


def test_a_config_saved_with_a_byte_order_mark_is_read(tmp_path) -> None:
    """Some Windows editors write one first; TOML's parser took it for a statement."""
    plain, marked = tmp_path / "plain.toml", tmp_path / "marked.toml"
    plain.write_text(EXAMPLE)
    marked.write_bytes(codecs.BOM_UTF8 + EXAMPLE.encode())
    assert load_config(marked) == load_config(plain)


@pytest.mark.parametrize("name", ["inspire_la", "ds_servo", "zlac706_can", "zlac706_rs232",
                                  "robot"])
def test_the_example_configs_in_deploy_are_valid(name) -> None:
    config = load_config(ROOT / "deploy" / "config" / f"{name}.toml")
    assert config.buses and all(bus.devices for bus in config.buses)


@pytest.mark.parametrize("key", ["channel", "bitrate", "interface", "bustype"])
def test_can_options_never_set_what_the_bus_sets_itself(key) -> None:
    """``options`` pass on to python-can besides the bus's own keys: a second ``channel``
    there made python-can raise at every open."""
    bus = {"name": "can0", "transport": "can", "interface": "virtual", "channel": "x",
           "options": {key: "y", "receive_own_messages": False},
           "devices": [{"name": "w1", "kind": "zlac706", "id": 1}]}
    with pytest.raises(ConfigError) as refused_:
        parse_config({"gateway": {"name": "gw1"}, "buses": [bus]})
    assert str(refused_.value).startswith(f"buses[0].options.{key}: set by the bus's own")


def can_options(options: dict) -> dict:
    """The options python-can is given by a CAN bus with ``options``."""
    bus = {"name": "can0", "transport": "can", "interface": "virtual", "channel": "x",
           "options": options, "devices": [{"name": "w1", "kind": "zlac706", "id": 1}]}
    config = parse_config({"gateway": {"name": "gw1"}, "buses": [bus]})
    assert isinstance(config.buses[0], CanBus)
    return config.buses[0].options.arguments()


def test_can_filters_reach_python_can_as_its_list_of_plain_dicts_beside_the_other_options(
) -> None:
    """python-can's own form, which the config could not write at all; ``extended`` only
    when given (python-can tells an absent one from false)."""
    filters = [{"can_id": 0x581, "can_mask": 0x7FF}, {"can_id": 2, "can_mask": 0x1FFFFFFF,
                                                       "extended": True}]
    arguments = can_options({"can_filters": filters, "tty_baudrate": 2000000,
                             "receive_own_messages": False, "sleep_after_open": 0.5})
    assert arguments == {"can_filters": filters, "tty_baudrate": 2000000,
                         "receive_own_messages": False, "sleep_after_open": 0.5}
    assert all(type(each) is dict for each in arguments["can_filters"])
    assert can_options({}) == {}
    built = CanOptions(can_filters=[CanFilter(can_id=1, can_mask=0x7FF)])  # the models too
    assert built.arguments() == {"can_filters": [{"can_id": 1, "can_mask": 0x7FF}]}


NOT_A_LIST = ("buses[0].options.can_filters: a list of tables, each with can_id and can_mask "
              "(and extended, true or false), as python-can takes them: can_filters = "
              "[{ can_id = 0x581, can_mask = 0x7FF }]")


@pytest.mark.parametrize(("filters", "line"), [
    ("x", NOT_A_LIST),  # passed, and python-can raised at every frame it read
    (0x581, NOT_A_LIST),
    ({"can_id": 1, "can_mask": 2}, NOT_A_LIST),
    ([1], NOT_A_LIST),
    ([{"can_id": 1}], "buses[0].options.can_filters[0].can_mask: Field required"),
    ([{"can_id": 1, "can_msk": 2}],
     "buses[0].options.can_filters[0]: unknown key `can_msk` (did you mean `can_mask`?)"),
    ([{"can_id": 0x20000000, "can_mask": 1}],
     "buses[0].options.can_filters[0].can_id: Input should be less than or equal to 536870911"),
    ([{"can_id": -1, "can_mask": 1}],
     "buses[0].options.can_filters[0].can_id: Input should be greater than or equal to 0"),
    ([{"can_id": "1", "can_mask": 1}],
     "buses[0].options.can_filters[0].can_id: Input should be a valid integer"),
    ([{"can_id": 1, "can_mask": 1, "extended": 1}],
     "buses[0].options.can_filters[0].extended: Input should be a valid boolean"),
])
def test_can_filters_in_any_other_shape_are_refused_naming_the_key(filters, line) -> None:
    with pytest.raises(ConfigError) as refused_:
        can_options({"can_filters": filters})
    assert str(refused_.value) == line


def test_a_metrics_port_over_65535_and_a_port_with_a_nul_are_refused_naming_the_key() -> None:
    error = refused(lambda d: d.update(metrics={"listen": "127.0.0.1:99999"}))
    assert error.path == "metrics.listen" and "over 65535" in str(error)
    error = refused(lambda d: d["buses"][0].update(port="/dev/tty\x00x"))
    assert error.path == "buses[0].port"
