"""Saved bases: the PCA basis, the hierarchical basis, the skin and the reduced model in one HDF5 file (no pickle).

Schema: docs/bases_schema.md. A loaded :class:`hood_decomp.core.method.bases.Bases` is all estimation and decomposition
need; every field is checked against ``Bases.model_id``.
"""

from __future__ import annotations

import functools
import json
import logging
import time
import weakref
from dataclasses import fields, replace
from pathlib import Path

import h5py
import numpy as np

from hood_decomp.core.method.bases import Bases
from hood_decomp.core.method.hierarchical import HIERARCHICAL_FITTED_ARRAYS, HierarchicalBasis
from hood_decomp.core.method.model_spread import PhysicalResponses
from hood_decomp.core.method.pca import PCA_FITTED_ARRAYS, PCABasis
from hood_decomp.core.method.surface_reading import ScanReadingBias
from hood_decomp.core.types import SENSITIVE_ARRAYS, ReducedModel, SkinSurface, ToleranceZone, fingerprint
from hood_decomp.errors import BasisError
from hood_decomp.io.hdf5 import Reader, open_hdf5

logger = logging.getLogger(__name__)

FORMAT = "hood_decomp.bases"
# 4: may hold /tolerance_zones and /parameters/measured_effects (written only then, so that a reader that does not
# know them refuses the file rather than ignoring its acceptance criteria or correcting a parameter without a
# boundary); 3: optional /scan_skin (prepared scan skin); 2: bases_id checked on load; 1 had none (refused)
SCHEMA_VERSION = 3
FEATURES_SCHEMA_VERSION = 4
READABLE_VERSIONS = (2, 3, 4)
_STR = h5py.string_dtype()

# The named dimensions of every array (docs/bases_schema.md): a digit is a fixed size.
_PCA_DIMS = {
    "lower_": ("P",), "upper_": ("P",), "mean_field_": ("N",), "mean_field_3d_": ("N", "3"), "mean_state_": ("P",),
    "mean_reaction_": ("U",), "components_": ("K", "N"), "components_3d_": ("K", "N", "3"),
    "component_states_": ("K", "P"), "component_reactions_": ("K", "U"), "reaction_scale_": ("U",),
    "gram_": ("K", "K"), "singular_values_": ("C",), "explained_variance_ratio_": ("C",),
}  # fmt: skip
_HIERARCHICAL_DIMS = {
    "fields_": (("F", "N"), "float"), "fields_3d_": (("F", "N", "3"), "float"), "field_states_": (("F", "P"), "float"),
    "field_member_": (("F",), "integer"), "independent_": (("F",), "bool"), "effect_mask_": (("E", "P"), "bool"),
    "effect_fields_": (("E", "2"), "integer"), "effect_rank_": (("E",), "integer"), "trace_": (("T", "3"), "float"),
    "rank_max_error_": (("R",), "float"), "gram_": (("F", "F"), "float"),
}  # fmt: skip
_REDUCED_DIMS = {
    "w0": ("N",), "R": ("N", "B"), "G": ("N", "S"), "z0": ("S",), "Sa": ("S", "B"), "H": ("S", "S"), "k": ("S",),
    "preload": ("S",), "pad_of": ("S",), "w0_3d": ("N", "3"), "R_3d": ("N", "3", "B"), "G_3d": ("N", "3", "S"),
}  # fmt: skip
_THERMAL_DIMS = {"w": ("N",), "z": ("S",), "w3": ("N", "3")}
#: /physics (issue 15, session 21): the FE model's responses behind its physical factors (model_spread
#: PhysicalResponses). What a normal estimate reads (skin normal and pad parts) is read and checked on load; the 3D
#: parts (3/4 of the bytes) only when a fit of all three components or a calibration first needs them
_PHYSICS_DIMS = {"gas_w": ("N",), "gas_z": ("S",), "thermal_w": ("N",), "thermal_z": ("S",),
                 "thermal_moves": ("B",)}
_PHYSICS_3D_DIMS = {"gas_w3": ("N", "3"), "thermal_w3": ("N", "3")}
#: the thickness sensitivities' arrays, stacked over the sheet groups (G, ...) as physics/thickness_<name>
_THICKNESS_NORMAL = tuple(name for name in SENSITIVE_ARRAYS if not name.endswith("_3d"))
_THICKNESS_3D = tuple(name for name in SENSITIVE_ARRAYS if name.endswith("_3d"))
#: calibrated bases' optional discrepancy terms since session 11 (core.method.bases.Bases): name -> column dimension
_DISCREPANCY_TERMS = {"discrepancy_noise": "DW", "calibration_noise": "DE"}


