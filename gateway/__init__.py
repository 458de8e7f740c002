"""Everything that touches a port, a clock, a thread or zenoh: bus owners, scheduler, device
drivers, the zenoh bridge, the daemon, the CLI and the simulators."""

from importlib import metadata


def installed_version() -> str:
    """busgate's version as installed (``busgate --version``, the ``info`` reply)."""
    try:
        return metadata.version("busgate")
    except metadata.PackageNotFoundError:
        return "unknown"
