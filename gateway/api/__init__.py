"""The zenoh API: the gateway's commands without zenoh (``commands``), group moves and scans
(``group``), and the one module that speaks zenoh for the daemon (``bridge``, its session
built by ``busgate.schemas.zenoh_session``)."""
