"""The on-disk ensemble store: one HDF5 file, readable with any HDF5 tool, no pickle.

Schema (``schema`` = "hood_decomp.ensemble", ``schema_version`` = 1; also in docs/ensemble_schema.md)::

    /                          attrs: schema, schema_version, model_id (str), n_bilateral (int), solver (str),
                                      solver_backend (str), created_utc (ISO 8601 str), pad_counts (JSON str)
    /names                     (P,)      UTF-8 strings: parameter labels, bilateral first then unilateral
    /lower, /upper             (P,)      float64, mm: declared ranges
    /skin/points               (N, 3)    float64, mm: visible skin nodes (the node order of every per-node array)
    /skin/normals              (N, 3)    float64: unit outward normals
    /skin/triangles            (T, 3)    int64: skin triangles (quads split in two), indices into points
    /<group>/commanded         (M, P)    float64, mm: commanded parameter states
    /<group>/effective         (M, P)    float64, mm: effective states (types.Ensemble)
    /<group>/contact_fraction  (M, U)    float64: fraction of each pad's springs in contact (0 lifted, 1 full)
    /<group>/reactions         (M, U)    float64, N: total pad force
    /<group>/rank              (M,)      int64: non-zero commanded parameters (Table 1), -1 for random members
    /<group>/normal_displacement (M, N)  float32, mm: skin normal displacement
    /<group>/displacement      (M, N, 3) float32, mm: skin 3D displacement
    <group> attrs: complete (bool: all M members written), n_members (int)

Groups: ``training`` (full factorial, section 3.1.1) and ``validation`` (uniform random, section 4.1).
Large arrays are chunked per member so one member reads fast. Progress of :func:`write_ensemble` goes to this
module's logger.
"""

from __future__ import annotations

import datetime
import json
import logging
from pathlib import Path

import h5py
import numpy as np

from hood_decomp.core.fe.ensemble import contact_counts, factorial_plan, iter_members, validation_plan
from hood_decomp.core.types import DisplacementField, Ensemble, ReducedModel, SkinSurface
from hood_decomp.errors import EnsembleError
from hood_decomp.io.fields import write_field
from hood_decomp.io.hdf5 import open_hdf5

logger = logging.getLogger(__name__)

SCHEMA = "hood_decomp.ensemble"
SCHEMA_VERSION = 1
GROUPS = ("training", "validation")
MEMBER_ARRAYS = ("commanded", "effective", "contact_fraction", "reactions", "rank", "normal_displacement",
                 "displacement")


