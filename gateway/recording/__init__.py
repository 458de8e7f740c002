"""Recording busgate's telemetry as MCAP (``mcap_log``): what ``busgate record`` writes and
``busgate replay`` and ``busgate record --info`` read."""
