"""The one way an input file is opened (:func:`open_regular`: a regular file only, checked on the open descriptor)
and a small one (a REF.json or CAL.json, a scanner pose, a model.yaml, a --truth JSON) read whole, never more than a
bound (:func:`read_small_file`).

Checking ``stat().st_size`` or ``is_file()`` and then opening the path is not enough: a FIFO or a character device
(/dev/zero) reports size 0 and then blocks the reader or feeds it until memory runs out, and another file can be
swapped in between the check and the open. So the file is opened without blocking (opening a FIFO for reading
otherwise waits for a writer), the open descriptor is checked to be a regular file, and everything is read from that
same descriptor (a reader that takes only a name gets :func:`descriptor_path`, which opens that very file again)."""

from __future__ import annotations

import os
import stat
from typing import BinaryIO

from hood_decomp.errors import HoodDecompError

_KINDS = ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
          (stat.S_ISDIR, "a directory"), (stat.S_ISSOCK, "a socket"))


def open_regular(path: str | os.PathLike, error: type[HoodDecompError], what: str) -> BinaryIO:
    """``path`` opened for binary reading when it is a regular file, judged on the open descriptor (so a FIFO swapped
    in after a caller's check is refused, not waited on). ``error`` (one line, naming ``what`` and the path) for a
    FIFO, a device, a directory or a socket; OSError when it cannot be opened (the caller names it)."""
    descriptor = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    try:
        mode = os.fstat(descriptor).st_mode
        if not stat.S_ISREG(mode):
            kind = next((name for test, name in _KINDS if test(mode)), "of another kind")
            raise error(f"{what} {path} is {kind}, not a regular file")
        os.set_blocking(descriptor, True)
        return os.fdopen(descriptor, "rb")
    except BaseException:
        os.close(descriptor)
        raise


def descriptor_path(handle: BinaryIO, path: str | os.PathLike) -> str:
    """A name for a reader that takes only a name (meshio): /proc/self/fd/N on Linux, which opens the file ``handle``
    holds (the one :func:`open_regular` checked), not whatever ``path`` names now; ``path`` where /proc is missing."""
    proc = f"/proc/self/fd/{handle.fileno()}"
    return proc if os.path.exists(proc) else os.fspath(path)


def read_small_file(path: str | os.PathLike, max_bytes: int, error: type[HoodDecompError], what: str) -> bytes:
    """The bytes of the regular file ``path`` (at most ``max_bytes``; :func:`open_regular`). ``error`` (one line,
    naming ``what`` and the path) for anything else: a FIFO, a device, a directory, a socket, or a file of more than
    ``max_bytes`` bytes. OSError when it cannot be opened or read (the caller names it)."""
    chunks, left = [], max_bytes + 1
    with open_regular(path, error, what) as handle:
        while left > 0:  # in pieces: one read of max_bytes + 1 would allocate that much for a 400-byte file
            chunk = handle.read(min(left, 1 << 20))
            if not chunk:
                break
            chunks.append(chunk)
            left -= len(chunk)
    data = b"".join(chunks)
    if len(data) > max_bytes:
        raise error(f"{what} {path} is larger than {max_bytes} bytes")
    return data
