"""model.yaml validation beyond the matrix: the alias bomb's memory, and a valid model still loading exactly."""

import tracemalloc

import pytest

from hood_decomp.errors import ModelError
from hood_decomp.io.model_files import load_model
from tests.bad_inputs import BOMB


def test_an_alias_bomb_is_refused_without_expanding(tmp_path):
    """Fails if the 421-byte YAML alias bomb is expanded (loaded, walked or printed) before it is refused: the peak
    of Python allocations while refusing it stays under 2 MB (expanded it is billions of list entries), and the
    message is one short line naming aliases."""
    (tmp_path / "model.yaml").write_text(BOMB)
    tracemalloc.start()
    try:
        with pytest.raises(ModelError) as refused:
            load_model(tmp_path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 2 * 2**20, f"peak {peak / 2**20:.1f} MB"
    message = str(refused.value)
    assert "aliases" in message and "\n" not in message and len(message) < 300


def test_the_tiny_hood_round_trips(tiny_workspace):
    """Fails if the stricter reader refuses a model the writer wrote, or changes its geometry (model_id)."""
    from hood_decomp.core.fe.hood_preset import build_hood

    assert load_model(tiny_workspace.model).model_id == build_hood(grid=(20, 20)).model_id