def bases_id(bases: Bases) -> str:
    """The content fingerprint of ``bases`` (16 hex digits): model_id, parameter names, skin, every fitted array and
    setting of both bases and the reduced model. Stored as the file's ``bases_id`` and recomputed on load, so a file
    whose model_id or arrays were rewritten after writing is refused."""
    pca, hier, reduced = bases.pca, bases.hierarchical, bases.reduced_model
    items: list[np.ndarray | str] = [
        bases.model_id, "\x00".join(bases.names), str(pca.n_bilateral_), bases.skin.points, bases.skin.normals,
        bases.skin.triangles, repr((pca.n_components, pca.explained_variance, float(pca.rtol), pca.n_components_,
                                     float(pca.training_residual_rms_), list(pca.notes_))),
        *(np.asarray(getattr(pca, name)) for name in PCA_FITTED_ARRAYS),
        repr(float(hier.epsilon_)), "\x00".join(hier.effect_names_),
        *(np.asarray(getattr(hier, name)) for name in HIERARCHICAL_FITTED_ARRAYS),
    ]
    if reduced is not None:
        items += ["reduced", reduced.model_id, "\x00".join(reduced.names), str(reduced.n_bilateral),
                  reduced.parameter_states,
                  *(np.asarray(getattr(reduced, name)) for name in _REDUCED_DIMS)]
    if bases.calibration:  # uncalibrated bases keep the ids they always had
        items += ["calibration", bases.calibration]
    if bases.thermal is not None:
        items += ["thermal", *bases.thermal]
    if bases.discrepancy is not None:
        items += ["discrepancy", bases.discrepancy]
    if bases.discrepancy_local is not None:
        items += ["discrepancy_local", bases.discrepancy_local]
    for name in _DISCREPANCY_TERMS:  # absent before session 11: those files keep their ids
        if getattr(bases, name) is not None:
            items += [name, getattr(bases, name)]
    if bases.measured_effects:
        items += ["measured_effects", "\x00".join(bases.measured_effects)]
    return fingerprint(*items)


#: per Bases object that load_bases returned: (a weak reference to it, the bases_id its file was verified against)
_LOADED_IDS: dict[int, tuple[weakref.ref, str]] = {}


def loaded_bases_id(bases: Bases) -> str:
    """:func:`bases_id` of ``bases``; for an object :func:`load_bases` returned, the id its content was verified
    against on load, not hashed again (0.1-0.2 s at paper resolution). Loaded bases are not changed in place."""
    entry = _LOADED_IDS.get(id(bases))
    if entry is not None and entry[0]() is bases:
        return entry[1]
    return bases_id(bases)


def calibration_id(bases: Bases) -> str:
    """The id of the calibration ``bases`` were rebuilt with (what :func:`bases_provenance` reports as the
    calibration's ``id`` and a results history row records), "" for uncalibrated bases."""
    return json.loads(bases.calibration)["id"] if bases.calibration else ""


def bases_provenance(bases: Bases) -> dict:
    """Which bases and which calibration an estimate used (what ``estimate --json`` and the nodes' /diagnostics
    report): ``bases_id`` and ``calibration`` (null for uncalibrated bases, else the calibration's id, entries,
    leave-one-out RMS, mm, the physical factors with their std (``factors``, ``factor_std``: name -> value) and the
    model discrepancy the stated std includes: its rank and RMS, mm; null for a record made before the discrepancy was
    stated)."""
    record = json.loads(bases.calibration) if bases.calibration else None
    return {"bases_id": loaded_bases_id(bases), "calibration": None if record is None else {
        "id": record["id"], "entries": [e["name"] for e in record["entries"]], "loo_rms_mm": record["loo_rms_mm"],
        "factors": record.get("factors"), "factor_std": record.get("factor_std"),
        "discrepancy": record.get("discrepancy")}}


# --- writing -----------------------------------------------------------------------------------------------------
def _write_array(group: h5py.Group, name: str, values: np.ndarray, pack: bool = True) -> None:
    """Integer and boolean arrays gzip level 1 with shuffle when ``pack``; floats plain: they shrink by a quarter at
    most, and inflating them cost more than half of a one-off `estimate --scan`'s file reading at paper
    resolution."""
    values = np.asarray(values)
    packed = pack and values.dtype.kind in "iub"
    group.create_dataset(name, data=values, **({"compression": "gzip", "compression_opts": 1, "shuffle": True}
                                               if packed else {}))


def _write_arrays(group: h5py.Group, obj: object, names: tuple[str, ...]) -> None:
    for name in names:
        _write_array(group, name.rstrip("_"), getattr(obj, name))


def prepared_id(content_id: str, arrays: dict[str, np.ndarray]) -> str:
    """The fingerprint of a prepared scan skin: the bases' ``bases_id`` and every array, so a prepared skin altered
    or moved from another bases file is refused."""
    from hood_decomp.core.scan.scan_field import PREPARED_SKIN

    return fingerprint(content_id, *(item for name in PREPARED_SKIN if name in arrays
                                     for item in (name, np.asarray(arrays[name]))))


