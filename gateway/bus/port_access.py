"""What stands between the gateway and a serial port, said in one line with what to do.

Why a module of its own: ``busgate run`` at start-up (it refuses a port another process holds
rather than retrying forever), ``busgate check-config`` and the serial owner's runtime
messages must tell the same story about the same troubles — the port is missing (the
adapter is unplugged), another process holds it, this user may not open it, or the path is no
device file at all (a regular file, a directory, a loop of links: it never will be a port) —
so it is written once, here.

Rules of this file: nothing here opens a port (opening a tty raises its modem lines, which
``check-config`` must not do). Presence and access come from the file system (``os.access``
with read and write, as the open would need); a holder from ``/proc/locks``, where the
``flock`` that pyserial's ``exclusive=True`` takes is listed with its process. Linux only,
like the gateway; where ``/proc/locks`` cannot be read, no holder is seen.
"""

from __future__ import annotations

import errno
import grp
import os
import pwd
import stat
from dataclasses import dataclass
from pathlib import Path

#: The udev rules that give busgate's adapters a stable name, group ``dialout`` and mode 0660.
UDEV_RULES = "deploy/udev/99-busgate.rules"
PROC_LOCKS = Path("/proc/locks")
#: Each character device driver's name by major number (``not_permitted``).
PROC_DEVICES = Path("/proc/devices")
SERIAL_GROUP = "dialout"

MISSING, LOCKED, DENIED, NOT_A_DEVICE = "missing", "locked", "permission_denied", "not_a_device"
#: What a path that can never be a port is told to be instead.
_NO_PORT = "a serial port is a device file (/dev/ttyUSB0, /dev/serial/by-id/…); give its path"
_MISSING_ERRNOS = {errno.ENOENT, errno.ENODEV, errno.ENXIO}
_DENIED_ERRNOS = {errno.EACCES}
_LOCKED_ERRNOS = {errno.EAGAIN, errno.EBUSY}  # flock refused (EWOULDBLOCK); TIOCEXCL (EBUSY)


@dataclass(frozen=True, slots=True)
class PortProblem:
    """Why a port cannot be opened now: ``kind`` (``MISSING``, ``LOCKED``, ``DENIED`` or
    ``NOT_A_DEVICE``) and one line naming the port, what is wrong and what to do."""

    kind: str
    message: str


def port_problem(port: str) -> PortProblem | None:
    """What would keep this process from opening ``port`` now, or ``None`` when nothing
    visible would (the open can still fail: a device can vanish between the look and the
    open).

    >>> port_problem("/nonexistent/ttyUSB9").kind
    'missing'
    """
    try:
        found = os.stat(port)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            return PortProblem(NOT_A_DEVICE, f"{port} is a loop of symbolic links: {_NO_PORT}")
        return PortProblem(MISSING, missing(port))
    if not stat.S_ISCHR(found.st_mode):
        return PortProblem(NOT_A_DEVICE, f"{port} is {_file_kind(found.st_mode)}: {_NO_PORT}")
    kind = _device_class(found.st_rdev)
    if kind not in (None, "tty"):
        return PortProblem(NOT_A_DEVICE, f"{port} is a {kind} device, no tty: {_NO_PORT}")
    holder = lock_holder(port)
    if holder is not None:
        return PortProblem(LOCKED, locked(port, holder))
    if not os.access(port, os.R_OK | os.W_OK):
        return PortProblem(DENIED, denied(port))
    return None


def describe_open_error(port: str, exc: BaseException) -> str:
    """One line for a failed open of ``port``: what is wrong and what to do.

    ``exc`` is what the open raised — ``OSError`` from ``os.open``, pyserial's
    ``SerialException`` (an ``OSError`` carrying the errno), or an error raised ``from`` one
    of those (``BusUnavailableError``); the errno decides the story.

    >>> import errno
    >>> describe_open_error("/dev/ttyUSB9", FileNotFoundError(errno.ENOENT, "No such file"))
    '/dev/ttyUSB9 does not exist on this host (is the adapter plugged in?); the gateway retries...'
    """
    cause = _os_error(exc)
    code = cause.errno if cause is not None else None
    if code in _MISSING_ERRNOS:
        return missing(port)
    if code in _DENIED_ERRNOS:
        return denied(port)
    if code == errno.EPERM:
        return not_permitted(port)
    if code in _LOCKED_ERRNOS:
        return locked(port, lock_holder(port))
    reason = (cause.strerror or str(cause)) if cause is not None else str(exc)
    return f"cannot open {port}: {reason}"


def _device_class(device: int) -> str | None:
    """The kernel's class of the character device ``device`` (``tty`` for every serial port
    and terminal, ``mem`` for ``/dev/null`` …), ``None`` where sysfs does not say (a
    pseudo-terminal has no entry there, nor has a container without /sys)."""
    entry = Path("/sys/dev/char") / f"{os.major(device)}:{os.minor(device)}" / "subsystem"
    try:
        return Path(os.readlink(entry)).name
    except OSError:
        return None


