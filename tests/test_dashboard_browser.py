"""The dashboard in a real browser (``tests.browser``: Debian's Chromium under Playwright),
served by ``busgate demo``: every device appears with its state, values and plots move while
a client moves a device, events are logged, the buttons e-stop, reset the e-stop (once the
operator confirms) and re-enable, and the demo's base shows its twist and its track while a
client drives it."""

from __future__ import annotations

import json
import time

import pytest
import zenoh
from playwright.sync_api import TimeoutError as PlaywrightTimeoutError

import busgate.client as bc
from busgate.schemas.zenoh_session import session_config
from tests.browser import browser_page, needs_chromium
from tests.sdk_helpers import patiently

pytestmark = needs_chromium

DEVICES = ["la1", "la2", "la3", "servo1", "servo2", "wheel", "wheel_l", "wheel_r", "drive"]
#: Each device's power badge as the demo starts it (a test that changes one puts it back).
#: The devices the demo starts disabled: the CAN wheel, the RS232 drive, the base's wheels.
STARTED_OFF = ("wheel", "drive", "wheel_l", "wheel_r")
AS_STARTED = {name: "off" if name in STARTED_OFF else "enabled" for name in DEVICES}
WAIT_MS = 15_000  # a hang guard: conditions are waited for, not timed


@pytest.fixture(scope="module")
def client(module_demo):
    with bc.connect(module_demo.endpoint, client_id="browser-test") as c:
        yield c


@pytest.fixture
def page(module_demo):
    with browser_page(module_demo.dashboard) as page:
        page.wait_for_selector("#link[data-state=live]", timeout=WAIT_MS)
        yield page


def device(page, name: str):
    return page.locator(f'article[data-device="demo/{name}"]')


def field(page, name: str, label: str) -> str:
    return device(page, name).locator(f'dd[data-field="{label}"]').inner_text()


def badges(page, name: str) -> tuple[str, str]:
    card = device(page, name)
    return (card.locator(".link-badge").get_attribute("data-value"),
            card.locator(".power-badge").get_attribute("data-value"))


def until(page, condition: str, *args) -> None:
    page.wait_for_function(condition, arg=list(args), timeout=WAIT_MS)


def test_every_bus_and_device_of_the_gateway_appears_online(page) -> None:
    gateway = page.locator('section[data-gateway="demo"]')
    assert gateway.locator(".gateway-name").inner_text() == "demo"
    rows = gateway.locator("tbody tr")
    until(page, "() => document.querySelectorAll('section[data-gateway=demo] td.up').length == 4")
    assert sorted(rows.nth(i).get_attribute("data-bus") for i in range(4)) == [
        "can0", "rs232", "uart0", "uart1"]
    cards = page.locator("article[data-device]")
    assert sorted(cards.nth(i).get_attribute("data-device") for i in range(cards.count())) == (
        sorted(f"demo/{name}" for name in DEVICES))
    until(page, "() => [...document.querySelectorAll('article[data-device] .link-badge')]"
          ".every(b => b.dataset.value === 'online')")  # (a loaded host drops one now and then)
    assert badges(page, "la1")[1] == "enabled" and badges(page, "wheel")[1] == "off"
    assert field(page, "la1", "temperature").endswith("°C")
    assert field(page, "la1", "faults") == "none"
    until(page, "() => document.querySelector('#counts').textContent == "
          "'1 gateways · 9 devices · 1 bases'")  # the base: as soon as its odometry comes


def test_values_and_the_plot_follow_a_device_a_client_moves(page, client) -> None:
    """The values raw, the plot its joint's in SI (``la1``'s calibration, from ``info``)."""
    la1 = client.device("la1")
    start = la1.state().position
    goal = 1900 if start < 1000 else 100
    renders = page.evaluate("() => window.busgateDashboard.renders()")
    patiently(la1.move, goal)
    for label in ("target", "position"):
        until(page, "([selector, goal]) => document.querySelector(selector).textContent == goal",
              f'article[data-device="demo/la1"] dd[data-field={label}]', str(goal))
    series = page.evaluate("() => window.busgateDashboard.series('demo/la1')")
    joint = la1.joint.info
    low, high = sorted(joint.offset + joint.scale * raw for raw in (start, goal))
    reached = joint.offset + joint.scale * goal
    positions = [p for p in series["position"] if p is not None]
    between = [p for p in positions if low < p < high]
    assert between, "the plot holds the way there, not only the ends"
    assert series["target"][-1] == pytest.approx(reached)
    assert positions[-1] == pytest.approx(reached)
    assert series["t"] == sorted(series["t"])
    assert page.evaluate("() => window.busgateDashboard.renders()") > renders
    patiently(la1.move, start)


