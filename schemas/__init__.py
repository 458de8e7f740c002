"""Pydantic models of busgate's public data: JSON commands, replies, telemetry and config.

Commands are tagged by ``op``; one module per device kind (``inspire_la``, ``ds_servo``,
``zlac706``) defines its ``Command`` union and ``COMMAND_ADAPTER``.
"""
