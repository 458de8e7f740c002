"""A trajectory played by the gateway: pure sampling (``interpolation``: each device's value
as a function of the time since the trajectory's start, from the ``play`` command's points and
the device's start value). No clock, thread or I/O here."""