def _file_kind(mode: int) -> str:
    """What a path that is no device file is, for a refusal."""
    if stat.S_ISDIR(mode):
        return "a directory"
    if stat.S_ISFIFO(mode):
        return "a named pipe"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "a regular file" if stat.S_ISREG(mode) else "not a character device"


def missing(name: str) -> str:
    """A port (or CAN interface) this host does not have, yet."""
    return (
        f"{name} does not exist on this host (is the adapter plugged in?); the gateway "
        f"retries until it appears"
    )


def locked(port: str, holder: int | None) -> str:
    """A port another process holds exclusively."""
    who = "another process" if holder is None else f"another process ({_process(holder)})"
    return (
        f"{port} is locked by {who}: stop that process (another busgate run or demo? a "
        f"serial terminal?) or give this bus another port"
    )


def denied(port: str) -> str:
    """A port this user may not read and write, and the two ways to be let in."""
    user, group = _user(), _group_to_join(port)
    return (
        f"{port}: permission denied for user {user}: add it to the {group} group "
        f"(sudo usermod -aG {group} {user}, then log in again) or install {UDEV_RULES}, "
        f"which gives the adapters to group {SERIAL_GROUP} with mode 0660"
    )


def not_permitted(port: str) -> str:
    """A port whose open the kernel refuses whatever the file's mode (``EPERM``): a device
    cgroup's, as the systemd unit's ``DeviceAllow=`` makes one, names the drivers allowed."""
    driver = _driver_name(port)
    allow = f"char-{driver}" if driver else "char-<its driver in /proc/devices>"
    return (
        f"{port}: not permitted, whatever its mode: under the systemd unit only the tty "
        "drivers its DeviceAllow= lines name may be opened (ttyUSB, ttyACM, ttyS, ttyAMA); "
        f'add this one\'s in a drop-in (systemctl edit busgate: "DeviceAllow={allow} rw")'
    )


def _driver_name(port: str) -> str | None:
    """The name ``/proc/devices`` gives the driver of the character device ``port`` (what
    a device cgroup's ``char-`` rule names), ``None`` when not found. Drivers may share a
    major number (4: ``tty`` and ``ttyS``): the longest that the device file's name starts
    with is its."""
    try:
        major = os.major(os.stat(port).st_rdev)
        table = PROC_DEVICES.read_text()
    except OSError:
        return None
    file_name = os.path.basename(os.path.realpath(port))
    characters = table.split("Block devices:")[0].splitlines()
    names = [
        name
        for number, _, name in (line.strip().partition(" ") for line in characters)
        if number == str(major) and file_name.startswith(name)
    ]
    return max(names, key=len, default=None)


def lock_holder(port: str) -> int | None:
    """The process holding a ``flock`` on ``port`` (the file it leads to), as ``/proc/locks``
    lists it; ``None`` when none is listed or the table cannot be read."""
    try:
        device = os.stat(port)
        table = PROC_LOCKS.read_text()
    except OSError:
        return None
    inode = f"{os.major(device.st_dev):02x}:{os.minor(device.st_dev):02x}:{device.st_ino}"
    for line in table.splitlines():
        # "1: FLOCK  ADVISORY  WRITE 3693 00:1a:3 0 EOF"; a waiter's line has "->" after "1:".
        fields = line.split()
        if len(fields) > 5 and fields[1] == "FLOCK" and fields[5] == inode:
            return int(fields[4]) if fields[4].isdigit() else None
    return None


def _os_error(exc: BaseException | None) -> OSError | None:
    """The first error carrying an errno in ``exc``'s chain of causes."""
    while exc is not None:
        if isinstance(exc, OSError) and exc.errno is not None:
            return exc
        exc = exc.__cause__ or exc.__context__
    return None


def _process(pid: int) -> str:
    """``pid 1234: busgate run --config …``, or just the pid when its command line is hidden
    (another user's process under ``ProtectProc=invisible``)."""
    try:
        command = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").strip()
    except OSError:
        return f"pid {pid}"
    if not command:
        return f"pid {pid}"
    text = command.decode(errors="replace")
    return f"pid {pid}: {text if len(text) <= 80 else text[:77] + '...'}"


def _user() -> str:
    try:
        return pwd.getpwuid(os.getuid()).pw_name
    except KeyError:
        return str(os.getuid())


def _group_to_join(port: str) -> str:
    """The group that may read and write ``port`` (``uucp`` on some distributions), else the
    group the udev rules give it."""
    try:
        device = os.stat(port)
        owner_group = grp.getgrgid(device.st_gid).gr_name
    except (OSError, KeyError):
        return SERIAL_GROUP
    group_rw = stat.S_IRGRP | stat.S_IWGRP
    if device.st_gid != 0 and device.st_mode & group_rw == group_rw:
        return owner_group
    return SERIAL_GROUP
