"""The bus threads' wake-up flag (``flag.Flag``) keeps ``threading.Event``'s meaning: raised
by any thread, it stays raised through its waits until its waiter lowers it."""

from __future__ import annotations

import threading
import time

import pytest

from busgate.gateway.bus.flag import Flag


@pytest.fixture(params=[threading.Event, Flag], ids=["Event", "Flag"])
def flag(request):
    """Each check runs on ``threading.Event`` too: what it asserts is an Event's meaning."""
    return request.param()


def test_a_new_flag_is_lowered_and_a_wait_on_it_times_out(flag) -> None:
    assert not flag.is_set()
    started = time.perf_counter()
    assert flag.wait(0.02) is False
    assert time.perf_counter() - started >= 0.015


def test_a_raised_flag_stays_raised_through_its_waits_until_lowered(flag) -> None:
    flag.set()
    flag.set()  # raising a raised flag changes nothing
    assert flag.wait(0.0) is True and flag.wait(1.0) is True and flag.is_set()
    flag.clear()
    assert not flag.is_set() and flag.wait(0.0) is False
    flag.clear()  # lowering a lowered one neither
    assert not flag.is_set()


def test_no_time_left_is_one_look_and_none_waits_for_ever(flag) -> None:
    assert flag.wait(-0.001) is False  # a deadline passed while computing the timeout
    woken = []
    waiter = threading.Thread(target=lambda: woken.extend((flag.wait(None), flag.wait())),
                              daemon=True)
    waiter.start()
    time.sleep(0.02)
    assert woken == []  # still waiting
    flag.set()
    waiter.join(5.0)
    assert woken == [True, True]


def test_a_set_from_another_thread_wakes_the_waiter_at_once(flag) -> None:
    woken = []
    waiter = threading.Thread(target=lambda: woken.append(flag.wait(10.0)), daemon=True)
    waiter.start()
    time.sleep(0.02)
    started = time.perf_counter()
    flag.set()
    waiter.join(5.0)
    assert woken == [True] and time.perf_counter() - started < 5.0
    assert flag.is_set()


def test_every_waiter_is_woken_in_turn(flag) -> None:
    woken = []
    waiters = [threading.Thread(target=lambda: woken.append(flag.wait(10.0)), daemon=True)
               for _ in range(3)]
    for waiter in waiters:
        waiter.start()
    time.sleep(0.02)
    flag.set()
    for waiter in waiters:
        waiter.join(5.0)
    assert woken == [True, True, True]
