"""JSON out and in: non-finite numbers become null on the way out, and are refused on the way in."""

import json

import numpy as np
import pytest

from hood_decomp.cli import main
from hood_decomp.io.json_values import json_ready, loads_strict


def test_non_finite_numbers_become_null_everywhere():
    """Fails if a NaN or infinity anywhere in a nested result (numpy scalar, array, tuple, mapping) survives into
    JSON, or a finite number or a bool changes."""
    payload = {"a": np.float32("nan"), "b": [1.5, np.inf, (-np.inf, 2)], "c": np.array([[0.25, np.nan]]),
               "d": {"e": np.bool_(True), "f": np.int64(3)}}
    assert json.dumps(json_ready(payload), allow_nan=False) == (
        '{"a": null, "b": [1.5, null, [null, 2]], "c": [[0.25, null]], "d": {"e": true, "f": 3}}')


@pytest.mark.parametrize("text", ['{"x": NaN}', '[Infinity]', '{"y": -Infinity}', "[" * 50_000])
def test_the_strict_reader_refuses_what_json_does_not_have(text):
    """Fails if NaN, Infinity or stack-exhausting nesting are read (Python's json module accepts the first three)."""
    with pytest.raises(ValueError):
        loads_strict(text)


def test_every_json_a_verb_prints_is_strict_json(tiny_workspace, tmp_path, capsys):
    """Fails if simulate, estimate or decompose print anything a strict JSON reader refuses (NaN, Infinity) on a
    field whose unseen nodes are NaN."""
    from hood_decomp.io.bases import load_bases
    from hood_decomp.io.fields import read_field, write_field

    ws = tiny_workspace
    assert main(["simulate", "--model", str(ws.model), "--set", "LOCK_L=0.3", "--out", str(tmp_path / "f.vtu")]) == 0
    printed = [capsys.readouterr().out]
    field, _ = read_field(tmp_path / "f.vtu")
    field.normal_displacement[:100] = np.nan  # a quarter of the skin unseen
    field.displacement[:100] = np.nan  # and its 3D displacement with it (simulate writes one)
    write_field(tmp_path / "partial.vtu", load_bases(ws.bases).skin, field)
    for verb in ("estimate", "decompose"):
        assert main([verb, "--bases", str(ws.bases), "--field", str(tmp_path / "partial.vtu")]) == 0
        printed.append(capsys.readouterr().out)
    for text in printed:
        assert isinstance(loads_strict(text), dict)
