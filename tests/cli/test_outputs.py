"""--out and every other output: checked before any work, never an input (by path, symlink or hard link), written
whole or not at all."""

import hashlib
import os
import shutil

import pytest

from hood_decomp.cli import main


def _digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture
def ws(tiny_workspace, tmp_path):
    """A private copy of the workspace's model, ensemble and bases (these tests try to overwrite them)."""
    shutil.copytree(tiny_workspace.model, tmp_path / "model")
    for name in ("ensemble.h5", "bases.h5", "field.vtu"):
        shutil.copyfile(tiny_workspace.root / name, tmp_path / name)
    return tmp_path


def _refused(argv, capsys, *fragments):
    status = main(argv)
    err = capsys.readouterr().err.strip()  # progress lines may come first; the error is one line, the last
    errors = [line for line in err.splitlines() if ": error: " in line]
    assert status == 2 and errors == err.splitlines()[-1:] and "Traceback" not in err, err
    for fragment in fragments:
        assert fragment in errors[0], err
    return errors[0]


def test_an_output_is_never_an_input(ws, capsys):
    """Fails if any of the issue's destructive commands (bases --out E, ensemble --out M/model.yaml, simulate --out
    M/mesh.vtu, ensemble --export --field E, close-loop into the bases' directory) or the same through a symlink or a
    hard link overwrites an input, or is not refused with one named line."""
    os.link(ws / "ensemble.h5", ws / "hard_link.h5")
    os.symlink(ws / "ensemble.h5", ws / "soft_link.h5")
    shutil.copyfile(ws / "bases.h5", ws / "model" / "bases_closed_loop.h5")
    before = {p: _digest(p) for p in ws.rglob("*") if p.is_file()}
    model = str(ws / "model")
    for argv in (["bases", "--ensemble", str(ws / "ensemble.h5"), "--out", str(ws / "ensemble.h5")],
                 ["bases", "--ensemble", str(ws / "ensemble.h5"), "--out", str(ws / "hard_link.h5")],
                 ["bases", "--ensemble", str(ws / "ensemble.h5"), "--out", str(ws / "soft_link.h5")],
                 ["bases", "--ensemble", str(ws / "ensemble.h5"), "--model", model, "--out",
                  str(ws / "model" / "mesh.vtu")],
                 ["ensemble", "--model", model, "--out", str(ws / "model" / "model.yaml")],
                 ["simulate", "--model", model, "--out", str(ws / "model" / "mesh.vtu")],
                 ["scan", "--model", model, "--out", str(ws / "model" / "model.yaml")],
                 ["ensemble", "--export", "training:0", "--out", str(ws / "ensemble.h5"), "--field",
                  str(ws / "hard_link.h5")],
                 ["estimate", "--bases", str(ws / "bases.h5"), "--field", str(ws / "field.vtu"), "--json",
                  str(ws / "field.vtu")],
                 ["close-loop", "--model", model, "--bases", str(ws / "model" / "bases_closed_loop.h5"), "--field",
                  str(ws / "field.vtu"), "--out", model]):
        _refused(argv, capsys, "overwrite the input")
    assert {p: _digest(p) for p in ws.rglob("*") if p.is_file()} == before


def test_a_bad_output_is_refused_before_any_work(ws, capsys, monkeypatch):
    """Fails if an output in a missing directory, a directory given for a file, a file given for a directory or an
    unwritable place is found only after the computation (the computation is replaced by a tripwire here)."""
    import hood_decomp.core.method.bases as method_bases

    def tripwire(*args, **kwargs):
        raise AssertionError("the work started before the output was checked")

    monkeypatch.setattr(method_bases, "build_bases", tripwire)
    ensemble = str(ws / "ensemble.h5")
    _refused(["bases", "--ensemble", ensemble, "--out", str(ws / "missing" / "b.h5")], capsys, "does not exist")
    _refused(["bases", "--ensemble", ensemble, "--out", str(ws / "model")], capsys, "is a directory")
    _refused(["bases", "--ensemble", ensemble, "--out", "/proc/hood_decomp_bases.h5"], capsys, "cannot write")
    _refused(["bases", "--ensemble", ensemble, "--out", str(ws / "b.h5"), "--plots", str(ws / "field.vtu")], capsys,
             "is a file")
    _refused(["close-loop", "--model", str(ws / "model"), "--bases", str(ws / "bases.h5"), "--field",
              str(ws / "field.vtu"), "--out", str(ws / "field.vtu")], capsys, "is a file")
    _refused(["decompose", "--bases", str(ws / "bases.h5"), "--field", str(ws / "field.vtu"), "--json",
              str(ws / "nowhere" / "d.json")], capsys, "does not exist")
    _refused(["model", "--out", str(ws / "field.vtu")], capsys, "is a file")
    assert not (ws / "b.h5").exists()


def test_a_failed_write_leaves_no_half_file_and_keeps_the_old_one(ws, capsys, monkeypatch):
    """Fails if a verb that fails while writing its output leaves a partial file, or destroys the file that was at
    --out before (outputs go to a temporary file renamed on success), or if a new output keeps the temporary file's
    private mode instead of the one a plain write gives."""
    import hood_decomp.io.bases as io_bases
    from hood_decomp.errors import BasisError

    real = io_bases.save_bases

    def half_then_fail(path, bases):
        real(path, bases)
        with open(path, "r+b") as handle:
            handle.truncate(1000)
        raise BasisError("disk full (simulated)")

    monkeypatch.setattr(io_bases, "save_bases", half_then_fail)
    out = ws / "b.h5"
    out.write_bytes(b"the previous bases")
    _refused(["bases", "--ensemble", str(ws / "ensemble.h5"), "--out", str(out)], capsys, "disk full")
    assert out.read_bytes() == b"the previous bases"
    assert sorted(p.name for p in ws.iterdir() if p.name.startswith(".")) == []
    monkeypatch.setattr(io_bases, "save_bases", real)
    assert main(["bases", "--ensemble", str(ws / "ensemble.h5"), "--out", str(out)]) == 0
    assert out.stat().st_size > 10_000
    fresh = ws / "fresh.h5"
    assert main(["bases", "--ensemble", str(ws / "ensemble.h5"), "--out", str(fresh)]) == 0
    umask = os.umask(0)
    os.umask(umask)
    assert fresh.stat().st_mode & 0o777 == 0o666 & ~umask  # not the temporary file's 0600


@pytest.mark.parametrize("method", ["contact", "pca"])
def test_an_estimator_that_cannot_be_fitted_while_the_field_is_read_still_fails_once_by_name(ws, capsys, method):
    """`estimate` fits its estimator in a second thread while it reads the field. Fails if an error of that fit (a
    part temperature for bases without a thermal response) is lost (exit 0, or a result written), reported twice, or
    shown as a traceback instead of the one named line with exit status 2."""
    out = ws / "estimate.json"
    line = _refused(["estimate", "--bases", str(ws / "bases.h5"), "--field", str(ws / "field.vtu"), "--method",
                     method, "--temperature-k", "5", "--json", str(out)], capsys, "thermal response")
    assert not out.exists(), line
