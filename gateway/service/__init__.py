"""The daemon and what it stands on: assembling buses from the config, the bus budget,
metrics and systemd notification."""
