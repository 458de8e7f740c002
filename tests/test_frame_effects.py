"""What each op's frames do in the authority's eyes, on every family, by plain calls: a
motion needs the claim and is refused while e-stopped, a stop never is (an e-stop, a pause,
torque off, 0 rpm, a release), a read only asks, anything else changes a setting."""

from __future__ import annotations

import pytest

from busgate.gateway.drivers.base import Driver, Effect
from busgate.gateway.drivers.ds_servo import DsServoDriver
from busgate.gateway.drivers.inspire_la import InspireLaDriver
from busgate.gateway.drivers.zlac706_can import Zlac706CanDriver
from busgate.gateway.drivers.zlac706_rs232 import Zlac706Rs232Driver

#: A ZLAC706 op does the same on both protocols, with every one of its frames.
ZLAC706 = [
    ('{"op":"velocity","rpm":120}', Effect.MOTION),
    ('{"op":"velocity","rpm":0}', Effect.STOP),
    ('{"op":"enable"}', Effect.SETTING),
    ('{"op":"disable"}', Effect.STOP),
    ('{"op":"move","position":1000}', Effect.MOTION),  # RS232: both halves
    ('{"op":"torque","current_a":1.5}', Effect.MOTION),
    ('{"op":"home"}', Effect.MOTION),  # an origin search runs the motor
    ('{"op":"set_mode","mode":"velocity"}', Effect.SETTING),
    ('{"op":"set_velocity_ramp","accel_ms":500,"decel_ms":500}', Effect.SETTING),
    ('{"op":"set_max_speed","rpm":100}', Effect.SETTING),
]
INSPIRE_LA = [
    ('{"op":"move","position":1000}', Effect.MOTION),
    ('{"op":"follow","position":1000,"reply":false}', Effect.MOTION),
    ('{"op":"group_move","targets":[{"id":1,"position":1300}]}', Effect.MOTION),
    ('{"op":"group_follow","targets":[{"id":1,"position":1300}]}', Effect.MOTION),
    ('{"op":"write","index":55,"data":"1405"}', Effect.MOTION),  # the target register
    ('{"op":"write","index":98,"data":"c102"}', Effect.SETTING),
    ('{"op":"status"}', Effect.READ),
    ('{"op":"read","index":98,"length":2}', Effect.READ),
    ('{"op":"estop"}', Effect.STOP),
    ('{"op":"pause"}', Effect.STOP),
    ('{"op":"enable"}', Effect.SETTING),  # no motion until a new target (manual 3.5.4)
    ('{"op":"clear_fault"}', Effect.SETTING),
    ('{"op":"save"}', Effect.SETTING),
    ('{"op":"set_overcurrent","current_ma":1000}', Effect.SETTING),
]
DS_SERVO = [
    ('{"op":"torque","on":false}', Effect.STOP),
    ('{"op":"torque","on":true}', Effect.SETTING),
    ('{"op":"write","address":48,"data":"00"}', Effect.SETTING),  # a 0, not the torque's
    ('{"op":"write","address":42,"data":"0064"}', Effect.MOTION),  # the target
    # Where and how the shaft is driven with torque on: the same target is another angle, a
    # servo made a motor may spin (they were settings, taken while e-stopped)
    ('{"op":"write","address":20,"data":"0010"}', Effect.MOTION),  # the centre's offset
    ('{"op":"write","address":28,"data":"01"}', Effect.MOTION),  # the motor mode
    ('{"op":"write","address":29,"data":"01"}', Effect.MOTION),  # its direction
    # the travel's limits: the servo clamps each target to them (a raised min drives it)
    ('{"op":"write","address":9,"data":"0100"}', Effect.MOTION),
    ('{"op":"write","address":16,"data":"0320"}', Effect.SETTING),  # the torque's limit
    ('{"op":"move","position":100}', Effect.MOTION),
    ('{"op":"goto_preset","n":2}', Effect.MOTION),
    ('{"op":"ping"}', Effect.READ),
    ('{"op":"read","address":56,"length":2}', Effect.READ),
    ('{"op":"reset"}', Effect.MOTION),  # factory settings switch torque on: the shaft is driven
    ('{"op":"set_id","new_id":3}', Effect.SETTING),
]
CASES = [
    *((Zlac706CanDriver, text, effect) for text, effect in ZLAC706),
    *((Zlac706Rs232Driver, text, effect) for text, effect in ZLAC706),
    (Zlac706Rs232Driver, '{"op":"monitor"}', Effect.READ),
    *((InspireLaDriver, text, effect) for text, effect in INSPIRE_LA),
    *((DsServoDriver, text, effect) for text, effect in DS_SERVO),
]


@pytest.mark.parametrize(("family", "text", "effect"), CASES,
                         ids=[f"{family.__name__}-{text}" for family, text, _ in CASES])
def test_each_ops_frames_do_what_the_authority_judges(family: type[Driver], text, effect):
    driver = family("d", 1)
    frames = driver.frames_of(driver.parse(text))
    assert frames and [driver.effect(frame) for frame in frames] == [effect] * len(frames)