def reading_bias_id(content_id: str, bias: ScanReadingBias) -> str:
    """The fingerprint of the scan reading bias of the bases whose ``bases_id`` is ``content_id``: measured from them
    (not part of their value, like the prepared scan skin), so an edited one or one moved from other bases is
    refused."""
    return fingerprint(content_id, repr(float(bias.radius_mm)), bias.mean, bias.components)


def zones_id(content_id: str, zones: tuple[ToleranceZone, ...]) -> str:
    """The fingerprint of the tolerance zones of the bases whose ``bases_id`` is ``content_id``: names, regions,
    limits, coverages and node sets, so an edited zone or one moved from another bases file is refused."""
    items: list[np.ndarray | str] = [content_id]
    for zone in zones:
        items += [zone.name, zone.region, np.array([zone.lower_mm, zone.upper_mm, zone.min_coverage]),
                  np.asarray(zone.nodes, dtype=np.int64)]
    return fingerprint(*items)


def physics_id(content_id: str, groups: tuple[str, ...], arrays: dict[str, np.ndarray]) -> str:
    """The fingerprint of the /physics group's normal and pad parts (``arrays``: name -> the dataset's values) of the
    bases whose ``bases_id`` is ``content_id``, with the sheet ``groups``: an edited response, or one taken from other
    bases, is refused on load. The 3D parts have their own id over this one (:func:`physics_3d_id`)."""
    return fingerprint(content_id, "\x00".join(groups), *(item for name in sorted(arrays)
                                                          for item in (name, np.asarray(arrays[name]))))


def physics_3d_id(normal_id: str, arrays: dict[str, np.ndarray]) -> str:
    """The fingerprint of the /physics group's 3D parts, bound to its :func:`physics_id` ``normal_id``."""
    return fingerprint(normal_id, *(item for name in sorted(arrays) for item in (name, np.asarray(arrays[name]))))


