"""Everything that touches a port, a clock, a thread or zenoh: bus owners, scheduler, device
drivers, the zenoh bridge, the daemon, the CLI and the simulators."""
