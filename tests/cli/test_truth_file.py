"""`close-loop --truth` is read as every small input is (io.small_files.read_small_file): a FIFO or a device given as
the truth file is refused at once with one line and exit status 2, never waited on or read without end."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest


@pytest.mark.parametrize("kind", ["fifo", "zero"])
def test_truth_that_is_no_regular_file_is_one_line_and_exit_2(tiny_workspace, tmp_path, kind):
    """Fails if close-loop opens a FIFO given as --truth blocking (no writer ever comes: the run times out) or reads
    /dev/zero (endless; the process is held to 2 GB of address space, so it dies instead of eating the machine),
    instead of refusing either with exit status 2 and one error line naming the kind of file, before any output."""
    import resource

    truth = tmp_path / "truth.json"
    if kind == "fifo":
        os.mkfifo(truth)
    else:
        truth = "/dev/zero"
    out = tmp_path / "out"
    command = [sys.executable, "-m", "hood_decomp.cli", "close-loop", "--model", str(tiny_workspace.model), "--bases",
               str(tiny_workspace.bases), "--field", str(tiny_workspace.field), "--truth", str(truth), "--out",
               str(out)]
    run = subprocess.run(command, capture_output=True, text=True, timeout=60,
                         preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30)))
    lines = run.stderr.strip().splitlines()
    named = "a FIFO" if kind == "fifo" else "a character device"
    assert run.returncode == 2, run.stderr[-2000:]
    assert len(lines) == 1 and f"--truth {truth} is {named}, not a regular file" in lines[0], run.stderr[-2000:]
    assert not out.exists()