def test_a_claim_appears_in_the_event_log_its_renewals_folded_into_its_line(page, client) -> None:
    claimed = ("[...document.querySelectorAll('#events li')].filter(li => li.textContent"
               ".includes('demo/la2 claimed') && li.textContent.includes('client=browser-test'))")
    with client.device("la2").claim(ttl_s=1.0):  # renewed every third of a second
        until(page, f"() => {claimed}.some(li => li.textContent.includes('×3'))")
        assert page.evaluate(f"() => {claimed}.length") == 1
    until(page, "() => [...document.querySelectorAll('#events li')].some("
          "li => li.textContent.includes('demo/la2 released'))")


def test_the_gateway_estop_button_stops_every_device_and_enable_brings_each_back(
        page, client) -> None:
    page.locator('section[data-gateway="demo"] .estop-gateway').click()
    until(page, "() => [...document.querySelectorAll('article[data-device] .power-badge')]"
          ".every(b => b.dataset.value === 'e-stopped')")
    assert "e-stop demo: sent" in page.locator("#notice").inner_text()
    until(page, "() => [...document.querySelectorAll('#events li[data-type=estop]')].length > 0")
    for name in DEVICES:
        enable_by_its_button(page, name)
        until(page, "([key]) => document.querySelector(`article[data-device=\"${key}\"] "
              ".power-badge`).dataset.value !== 'e-stopped'", f"demo/{name}")
    assert badges(page, "la1")[1] == "enabled" and badges(page, "servo1")[1] == "enabled"
    for name in STARTED_OFF:  # as the demo starts them
        patiently(client.device(name).send, {"op": "disable"})


def enable_by_its_button(page, name: str) -> None:
    """``name``'s enable button pressed until its notice says sent: the dashboard sends an
    enable once, and a reply that timed out (a simulator late on a loaded host) is the
    operator's to press again, as here, up to three times."""
    for _ in range(3):
        page.evaluate("() => { document.getElementById('notice').textContent = ''; }")
        device(page, name).locator("button.enable").click()
        until(page, "([what]) => document.getElementById('notice').textContent"
              ".startsWith(what)", f"enable demo/{name}:")
        if "device_timeout" not in page.locator("#notice").inner_text():
            return


#: Each named device's power badge, as the page shows it now (``null``: no badge).
POWERS = ("(names) => Object.fromEntries(names.map((name) => [name, document.querySelector("
          "`article[data-device=\"demo/${name}\"] .power-badge`)?.dataset.value ?? null]))")


def until_powers(page, want: dict[str, str]) -> None:
    """Until the power badge of each device ``want`` names shows what it says; a failure
    says what the badges showed instead."""
    try:
        until(page, f"([want]) => Object.entries(({POWERS})(Object.keys(want)))"
              ".every(([name, value]) => value === want[name])", want)
    except PlaywrightTimeoutError:
        shown = page.evaluate(POWERS, list(want))
        raise AssertionError(f"power badges: {shown}, not {want}") from None


def test_the_reset_button_asks_first_and_puts_every_device_back_as_it_was(page) -> None:
    until_powers(page, AS_STARTED)
    page.locator('section[data-gateway="demo"] .estop-gateway').click()
    until_powers(page, dict.fromkeys(DEVICES, "e-stopped"))
    asked, resets = [], []
    page.on("request", lambda r: r.url.endswith("/api/reset_estop") and resets.append(r.post_data))
    reset = page.locator('section[data-gateway="demo"] .reset-estop')
    page.once("dialog", lambda dialog: (asked.append(dialog.message), dialog.dismiss()))
    reset.click()
    page.once("dialog", lambda dialog: (asked.append(dialog.message), dialog.accept()))
    reset.click()
    until_powers(page, AS_STARTED)
    assert asked == 2 * ["Reset the e-stop of gateway demo? Each device goes back to the power "
                         "state it had before the stop and holds still; nothing moves until a "
                         "new command. A device a client claims stays e-stopped for that client "
                         "to reset."]
    assert [json.loads(body) for body in resets] == [{"gateway": "demo"}]  # dismissed: nothing
    assert "reset demo: sent" in page.locator("#notice").inner_text()
    until(page, "() => [...document.querySelectorAll('#events li[data-type=estop_reset]')]"
          ".length > 0")


