"""Which files of a directory a block of code opens, seen by the kernel (inotify IN_OPEN), so opens made by C
libraries (the HDF5 library reading external storage or following an external link) are seen as well as Python's.

Linux only: :func:`watch_opens` raises OSError where inotify is missing (the tests that use it then fail, they do not
pass silently).
"""

from __future__ import annotations

import ctypes
import os
import struct
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

_IN_OPEN = 0x00000020
_HEADER = struct.Struct("iIII")  # struct inotify_event: wd, mask, cookie, len (then len bytes of name)


@contextmanager
def watch_opens(*directories: Path) -> Iterator[set[Path]]:
    """Yield a set that, after the block, holds every file in ``directories`` opened (by anyone) during the block."""
    libc = ctypes.CDLL(None, use_errno=True)
    fd = libc.inotify_init1(os.O_NONBLOCK | os.O_CLOEXEC)
    if fd < 0:
        raise OSError(ctypes.get_errno(), "inotify_init1 failed")
    opened: set[Path] = set()
    try:
        watches = {}
        for directory in directories:
            wd = libc.inotify_add_watch(fd, os.fsencode(directory), _IN_OPEN)
            if wd < 0:
                raise OSError(ctypes.get_errno(), f"inotify_add_watch {directory} failed")
            watches[wd] = Path(directory)
        yield opened
        while True:
            try:
                buffer = os.read(fd, 1 << 16)
            except BlockingIOError:
                break
            offset = 0
            while offset < len(buffer):
                wd, mask, _, length = _HEADER.unpack_from(buffer, offset)
                name = buffer[offset + _HEADER.size: offset + _HEADER.size + length].rstrip(b"\0")
                offset += _HEADER.size + length
                if mask & _IN_OPEN and name:
                    opened.add(watches[wd] / os.fsdecode(name))
    finally:
        os.close(fd)
