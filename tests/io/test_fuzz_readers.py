"""Property-based fuzzing of every file reader (hypothesis): random truncation, bit flips, byte runs and header lies
applied to a valid file. Each reader must give a named project error (HoodDecompError) or a correct result, never
another exception and never a hang (a generous alarm per example). Examples are derandomized (the same every run,
so CI is stable) and counted; the counts are printed.
"""

from __future__ import annotations

import re
import shutil
import signal
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hood_decomp.errors import HoodDecompError

EXAMPLES = 500
HANG_GUARD_S = 20  # no example comes near this; it only turns a hang into a failure


class HangError(Exception):
    pass


def _alarm(signum, frame):
    raise HangError(f"a reader ran longer than {HANG_GUARD_S} s")


@st.composite
def mutations(draw, size: int, header: int) -> list[tuple]:
    """A list of edits of a file of ``size`` bytes whose first ``header`` bytes are its header: truncations, bit
    flips (anywhere, or in the header), runs of 0x00/0xff/random bytes."""
    kinds = st.sampled_from(["truncate", "flip", "flip header", "run"])
    edits = []
    for kind in draw(st.lists(kinds, min_size=1, max_size=4)):
        if kind == "truncate":
            edits.append(("truncate", draw(st.integers(0, size))))
        elif kind in ("flip", "flip header"):
            end = max(1, min(size, header) if kind == "flip header" else size)
            edits.append(("flip", draw(st.integers(0, end - 1)), draw(st.integers(0, 7))))
        else:
            edits.append(("run", draw(st.integers(0, size)), draw(st.binary(min_size=1, max_size=64))))
    return edits


def apply(data: bytes, edits: list[tuple]) -> bytes:
    buffer = bytearray(data)
    for edit in edits:
        if edit[0] == "truncate":
            del buffer[edit[1]:]
        elif edit[0] == "flip" and edit[1] < len(buffer):
            buffer[edit[1]] ^= 1 << edit[2]
        elif edit[0] == "run":
            buffer[edit[1]:edit[1] + len(edit[2])] = edit[2]
    return bytes(buffer)


def header_lie(text: bytes, number: int) -> bytes:
    """Replace one whole number of a text header (a count, a size, an index) by ``number``."""
    matches = list(re.finditer(rb"(?<![\w.])\d+(?![\w.])", text))
    if not matches:
        return text
    match = matches[number % len(matches)]
    return text[: match.start()] + str(number).encode() + text[match.end():]


LIES = st.sampled_from([0, 1, 2, 3, 7, 255, 65536, 10**6, 10**9, 2**31, 2**63, 10**30])


def fuzz(reader: Callable[[Path], object], valid: Path, check: Callable[[object], None], tmp: Path,
         header: int, capsys, name: str, text_header: bool = False) -> None:
    """Run ``EXAMPLES`` mutations of ``valid`` through ``reader``; ``check`` validates a result that is returned."""
    data = valid.read_bytes()
    outcomes = {"named error": 0, "result": 0}
    target = tmp / f"fuzzed{valid.suffix}"

    @settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
    @given(edits=mutations(len(data), header), lie=LIES, lie_at=st.integers(0, 50))
    def run(edits, lie, lie_at):
        mutated = apply(data, edits)
        if text_header:
            mutated = header_lie(mutated[:header], lie_at * 1000 + lie) if lie_at % 3 == 0 else mutated
            mutated = header_lie(mutated, lie) if lie_at % 3 == 1 else mutated
        target.write_bytes(mutated)
        previous = signal.signal(signal.SIGALRM, _alarm)
        signal.alarm(HANG_GUARD_S)
        try:
            result = reader(target)
        except HoodDecompError:
            outcomes["named error"] += 1
            return
        finally:
            signal.alarm(0)
            signal.signal(signal.SIGALRM, previous)
        check(result)
        outcomes["result"] += 1

    run()
    total = sum(outcomes.values())
    with capsys.disabled():
        print(f"\nfuzz {name}: {total} examples: {outcomes['named error']} named errors, {outcomes['result']} "
              "correct results, 0 other exceptions, 0 hangs")
    assert total >= EXAMPLES


