"""The Prometheus endpoint against a real bus: a runner on the LA simulator's pty, the endpoint
on 127.0.0.1 (a free port), ``/metrics`` fetched over HTTP and parsed with prometheus_client's
own parser. The figures move as the bus works; nothing is asserted about how fast."""

from __future__ import annotations

import select
import socket
import threading
import time
import urllib.request

import pytest
from prometheus_client.parser import text_string_to_metric_families

from busgate.codecs import inspire_la as la
from busgate.gateway.service import scrape_server
from busgate.gateway.service.assembly import build_bus
from busgate.gateway.service.metrics import Metrics
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.pty_link import PtyLink
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.schemas.config import SerialBus

BAUD = 921_600


@pytest.fixture
def runner(tmp_path):
    link = PtyLink(str(tmp_path / "usb-la"))
    with SerialSimulator(la, [InspireLaDevice(1), InspireLaDevice(2)], baudrate=BAUD,
                         link=link) as sim:
        devices = [{"name": f"la{i}", "kind": "inspire_la", "id": i, "poll_hz": 50}
                   for i in (1, 2, 3)]  # la3 never answers
        # A reply margin with room for the simulator, which shares this process and a
        # loaded machine's cores: la1 and la2 must not pass for silent.
        bus = SerialBus(name="uart0", transport="serial", port=sim.port, baudrate=BAUD,
                        reply_margin_ms=50, devices=devices)
        runner = build_bus(bus).start()
        try:
            yield runner
        finally:
            runner.stop()


@pytest.fixture
def metrics(runner):
    metrics = Metrics({"uart0": runner}, clients=lambda: 2).start("127.0.0.1:0")
    try:
        yield metrics
    finally:
        metrics.stop()


def scrape(metrics: Metrics) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    """Every sample of ``/metrics``: (name, sorted labels) → value."""
    url = f"http://127.0.0.1:{metrics.port}/metrics"
    with urllib.request.urlopen(url, timeout=5) as response:
        text = response.read().decode()
    return {
        (sample.name, tuple(sorted(sample.labels.items()))): sample.value
        for family in text_string_to_metric_families(text)
        for sample in family.samples
    }


def bus(**labels: str) -> tuple[tuple[str, str], ...]:
    return tuple(sorted({"bus": "uart0", **labels}.items()))


def device(name: str) -> tuple[tuple[str, str], ...]:
    return bus(device=name, kind="inspire_la")


def test_the_endpoint_serves_the_bus_and_device_figures(wait_for, runner, metrics) -> None:
    wait_for(lambda: runner.drivers["la1"].online and runner.drivers["la2"].online)
    first = scrape(metrics)
    assert first[("busgate_device_online", device("la1"))] == 1
    assert first[("busgate_device_online", device("la3"))] == 0
    assert first[("busgate_device_last_reply_age_seconds", device("la1"))] >= 0
    assert ("busgate_device_last_reply_age_seconds", device("la3")) not in first  # never heard
    assert first[("busgate_bus_up", bus())] == 1
    assert first[("busgate_bus_frames_total", bus(direction="out"))] > 0
    assert first[("busgate_bus_bytes_total", bus(direction="in"))] > 0
    assert first[("busgate_bus_smallest_gap_seconds", bus())] >= 0.001
    assert 0 < first[("busgate_bus_utilisation_ratio", bus())] <= 1
    assert first[("busgate_zenoh_clients", ())] == 2
    for counter in ("timeouts", "checksum_errors", "reconnects", "skipped_polls"):
        assert ("busgate_bus_" + counter + "_total", bus()) in first

    frames = first[("busgate_bus_frames_total", bus(direction="out"))]
    wait_for(lambda: scrape(metrics)[("busgate_bus_frames_total", bus(direction="out"))]
             > frames)
    wait_for(lambda: scrape(metrics)[("busgate_bus_timeouts_total", bus())] > 0)  # la3


def test_follow_interval_error_appears_once_a_stream_ran(wait_for, runner, metrics) -> None:
    wait_for(lambda: runner.drivers["la1"].online)
    assert ("busgate_bus_follow_interval_error_seconds", bus(quantile="0.99")) not in scrape(
        metrics)
    target = runner.drivers["la1"].follow_target({"position": 1200})

    def streamed() -> bool:  # a client sending its target until three intervals went out
        runner.follow("la1", target, "position")
        return runner.statistics().follow_intervals > 2

    wait_for(streamed, timeout=10)
    samples = scrape(metrics)
    assert samples[("busgate_bus_follow_interval_error_seconds", bus(quantile="0.5"))] >= 0
    assert samples[("busgate_bus_follow_interval_error_seconds", bus(quantile="0.99"))] >= 0
    assert samples[("busgate_bus_follow_intervals_total", bus())] > 2


