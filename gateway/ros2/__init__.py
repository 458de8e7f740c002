"""busgate's face in ROS 2, on rmw_zenoh's wire format: the node and its entities on a zenoh
session (``node``), the face that joins them to the gateway (``face``), and, pure, what a
commands message asks of each joint (``commands``), a ROS trajectory as the gateway's
(``trajectory``) and the diagnostics (``diagnostics``)."""
