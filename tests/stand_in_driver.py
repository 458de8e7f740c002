"""The least driver the scheduler's and the authority's tests need: a name, an id, frames that
move, no state; its joint takes positions of any size, so a follow tick carries its targets
as they came."""

from __future__ import annotations

from busgate.gateway.drivers.base import Driver, Effect
from busgate.schemas.joints import JointDeclaration

ANY_POSITION = JointDeclaration(
    raw_range=(-(10**6), 10**6),
    position="position",
    target="target",
    move=("move", "position"),
    follow_position="position",
)


class StandInDriver(Driver):
    kind = protocol = "test"
    plan_frames = poll = safe_stop = frames_of = lambda self, *a: []
    apply = telemetry = lambda self, *a: {}
    effect = lambda self, frame: Effect.MOTION  # noqa: E731

    @classmethod
    def joint_declaration(cls) -> JointDeclaration:
        return ANY_POSITION
