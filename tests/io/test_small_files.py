"""Small input files other than references (a scanner pose, a model.yaml) are read as a reference is
(io.small_files.read_small_file): from a regular file only, never more than their bound. A FIFO is refused at once by
name (it would block the reader), and a file over the bound is refused without being read whole."""

from __future__ import annotations

import os

import pytest

from hood_decomp.errors import ModelError, ScanError
from hood_decomp.io.model_files import load_model
from hood_decomp.io.poses import MAX_POSE_FILE_BYTES, read_pose_file


@pytest.mark.parametrize(("reader", "error", "name"), [
    (read_pose_file, ScanError, "pose.json"),
    (load_model, ModelError, "model.yaml"),
])
def test_a_fifo_is_refused_by_name_without_blocking(tmp_path, reader, error, name):
    """Fails if the reader opens the FIFO blocking (the test would hang: no writer ever comes; run it with a timeout
    to see it red) or reads it instead of refusing it with a one-line error naming the kind of file."""
    os.mkfifo(tmp_path / name)
    with pytest.raises(error, match=f"{name} is a FIFO, not a regular file$"):
        reader(tmp_path / name)


def test_a_pose_file_over_its_bound_is_refused(tmp_path):
    """Fails if a pose file of more than MAX_POSE_FILE_BYTES (a list of 16 numbers padded with spaces: valid JSON)
    is read and accepted instead of refused naming the bound."""
    path = tmp_path / "pose.json"
    numbers = "[1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]"
    path.write_text(numbers + " " * MAX_POSE_FILE_BYTES)
    with pytest.raises(ScanError, match=f"larger than {MAX_POSE_FILE_BYTES} bytes"):
        read_pose_file(path)
    path.write_text(numbers)
    assert read_pose_file(path).shape == (4, 4)
