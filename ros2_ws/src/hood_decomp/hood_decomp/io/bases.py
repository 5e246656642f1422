"""Saved bases: the PCA basis, the hierarchical basis, the skin and the reduced model in one HDF5 file (no pickle).

Schema: docs/bases_schema.md. A loaded :class:`hood_decomp.core.method.bases.Bases` is all estimation and decomposition
need; every field is checked against ``Bases.model_id``.
"""

from __future__ import annotations

import json
from dataclasses import fields
from pathlib import Path

import h5py
import numpy as np

from hood_decomp.core.method.bases import Bases
from hood_decomp.core.method.hierarchical import HIERARCHICAL_FITTED_ARRAYS, HierarchicalBasis
from hood_decomp.core.method.pca import PCA_FITTED_ARRAYS, PCABasis
from hood_decomp.core.types import ReducedModel, SkinSurface
from hood_decomp.errors import BasisError
from hood_decomp.io.hdf5 import open_hdf5

FORMAT = "hood_decomp.bases"
SCHEMA_VERSION = 1
_STR = h5py.string_dtype()


# --- writing -----------------------------------------------------------------------------------------------------
def _write_arrays(group: h5py.Group, obj: object, names: tuple[str, ...]) -> None:
    for name in names:
        group.create_dataset(name.rstrip("_"), data=np.asarray(getattr(obj, name)), compression="gzip",
                             compression_opts=1, shuffle=True)


def save_bases(path: str | Path, bases: Bases) -> None:
    """Write ``bases`` to an HDF5 file (overwrites)."""
    with h5py.File(path, "w") as h5:
        h5.attrs.update(format=FORMAT, schema_version=SCHEMA_VERSION, model_id=bases.model_id)
        skin = h5.create_group("skin")
        skin.attrs["model_id"] = bases.skin.model_id
        for name in ("points", "normals", "triangles"):
            skin.create_dataset(name, data=getattr(bases.skin, name))
        params = h5.create_group("parameters")
        params.create_dataset("names", data=np.array(bases.names, dtype=object), dtype=_STR)
        params.attrs["n_bilateral"] = bases.pca.n_bilateral_

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


# --- reading -----------------------------------------------------------------------------------------------------
def _strings(dataset: h5py.Dataset) -> tuple[str, ...]:
    return tuple(s.decode() if isinstance(s, bytes) else str(s) for s in dataset[()])


def _read_arrays(group: h5py.Group, obj: object, names: tuple[str, ...]) -> None:
    for name in names:
        key = name.rstrip("_")
        if key not in group:
            raise BasisError(f"bases file group '{group.name}' lacks dataset '{key}'")
        setattr(obj, name, group[key][()])


def load_bases(path: str | Path) -> Bases:
    """Read a bases file written by :func:`save_bases`; raises BasisError for a missing or foreign file."""
    path = Path(path)
    with open_hdf5(path, "bases file", BasisError) as h5:
        if h5.attrs.get("format") != FORMAT:
            raise BasisError(f"{path} is not a hood_decomp bases file (format {h5.attrs.get('format')!r})")
        version = int(h5.attrs.get("schema_version", -1))
        if version != SCHEMA_VERSION:
            raise BasisError(f"{path} has bases schema version {version}, this reader knows {SCHEMA_VERSION}")
        model_id = str(h5.attrs["model_id"])
        names = _strings(h5["parameters/names"])
        n_bilateral = int(h5["parameters"].attrs["n_bilateral"])
        skin = SkinSurface(
            points=h5["skin/points"][()], normals=h5["skin/normals"][()], triangles=h5["skin/triangles"][()],
            model_id=str(h5["skin"].attrs["model_id"]),
        )

        group = h5["pca"]
        requested = int(group.attrs["n_components_requested"])
        variance = float(group.attrs["explained_variance_requested"])
        pca = PCABasis(None if requested < 0 else requested, None if np.isnan(variance) else variance,
                       float(group.attrs["rtol"]))
        _read_arrays(group, pca, PCA_FITTED_ARRAYS)
        pca.model_id_, pca.names_, pca.n_bilateral_ = str(group.attrs["model_id"]), names, n_bilateral
        pca.n_components_ = int(group.attrs["n_components"])
        pca.training_residual_rms_ = float(group.attrs["training_residual_rms"])
        pca.notes_ = tuple(json.loads(group.attrs["notes"]))

        group = h5["hierarchical"]
        hier = HierarchicalBasis(epsilon=float(group.attrs["epsilon"]))
        _read_arrays(group, hier, HIERARCHICAL_FITTED_ARRAYS)
        hier.model_id_, hier.names_, hier.n_bilateral_ = str(group.attrs["model_id"]), names, n_bilateral
        hier.epsilon_ = float(group.attrs["epsilon"])
        hier.effect_names_ = _strings(group["effect_names"])

        reduced = None
        if "reduced_model" in h5:
            group = h5["reduced_model"]
            values = {}
            for item in fields(ReducedModel):
                if item.name == "names":
                    values["names"] = _strings(group["names"])
                elif item.name in group:
                    values[item.name] = group[item.name][()]
                elif item.name == "parameter_states":  # files written before hood-paper: the only convention then
                    values[item.name] = str(group.attrs.get(item.name, "effective"))
                else:
                    values[item.name] = group.attrs[item.name]
            values["model_id"] = str(values["model_id"])
            values["n_bilateral"] = int(values["n_bilateral"])
            reduced = ReducedModel(**values)

    for what, other in (("skin", skin.model_id), ("PCA basis", pca.model_id_), ("hierarchical basis", hier.model_id_),
                        ("reduced model", None if reduced is None else reduced.model_id)):
        if other is not None and other != model_id:
            raise BasisError(f"{path}: {what} model_id {other!r} differs from the file's {model_id!r}")
    return Bases(model_id, skin, pca, hier, reduced)
