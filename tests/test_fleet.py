"""Three gateways (processes, each on its own simulated devices of every kind, each in a
network namespace of its own joined by a veth pair where the machine allows it, else on
loopback), one ``busgate router``, and ``busgate dashboard`` connected to the router
(``tests.fleet``), watched in a real browser: everything appears, moves and is logged, the
fleet e-stop button reaches every device of every gateway (checked on each simulator's wire
record), and a gateway that dies leaves the page within 2 s and comes back when restarted."""

from __future__ import annotations

import time

import pytest

import busgate.client as bc
from busgate.gateway.cli import main
from tests.browser import browser_page, needs_chromium
from tests.fleet import DEVICES_PER_GATEWAY, Hosts, running_fleet
from tests.sdk_helpers import RETRY_PAUSE_S, TRIES, patiently

pytestmark = needs_chromium

NAMES = ["gw1", "gw2", "gw3"]
WAIT_MS = 40_000  # a hang guard: conditions are waited for, not timed
GONE_WITHIN_MS = 2_000  # the contract's bound for a dead gateway to leave the page


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    with running_fleet(tmp_path_factory.mktemp("fleet"), NAMES) as fleet:
        yield fleet


@pytest.fixture(scope="module")
def client(fleet):
    with bc.connect(fleet.router, client_id="fleet-test") as c:
        yield c


@pytest.fixture(scope="module")
def page(fleet):
    with browser_page(fleet.dashboard) as page:
        page.wait_for_selector("#link[data-state=live]", timeout=WAIT_MS)
        yield page


def until(page, condition: str, *args, timeout: int = WAIT_MS) -> None:
    page.wait_for_function(condition, arg=list(args), timeout=timeout)


def cards_of(page, gateway: str) -> int:
    return page.locator(f'section[data-gateway="{gateway}"] article[data-device]').count()


def test_each_gateway_joins_the_router_from_a_host_of_its_own_where_possible(fleet) -> None:
    assert fleet.on_hosts == Hosts.possible()
    addresses = {gateway.connect for gateway in fleet.gateways.values()}
    if fleet.on_hosts:  # a veth pair each, the router listening on this side of every one
        assert len(addresses) == 3 and not any("127.0.0.1" in a for a in addresses)
        assert all(g.within[:3] == ["ip", "netns", "exec"] for g in fleet.gateways.values())
    else:
        assert addresses == {fleet.router}


def test_every_gateway_and_every_device_appears(page) -> None:
    until(page, "([n]) => document.querySelectorAll('article[data-device]').length == n",
          3 * DEVICES_PER_GATEWAY)
    names = page.locator("section[data-gateway]")
    assert sorted(names.nth(i).get_attribute("data-gateway") for i in range(3)) == NAMES
    for name in NAMES:
        assert cards_of(page, name) == DEVICES_PER_GATEWAY
    until(page, "() => [...document.querySelectorAll('article[data-device] .link-badge')]"
          ".every(b => b.dataset.value === 'online')")


def test_a_device_moved_through_the_router_moves_on_the_page(page, client) -> None:
    la1 = client.device("gw2/la1")
    goal = 1700 if la1.state().position < 1000 else 300
    patiently(la1.move, goal)
    until(page, "([goal]) => document.querySelector('article[data-device=\"gw2/la1\"] "
          "dd[data-field=position]').textContent == String(goal)", goal)
    series = page.evaluate("() => window.busgateDashboard.series('gw2/la1')")
    joint = la1.joint.info  # the plot is of its joint, in SI
    assert series["position"][-1] == pytest.approx(joint.offset + joint.scale * goal)
    assert len(series["t"]) > 2


def test_a_bare_device_name_every_gateway_has_is_refused_and_nothing_moves(
        fleet, client, capsys) -> None:
    """``busgate send la1 …`` through the router moved la1 on every gateway, where the SDK
    refuses the name as ambiguous."""
    move = '{"op":"move","position":1234}'
    assert main(["send", "la1", move, "--connect", fleet.router]) == 2
    assert capsys.readouterr().err == (
        "busgate send: error: 3 gateways have a device 'la1' (gw1, gw2, gw3): name one, e.g. "
        "gw1/la1; nothing was sent\n")
    for _ in range(TRIES):  # named: it goes (again after a loaded simulator's time-out)
        sent = main(["send", "gw3/la1", move, "--connect", fleet.router])
        if "device_timeout" not in capsys.readouterr().err:
            break
        time.sleep(RETRY_PAUSE_S)
    assert sent == 0
    assert [client.device(f"{g}/la1").state().target == 1234 for g in NAMES] == [
        False, False, True]


def test_an_event_of_one_gateway_appears(page, client) -> None:
    with client.device("gw3/la2").claim(ttl_s=2.0):
        until(page, "() => [...document.querySelectorAll('#events li')].some("
              "li => li.textContent.includes('gw3/la2 claimed'))")


def test_the_fleet_estop_button_stops_every_device_of_every_gateway_on_the_wire(
        page, client, fleet, wait_for) -> None:
    clicked = time.perf_counter()
    page.locator("#estop-fleet").click()
    expected = fleet.expected_stops()
    wait_for(lambda: set(fleet.estop_frames_after(clicked)) == expected)
    assert len(expected) == 3 * DEVICES_PER_GATEWAY
    until(page, "() => [...document.querySelectorAll('article[data-device] .power-badge')]"
          ".every(b => b.dataset.value === 'e-stopped')")
    for gateway in NAMES:
        for bus in client.gateways()[gateway]["buses"]:
            for entry in bus["devices"]:
                patiently(client.device(f"{gateway}/{entry['name']}").enable)
    until(page, "() => ![...document.querySelectorAll('article[data-device] .power-badge')]"
          ".some(b => b.dataset.value === 'e-stopped')")


def test_a_gateway_that_dies_leaves_the_page_within_2_s_and_comes_back(page, fleet) -> None:
    fleet.kill_gateway("gw1")
    until(page, "() => !document.querySelector('section[data-gateway=gw1]')",
          timeout=GONE_WITHIN_MS)
    assert cards_of(page, "gw2") == cards_of(page, "gw3") == DEVICES_PER_GATEWAY
    fleet.start_gateway("gw1")
    until(page, "([n]) => document.querySelectorAll("
          "'section[data-gateway=gw1] article[data-device]').length == n", DEVICES_PER_GATEWAY)
