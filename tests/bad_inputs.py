"""Bad inputs made by code, not stored: a small valid workspace (a 20 x 20 hood, its ensemble, bases, a field and a
scan) and generators that turn a copy of one of its files into a broken or hostile one.

Used by the bad-input matrix (tests/cli/test_bad_inputs.py), the hostile-file tests (tests/io/test_hostile_files.py)
and the reader fuzz tests (tests/io/test_fuzz_readers.py).
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import threading
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np

#: the text a hostile file tries to leak; it must never appear in any output
SECRET = "root:x:0:0:SECRET-7f3a9c:/root:/bin/bash"
#: a YAML alias bomb of 421 bytes: 9 levels of 9 aliases, 9**10 = 3.5e9 leaves once expanded
BOMB = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{chr(98 + i)}: &{chr(98 + i)} [" + ", ".join([f"*{chr(97 + i)}"] * 9) + "]\n" for i in range(9))


@dataclasses.dataclass(frozen=True)
class Workspace:
    """Valid inputs of every verb on a 20 x 20 hood (400 skin nodes), and a directory of decoys a hostile file may
    point at (``secret``: a text file holding :data:`SECRET`; ``other``: an HDF5 file of that text and numbers)."""

    root: Path
    model: Path
    ensemble: Path
    bases: Path
    field: Path
    scan: Path
    decoys: Path

    @property
    def secret(self) -> Path:
        return self.decoys / "secret.txt"

    @property
    def other(self) -> Path:
        return self.decoys / "other.h5"


def build_workspace(root: Path) -> Workspace:
    """Write the valid workspace under ``root`` (about 10 s: the hierarchical basis dominates)."""
    from hood_decomp.core.fe.ensemble import simulate_setting
    from hood_decomp.core.fe.hood_preset import build_hood
    from hood_decomp.core.fe.model import skin_surface
    from hood_decomp.core.fe.solver import build_solver, reduce_model
    from hood_decomp.core.loop.calibration import model_physics
    from hood_decomp.core.method.bases import build_bases
    from hood_decomp.core.types import DisplacementField
    from hood_decomp.io.bases import save_bases
    from hood_decomp.io.ensemble_store import load_ensemble, write_ensemble
    from hood_decomp.io.fields import write_field
    from hood_decomp.io.model_files import save_model
    from hood_decomp.io.ply import write_scan

    model = build_hood(grid=(20, 20))
    save_model(model, root / "model")
    solver = build_solver(model)
    reduced = reduce_model(solver)
    skin = skin_surface(model)
    write_ensemble(root / "ensemble.h5", reduced, skin, model.lower, model.upper, n_validation=8)
    # as `bases --model` writes it: with the model's physical responses (/physics)
    save_bases(root / "bases.h5", dataclasses.replace(build_bases(load_ensemble(root / "ensemble.h5"), skin, reduced),
                                                      physics=model_physics(model, reduced, solver)))
    result = simulate_setting(solver, {"LOCK_L": 0.4})
    write_field(root / "field.vtu", skin, DisplacementField(skin.model_id, result.normal_displacement, 1.0, 0.0,
                                                            displacement=result.displacement))
    # a scan in the part frame: the displaced skin nodes, densified, with a little noise
    rng = np.random.default_rng(0)
    points = skin.points + result.displacement
    cloud = np.repeat(points, 40, axis=0) + rng.normal(0, 1.5, (40 * len(points), 3)) * [1, 1, 0]
    write_scan(root / "scan.ply", cloud)
    decoys = root / "decoys"
    decoys.mkdir()
    (decoys / "secret.txt").write_text(SECRET + "\n")
    with h5py.File(decoys / "other.h5", "w") as h5:
        h5.create_dataset("names", data=np.array([SECRET] * 64, dtype=object), dtype=h5py.string_dtype())
        h5.create_dataset("numbers", data=np.full(1 << 16, 7.0))
    return Workspace(root, root / "model", root / "ensemble.h5", root / "bases.h5", root / "field.vtu",
                     root / "scan.ply", decoys)


# --- HDF5: what a hostile or broken bases file / ensemble store holds ---------------------------------------------
H5Mutation = Callable[[h5py.File, str, Workspace], None]


def _replace(h5: h5py.File, name: str) -> tuple[tuple[int, ...], np.dtype]:
    shape, dtype = h5[name].shape, h5[name].dtype
    del h5[name]
    return shape, dtype


def _external_storage(h5: h5py.File, name: str, ws: Workspace) -> None:
    shape, _ = _replace(h5, name)
    size = ws.secret.stat().st_size
    h5.create_dataset(name, shape=(size,), dtype="S1", external=[(str(ws.secret), 0, size)])
    del shape


def _external_storage_numbers(h5: h5py.File, name: str, ws: Workspace) -> None:
    shape, _ = _replace(h5, name)
    h5.create_dataset(name, shape=shape, dtype="u1", external=[(str(ws.secret), 0, h5py.h5f.UNLIMITED)])


def _external_link(h5: h5py.File, name: str, ws: Workspace) -> None:
    _replace(h5, name)
    h5[name] = h5py.ExternalLink(str(ws.other), "/names")


def _external_link_group(h5: h5py.File, name: str, ws: Workspace) -> None:
    group = name.rsplit("/", 1)[0] + "/extra"
    h5[group] = h5py.ExternalLink(str(ws.other), "/")


def _virtual(h5: h5py.File, name: str, ws: Workspace) -> None:
    shape, _ = _replace(h5, name)
    count = min(int(np.prod(shape)), 1 << 16)
    layout = h5py.VirtualLayout(shape=(count,), dtype="f8")
    layout[:] = h5py.VirtualSource(str(ws.other), "/numbers", shape=(1 << 16,))[:count]
    h5.create_virtual_dataset(name, layout)


def _dangling_soft_link(h5: h5py.File, name: str, ws: Workspace) -> None:
    _replace(h5, name)
    h5[name] = h5py.SoftLink("/nowhere/at_all")


def _soft_link(h5: h5py.File, name: str, ws: Workspace) -> None:
    target = next(k for k in ("/skin/points", "/names", "/parameters/names") if k in h5 and k != "/" + name)
    _replace(h5, name)
    h5[name] = h5py.SoftLink(target)


def _object_references(h5: h5py.File, name: str, ws: Workspace) -> None:
    shape, _ = _replace(h5, name)
    h5.create_dataset(name, shape=shape[:1], dtype=h5py.ref_dtype)


def _vlen_numbers(h5: h5py.File, name: str, ws: Workspace) -> None:
    shape, _ = _replace(h5, name)
    dataset = h5.create_dataset(name, shape=shape[:1], dtype=h5py.vlen_dtype("f8"))
    dataset[0] = np.arange(3.0)


def _compound(h5: h5py.File, name: str, ws: Workspace) -> None:
    shape, _ = _replace(h5, name)
    h5.create_dataset(name, shape=shape, dtype=[("a", "f8"), ("b", "i4")])


def _strings_for_numbers(h5: h5py.File, name: str, ws: Workspace) -> None:
    shape, _ = _replace(h5, name)
    h5.create_dataset(name, data=np.array(["1.0"] * shape[0], dtype=object), dtype=h5py.string_dtype())


def _missing(h5: h5py.File, name: str, ws: Workspace) -> None:
    del h5[name]


def _nan(h5: h5py.File, name: str, ws: Workspace) -> None:
    values = h5[name][()]
    values.flat[len(values.flat) // 2] = np.nan
    h5[name][...] = values


def _inf(h5: h5py.File, name: str, ws: Workspace) -> None:
    values = h5[name][()]
    values.flat[0] = -np.inf
    h5[name][...] = values


def _huge_shape(h5: h5py.File, name: str, ws: Workspace) -> None:
    shape, dtype = _replace(h5, name)
    h5.create_dataset(name, shape=(200_000, *(1_000_000 for _ in shape[1:])) if len(shape) > 1
                      else (400_000_000_000,), dtype=dtype, chunks=(1,) * len(shape))


def _wrong_width(h5: h5py.File, name: str, ws: Workspace) -> None:
    shape, dtype = _replace(h5, name)
    h5.create_dataset(name, data=np.zeros((*shape[:-1], shape[-1] - 1), dtype=dtype))


def _extra_dimension(h5: h5py.File, name: str, ws: Workspace) -> None:
    shape, dtype = _replace(h5, name)
    h5.create_dataset(name, data=np.zeros((*shape, 2), dtype=dtype))


def _unknown_filter(h5: h5py.File, name: str, ws: Workspace) -> None:
    shape, dtype = _replace(h5, name)
    h5.create_dataset(name, shape=shape, dtype=dtype, compression=32001, allow_unknown_filter=True,
                      chunks=shape if all(shape) else None)


def _group_for_dataset(h5: h5py.File, name: str, ws: Workspace) -> None:
    _replace(h5, name)
    h5.create_group(name)


#: mutation -> what its one-line error must contain (case-insensitive)
H5_MUTATIONS: dict[str, tuple[H5Mutation, str]] = {
    "external storage (text)": (_external_storage, "external"),
    "external storage (numbers)": (_external_storage_numbers, "external"),
    "external link": (_external_link, "external link"),
    "external link beside": (_external_link_group, "external link"),
    "virtual dataset": (_virtual, "virtual"),
    "dangling soft link": (_dangling_soft_link, "softlink"),
    "soft link": (_soft_link, "softlink"),
    "object references": (_object_references, "object references"),
    "variable-length numbers": (_vlen_numbers, "variable-length"),
    "compound dtype": (_compound, "compound"),
    "strings for numbers": (_strings_for_numbers, "expected"),
    "missing dataset": (_missing, "missing"),
    "NaN value": (_nan, "non-finite"),
    "inf value": (_inf, "non-finite"),
    "shape claim of TiB": (_huge_shape, "claims shape"),
    "wrong width": (_wrong_width, "has"),
    "extra dimension": (_extra_dimension, "shape"),
    "unknown filter (plugin)": (_unknown_filter, "filter 32001"),
    "group for a dataset": (_group_for_dataset, "group"),
}


def mutated_copy(source: Path, target: Path, edit: Callable[[h5py.File], None]) -> Path:
    """A copy of HDF5 file ``source`` at ``target`` with ``edit`` applied."""
    shutil.copyfile(source, target)
    with h5py.File(target, "a") as h5:
        edit(h5)
    return target


def outcome_without_blocking(read: Callable[[], object], fifo: os.PathLike) -> BaseException | None:
    """What ``read()`` raised (None: it returned); a reader blocked on ``fifo`` for 10 s is unblocked (a writer opens
    and closes it) and the test fails, rather than hangs."""
    outcome: list[BaseException | None] = []

    def run() -> None:
        try:
            read()
            outcome.append(None)
        except BaseException as error:  # handed to the test's thread
            outcome.append(error)

    reader = threading.Thread(target=run, daemon=True)
    reader.start()
    reader.join(10.0)
    blocked = reader.is_alive()
    if blocked:
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        reader.join(10.0)
    assert not blocked, f"the reader blocked on the FIFO {fifo}"
    return outcome[0]
