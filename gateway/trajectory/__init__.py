"""The trajectories the gateway plays: their commands and watching (``playing``), a play's
checks (``checks``), a running one's verdict (``verdicts``), where the commands wait
(``lanes``); and, pure (no clock, thread or I/O), each device's value as a function of the time
since the start (``interpolation``) and whether a device takes every value of a path
(``bounds``)."""