def test_hostile_telemetry_is_shown_as_text_and_the_page_goes_on(page, client, module_demo) -> None:
    """What a broken or hostile peer publishes on the demo's keys, or as a gateway of its own
    (a liveliness token and an info answer), reaches the page as text: no markup, no script,
    and the next real state is shown as ever."""
    session = zenoh.open(session_config(mode="client", connect=[module_demo.endpoint]))
    markup = '<img src=x onerror="window.pwned=1">'
    info = {"ok": True, "gateway": "evil", "version": markup, "buses": [
        {"name": "uart0", "protocol": markup, "devices": [{"name": "la1", "kind": markup}]}]}
    queryable = session.declare_queryable(
        "busgate/evil/info", lambda query: query.reply(query.key_expr, json.dumps(info)))
    token = session.liveliness().declare_token("busgate/evil/alive")
    try:
        until(page, "() => document.querySelector('article[data-device=\"evil/la1\"]')")
        hostile = {"ts": time.time(), "device": "la1", "kind": markup, "online": True,
                   "position": markup, "faults": "not a list", "temperature_c": {"x": 1}}
        session.put("busgate/demo/dev/la2/state", json.dumps(hostile))
        session.put("busgate/evil/dev/la1/state", json.dumps(hostile))
        # an event whose type is the page's own classes: its line takes none of their looks
        session.put("busgate/evil/events", json.dumps(
            {"ts": time.time(), "device": "la1", "type": "gateway device estop", "x": markup}))
        until(page, "() => document.querySelector('section[data-gateway=evil] "
              "dd[data-field=position]')?.textContent.includes('<img')")
        until(page, "() => [...document.querySelectorAll('#events li')].some("
              "li => li.textContent.includes('evil/la1 gateway device estop'))")
        assert page.evaluate("() => document.querySelectorAll('#events li[class]').length") == 0
        evil = page.locator('section[data-gateway="evil"]')
        assert evil.locator("img").count() == 0
        assert evil.locator(".gateway-version").inner_text() == f"busgate {markup}"
        assert page.evaluate("() => window.pwned") is None
        assert page.evaluate("() => window.busgateDashboard.leftOut()") == 0
        la2 = client.device("la2")
        goal = 1234 if la2.state().position != 1234 else 1235
        patiently(la2.move, goal)  # the demo's next real state replaces the hostile one
        until(page, "([goal]) => document.querySelector('article[data-device=\"demo/la2\"] "
              "dd[data-field=target]').textContent == String(goal)", goal)
    finally:
        token.undeclare()
        queryable.undeclare()
        session.close()
    until(page, "() => !document.querySelector('section[data-gateway=evil]')")


def test_each_device_shows_its_joint_with_its_unit_beside_its_raw_values(page, client) -> None:
    """A position joint's position and target in its unit, a velocity joint's velocity in its
    unit a second, the raw values beside them."""
    la3 = client.device("la3")
    patiently(la3.enable)
    joint = la3.joint.info
    goal = 1500 if la3.state().position != 1500 else 1502
    shown = page.evaluate("([v, unit]) => `${Number(v.toPrecision(4))} ${unit}`",
                          [joint.offset + joint.scale * goal, joint.unit])
    patiently(la3.joint.move, joint.offset + joint.scale * goal)
    until(page, "([shown]) => document.querySelector('article[data-device=\"demo/la3\"] "
          "dd[data-field=joint]').textContent == shown", shown)
    assert field(page, "la3", "position") == str(goal)  # the raw value stays beside it
    assert field(page, "la3", "joint target") == shown
    assert field(page, "la3", "effort").endswith(" N")
    wheel = client.joint("wheel")
    until(page, "([unit]) => document.querySelector('article[data-device=\"demo/wheel\"] "
          "dd[data-field=joint]').textContent.endsWith(` ${unit}/s`)", wheel.unit)


BASE = "() => window.busgateDashboard.base('demo/base')"


def base_field(page, label: str) -> str:
    return page.locator(f'article[data-base="demo/base"] dd[data-field="{label}"]').inner_text()


def until_base_field(page, label: str, condition: str) -> None:
    """Until ``condition`` holds of the text ``t`` of the demo's base's field ``label``."""
    until(page, "([label]) => { const t = document.querySelector("
          "`article[data-base=\"demo/base\"] dd[data-field=\"${label}\"]`).textContent; "
          f"return {condition}; }}", label)


def test_the_base_a_client_drives_shows_its_twist_pose_and_track(page, client) -> None:
    """Commanded and measured twist, the pose, and the track drawn as the base goes."""
    base = client.base("demo/base")
    patiently(base.enable)
    until(page, f"() => ({BASE})()?.draws > 0")
    before = page.evaluate(BASE)
    patiently(base.drive, 0.3, 0.5, 10.0)  # held while the page is watched, then stopped
    try:
        until_base_field(page, "commanded linear", "t == '0.300 m/s'")
        assert base_field(page, "commanded angular") == "0.500 rad/s"
        until_base_field(page, "measured linear", "parseFloat(t) > 0.1")  # the wheels' own
        until(page, f"([count]) => ({BASE})().track.length >= count + 10", len(before["track"]))
        after = page.evaluate(BASE)
        assert after["draws"] > before["draws"]
        assert [p[0] for p in after["track"]] == sorted(p[0] for p in after["track"])
        for label, unit in [("measured angular", " rad/s"), ("x", " m"), ("y", " m"),
                            ("theta", "°"), ("age", " s")]:
            assert base_field(page, label).endswith(unit), label
        canvas = page.locator('article[data-base="demo/base"] canvas.track').bounding_box()
        assert canvas["width"] == canvas["height"]
    finally:
        patiently(base.stop)
