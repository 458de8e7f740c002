"""Device drivers, sans-I/O: a JSON command (a ``busgate.schemas`` model) becomes codec frames.

One module per wire protocol; each exposes ``frames_for(command, device_id)`` returning the
frames, in order, that carry out the command.
"""