# --- the valid files ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small_files(tmp_path_factory, tiny_workspace):
    """Small valid files of every format (small so 500 examples each stay within the CI budget)."""
    from hood_decomp.core.fe.calculix import load_cases, write_deck
    from hood_decomp.core.fe.hood_preset import build_hood
    from hood_decomp.core.method.bases import build_bases
    from hood_decomp.io.bases import save_bases
    from hood_decomp.io.ensemble_store import EnsembleWriter
    from hood_decomp.io.ply import write_ply, write_scan
    from tests.toy_models import full_factorial, make_ensemble, make_reduced_model, make_skin

    root = tmp_path_factory.mktemp("fuzz")
    skin = make_skin(8, 6)
    model = make_reduced_model(skin, seed=8)
    states, rank = full_factorial(6)
    ensemble = make_ensemble(model, states[:64], rank[:64])
    save_bases(root / "bases.h5", build_bases(make_ensemble(model, states, rank), skin, model, n_components=6,
                                              epsilon=0.05))
    with EnsembleWriter(root / "ensemble.h5", skin, ensemble.names, ensemble.n_bilateral, ensemble.lower,
                        ensemble.upper, {"training": 64}) as writer:
        writer.write("training", slice(0, 64), **{k: getattr(ensemble, k) for k in (
            "commanded", "effective", "contact_fraction", "reactions", "rank", "normal_displacement",
            "displacement")})
        writer.finish("training")
    rng = np.random.default_rng(1)
    write_scan(root / "scan.ply", rng.normal(0, 100, (300, 3)), scanner_pose=np.eye(4),
               markers=rng.normal(0, 100, (3, 3)), markers_nominal=rng.normal(0, 100, (3, 3)))
    write_ply(root / "mesh.ply", rng.normal(0, 1, (20, 3)), triangles=rng.integers(0, 20, (30, 3)))
    (root / "ascii.ply").write_text("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
                                    "property float z\nelement face 2\nproperty list uchar int vertex_indices\n"
                                    "end_header\n0 0 0\n1 0 0\n0 1 0\n1 1 0\n3 0 1 2\n3 1 3 2\n")
    hood = build_hood(grid=(20, 20))
    cases, constrained = load_cases(hood)
    write_deck(hood, cases[0], constrained, root / "deck.inp")
    shutil.copytree(tiny_workspace.model, root / "model")
    shutil.copyfile(tiny_workspace.field, root / "field.vtu")
    (root / "sidecar.json").write_text('{"truth": {"LOCK_L": 0.5}, "noise_mm": 0.02, "scans": [1, 2, 3]}')
    return root


# --- one test per reader ------------------------------------------------------------------------------------------
def _finite_points(result) -> None:
    assert result.points.dtype == np.float64 and result.points.ndim == 2 and result.points.shape[1] == 3


def test_fuzz_ply_scan(small_files, tmp_path, capsys):
    """Fails if a mutated binary scan PLY makes read_scan raise anything but ScanError, hang, or return points that
    are not an (M, 3) array / a pose that is not 4 x 4."""
    from hood_decomp.io.ply import read_scan

    def check(scan):
        _finite_points(scan)
        assert scan.scanner_pose is None or scan.scanner_pose.shape == (4, 4)
        assert scan.markers.shape == scan.markers_nominal.shape == (len(scan.marker_ids), 3)

    header = small_files.joinpath("scan.ply").read_bytes().index(b"end_header") + 11
    fuzz(read_scan, small_files / "scan.ply", check, tmp_path, header, capsys, "PLY scan (binary)", True)


def test_fuzz_ply_mesh_ascii(small_files, tmp_path, capsys):
    """Fails if a mutated ASCII PLY with faces makes read_ply raise anything but ScanError, hang, or return faces
    that index missing vertices."""
    from hood_decomp.io.ply import read_ply

    def check(ply):
        _finite_points(ply)
        if ply.triangles is not None and ply.triangles.size:
            assert ply.triangles.min() >= 0 and ply.triangles.max() < len(ply.points)

    header = small_files.joinpath("ascii.ply").read_bytes().index(b"end_header") + 11
    fuzz(read_ply, small_files / "ascii.ply", check, tmp_path, header, capsys, "PLY mesh (ASCII)", True)


def test_fuzz_bases(small_files, tmp_path, capsys):
    """Fails if a mutated bases file makes load_bases raise anything but BasisError, hang, or return bases whose
    arrays are not finite or whose content differs from what was written (bases_id checked on load)."""
    from hood_decomp.io.bases import bases_id, load_bases

    original = bases_id(load_bases(small_files / "bases.h5"))

    def check(bases):
        assert bases_id(bases) == original  # a flip that passes must have hit bytes that carry no content
        assert np.all(np.isfinite(bases.pca.components_))

    fuzz(load_bases, small_files / "bases.h5", check, tmp_path, 2048, capsys, "HDF5 bases")


def test_fuzz_ensemble(small_files, tmp_path, capsys):
    """Fails if a mutated ensemble store makes load_ensemble raise anything but EnsembleError, hang, or return
    non-finite members or arrays of inconsistent shapes."""
    from hood_decomp.io.ensemble_store import load_ensemble

    def check(ensemble):
        m, n = ensemble.normal_displacement.shape
        assert ensemble.displacement.shape == (m, n, 3) and ensemble.commanded.shape == (m, len(ensemble.names))
        assert np.all(np.isfinite(ensemble.normal_displacement))

    fuzz(load_ensemble, small_files / "ensemble.h5", check, tmp_path, 2048, capsys, "HDF5 ensemble store")


