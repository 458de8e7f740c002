"""The scheduler: decides what goes on each bus and when (``planner``, pure and tested with a
fake clock), and carries it out on a dedicated thread per bus (``runner``)."""
