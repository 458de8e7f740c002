"""The gateway's bases: two ZLAC706 hub motors driven as one differential drive. Pure: the
kinematics, limits and odometry (``kinematics``); the live twist the wheels' ticks sample
(``drive``); and the base keys' commands, claims, deadman and odometry (``bases``)."""