def test_command_latency_is_a_histogram(metrics) -> None:
    metrics.observe(0.0008)
    metrics.observe(0.03)
    samples = scrape(metrics)
    assert samples[("busgate_command_latency_seconds_count", ())] == 2
    assert samples[("busgate_command_latency_seconds_bucket", (("le", "0.001"),))] == 1
    assert samples[("busgate_command_latency_seconds_bucket", (("le", "+Inf"),))] == 2


def test_stop_closes_the_port_and_may_be_repeated(runner) -> None:
    metrics = Metrics({"uart0": runner}, clients=lambda: 0).start("127.0.0.1:0")
    port = metrics.port
    metrics.stop()
    metrics.stop()
    with pytest.raises(OSError):
        urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=2)


def test_idle_connections_hold_no_more_than_their_slots_and_are_closed(runner, monkeypatch):
    """prometheus_client's server gave each connection a thread for as long as it stayed
    open: 2,000 idle ones held 2,000 threads, and some 980 took every descriptor a gateway
    under systemd's default limit had. Now a few are served at once, the rest closed when
    accepted, and an idle one closed after a while, without a word in the log."""
    monkeypatch.setattr(scrape_server._Handler, "timeout", 2.0)
    metrics = Metrics({"uart0": runner}, clients=lambda: 0).start("127.0.0.1:0")
    threads_before = threading.active_count()
    idle = [socket.create_connection(("127.0.0.1", metrics.port)) for _ in range(40)]
    try:
        time.sleep(0.5)  # each accepted: served, or closed at once
        closed, _, _ = select.select(idle, [], [], 0)
        assert len(closed) == len(idle) - scrape_server.MAX_SCRAPES
        assert all(connection.recv(1) == b"" for connection in closed)
        assert threading.active_count() <= threads_before + scrape_server.MAX_SCRAPES
        for connection in idle:  # the served ones are closed once idle too
            connection.settimeout(10)
            assert connection.recv(1) == b""
        assert scrape(metrics)[("busgate_zenoh_clients", ())] == 0  # their slots are free again
    finally:
        for connection in idle:
            connection.close()
        metrics.stop()


def test_a_head_sent_a_line_at_a_time_is_cut_at_its_deadline_and_its_slot_freed(
        runner, monkeypatch) -> None:
    """A line a second is never idle: eight such connections held the metrics from every
    scraper for as long as they trickled."""
    monkeypatch.setattr(scrape_server, "IDLE_S", 1.0)
    metrics = Metrics({"uart0": runner}, clients=lambda: 0).start("127.0.0.1:0")
    tricklers = [socket.create_connection(("127.0.0.1", metrics.port))
                 for _ in range(scrape_server.MAX_SCRAPES)]
    try:
        for connection in tricklers:
            connection.sendall(b"GET /metrics HTTP/1.1\r\n")
        started = time.monotonic()
        for connection in tricklers:
            connection.settimeout(10)
            while True:  # a header line every 0.3 s until the server ends it
                try:
                    connection.sendall(b"X-Slow: 1\r\n")
                except OSError:
                    break
                readable, _, _ = select.select([connection], [], [], 0.3)
                if readable and connection.recv(1) == b"":
                    break
                assert time.monotonic() - started < 10, "the trickle was never cut"
        assert scrape(metrics)[("busgate_zenoh_clients", ())] == 0  # their slots are free
    finally:
        for connection in tricklers:
            connection.close()
        metrics.stop()


def test_only_the_metrics_path_is_served(runner) -> None:
    metrics = Metrics({"uart0": runner}, clients=lambda: 0).start("127.0.0.1:0")
    try:
        for path in ("/", "/../../etc/passwd", "/metricsx"):
            with pytest.raises(urllib.error.HTTPError) as refused:
                urllib.request.urlopen(f"http://127.0.0.1:{metrics.port}{path}", timeout=5)
            assert refused.value.code == 404
            assert refused.value.read() == b"no such page: the metrics are at /metrics\n"
        assert scrape(metrics)[("busgate_zenoh_clients", ())] == 0
    finally:
        metrics.stop()