def test_fuzz_field(small_files, tmp_path, capsys):
    """Fails if a mutated field .vtu makes read_field raise anything but FieldError (meshio's own exceptions and
    sys.exit included), hang, or return values beyond the plausible bound or infinite."""
    from hood_decomp.io.fields import MAX_ABS_MM, read_field

    def check(result):
        field, vectors = result
        values = field.normal_displacement
        assert not np.any(np.isinf(values)) and np.nanmax(np.abs(values), initial=0) <= MAX_ABS_MM
        assert vectors is None or vectors.shape == (len(values), 3)

    text = small_files.joinpath("field.vtu").read_bytes()
    fuzz(read_field, small_files / "field.vtu", check, tmp_path, text.index(b"<PointData") if b"<PointData" in text
         else 400, capsys, "field .vtu", True)


def test_fuzz_model_yaml(small_files, tmp_path, capsys):
    """Fails if a mutated model.yaml (its mesh intact) makes load_model raise anything but ModelError, hang, or
    return a model with non-finite values."""
    from hood_decomp.io.model_files import load_model

    directory = tmp_path / "model"
    shutil.copytree(small_files / "model", directory)

    def read(path):
        shutil.copyfile(path, directory / "model.yaml")
        return load_model(directory)

    def check(model):
        assert all(np.isfinite(p.thickness) for p in model.parts)
        assert all(np.isfinite([b.force, b.stiffness, b.preload, *b.axis]).all() for b in model.boundaries)

    size = small_files.joinpath("model", "model.yaml").stat().st_size
    fuzz(read, small_files / "model" / "model.yaml", check, tmp_path, size, capsys, "model.yaml", True)


def test_fuzz_model_mesh_vtu(small_files, tmp_path, capsys):
    """Fails if a mutated model mesh .vtu makes read_mesh raise anything but MeshError, or hang."""
    from hood_decomp.io.mesh import read_mesh

    def check(result):
        _, cells, part = result
        assert cells.ndim == 2 and len(part) == len(cells)

    fuzz(read_mesh, small_files / "model" / "mesh.vtu", check, tmp_path, 400, capsys, "model mesh .vtu", True)


def test_fuzz_inp_deck(small_files, tmp_path, capsys):
    """Fails if a mutated CalculiX deck read as a mesh makes read_inp_mesh raise anything but MeshError, hang, or
    return cells that index missing nodes."""
    from hood_decomp.io.mesh import read_inp_mesh

    def check(result):
        nodes, cells, elsets = result
        assert cells.min() >= 0 and cells.max() < len(nodes) and len(elsets) == len(cells)

    fuzz(read_inp_mesh, small_files / "deck.inp", check, tmp_path, 3000, capsys, ".inp deck", True)


def test_fuzz_bag_sidecar(small_files, tmp_path, capsys):
    """Fails if a mutated bag sidecar makes read_sidecar raise anything but BagError (NaN and Infinity refused),
    or hang."""
    from hood_decomp.io.bags import read_sidecar

    def read(path):
        shutil.copyfile(path, tmp_path / "bag.json")
        return read_sidecar(tmp_path / "bag")

    def check(content):
        assert isinstance(content, dict)

    fuzz(read, small_files / "sidecar.json", check, tmp_path, 80, capsys, "bag sidecar JSON", True)


def test_fuzzed_hdf5_examples_include_structure_damage(small_files):
    """Fails if the HDF5 fuzzing could not reach the file's structure (then it would only test data checks): a
    flip in the superblock must make the file unreadable as HDF5."""
    from hood_decomp.errors import BasisError
    from hood_decomp.io.bases import load_bases

    data = bytearray(small_files.joinpath("bases.h5").read_bytes())
    data[0] ^= 0xFF
    broken = small_files / "broken.h5"
    broken.write_bytes(bytes(data))
    with pytest.raises(BasisError, match="not an HDF5"):
        load_bases(broken)
    assert h5py.is_hdf5(small_files / "bases.h5")


def test_fuzz_bag(tmp_path, capsys):
    """Fails if a mutated MCAP file of a small bag (three std_msgs/String messages, written by io.bags) makes
    read_bag raise anything but BagError (rosbags' own exceptions included), hang, or yield records without topic
    and payload."""
    from hood_decomp.io.bags import Record, read_bag, write_bag

    bag = tmp_path / "bag"
    cdr = b"\x00\x01\x00\x00" + (6).to_bytes(4, "little") + b"hello\x00"  # CDR little endian std_msgs/String
    write_bag(bag, [Record("chatter", "std_msgs/msg/String", 10**9 * (i + 1), cdr) for i in range(3)])
    storage = next(bag.glob("*.mcap"))
    source = tmp_path / "source.mcap"
    shutil.copyfile(storage, source)

    def read(path):
        shutil.copyfile(path, storage)
        return list(read_bag(bag))

    def check(records):
        assert all(record.topic and isinstance(record.data, bytes) for record in records)

    fuzz(read, source, check, tmp_path, 64, capsys, "bag (MCAP)")
