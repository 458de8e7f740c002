"""The precise wait's timing logic on a fake clock: how early it asks the kernel to wake it,
what it learns from each wake-up, and that it never returns before its deadline."""

from __future__ import annotations

import sys
import threading
from pathlib import Path

import pytest

from busgate.gateway.bus import clock
from busgate.gateway.bus.clock import SPIN_S, WakeUpLead, name_thread, sleep_until


class FakeTime:
    """``now`` moves 1 µs per look (a spin); a sleep ends ``late_s`` after it was asked to."""

    def __init__(self, late_s: float) -> None:
        self.t = 100.0
        self.late_s = late_s
        self.sleeps: list[tuple[float, float]] = []  # (asked to end at, woke at)
        self.looks = 0

    def now(self) -> float:
        self.t += 1e-6
        self.looks += 1
        return self.t

    def sleep(self, seconds: float) -> None:
        asked = self.t + seconds
        self.t = asked + self.late_s
        self.sleeps.append((asked, self.t))


@pytest.fixture
def fake(monkeypatch):
    def make(late_s: float) -> FakeTime:
        fake_time = FakeTime(late_s)
        monkeypatch.setattr(clock, "now", fake_time.now)
        monkeypatch.setattr(clock.time, "sleep", fake_time.sleep)
        monkeypatch.setattr(clock, "_lead", WakeUpLead())
        return fake_time

    return make


def test_a_lead_learns_the_mean_lateness_within_its_bounds() -> None:
    lead = WakeUpLead()
    assert lead.lead_s == SPIN_S  # a new thread spins the most, until it knows better
    for _ in range(200):
        lead.learn(50e-6)
    assert lead.lead_s == pytest.approx(50e-6, abs=1e-7)
    for late in (30e-6, 70e-6) * 200:
        lead.learn(late)
    assert 40e-6 < lead.lead_s < 60e-6
    for _ in range(200):
        lead.learn(0.005)  # a loaded host: the spin is capped, the rest is lateness
    assert lead.lead_s == pytest.approx(SPIN_S)
    for _ in range(200):
        lead.learn(-1e-3)  # cannot be early, but a clock step must not make the lead negative
    assert 0.0 <= lead.lead_s < 1e-9


def test_each_thread_learns_its_own_lead() -> None:
    lead = WakeUpLead()
    lead.learn(0.0)
    seen: list[float] = []
    other = threading.Thread(target=lambda: seen.append(lead.lead_s))
    other.start()
    other.join()
    assert seen == [SPIN_S]
    assert lead.lead_s < SPIN_S


def test_the_wait_sleeps_to_its_lead_before_the_deadline_and_spins_less_as_it_learns(fake):
    fake_time = fake(late_s=40e-6)
    spins = []
    for _ in range(60):
        deadline = fake_time.t + 0.005
        assert sleep_until(deadline) >= deadline
        _, awake = fake_time.sleeps[-1]
        spins.append(max(0.0, deadline - awake))
    assert spins[0] == pytest.approx(SPIN_S - 40e-6, abs=5e-6)  # it asked SPIN_S early
    assert spins[-1] < 2e-6  # learnt: it wakes at its deadline, nothing left to spin
    assert clock._lead.lead_s == pytest.approx(40e-6, abs=2e-6)


def test_a_late_wake_up_returns_at_once_and_never_before_the_deadline(fake):
    fake_time = fake(late_s=0.003)  # later than any lead
    deadline = fake_time.t + 0.002
    woke = sleep_until(deadline)
    assert woke >= deadline
    assert woke - deadline < 0.003 + 1e-5  # the lateness, and no spin after it


def test_a_fixed_spin_is_not_learnt_from_and_zero_never_spins(fake):
    fake_time = fake(late_s=10e-6)
    deadline = fake_time.t + 0.002
    sleep_until(deadline, spin_s=0.0)
    asked, _ = fake_time.sleeps[-1]
    assert asked == pytest.approx(deadline, abs=2e-6)
    assert clock._lead.lead_s == SPIN_S
    looks = fake_time.looks
    sleep_until(fake_time.t + 0.002, spin_s=0.0)
    assert fake_time.looks - looks <= 3  # one look before the sleep, one after: no spinning


def test_a_deadline_already_past_or_within_the_lead_is_spun_without_sleeping(fake):
    fake_time = fake(late_s=40e-6)
    assert sleep_until(fake_time.t - 1.0) >= fake_time.t - 1.0
    deadline = fake_time.t + SPIN_S / 2
    assert sleep_until(deadline) >= deadline
    assert fake_time.sleeps == []


def test_a_sleep_shorter_than_the_shortest_worth_taking_is_spun(fake):
    """After a wait that ended at its lead and taught it (``woke_for``), the lead is a little
    shorter and what is left a little longer: a sleep of that difference would wake a
    wake-up's lateness past the deadline, so it is spun."""
    fake_time = fake(late_s=40e-6)
    lead = clock._lead.lead_s
    deadline = fake_time.t + lead + clock.MIN_SLEEP_S * 0.9
    assert sleep_until(deadline) >= deadline
    assert fake_time.sleeps == []
    deadline = fake_time.t + lead + clock.MIN_SLEEP_S * 2
    sleep_until(deadline)
    assert len(fake_time.sleeps) == 1


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prctl is Linux's")
def test_a_thread_named_shows_under_that_name_to_the_os() -> None:
    names = []

    def named() -> None:
        assert name_thread("bus-a-very-long-bus-name")
        names.append(Path(f"/proc/self/task/{threading.get_native_id()}/comm").read_text())

    thread = threading.Thread(target=named)
    thread.start()
    thread.join()
    assert names == ["bus-a-very-long\n"]  # the kernel keeps 15 bytes
