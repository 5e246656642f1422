"""A REF.json read once for a set of bases (io.calibration_files.read_reference, what ``--reference`` and the nodes'
``reference`` parameter and ``set_reference`` service use): the prepared reference makes any number of fields
relative as the written-out formula does, and the references a node must refuse are refused by name."""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from hood_decomp.core.fe.ensemble import solve_members
from hood_decomp.core.types import DisplacementField, FieldErrorModel
from hood_decomp.errors import CalibrationError
from hood_decomp.io.calibration_files import file_key, read_reference
from hood_decomp.io.fields import write_field
from tests.bad_inputs import outcome_without_blocking


def _reference(directory, skin, values, setting):
    write_field(directory / "ref.vtu", skin, DisplacementField(skin.model_id, values, 1.0, 0.01))
    (directory / "ref.json").write_text(json.dumps({"field": "ref.vtu", "setting": setting}))
    return directory / "ref.json"


def test_a_prepared_reference_is_measured_minus_reference_plus_the_models_field(coarse_hood, tmp_path):
    """Fails if a reference read once does not give, for each of several fields, measured - reference + the model's
    field at the reference's setting (written out here, the model's field solved by the FE reduction directly), with
    the node variances of field and reference added, unseen where the field is unseen."""
    reduced, skin = coarse_hood.reduced, coarse_hood.skin
    rng = np.random.default_rng(5)
    setting = np.zeros(len(reduced.names))
    setting[reduced.names.index("LOCK_L")] = 0.25
    reference_values = rng.normal(0.0, 0.3, skin.n_nodes)
    reference = read_reference(_reference(tmp_path, skin, reference_values, {"LOCK_L": 0.25}), coarse_hood.bases)
    own = solve_members(reduced, setting[None]).normal_displacement[0]
    assert reference.model_id == reduced.model_id
    for _ in range(3):
        values = rng.normal(0.0, 0.5, skin.n_nodes)
        values[:10] = np.nan
        field = DisplacementField(reduced.model_id, values, 1.0, 0.02, FieldErrorModel.stated(0.02, skin.n_nodes))
        relative = reference.relative(field, coarse_hood.bases)
        np.testing.assert_allclose(relative.normal_displacement, values - reference_values + own, atol=1e-6)
        np.testing.assert_allclose(relative.errors.node_std, np.hypot(0.02, 0.01))
        assert relative.coverage == pytest.approx(1.0 - 10 / skin.n_nodes)


def test_a_reference_of_another_model_or_for_bases_without_a_reduced_model_is_refused(coarse_hood, tmp_path):
    """Fails if a reference whose field is of another model_id, or a reference for bases without the reduced model
    it needs, is accepted instead of refused with a CalibrationError naming the problem and the file."""
    foreign = replace(coarse_hood.skin, model_id="0123456789abcdef")
    path = _reference(tmp_path, foreign, np.zeros(foreign.n_nodes), {})
    with pytest.raises(CalibrationError, match=r"ref\.json: reference model_id '0123456789abcdef' is not the bases'"):
        read_reference(path, coarse_hood.bases)
    path = _reference(tmp_path, coarse_hood.skin, np.zeros(foreign.n_nodes), {})
    with pytest.raises(CalibrationError, match="hold no reduced model"):
        read_reference(path, replace(coarse_hood.bases, reduced_model=None))


def _read_in_a_bounded_process(path: str) -> subprocess.CompletedProcess:
    """read_entries(path) in a process held to 1 GB of address space and 60 s: a reader that takes /dev/zero for a
    file fails there (MemoryError) instead of eating the machine's memory."""
    code = (f"from hood_decomp.io.calibration_files import read_entries\nread_entries({path!r}, None, single=True)")
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                          preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30)))


def test_a_fifo_or_a_device_given_as_a_reference_is_refused_by_name(coarse_hood, tmp_path):
    """Fails if a FIFO blocks the reader (it reports size 0; opening it for reading waits for a writer) or if
    /dev/zero (size 0, endless) is read instead of refused at once with a one-line CalibrationError naming the kind
    of file. A blocked reader is unblocked after 10 s (a writer opens and closes the FIFO) so the test fails, not
    hangs."""
    fifo = tmp_path / "ref.json"
    os.mkfifo(fifo)
    error = outcome_without_blocking(lambda: read_reference(fifo, coarse_hood.bases), fifo)
    assert isinstance(error, CalibrationError) and "is a FIFO, not a regular file" in str(error), error
    assert "\n" not in str(error)
    run = _read_in_a_bounded_process("/dev/zero")
    assert "CalibrationError: reference file /dev/zero is a character device, not a regular file" in run.stderr, (
        run.stderr[-2000:])


def test_a_reference_reads_the_same_files_until_either_changes(coarse_hood, tmp_path):
    """Fails if a prepared reference does not say it reads what REF.json ``path`` holds now (what lets parts naming
    the same file share one read), or still says so after the field file it names or the REF.json itself changed
    (a part given the file then would get the old field)."""
    skin = coarse_hood.skin
    path = _reference(tmp_path, skin, np.zeros(skin.n_nodes), {})
    reference = read_reference(path, coarse_hood.bases)
    assert reference.reads(file_key(path)) and reference.reads(file_key(tmp_path / "." / "ref.json"))
    write_field(tmp_path / "ref.vtu", skin, DisplacementField(skin.model_id, np.ones(skin.n_nodes), 1.0, 0.01))
    assert not reference.reads(file_key(path))
    reference = read_reference(path, coarse_hood.bases)
    os.utime(path, ns=(1, 1))
    assert not reference.reads(file_key(path))


def test_a_reference_is_refused_for_fields_used_with_other_bases(coarse_hood, tmp_path):
    """Fails if a reference read for the uncalibrated bases makes a field relative for calibrated ones (their
    reduced model stiffer: the model's field at the reference's setting is another) instead of refusing it with a
    CalibrationError saying to read it again."""
    skin, reduced = coarse_hood.skin, coarse_hood.reduced
    reference = read_reference(_reference(tmp_path, skin, np.zeros(skin.n_nodes), {"LOCK_L": 0.25}),
                               coarse_hood.bases)
    stiffer = replace(coarse_hood.bases, reduced_model=replace(reduced, k=reduced.k * 1.25))
    field = DisplacementField(reduced.model_id, np.zeros(skin.n_nodes), 1.0, 0.02)
    with pytest.raises(CalibrationError, match=r"ref\.json was read for bases [0-9a-f]{16}, the field is used with "
                       r"bases [0-9a-f]{16}: read the reference again"):
        reference.relative(field, stiffer)
