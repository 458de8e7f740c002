"""Bus owners: one per serial port or CAN interface, the only code that touches it.

An owner runs one exchange at a time (a request, and its reply when one is expected), feeds
what it receives to the protocol's decoder, applies the deadline computed from wire time, and
counts what happened. It knows nothing of device models or units, and nothing of *when* to
send: that is the scheduler's job.
"""