def _physics_arrays(physics: PhysicalResponses) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The /physics datasets of ``physics`` (whole, :meth:`~PhysicalResponses.with_3d`): (normal and pad parts, 3D
    parts), name -> values."""
    physics = physics.with_3d()
    sensitivities = tuple(physics.thickness.values())

    def stacked(name: str) -> np.ndarray:
        return np.stack([getattr(sens, name) for sens in sensitivities])

    normal = {name: getattr(physics, name) for name in _PHYSICS_DIMS} | {
        f"thickness_{name}": stacked(name) for name in _THICKNESS_NORMAL}
    return normal, {name: getattr(physics, name) for name in _PHYSICS_3D_DIMS} | {
        f"thickness_{name}": stacked(name) for name in _THICKNESS_3D}


def _write_physics(h5: h5py.File, content_id: str, physics: PhysicalResponses) -> None:
    """The /physics group: the normal and pad parts float64, the 3D parts float32 (half the bytes of 3/4 of the
    group; a three-component estimate's model effects move by 2e-8 of their size on the coarse hood)."""
    normal, three_d = _physics_arrays(physics)
    three_d = {name: np.asarray(values, np.float32) for name, values in three_d.items()}
    groups = tuple(physics.thickness)
    group = h5.create_group("physics")
    normal_id = physics_id(content_id, groups, normal)
    group.attrs.update(physics_id=normal_id, physics_3d_id=physics_3d_id(normal_id, three_d))
    group.create_dataset("groups", data=np.array(groups, dtype=object), dtype=_STR)
    for name, values in (normal | three_d).items():
        _write_array(group, name, values)


def _read_physics(read: Reader, content_id: str, reduced: ReducedModel | None) -> tuple[PhysicalResponses, bool]:
    """The optional /physics group's normal and pad parts, checked (kinds, named shapes, finite, distinct sheet
    groups), and whether their content matches ``physics_id`` (checked by the caller after ``bases_id``, so that a
    rewritten bases_id is named as such); its 3D parts are read by the returned responses'
    :meth:`~PhysicalResponses.with_3d` (:func:`_read_physics_3d`)."""
    if reduced is None:
        raise BasisError(f"{read.path}: /physics needs the reduced model, which the file lacks")
    groups = read.strings("physics/groups", "G")
    if not groups or len(set(groups)) != len(groups):
        raise BasisError(f"{read.path}: physics/groups {list(groups)} must name distinct sheet groups (at least one)")
    missing = [name for name in (*_PHYSICS_3D_DIMS, *(f"thickness_{n}" for n in _THICKNESS_3D))
               if f"physics/{name}" not in read.h5]
    if missing:
        raise BasisError(f"{read.path}: physics/{missing[0]} is missing")
    arrays = {name: read.array(f"physics/{name}", dims) for name, dims in _PHYSICS_DIMS.items()} | {
        f"thickness_{name}": read.array(f"physics/thickness_{name}", ("G", *_REDUCED_DIMS[name]))
        for name in _THICKNESS_NORMAL}
    stored = read.attr("physics", "physics_id", "str")
    matches = physics_id(content_id, groups, arrays) == stored
    empty = {name: getattr(reduced, name)[:0] for name in _THICKNESS_3D}  # not read: as ReducedModel.on_nodes
    thickness = {group: replace(reduced, **{name: arrays[f"thickness_{name}"][i] for name in _THICKNESS_NORMAL},
                                **empty) for i, group in enumerate(groups)}
    normal = PhysicalResponses(arrays["gas_w"], arrays["gas_z"], np.zeros((0, 3)), arrays["thermal_w"],
                               arrays["thermal_z"], np.zeros((0, 3)), thickness, arrays["thermal_moves"])
    sizes, path, mapped = {dim: read.dims[dim][0] for dim in ("N", "B", "S", "G")}, read.path, read.mapped
    return replace(normal, load_3d=functools.cache(
        lambda: _read_physics_3d(path, content_id, stored, normal, sizes, mapped))), matches


def _read_physics_3d(path: Path, content_id: str, normal_id: str, normal: PhysicalResponses, sizes: dict[str, int],
                     mapped: bool) -> PhysicalResponses:
    """``normal`` (the /physics group's normal parts read from the bases file ``path`` whose ``bases_id`` is
    ``content_id``) with its 3D parts read now: the file unchanged since (its bases_id and ``normal_id``), kinds,
    named shapes (``sizes``: N, B, S, G as bound on load), finite, and the content matching ``physics_3d_id``."""
    with open_hdf5(path, "bases file", BasisError) as h5:
        read = Reader(h5, path, BasisError, mapped)
        if (read.attr("/", "bases_id", "str"), read.attr("physics", "physics_id", "str")) != (content_id, normal_id):
            raise BasisError(f"{path} changed since it was loaded (another bases_id or physics_id); load it again")
        for dim, size in sizes.items():
            read.bind(dim, size, "the file as loaded")
        arrays = {name: read.array(f"physics/{name}", dims) for name, dims in _PHYSICS_3D_DIMS.items()} | {
            f"thickness_{name}": read.array(f"physics/thickness_{name}", ("G", *_REDUCED_DIMS[name]))
            for name in _THICKNESS_3D}
        stored = read.attr("physics", "physics_3d_id", "str")
    if physics_3d_id(normal_id, arrays) != stored:
        raise BasisError(f"{path}: the 3D physics do not match their physics_3d_id {stored!r} (edited after they "
                         "were written); rebuild the file with `hood-decomp bases --model`")
    thickness = {group: replace(sens, **{name: arrays[f"thickness_{name}"][i] for name in _THICKNESS_3D})
                 for i, (group, sens) in enumerate(normal.thickness.items())}
    return replace(normal, gas_w3=arrays["gas_w3"], thermal_w3=arrays["thermal_w3"], thickness=thickness)


def _write_zones(h5: h5py.File, content_id: str, zones: tuple[ToleranceZone, ...]) -> None:
    group = h5.create_group("tolerance_zones")
    group.attrs["zones_id"] = zones_id(content_id, zones)
    group.create_dataset("names", data=np.array([z.name for z in zones], dtype=object), dtype=_STR)
    group.create_dataset("regions", data=np.array([z.region for z in zones], dtype=object), dtype=_STR)
    for name in ("lower_mm", "upper_mm", "min_coverage"):
        group.create_dataset(name, data=np.array([getattr(z, name) for z in zones], dtype=float))
    group.create_dataset("node_indptr", data=np.cumsum([0, *(z.nodes.size for z in zones)]).astype(np.int64))
    group.create_dataset("node_indices", data=np.concatenate([z.nodes for z in zones]).astype(np.int64),
                         compression="gzip", compression_opts=1, shuffle=True)


def _read_reading_bias(read: Reader, content_id: str, pca: PCABasis) -> ScanReadingBias:
    """The optional /scan_reading_bias group: a radius > 0, finite arrays of named shapes, the content matching
    ``reading_id``."""
    bias = ScanReadingBias(read.attr("scan_reading_bias", "radius_mm", "float"),
                           read.array("scan_reading_bias/mean", ("N",)),
                           read.array("scan_reading_bias/components", ("K", "N")))
    try:
        bias.validate(pca)
    except BasisError as error:
        raise BasisError(f"{read.path}: {error}") from None
    if reading_bias_id(content_id, bias) != read.attr("scan_reading_bias", "reading_id", "str"):
        raise BasisError(f"{read.path}: scan_reading_bias does not match its reading_id (altered after it was "
                         "written, or taken from other bases); rebuild the file with `hood-decomp bases`")
    return bias


def _read_zones(read: Reader, content_id: str) -> tuple[ToleranceZone, ...]:
    """The optional /tolerance_zones group: kinds, named shapes, finite limits with lower < upper, coverages in
    0..1, every zone a non-empty set of skin nodes, and the content matching ``zones_id``."""
    names = read.strings("tolerance_zones/names", "Z")
    regions = read.strings("tolerance_zones/regions", "Z")
    lower, upper, coverage = (read.array(f"tolerance_zones/{name}", ("Z",))
                              for name in ("lower_mm", "upper_mm", "min_coverage"))
    read.bind("Z1", len(names) + 1, "tolerance_zones names plus one")
    indptr = read.array("tolerance_zones/node_indptr", ("Z1",), "integer").astype(np.int64)
    indices = _indices(read, "tolerance_zones/node_indices", ("M",), 0, "N")
    if indptr[0] != 0 or indptr[-1] != indices.size or np.any(np.diff(indptr) < 1):
        raise BasisError(f"{read.path}: tolerance_zones/node_indptr must rise from 0 to {indices.size} by at least "
                         "1 per zone (every zone holds a skin node)")
    bad = [n for n, lo, hi, c in zip(names, lower, upper, coverage, strict=True) if not (lo < hi and 0 <= c <= 1)]
    if bad:
        raise BasisError(f"{read.path}: tolerance zone(s) {bad} need lower_mm < upper_mm and min_coverage in 0..1")
    zones = tuple(ToleranceZone(name, indices[indptr[i]:indptr[i + 1]], float(lower[i]), float(upper[i]),
                                float(coverage[i]), regions[i]) for i, name in enumerate(names))
    stored = read.attr("tolerance_zones", "zones_id", "str")
    if zones_id(content_id, zones) != stored:
        raise BasisError(f"{read.path}: tolerance_zones do not match their zones_id {stored!r} (edited after they "
                         "were written, or taken from other bases); rebuild the file with `hood-decomp bases --model`")
    return zones


def save_bases(path: str | Path, bases: Bases, *, scan_skin: bool = True) -> Bases:
    """Write ``bases`` to an HDF5 file (overwrites); with ``scan_skin`` also the prepared scan skin (lookup grid,
    quadrics, kernel of the default ScanFieldEstimator), so that scans need not rebuild it, and the scan step's
    reading bias of the basis' fields measured through it (core.loop.scan_skin.reading_bias). Returns the bases as
    written (with that reading bias), which a caller that goes on with them in memory should use."""
    content_id = bases_id(bases)
    arrays = None
    if scan_skin:
        from hood_decomp.core.loop.scan_skin import scan_ready

        # with the smoothing bias' correlation measured on the part's states, and the basis' reading bias
        bases, arrays = scan_ready(bases)
    with h5py.File(path, "w") as h5:
        version = FEATURES_SCHEMA_VERSION if bases.tolerance_zones or bases.measured_effects else SCHEMA_VERSION
        h5.attrs.update(format=FORMAT, schema_version=version, model_id=bases.model_id, bases_id=content_id)
        if bases.calibration:
            h5.attrs["calibration"] = bases.calibration
        if bases.tolerance_zones:
            _write_zones(h5, content_id, bases.tolerance_zones)
        if bases.physics is not None and bases.reduced_model is not None:
            _write_physics(h5, content_id, bases.physics)
        if bases.thermal is not None:
            thermal = h5.create_group("thermal")
            for name, value in zip(_THERMAL_DIMS, bases.thermal, strict=True):
                thermal.create_dataset(name, data=value)
        if bases.discrepancy is not None:
            h5.create_dataset("discrepancy", data=bases.discrepancy)
        if bases.discrepancy_local is not None:
            h5.create_dataset("discrepancy_local", data=bases.discrepancy_local)
        for name in _DISCREPANCY_TERMS:
            if getattr(bases, name) is not None:
                h5.create_dataset(name, data=getattr(bases, name))
        skin = h5.create_group("skin")
        skin.attrs["model_id"] = bases.skin.model_id
        for name in ("points", "normals", "triangles"):
            skin.create_dataset(name, data=getattr(bases.skin, name))
        params = h5.create_group("parameters")
        params.create_dataset("names", data=np.array(bases.names, dtype=object), dtype=_STR)
        params.attrs["n_bilateral"] = bases.pca.n_bilateral_
        if bases.measured_effects:
            params.create_dataset("measured_effects", data=np.array(bases.measured_effects, dtype=object), dtype=_STR)

        pca = h5.create_group("pca")
        _write_arrays(pca, bases.pca, PCA_FITTED_ARRAYS)
        pca.attrs.update(
            model_id=bases.pca.model_id_,
            n_components_requested=-1 if bases.pca.n_components is None else int(bases.pca.n_components),
            explained_variance_requested=np.nan if bases.pca.explained_variance is None
            else float(bases.pca.explained_variance),
            rtol=bases.pca.rtol,
            n_components=bases.pca.n_components_,
            training_residual_rms=bases.pca.training_residual_rms_,
            notes=json.dumps(list(bases.pca.notes_)),
        )
        hier = h5.create_group("hierarchical")
        _write_arrays(hier, bases.hierarchical, HIERARCHICAL_FITTED_ARRAYS)
        hier.create_dataset("effect_names", data=np.array(bases.hierarchical.effect_names_, dtype=object), dtype=_STR)
        hier.attrs.update(model_id=bases.hierarchical.model_id_, epsilon=bases.hierarchical.epsilon_)

        if bases.reduced_model is not None:
            model = h5.create_group("reduced_model")
            for item in fields(ReducedModel):
                value = getattr(bases.reduced_model, item.name)
                if item.name == "names":
                    model.create_dataset("names", data=np.array(value, dtype=object), dtype=_STR)
                elif isinstance(value, np.ndarray):
                    model.create_dataset(item.name, data=value)
                else:
                    model.attrs[item.name] = value

        if arrays is not None:
            group = h5.create_group("scan_skin")
            group.attrs["prepared_id"] = prepared_id(content_id, arrays)
            for name, values in arrays.items():  # plain: every one-off scan reads them whole (the lookup grid and
                _write_array(group, name, values, pack=False)  # the kernel's indices: 80 ms of CPU to inflate, 44 MB)
        if bases.scan_reading_bias is not None:
            bias = bases.scan_reading_bias
            group = h5.create_group("scan_reading_bias")
            group.attrs.update(radius_mm=bias.radius_mm, reading_id=reading_bias_id(content_id, bias))
            group.create_dataset("mean", data=bias.mean)
            group.create_dataset("components", data=bias.components)
    return bases


# --- reading -----------------------------------------------------------------------------------------------------
def load_bases(path: str | Path, mapped: bool = False) -> Bases:
    """Read a bases file written by :func:`save_bases`. Raises BasisError for a missing, foreign, altered or malformed
    file: every dataset and attribute of docs/bases_schema.md present with its kind, its shape consistent with the
    others (named dimensions), its floats finite, its indices in range, and the content matching ``bases_id``.

    mapped: the arrays stored plainly (the floats, the prepared scan skin's) are read-only views of the file mapped
    into memory (:class:`~hood_decomp.io.hdf5.Reader`), for a process that ends soon after, as a command-line verb
    does."""
    path = Path(path)
    with open_hdf5(path, "bases file", BasisError) as h5:
        read = Reader(h5, path, BasisError, mapped)
        found = h5.attrs.get("format")
        if found != FORMAT:
            shown = found if isinstance(found, str) and len(found) < 60 else type(found).__name__
            raise BasisError(f"{path} is not a hood_decomp bases file (format {shown!r})")
        version = read.attr("/", "schema_version", "int")
        if version not in READABLE_VERSIONS:
            raise BasisError(f"{path} has bases schema version {version}, this reader knows "
                             f"{' and '.join(map(str, READABLE_VERSIONS))} (rebuild it with `hood-decomp bases`)")
        model_id = read.attr("/", "model_id", "str")
        names = read.strings("parameters/names", "P")
        n_bilateral = read.attr("parameters", "n_bilateral", "int")
        if not 0 <= n_bilateral <= len(names):
            raise BasisError(f"{path}: parameters n_bilateral is {n_bilateral}, expected 0..{len(names)}")
        read.bind("B", n_bilateral, "parameters n_bilateral")
        read.bind("U", len(names) - n_bilateral, "parameters names minus n_bilateral")
        skin = SkinSurface(points=read.array("skin/points", ("N", "3")), normals=read.array("skin/normals", ("N", "3")),
                           triangles=_indices(read, "skin/triangles", ("T'", "3"), 0, "N"),
                           model_id=str(read.attr("skin", "model_id", "str")))

        read.bind("K", read.attr("pca", "n_components", "int"), "pca n_components")
        requested = read.attr("pca", "n_components_requested", "int")
        variance = read.attr("pca", "explained_variance_requested", "float_or_nan")
        pca = PCABasis(None if requested < 0 else requested, None if np.isnan(variance) else variance,
                       read.attr("pca", "rtol", "float"))
        for name in PCA_FITTED_ARRAYS:
            setattr(pca, name, read.array(f"pca/{name.rstrip('_')}", _PCA_DIMS[name]))
        pca.model_id_, pca.names_, pca.n_bilateral_ = read.attr("pca", "model_id", "str"), names, n_bilateral
        pca.n_components_ = read.dims["K"][0]
        pca.training_residual_rms_ = read.attr("pca", "training_residual_rms", "float")
        pca.notes_ = _notes(read)

        epsilon = read.attr("hierarchical", "epsilon", "float")
        hier = HierarchicalBasis(epsilon=epsilon)
        hier.effect_names_ = read.strings("hierarchical/effect_names", "E")
        for name in HIERARCHICAL_FITTED_ARRAYS:
            dims, kind = _HIERARCHICAL_DIMS[name]
            setattr(hier, name, _indices(read, "hierarchical/effect_fields", dims, -1, "F") if name == "effect_fields_"
                    else read.array(f"hierarchical/{name.rstrip('_')}", dims, kind))
        hier.model_id_ = read.attr("hierarchical", "model_id", "str")
        hier.names_, hier.n_bilateral_ = names, n_bilateral
        hier.epsilon_ = epsilon

        reduced = None
        if "reduced_model" in h5:
            values: dict[str, object] = {
                "model_id": read.attr("reduced_model", "model_id", "str"),
                "names": read.strings("reduced_model/names", "P"),
                "n_bilateral": read.attr("reduced_model", "n_bilateral", "int"),
                "parameter_states": read.attr("reduced_model", "parameter_states", "str"),
            }
            for name, dims in _REDUCED_DIMS.items():
                values[name] = (_indices(read, "reduced_model/pad_of", dims, 0, "U") if name == "pad_of"
                                else read.array(f"reduced_model/{name}", dims))
            reduced = ReducedModel(**values)
            if reduced.parameter_states not in ("effective", "commanded"):
                raise BasisError(f"{path}: reduced_model parameter_states is {reduced.parameter_states!r}, expected "
                                 "'effective' or 'commanded'")
            if reduced.names != names or reduced.n_bilateral != n_bilateral:
                raise BasisError(f"{path}: reduced_model names {reduced.names} (n_bilateral {reduced.n_bilateral}) "
                                 f"differ from the parameters {names} (n_bilateral {n_bilateral})")
        stored_id = read.attr("/", "bases_id", "str")
        # optional (issue 16): the calibration record of calibrated bases, JSON text
        calibration = read.attr("/", "calibration", "str") if "calibration" in h5.attrs else ""
        thermal = None
        if "thermal" in h5:  # optional (issue 16): calibrated bases' response to 1 K
            if reduced is None:
                raise BasisError(f"{path}: a thermal response needs the reduced model, which the file lacks")
            thermal = tuple(read.array(f"thermal/{name}", dims) for name, dims in _THERMAL_DIMS.items())
        # optional (issue 16): calibrated bases' model discrepancy modes (N, D) mm
        discrepancy = read.array("discrepancy", ("N", "D")) if "discrepancy" in h5 else None
        # optional (issue 16, session 6): the discrepancy's part outside the smooth modes per node (N,) mm^2
        local = read.array("discrepancy_local", ("N",)) if "discrepancy_local" in h5 else None
        if local is not None and (discrepancy is None or np.any(local < 0)):
            raise BasisError(f"{path}: discrepancy_local must be non-negative variances beside /discrepancy")
        # optional (issue 16, session 11): the discrepancy rows' expected noise (N, K) and the correction's own
        # error (N, r) mm; a file without them (calibrated before) counts D D^T as it is
        terms = {name: read.array(name, ("N", dim)) if name in h5 else None
                 for name, dim in _DISCREPANCY_TERMS.items()}
        if any(value is not None for value in terms.values()) and discrepancy is None:
            raise BasisError(f"{path}: {' and '.join(n for n, v in terms.items() if v is not None)} need /discrepancy")
        has_scan_skin = version >= 3 and "scan_skin" in h5
        # optional (issue 15, session 16): the scan step's reading bias of the basis' fields
        reading = _read_reading_bias(read, stored_id, pca) if "scan_reading_bias" in h5 else None
        # optional (issue 17): acceptance criteria, outside bases_id, bound to it by their own zones_id
        zones = _read_zones(read, stored_id) if "tolerance_zones" in h5 else ()
        # optional (issue 15, session 21): the FE model's responses behind its physical factors
        physics, physics_matches = _read_physics(read, stored_id, reduced) if "physics" in h5 else (None, True)
        measured: tuple[str, ...] = ()
        if "parameters/measured_effects" in h5:
            measured = read.strings("parameters/measured_effects", "M")
            strays = [name for name in measured if name not in names[:n_bilateral]]
            if not measured or strays or len(set(measured)) != len(measured):
                raise BasisError(f"{path}: parameters/measured_effects {list(measured)} must name distinct bilateral "
                                 f"parameters of {list(names[:n_bilateral])} (at least one when present)")

    for what, other in (("skin", skin.model_id), ("PCA basis", pca.model_id_), ("hierarchical basis", hier.model_id_),
                        ("reduced model", None if reduced is None else reduced.model_id)):
        if other is not None and other != model_id:
            raise BasisError(f"{path}: {what} model_id {other!r} differs from the file's {model_id!r}")
    bases = Bases(model_id, skin, pca, hier, reduced, calibration, thermal, zones, discrepancy, measured, local,
                  **terms, physics=physics, scan_reading_bias=reading)
    if bases_id(bases) != stored_id:
        raise BasisError(f"{path}: content does not match its bases_id {stored_id!r} (the file was altered after "
                         "it was written: a rewritten model_id or array); rebuild it with `hood-decomp bases`")
    if not physics_matches:
        raise BasisError(f"{path}: physics do not match their physics_id (edited after they were written, or taken "
                         "from other bases); rebuild the file with `hood-decomp bases --model`")
    key = id(bases)
    _LOADED_IDS[key] = (weakref.ref(bases, lambda _: _LOADED_IDS.pop(key, None)), stored_id)
    if has_scan_skin:  # read when the first scan of this skin needs it (not for a field or a decomposition)
        from hood_decomp.core.scan.scan_field import register_prepared_skin

        held = weakref.ref(bases)  # the registry must not keep the bases alive
        register_prepared_skin(skin, lambda: _with_bias(load_scan_skin(path, stored_id, skin.n_nodes, mapped),
                                                        held()))
    return bases


def _with_bias(arrays: dict[str, np.ndarray], bases: Bases | None) -> dict[str, np.ndarray]:
    """A prepared skin of a file written before the smoothing bias' correlation (issue 15 run 10) or its variance
    floor (run 17) was stored with it: measured now from ``bases`` (core.loop.scan_skin; about 2 s of CPU at default
    resolution, once a process), the stored values kept; as read when both are stored, or the bases are gone (the
    scan step then states its area fallback and no floor)."""
    if {"bias_correlation", "bias_variance_floor"} <= arrays.keys() or bases is None:
        return arrays
    from hood_decomp.core.loop.scan_skin import measured_bias
    from hood_decomp.core.scan.scan_field import ScanFieldEstimator

    started = time.perf_counter()
    measured = measured_bias(ScanFieldEstimator().fit(bases.skin, prepared=arrays), bases)
    if measured:  # every process reading this file pays it again
        logger.warning("the bases file predates the stored scan bias: measured now in %.1f s; rebuild the bases "
                       "(hood-decomp bases) to store it", time.perf_counter() - started)
    return measured | arrays


def load_scan_skin(path: str | Path, content_id: str, n_nodes: int, mapped: bool = False) -> dict[str, np.ndarray]:
    """The prepared scan skin of the bases file ``path`` whose ``bases_id`` is ``content_id`` and skin has ``n_nodes``
    nodes (ScanFieldEstimator.prepared_skin arrays). Raises BasisError when the file changed since (another
    bases_id), the group is malformed (kinds, named shapes, finiteness) or its content does not match its
    ``prepared_id``; index ranges are checked by ``ScanFieldEstimator.fit``. ``mapped``: see :func:`load_bases`."""
    from hood_decomp.core.scan.scan_field import PREPARED_OPTIONAL, PREPARED_SKIN

    path = Path(path)
    with open_hdf5(path, "bases file", BasisError) as h5:
        read = Reader(h5, path, BasisError, mapped)
        if read.attr("/", "bases_id", "str") != content_id:
            raise BasisError(f"{path} changed since it was loaded (another bases_id); load it again")
        read.bind("N", n_nodes, "skin/points")
        read.bind("N1", n_nodes + 1, "skin/points plus one")
        arrays = {name: read.array(f"scan_skin/{name}", dims, kind) for name, (dims, kind) in PREPARED_SKIN.items()
                  if name not in PREPARED_OPTIONAL or f"scan_skin/{name}" in h5}
        stored = read.attr("scan_skin", "prepared_id", "str")
    if prepared_id(content_id, arrays) != stored:
        raise BasisError(f"{path}: scan_skin does not match its prepared_id {stored!r} (altered after it was "
                         "written); rebuild the file with `hood-decomp bases`")
    return arrays


def _indices(read: Reader, name: str, dims: tuple[str, ...], lowest: int, dim: str) -> np.ndarray:
    """An integer index array whose entries must lie in lowest .. size of ``dim`` - 1."""
    values = read.array(name, dims, "integer")
    size = read.dims[dim][0] if dim in read.dims else 0
    if values.size and (values.min() < lowest or values.max() >= size):
        raise BasisError(f"{read.path}: {name} holds indices {values.min()}..{values.max()}, expected "
                         f"{lowest}..{size - 1} ({dim} = {size})")
    return values.astype(np.int64)


def _notes(read: Reader) -> tuple[str, ...]:
    text = read.attr("pca", "notes", "str")
    try:
        notes = json.loads(text)
    except ValueError as error:
        raise BasisError(f"{read.path}: pca notes is not JSON: {error}") from error
    if not isinstance(notes, list) or not all(isinstance(n, str) for n in notes):
        raise BasisError(f"{read.path}: pca notes must be a JSON list of strings")
    return tuple(notes)
