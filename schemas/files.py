"""The small text files an operator names — a config, a password — read whole before use, and
the folders an operator names for the gateway to write in.

A wrong name is easy to give (``/dev/zero``, a directory, a named pipe, a binary file) and
must be a one-line refusal, never a read without end, a wait for ever or a traceback; the
gateway's config (``schemas.config``) and the command line's password file
(``cli.client_session``) are read here, so that both refuse the same things the same way.

Rules of this file:

1. A file is read to its limit and one byte more: a longer one is refused, whatever it is.
2. A named pipe is opened without waiting for a writer, then read as a file is (``--config
   <(envsubst < gw.toml)``): one nobody writes to reads as empty, and one whose writer sends
   nothing more for ``STALL_S`` (while keeping it open) is refused.
3. Text is UTF-8, after the byte-order mark some editors write first, if any; where it stops
   being UTF-8 is named (its line and byte).
4. Every refusal is a ``FileRefused`` whose message names the file.
5. A folder to write in is made where it is missing; a file in its place is named as one, not
   told in mkdir's words ("File exists").
"""

from __future__ import annotations

import codecs
import os
import select
from pathlib import Path

#: The longest a read waits for more of a file (rule 2): a pipe's writer sends what it has at
#: once (``envsubst``, ``cat``); one silent this long is stuck, and ``busgate run`` under
#: systemd would otherwise wait for ever, never starting nor failing.
STALL_S = 10.0
#: Why an empty path is refused wherever one is named: ``Path("")`` is the working directory,
#: which nobody means by it.
EMPTY_PATH = "an empty path names no file ('.' is this folder)"


class FileRefused(ValueError):
    """A file that cannot be what it was named as (rule 4)."""


def read_text(path: str | Path, limit: int, what: str) -> str:
    """The UTF-8 text of ``path``, at most ``limit`` bytes of it (rules 1–3); ``what`` the
    file should be, for a refusal (``a config``: "… is over 1 MiB: not a config")."""
    if not str(path):
        raise FileRefused(EMPTY_PATH)
    try:
        with open(path, "rb", opener=_opener_no_wait) as file:
            data = _read(file.fileno(), limit + 1, path)
    except OSError as exc:
        raise FileRefused(f"cannot read {path}: {exc.strerror}") from exc
    if len(data) > limit:
        raise FileRefused(f"{path} is over {_size(limit)}: not {what}")
    try:
        return data.removeprefix(codecs.BOM_UTF8).decode("utf-8")
    except UnicodeDecodeError as exc:
        line = exc.object.count(b"\n", 0, exc.start) + 1
        raise FileRefused(
            f"{path} is not UTF-8 text (line {line} has the byte "
            f"0x{exc.object[exc.start]:02x}): save it as UTF-8"
        ) from exc


def make_folder(path: str | Path) -> Path:
    """``path`` as a folder, made with its parents where missing (rule 5)."""
    if not str(path):
        raise FileRefused(EMPTY_PATH)
    folder = Path(path)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        there = (part for part in (folder, *folder.parents) if part.exists() or part.is_symlink())
        file = next(there)
        raise FileRefused(f"{file} is a file, not a folder") from None
    except OSError as exc:
        raise FileRefused(f"cannot make the folder {path}: {exc.strerror}") from exc
    return folder


def _read(fd: int, most: int, path: str | Path) -> bytes:
    """Up to ``most`` bytes of ``fd`` (opened not to wait), to its end: waiting for more at
    most ``STALL_S`` each time a writer has sent nothing yet (rules 1 and 2)."""
    chunks: list[bytes] = []
    left = most
    while left > 0:
        try:
            chunk = os.read(fd, left)
        except BlockingIOError:  # a writer holds it open and has sent nothing more yet
            if not select.select([fd], [], [], STALL_S)[0]:
                raise FileRefused(
                    f"{path}: nothing more came for {STALL_S:g} s: whatever writes it is "
                    "stuck; give a file, or a pipe that ends"
                ) from None
            continue
        if not chunk:  # its end, or a pipe nobody writes to
            break
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def _opener_no_wait(path: str, flags: int) -> int:
    """Open without waiting for a writer, should ``path`` be a named pipe (rule 2)."""
    return os.open(path, flags | os.O_NONBLOCK)


def _size(limit: int) -> str:
    """``1048576`` → ``1 MiB``, ``4096`` → ``4 KiB``."""
    for unit, size in (("MiB", 1024 * 1024), ("KiB", 1024)):
        if limit >= size:
            return f"{limit / size:g} {unit}"
    return f"{limit} bytes"
