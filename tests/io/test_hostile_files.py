"""Hostile HDF5 files: a bases file or ensemble store must not make hood-decomp open any other file (checked by the
kernel, inotify, so the HDF5 C library's opens count), leak another file's content, load a filter plugin, or pass
with a rewritten model_id."""

import hashlib

import h5py
import numpy as np
import pytest

from hood_decomp.cli import main
from tests.bad_inputs import H5_MUTATIONS, SECRET, mutated_copy
from tests.file_audit import watch_opens

#: (file kind, mutation, dataset it hits): every way a file can reach outside itself, in both file kinds
REACHING_OUT = [
    ("bases", "external storage (text)", "hierarchical/effect_names"),
    ("bases", "external storage (numbers)", "pca/components"),
    ("bases", "external link", "hierarchical/effect_names"),
    ("bases", "external link", "parameters/names"),
    ("bases", "external link beside", "pca/components"),
    ("bases", "virtual dataset", "pca/lower"),
    ("bases", "unknown filter (plugin)", "pca/components"),
    ("ensemble", "external storage (text)", "names"),
    ("ensemble", "external storage (numbers)", "training/normal_displacement"),
    ("ensemble", "external link", "names"),
    ("ensemble", "virtual dataset", "lower"),
    ("ensemble", "unknown filter (plugin)", "training/displacement"),
]


def _digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _argv(kind, path, ws, tmp_path):
    if kind == "bases":
        return ["decompose", "--bases", str(path), "--field", str(ws.field)]
    return ["bases", "--ensemble", str(path), "--out", str(tmp_path / "out.h5")]


@pytest.mark.parametrize(("kind", "mutation", "target"), REACHING_OUT, ids=[" ".join(c) for c in REACHING_OUT])
def test_no_file_outside_the_inputs_is_opened(kind, mutation, target, tiny_workspace, tmp_path, capsys):
    """Fails if a bases file or ensemble store can make hood-decomp open another file (external storage, external
    link, virtual dataset), load a filter plugin, or print the other file's content; or if the refusal is not one
    named line with exit status 2, or an output file is left behind."""
    ws = tiny_workspace
    edit, fragment = H5_MUTATIONS[mutation]
    source = ws.bases if kind == "bases" else ws.ensemble
    hostile = mutated_copy(source, tmp_path / f"hostile_{kind}.h5", lambda h5: edit(h5, target, ws))
    before = {p: _digest(p) for p in (hostile, ws.field, ws.secret, ws.other)}
    with watch_opens(ws.decoys, tmp_path, ws.root) as opened:
        status = main(_argv(kind, hostile, ws, tmp_path))
    out, err = capsys.readouterr()
    assert status == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and fragment.lower() in lines[0].lower(), err
    assert SECRET not in out + err and "SECRET" not in out + err
    inputs = {hostile, ws.field}
    own = {p for p in opened if p.name.startswith(".hood_decomp_probe_")}  # check_output's writability probe
    assert opened - own <= inputs, f"opened besides the inputs: {sorted(map(str, opened - own - inputs))}"
    assert {p: _digest(p) for p in before} == before
    assert not (tmp_path / "out.h5").exists()


def test_the_audit_sees_what_the_hdf5_library_opens(tiny_workspace, tmp_path):
    """Fails if the inotify audit above is blind to opens made inside the HDF5 C library (then the test above could
    not fail): reading an external-storage dataset through h5py directly must show the secret file opened."""
    ws = tiny_workspace
    edit, _ = H5_MUTATIONS["external storage (text)"]
    hostile = mutated_copy(ws.bases, tmp_path / "hostile.h5", lambda h5: edit(h5, "hierarchical/effect_names", ws))
    with watch_opens(ws.decoys) as opened, h5py.File(hostile, "r") as h5:
        leaked = h5["hierarchical/effect_names"][()].tobytes().decode()
    assert SECRET in leaked and ws.secret in opened
    with watch_opens(ws.decoys) as opened, h5py.File(hostile, "r") as h5:
        h5["hierarchical/effect_names"]  # opening the dataset object alone does not read the file
    assert ws.secret not in opened


def _rewrite_model_id(h5):
    for name in ("/", "skin", "pca", "hierarchical", "reduced_model"):
        (h5.attrs if name == "/" else h5[name].attrs)["model_id"] = "0123456789abcdef"


def _shift_one_array(h5):
    h5["pca/mean_field"][0] = h5["pca/mean_field"][0] + 0.5


@pytest.mark.parametrize("edit", [_rewrite_model_id, _shift_one_array], ids=["model_id rewritten", "array altered"])
def test_a_rewritten_bases_file_does_not_pass(edit, tiny_workspace, tmp_path, capsys):
    """Fails if a bases file whose model_id attributes (all five, consistently) or one array were rewritten after
    writing loads: the stored bases_id no longer matches the content."""
    forged = mutated_copy(tiny_workspace.bases, tmp_path / "forged.h5", edit)
    assert main(["estimate", "--bases", str(forged), "--field", str(tiny_workspace.field)]) == 2
    assert "does not match its bases_id" in capsys.readouterr().err


def test_a_rewritten_ensemble_store_does_not_pass(tiny_workspace, tmp_path, capsys):
    """Fails if an ensemble store whose model_id or skin was rewritten loads (content_id no longer matches)."""
    for name, edit in (("id", lambda h5: h5.attrs.__setitem__("model_id", "0123456789abcdef")),
                       ("skin", lambda h5: h5["skin/points"].__setitem__((0, 0), np.float64(1e3)))):
        forged = mutated_copy(tiny_workspace.ensemble, tmp_path / f"forged_{name}.h5", edit)
        assert main(["bases", "--ensemble", str(forged), "--out", str(tmp_path / "b.h5")]) == 2
        assert "does not match its content_id" in capsys.readouterr().err


def test_a_node_given_a_hostile_bases_file_reports_it_without_the_secret(tiny_workspace, tmp_path):
    """Fails if the nodes' bases loader (every node loads its bases through it) takes a bases file whose effect names
    live in another file, or puts that file's content into the reason it reports on /diagnostics (the issue's leak:
    the decomposition node published /etc/passwd as effect names)."""
    from hood_decomp.ros.node_common import load_bases_or_reason

    edit, _ = H5_MUTATIONS["external storage (text)"]
    hostile = mutated_copy(tiny_workspace.bases, tmp_path / "hostile.h5",
                           lambda h5: edit(h5, "hierarchical/effect_names", tiny_workspace))
    with watch_opens(tiny_workspace.decoys) as opened:
        bases, reason = load_bases_or_reason(str(hostile))
    assert bases is None and "external" in reason and SECRET not in reason and not opened