class EnsembleWriter:
    """Create a store and fill it member block by member block. Use as a context manager.

    sizes: members per group, e.g. {"training": 729, "validation": 1400}.
    """

    def __init__(self, path: str | Path, skin: SkinSurface, names: tuple[str, ...], n_bilateral: int,
                 lower: np.ndarray, upper: np.ndarray, sizes: dict[str, int], solver: str = "embedded",
                 solver_backend: str = "") -> None:
        self.path = Path(path)
        self._skin, self._names, self._n_bilateral = skin, tuple(names), int(n_bilateral)
        self._lower, self._upper, self._sizes = lower, upper, dict(sizes)
        self._solver, self._backend = solver, solver_backend
        self._file: h5py.File | None = None

    def __enter__(self) -> EnsembleWriter:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        f = h5py.File(self.path, "w")
        self._file = f
        f.attrs.update({
            "schema": SCHEMA, "schema_version": SCHEMA_VERSION, "model_id": self._skin.model_id,
            "n_bilateral": self._n_bilateral, "solver": self._solver, "solver_backend": self._backend,
            "created_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        })
        f.create_dataset("names", data=np.array(self._names, dtype=object), dtype=h5py.string_dtype())
        f.create_dataset("lower", data=np.asarray(self._lower, dtype=float))
        f.create_dataset("upper", data=np.asarray(self._upper, dtype=float))
        skin = f.create_group("skin")
        skin.create_dataset("points", data=self._skin.points)
        skin.create_dataset("normals", data=self._skin.normals)
        skin.create_dataset("triangles", data=self._skin.triangles)
        P, U, N = len(self._names), len(self._names) - self._n_bilateral, self._skin.n_nodes
        for group, m in self._sizes.items():
            g = f.create_group(group)
            g.attrs.update({"complete": False, "n_members": m})
            g.create_dataset("commanded", (m, P), dtype="f8")
            g.create_dataset("effective", (m, P), dtype="f8")
            g.create_dataset("contact_fraction", (m, U), dtype="f8")
            g.create_dataset("reactions", (m, U), dtype="f8")
            g.create_dataset("rank", (m,), dtype="i8")
            g.create_dataset("normal_displacement", (m, N), dtype="f4", chunks=(1, N) if m else None)
            g.create_dataset("displacement", (m, N, 3), dtype="f4", chunks=(1, N, 3) if m else None)
        return self

    def write(self, group: str, rows: slice, **arrays: np.ndarray) -> None:
        """Write members ``rows`` of ``group``; keyword names are the MEMBER_ARRAYS."""
        if self._file is None:
            raise EnsembleError("EnsembleWriter.write outside its 'with' block")
        unknown = set(arrays) - set(MEMBER_ARRAYS)
        if unknown:
            raise EnsembleError(f"unknown ensemble arrays {sorted(unknown)}; expected among {MEMBER_ARRAYS}")
        for name, value in arrays.items():
            self._file[group][name][rows] = value

    def finish(self, group: str, **attrs: object) -> None:
        """Mark a group complete (all members written); extra attrs (JSON-able) go to the root."""
        self._file[group].attrs["complete"] = True
        for key, value in attrs.items():
            self._file.attrs[key] = json.dumps(value)

    def __exit__(self, *exc: object) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


def write_ensemble(path: str | Path, reduced: ReducedModel, skin: SkinSurface, lower: np.ndarray, upper: np.ndarray,
                   n_validation: int = 1400, seed: int = 0, solver: str = "embedded", solver_backend: str = ""
                   ) -> dict[str, object]:
    """Solve the full factorial (training) and ``n_validation`` uniform random members and store them at ``path``.

    Returns a summary: member counts, pad contact counts per group (lifted / partial / full (member, pad) pairs).
    """
    if skin.model_id != reduced.model_id:
        raise EnsembleError(f"skin model_id {skin.model_id} does not match the reduced model's {reduced.model_id}")
    training, rank = factorial_plan(lower, upper)
    plans = {"training": (training, rank)}
    if n_validation:
        plans["validation"] = (validation_plan(lower, upper, n_validation, seed), np.full(n_validation, -1))
    summary: dict[str, object] = {"seed": seed}
    with EnsembleWriter(path, skin, reduced.names, reduced.n_bilateral, lower, upper,
                        {g: len(c) for g, (c, _) in plans.items()}, solver, solver_backend) as writer:
        for group, (commanded, ranks) in plans.items():
            fractions = []
            for rows, block in iter_members(reduced, commanded):
                writer.write(group, rows, commanded=commanded[rows], effective=block.effective,
                             contact_fraction=block.contact_fraction, reactions=block.reactions, rank=ranks[rows],
                             normal_displacement=block.normal_displacement.astype(np.float32),
                             displacement=block.displacement.astype(np.float32))
                fractions.append(block.contact_fraction)
                logger.info("%s: %d/%d members", group, rows.stop, len(commanded))
            counts = contact_counts(np.concatenate(fractions))
            summary[group] = {"members": len(commanded), "pad_contact": counts}
            writer.finish(group, **{f"{group}_pad_contact": counts})
    return summary


def _open(path: str | Path) -> h5py.File:
    f = open_hdf5(path, "ensemble store", EnsembleError)
    schema, version = f.attrs.get("schema"), f.attrs.get("schema_version")
    if schema != SCHEMA or version is None or int(version) != SCHEMA_VERSION:
        f.close()
        raise EnsembleError(
            f"{path}: expected schema {SCHEMA!r} version {SCHEMA_VERSION}, got {schema!r} version {version!r}"
        )
    return f


def load_ensemble(path: str | Path, group: str = "training", members: slice | None = None) -> Ensemble:
    """Read one group of a store as a types.Ensemble (float64 arrays). ``members`` selects a row range."""
    if group not in GROUPS:
        raise EnsembleError(f"group must be one of {GROUPS}, got {group!r}")
    rows = members if members is not None else slice(None)
    with _open(path) as f:
        if group not in f:
            raise EnsembleError(f"{path}: group {group!r} is missing")
        g = f[group]
        if not bool(g.attrs.get("complete", False)):
            raise EnsembleError(f"{path}: group {group!r} is incomplete (the run did not finish)")
        return Ensemble(
            model_id=str(f.attrs["model_id"]),
            names=tuple(n.decode() if isinstance(n, bytes) else str(n) for n in f["names"][()]),
            n_bilateral=int(f.attrs["n_bilateral"]),
            lower=f["lower"][()],
            upper=f["upper"][()],
            commanded=g["commanded"][rows],
            effective=g["effective"][rows],
            contact_fraction=g["contact_fraction"][rows],
            reactions=g["reactions"][rows],
            rank=g["rank"][rows],
            normal_displacement=g["normal_displacement"][rows].astype(np.float64),
            displacement=g["displacement"][rows].astype(np.float64),
        )


def load_skin(path: str | Path) -> SkinSurface:
    """The visible skin stored with an ensemble."""
    with _open(path) as f:
        return SkinSurface(
            points=f["skin/points"][()],
            normals=f["skin/normals"][()],
            triangles=f["skin/triangles"][()],
            model_id=str(f.attrs["model_id"]),
        )


def store_info(path: str | Path) -> dict[str, object]:
    """Root attributes and group sizes of a store (JSON-able)."""
    with _open(path) as f:
        info: dict[str, object] = {k: (v.item() if hasattr(v, "item") else v) for k, v in f.attrs.items()}
        for group in GROUPS:
            if group in f:
                info[f"{group}_members"] = int(f[group].attrs["n_members"])
                info[f"{group}_complete"] = bool(f[group].attrs["complete"])
        return info


def export_member(path: str | Path, group: str, index: int, out: str | Path) -> Path:
    """Write member ``index`` of ``group`` as a field file (.vtu: point data displacement, normal_displacement) for
    ParaView."""
    info = store_info(path)
    size = int(info.get(f"{group}_members", 0))
    if not 0 <= index < size:
        raise EnsembleError(f"{path}: group {group!r} has members 0..{size - 1}, asked for {index}")
    member = load_ensemble(path, group, members=slice(index, index + 1))
    field = DisplacementField(model_id=member.model_id, normal_displacement=member.normal_displacement[0],
                              coverage=1.0, noise_rms=float("nan"))
    write_field(out, load_skin(path), field, member.displacement[0])
    return Path(out)
