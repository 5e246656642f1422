"""The one way a small input file (a REF.json or CAL.json, a scanner pose, a model.yaml) is read whole: from a
regular file only and never more than a bound.

Checking ``stat().st_size`` and then reading the path is not enough: a FIFO or a character device (/dev/zero)
reports size 0 and then blocks the reader or feeds it until memory runs out, and a file can grow between the check
and the read. So the file is opened without blocking (opening a FIFO for reading otherwise waits for a writer), the
open handle is checked to be a regular file, and at most ``max_bytes + 1`` bytes are read from that same handle."""

from __future__ import annotations

import os
import stat

from hood_decomp.errors import HoodDecompError

_KINDS = ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
          (stat.S_ISDIR, "a directory"), (stat.S_ISSOCK, "a socket"))


def read_small_file(path: str | os.PathLike, max_bytes: int, error: type[HoodDecompError], what: str) -> bytes:
    """The bytes of the regular file ``path`` (at most ``max_bytes``). ``error`` (one line, naming ``what`` and the
    path) for anything else: a FIFO, a device, a directory, a socket, or a file of more than ``max_bytes`` bytes.
    OSError when it cannot be opened or read (the caller names it)."""
    descriptor = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    try:
        mode = os.fstat(descriptor).st_mode
        if not stat.S_ISREG(mode):
            kind = next((name for test, name in _KINDS if test(mode)), "of another kind")
            raise error(f"{what} {path} is {kind}, not a regular file")
        os.set_blocking(descriptor, True)
        chunks, left = [], max_bytes + 1
        while left > 0:
            chunk = os.read(descriptor, min(left, 1 << 20))
            if not chunk:
                break
            chunks.append(chunk)
            left -= len(chunk)
    finally:
        os.close(descriptor)
    data = b"".join(chunks)
    if len(data) > max_bytes:
        raise error(f"{what} {path} is larger than {max_bytes} bytes")
    return data
