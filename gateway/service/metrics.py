"""The Prometheus endpoint: bus and device figures, command latency, zenoh clients.

Rules of this file:

1. Nothing here runs on a bus thread. The figures are read at scrape time: each bus's
   ``BusStats`` snapshot (``statistics()``, safe from any thread) and each driver's ``online``
   and ``last_reply`` (single attribute reads). The bus threads do no per-frame work for us.
2. Everything lives in the ``Metrics`` object's own ``CollectorRegistry`` (never the global
   one), so two gateways in one process, or one per test, do not collide; names start with
   ``busgate_``.
3. The only thing pushed rather than read is the command latency, which the API observes
   once per command on its own thread (``observe``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from typing import Any

from prometheus_client import CollectorRegistry, Histogram
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from busgate.gateway.bus.clock import now
from busgate.gateway.bus.stats import BusStats
from busgate.gateway.scheduler.runner import BusRunner
from busgate.gateway.service import scrape_server

#: Command latency buckets: from a frame on a fast UART to a timed-out command with retries.
LATENCY_BUCKETS = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0)

#: Per-bus counters: (name between ``busgate_bus_`` and ``_total``, help, {direction: the
#: ``BusStats`` field}); a direction of ``""`` means the counter has no ``direction`` label.
_BUS_COUNTERS: tuple[tuple[str, str, dict[str, str]], ...] = (
    ("frames", "Frames sent (out) and received (in)", {"out": "frames_out", "in": "frames_in"}),
    ("bytes", "Bytes sent (out) and received (in)", {"out": "bytes_out", "in": "bytes_in"}),
    ("timeouts", "Requests whose reply did not come in time", {"": "timeouts"}),
    ("retries", "Idempotent requests sent again after a timeout", {"": "retries"}),
    ("checksum_errors", "Replies with a bad checksum", {"": "checksum_errors"}),
    ("discarded_bytes", "Received bytes that were not part of a frame", {"": "discarded_bytes"}),
    (
        "late_replies",
        "Replies that came after their deadline and were flushed",
        {"": "late_replies"},
    ),
    (
        "early_replies",
        "Replies read before their request could have left the wire",
        {"": "early_replies"},
    ),
    ("reconnects", "Times the link came back after it was lost", {"": "reconnects"}),
    ("skipped_polls", "Polls skipped because the bus had no room for them", {"": "skipped_polls"}),
    ("busy_commands", "Commands refused with busy (queue full)", {"": "busy_commands"}),
    ("follow_intervals", "Follow intervals measured", {"": "follow_intervals"}),
)


class GatewayCollector(Collector):
    """Reads the buses' and devices' figures at each scrape."""

    def __init__(self, runners: Mapping[str, BusRunner], clients: Callable[[], int]) -> None:
        self.runners = runners
        self.clients = clients

    def collect(self) -> Iterator[Metric]:
        stats = {name: runner.statistics() for name, runner in self.runners.items()}
        yield from self._bus_counters(stats)
        yield from self._bus_gauges(stats)
        yield from self._devices()
        clients = GaugeMetricFamily("busgate_zenoh_clients", "Zenoh clients connected")
        clients.add_metric([], self.clients())
        yield clients

    def _bus_counters(self, stats: dict[str, BusStats]) -> Iterator[Metric]:
        for name, help_text, fields in _BUS_COUNTERS:
            split = "" not in fields
            family = CounterMetricFamily(
                f"busgate_bus_{name}", help_text, labels=["bus", "direction"] if split else ["bus"]
            )
            for bus, snapshot in stats.items():
                for direction, field in fields.items():
                    labels = [bus, direction] if split else [bus]
                    family.add_metric(labels, getattr(snapshot, field))
            yield family

    def _bus_gauges(self, stats: dict[str, BusStats]) -> Iterator[Metric]:
        up = GaugeMetricFamily("busgate_bus_up", "1 while the bus is open", labels=["bus"])
        use = GaugeMetricFamily(
            "busgate_bus_utilisation_ratio",
            "Share of the time since start the line was busy",
            labels=["bus"],
        )
        gap = GaugeMetricFamily(
            "busgate_bus_smallest_gap_seconds",
            "Smallest idle line seen between two exchanges",
            labels=["bus"],
        )
        error = GaugeMetricFamily(
            "busgate_bus_follow_interval_error_seconds",
            "Follow tick interval minus the period, over the last intervals (p50, p99)",
            labels=["bus", "quantile"],
        )
        for bus, snapshot in stats.items():
            up.add_metric([bus], float(self.runners[bus].owner.is_open))
            use.add_metric([bus], snapshot.utilisation)
            _add_known(gap, [bus], snapshot.smallest_gap_s)
            _add_known(error, [bus, "0.5"], snapshot.follow_error_p50_s)
            _add_known(error, [bus, "0.99"], snapshot.follow_error_p99_s)
        yield from (up, use, gap, error)

    def _devices(self) -> Iterator[Metric]:
        labels = ["bus", "device", "kind"]
        online = GaugeMetricFamily(
            "busgate_device_online", "1 while the device answers", labels=labels
        )
        age = GaugeMetricFamily(
            "busgate_device_last_reply_age_seconds",
            "Time since the device last answered",
            labels=labels,
        )
        moment = now()
        for bus, runner in self.runners.items():
            for name, driver in runner.drivers.items():
                values = [bus, name, driver.kind]
                online.add_metric(values, float(driver.online))
                last = driver.last_reply
                _add_known(age, values, None if last is None else moment - last)
        yield from (online, age)


def _add_known(family: GaugeMetricFamily, labels: list[str], value: float | None) -> None:
    """A sample only when there is a value (no reply yet, no follow interval yet: none)."""
    if value is not None:
        family.add_metric(labels, value)


class Metrics:
    """The gateway's metrics in a registry of their own, served on ``/metrics``."""

    def __init__(self, runners: Mapping[str, BusRunner], clients: Callable[[], int]) -> None:
        self.registry = CollectorRegistry()
        self.registry.register(GatewayCollector(runners, clients))
        self._latency = Histogram(
            "busgate_command_latency_seconds",
            "Time from a command's arrival to its reply",
            buckets=LATENCY_BUCKETS,
            registry=self.registry,
        )
        self._server: Any = None
        self._thread: Any = None

    def observe(self, seconds: float) -> None:
        """One command's latency (from any thread)."""
        self._latency.observe(seconds)

    def start(self, listen: str = "127.0.0.1:9108") -> Metrics:
        """Serve ``/metrics`` on ``host:port`` (port 0: any free one, see ``port``), bounded
        (``scrape_server``)."""
        host, port = listen.rsplit(":", 1)
        self._server, self._thread = scrape_server.serve(self.registry, host, int(port))
        return self

    @property
    def port(self) -> int:
        """The port served on, once started."""
        return self._server.server_address[1]

    def stop(self) -> None:
        """Stop serving (idempotent)."""
        if self._server is None:
            return
        self._server.shutdown()
        self._server.server_close()
        self._thread.join()
        self._server = self._thread = None
