"""The on-disk ensemble store: one HDF5 file, readable with any HDF5 tool, no pickle.

Schema (``schema`` = "hood_decomp.ensemble", ``schema_version`` = 1; also in docs/ensemble_schema.md)::

    /                          attrs: schema, schema_version, model_id (str), n_bilateral (int), solver (str),
                                      solver_backend (str), created_utc (ISO 8601 str), pad_counts (JSON str),
                                      physics (str: linear | geometric-nonlinear), physics_detail (JSON str)
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
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import h5py
import numpy as np

from hood_decomp.core.fe.ensemble import contact_counts, factorial_plan, iter_members, validation_plan
from hood_decomp.core.types import DisplacementField, Ensemble, ReducedModel, SkinSurface, fingerprint
from hood_decomp.errors import EnsembleError
from hood_decomp.io.fields import write_field
from hood_decomp.io.hdf5 import Reader, open_hdf5

if TYPE_CHECKING:
    from hood_decomp.core.fe.reduced_geometric import ReducedGeometricModel

logger = logging.getLogger(__name__)

SCHEMA = "hood_decomp.ensemble"
SCHEMA_VERSION = 2  # 2: content_id checked on open
GROUPS = ("training", "validation")
MEMBER_ARRAYS = ("commanded", "effective", "contact_fraction", "reactions", "rank", "normal_displacement",
                 "displacement")


class EnsembleWriter:
    """Create a store and fill it member block by member block. Use as a context manager.

    sizes: members per group, e.g. {"training": 729, "validation": 1400}.
    """

    def __init__(self, path: str | Path, skin: SkinSurface, names: tuple[str, ...], n_bilateral: int,
                 lower: np.ndarray, upper: np.ndarray, sizes: dict[str, int], solver: str = "embedded",
                 solver_backend: str = "", physics: str = "linear", physics_detail: str = "{}") -> None:
        self.path = Path(path)
        self._skin, self._names, self._n_bilateral = skin, tuple(names), int(n_bilateral)
        self._lower, self._upper, self._sizes = lower, upper, dict(sizes)
        self._solver, self._backend = solver, solver_backend
        self._physics, self._physics_detail = physics, physics_detail
        self._file: h5py.File | None = None

    def __enter__(self) -> EnsembleWriter:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        f = h5py.File(self.path, "w")
        self._file = f
        f.attrs.update({
            "schema": SCHEMA, "schema_version": SCHEMA_VERSION, "model_id": self._skin.model_id,
            "n_bilateral": self._n_bilateral, "solver": self._solver, "solver_backend": self._backend,
            "physics": self._physics, "physics_detail": self._physics_detail,
            "created_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "content_id": content_id(self._skin, self._names, self._n_bilateral, self._lower, self._upper),
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
                   n_validation: int = 1400, seed: int = 0, solver: str = "embedded", solver_backend: str = "",
                   nonlinear: ReducedGeometricModel | None = None) -> dict[str, object]:
    """Solve the full factorial (training) and ``n_validation`` uniform random members and store them at ``path``.

    nonlinear: solve the members with this reduced geometrically nonlinear model (built for [lower, upper]) instead
    of ``reduced``'s linear superposition; the store records ``physics`` = "geometric-nonlinear" and the model's size.
    Returns a summary: member counts, pad contact counts per group (lifted / partial / full (member, pad) pairs).
    """
    if skin.model_id != reduced.model_id:
        raise EnsembleError(f"skin model_id {skin.model_id} does not match the reduced model's {reduced.model_id}")
    physics, detail = "linear", {}
    if nonlinear is not None:
        if not (np.array_equal(nonlinear.lower, lower) and np.array_equal(nonlinear.upper, upper)):
            raise EnsembleError(f"the nonlinear model was built for ranges {nonlinear.lower.tolist()} .. "
                                f"{nonlinear.upper.tolist()}, the ensemble asks for {list(lower)} .. {list(upper)}")
        physics = "geometric-nonlinear"
        detail = {"model": "reduced Green-Lagrange membrane (core/fe/reduced_geometric.py)",
                  "correction_modes": nonlinear.modes, "pad_force_shapes": int(nonlinear.Bf.shape[1]),
                  "build_residual_mm": nonlinear.residual}
    training, rank = factorial_plan(lower, upper)
    plans = {"training": (training, rank)}
    if n_validation:
        plans["validation"] = (validation_plan(lower, upper, n_validation, seed), np.full(n_validation, -1))
    summary: dict[str, object] = {"seed": seed, "physics": physics}
    with EnsembleWriter(path, skin, reduced.names, reduced.n_bilateral, lower, upper,
                        {g: len(c) for g, (c, _) in plans.items()}, solver, solver_backend, physics,
                        json.dumps(detail)) as writer:
        for group, (commanded, ranks) in plans.items():
            fractions = []
            solve = None if nonlinear is None else nonlinear.members
            for rows, block in iter_members(reduced, commanded, solve=solve):
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


@dataclass(frozen=True)
class _Header:
    """What every member refers to, read and checked on open."""

    skin: SkinSurface
    names: tuple[str, ...]
    n_bilateral: int
    lower: np.ndarray
    upper: np.ndarray


@contextmanager
def _open(path: str | Path) -> Iterator[tuple[h5py.File, Reader, _Header]]:
    """For a ``with`` block: the audited store, a Reader with N, P and U bound, and the header; EnsembleError for a
    foreign schema, a damaged file or a content that does not match its ``content_id``."""
    with open_hdf5(path, "ensemble store", EnsembleError) as f:
        read = Reader(f, path, EnsembleError)
        schema, version = f.attrs.get("schema"), f.attrs.get("schema_version")
        if schema != SCHEMA or not isinstance(version, int | np.integer) or int(version) != SCHEMA_VERSION:
            shown = [v if isinstance(v, str | int | np.integer) and len(str(v)) < 60 else type(v).__name__
                     for v in (schema, version)]
            raise EnsembleError(f"{path}: expected schema {SCHEMA!r} version {SCHEMA_VERSION}, got {shown[0]!r} "
                                f"version {shown[1]!r}")
        names = read.strings("names", "P")
        n_bilateral = read.attr("/", "n_bilateral", "int")
        if not 0 <= n_bilateral <= len(names):
            raise EnsembleError(f"{path}: n_bilateral is {n_bilateral}, expected 0..{len(names)}")
        read.bind("U", len(names) - n_bilateral, "names minus n_bilateral")
        skin = SkinSurface(points=read.array("skin/points", ("N", "3")), normals=read.array("skin/normals", ("N", "3")),
                           triangles=read.array("skin/triangles", ("T", "3"), "integer").astype(np.int64),
                           model_id=read.attr("/", "model_id", "str"))
        if skin.triangles.size and (skin.triangles.min() < 0 or skin.triangles.max() >= skin.n_nodes):
            raise EnsembleError(f"{path}: skin/triangles index nodes {skin.triangles.min()}..{skin.triangles.max()}, "
                                f"the skin has 0..{skin.n_nodes - 1}")
        lower, upper = read.array("lower", ("P",)), read.array("upper", ("P",))
        if content_id(skin, names, n_bilateral, lower, upper) != read.attr("/", "content_id", "str"):
            raise EnsembleError(f"{path}: content does not match its content_id (the file was altered after it was "
                                "written: a rewritten model_id, skin or range); compute it again")
        yield f, read, _Header(skin, names, n_bilateral, lower, upper)


def content_id(skin: SkinSurface, names: tuple[str, ...], n_bilateral: int, lower: np.ndarray, upper: np.ndarray
               ) -> str:
    """Fingerprint of what the members refer to: model_id, skin, parameter names and ranges (stored as
    ``content_id``; recomputed on every open, so a rewritten model_id does not pass)."""
    return fingerprint(skin.model_id, skin.points, skin.normals, np.asarray(skin.triangles, dtype=np.int64),
                       "\x00".join(names), str(int(n_bilateral)), np.asarray(lower, dtype=float),
                       np.asarray(upper, dtype=float))


def load_ensemble(path: str | Path, group: str = "training", members: slice | None = None) -> Ensemble:
    """Read one group of a store as a types.Ensemble (float64 arrays). ``members`` selects a row range. Every array
    is checked for its kind, its shape against the others and finite values (EnsembleError naming the dataset)."""
    if group not in GROUPS:
        raise EnsembleError(f"group must be one of {GROUPS}, got {group!r}")
    rows = members if members is not None else slice(None)
    with _open(path) as (f, read, head):
        if group not in f:
            raise EnsembleError(f"{path}: group {group!r} is missing")
        if not read.attr(group, "complete", "bool"):
            raise EnsembleError(f"{path}: group {group!r} is incomplete (the run did not finish)")
        read.bind("M", read.attr(group, "n_members", "int"), f"{group} n_members")
        arrays = {name: read.array(f"{group}/{name}", dims, kind, rows)
                  for name, (dims, kind) in _MEMBER_DIMS.items()}
        return Ensemble(
            model_id=head.skin.model_id, names=head.names, n_bilateral=head.n_bilateral, lower=head.lower,
            upper=head.upper, commanded=arrays["commanded"], effective=arrays["effective"],
            contact_fraction=arrays["contact_fraction"], reactions=arrays["reactions"],
            rank=arrays["rank"].astype(np.int64),
            normal_displacement=arrays["normal_displacement"].astype(np.float64),
            displacement=arrays["displacement"].astype(np.float64),
        )


#: member arrays: named dimensions (M members, P parameters, U unilateral, N skin nodes) and kind
_MEMBER_DIMS = {
    "commanded": (("M", "P"), "float"), "effective": (("M", "P"), "float"), "contact_fraction": (("M", "U"), "float"),
    "reactions": (("M", "U"), "float"), "rank": (("M",), "integer"), "normal_displacement": (("M", "N"), "float"),
    "displacement": (("M", "N", "3"), "float"),
}  # fmt: skip


def load_skin(path: str | Path) -> SkinSurface:
    """The visible skin stored with an ensemble."""
    with _open(path) as (_, _, head):
        return head.skin


def store_info(path: str | Path) -> dict[str, object]:
    """Root attributes and group sizes of a store (JSON-able)."""
    with _open(path) as (f, read, _):
        info: dict[str, object] = {k: read.attr("/", k, "str") for k in ("model_id", "solver", "created_utc")}
        info["physics"] = read.attr("/", "physics", "str") if "physics" in f.attrs else "linear"
        for group in GROUPS:
            if group in f:
                info[f"{group}_members"] = read.attr(group, "n_members", "int")
                info[f"{group}_complete"] = read.attr(group, "complete", "bool")
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
                              coverage=1.0, noise_rms=float("nan"), displacement=member.displacement[0])
    write_field(out, load_skin(path), field)
    return Path(out)
