"""The one mapping from an exception to its reply's code (schemas/replies.py), on the
exceptions each path really raises: the schemas' refusals as pydantic makes them, as the CLI
and the drivers word them, the codecs' encode errors, the bus thread's, and a bug. Pure
calls."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

import busgate.codecs.errors as old_home
import busgate.errors as tree
from busgate.codecs import zlac706_can as zcan
from busgate.codecs.errors import EncodeError
from busgate.errors import (
    BusUnavailableError,
    BusyError,
    CommandError,
    DeviceRefusedError,
    DeviceTimeoutError,
    RefusedError,
)
from busgate.gateway.bus.request import Request
from busgate.gateway.drivers.inspire_la import InspireLaDriver
from busgate.gateway.drivers.zlac706_can import Zlac706CanDriver
from busgate.schemas import ds_servo, inspire_la
from busgate.schemas.bases import BASE_COMMAND_ADAPTER
from busgate.schemas.replies import error_code, error_reply


def raised(call, *args) -> BaseException:
    with pytest.raises(Exception) as caught:
        call(*args)
    return caught.value


def refused(adapter, value: dict) -> ValidationError:
    error = raised(adapter.validate_python, value)
    assert isinstance(error, ValidationError)
    return error


def test_a_value_outside_its_bounds_is_out_of_range_anything_else_bad_command():
    assert error_code(refused(inspire_la.COMMAND_ADAPTER, {"op": "move", "position": 2001})) == (
        "out_of_range")
    assert error_code(refused(inspire_la.COMMAND_ADAPTER, {"op": "move"})) == "bad_command"
    assert error_code(refused(inspire_la.COMMAND_ADAPTER, {"op": "move", "position": "1"})) == (
        "bad_command")
    both = refused(inspire_la.COMMAND_ADAPTER, {"op": "move", "position": 2001, "x": 1})
    assert error_code(both) == "bad_command", "out_of_range only when every problem is a range"


@pytest.mark.parametrize(("value", "message"), [
    ({"linear": 1}, 'no \'op\': a command names what it is ({"op": …})'),
    ({"op": "fly"}, "unknown 'op' 'fly': one of 'twist', 'stop', 'claim'"),
])  # fmt: skip
def test_a_missing_or_unknown_op_is_said_so_not_in_pydantics_words(value, message):
    """pydantic's "Unable to extract tag using discriminator 'op'" named nothing a client
    wrote (a base's command here; every kind's command is such a union)."""
    reply = error_reply(refused(BASE_COMMAND_ADAPTER, value))
    assert reply["error"]["code"] == "bad_command"
    assert reply["error"]["message"].startswith(f"invalid command: {message}")


def test_an_encode_error_is_out_of_range_however_it_is_raised():
    # The codec's own check, run by a schema's validator (pydantic wraps it), …
    in_validator = refused(ds_servo.COMMAND_ADAPTER, {"op": "read", "address": 56, "length": 30})
    assert error_code(in_validator) == "out_of_range"
    # … the codec encoding what a driver planned, …
    control_word = zcan.Write(5, zcan.CanRegister.CONTROL_WORD, 0x10)
    assert error_code(raised(Request.of, zcan, control_word)) == "out_of_range"
    # … and a driver's rule that is the codec's check.
    driver = InspireLaDriver("la1", 1)
    too_low = driver.parse('{"op":"set_overtemp","temp_c":64.9}')
    rule = raised(driver.plan, too_low)
    assert isinstance(rule, EncodeError) and error_code(rule) == "out_of_range"
    assert error_reply(rule)["error"] == {"code": "out_of_range", "message": str(rule)}


def test_a_refusal_worded_in_one_line_keeps_the_code_of_what_was_refused():
    driver = Zlac706CanDriver("wheel", 5)
    out_of_bounds = raised(driver.parse, '{"op":"velocity","rpm":99999}')
    assert isinstance(out_of_bounds, CommandError) and error_code(out_of_bounds) == "out_of_range"
    unknown = raised(driver.parse, '{"op":"fly"}')
    assert error_code(unknown) == "bad_command"
    stream = raised(InspireLaDriver("la1", 1).follow_target, {"position": 9999})
    assert error_code(stream) == "out_of_range" and "follow target" in str(stream)
    assert error_code(CommandError("move before enable")) == "bad_command"


def test_the_bus_threads_errors_keep_their_codes_and_a_bug_is_internal():
    cases = {
        "busy": BusyError("queue full"),
        "bus_unavailable": BusUnavailableError("down"),
        "device_timeout": DeviceTimeoutError("silent", device_id=1),
        "device_refused": DeviceRefusedError("no register 0x14", device_id=1),
        "claimed": RefusedError("claimed", "held by ui-1"),
        "internal": RuntimeError("a driver bug"),
    }
    assert {code: error_code(exc) for code, exc in cases.items()} == {c: c for c in cases}
    assert error_reply(KeyError())["error"] == {"code": "internal", "message": "KeyError"}
    invalid = error_reply(refused(inspire_la.COMMAND_ADAPTER, {"op": "move", "position": -1}))
    assert invalid["error"]["message"].startswith("invalid command: move.position")


@pytest.mark.parametrize("name", ["ConfigError", "BusUnavailableError", "BusIOError",
                                  "DeviceError", "DeviceTimeoutError", "RefusedError"])
def test_a_class_that_moved_up_to_busgate_errors_is_found_by_its_old_name_with_a_warning(name):
    with pytest.warns(DeprecationWarning, match=f"is busgate.errors.{name}: import it from"):
        assert getattr(old_home, name) is getattr(tree, name)
    with pytest.raises(AttributeError, match="no attribute 'Nothing'"):
        old_home.Nothing  # noqa: B018 - the lookup is the test
