"""Shared result types of the numerical core: frozen dataclasses of numpy arrays.

These are the contracts between the layers: the FE side produces :class:`SkinSurface` and :class:`ReducedModel`, the
scan side produces :class:`DisplacementField`, the method produces :class:`ParameterEstimate` and
:class:`Decomposition`; the ROS adapters convert them to and from messages. Units are millimetres throughout. Every
per-node array is in the model's visible-skin node order (N nodes).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np


def fingerprint(*arrays: np.ndarray | str) -> str:
    """A short, stable hex digest of arrays and strings (dtype, shape and bytes), used for ``model_id``.

    The same content always gives the same id on any machine; any change in geometry, node order or basis changes it.
    """
    digest = hashlib.sha256()
    for item in arrays:
        if isinstance(item, str):
            digest.update(b"s" + item.encode())
        else:
            array = np.ascontiguousarray(item)
            digest.update(f"a{array.dtype.str}{array.shape}".encode())
            digest.update(array.tobytes())
    return digest.hexdigest()[:16]


@dataclass(frozen=True)
class SkinSurface:
    """The visible outer skin the scanner sees.

    points: (N, 3) float64, mm, nominal node positions in the part frame.
    normals: (N, 3) float64, unit outward normals (pointing towards the scanner side).
    triangles: (T, 3) int64, indices into ``points`` (quads of the FE mesh split in two).
    model_id: fingerprint of the model this skin belongs to.
    """

    points: np.ndarray
    normals: np.ndarray
    triangles: np.ndarray
    model_id: str

    @property
    def n_nodes(self) -> int:
        return int(self.points.shape[0])


@dataclass(frozen=True)
class DisplacementField:
    """A signed normal displacement per visible skin node (paper: the condensed scalar field).

    normal_displacement: (N,) float64, mm, NaN where the scan gave no support.
    coverage: fraction of skin nodes with a finite value, 0..1.
    noise_rms: estimated scan noise, mm (NaN when unknown, e.g. a simulated field).
    """

    model_id: str
    normal_displacement: np.ndarray
    coverage: float
    noise_rms: float

    def vectors(self, normals: np.ndarray) -> np.ndarray:
        """The 3D displacement (N, 3) mm as normal times value, as the paper does."""
        return normals * self.normal_displacement[:, None]


@dataclass(frozen=True)
class ReducedModel:
    """The FE model condensed to what estimation needs: affine in the parameters for a fixed pad contact state.

    With bilateral parameter states ``a`` (B,), mm, and pad spring forces ``f`` (S,) >= 0, N:
        w = w0 + R a + G f                       (visible skin normal displacement, mm)
        z = z0 + Sa a + H f                      (pad node displacement along the pad axis, mm)
        f_k = k_k * max(0, b[pad_of_k] + preload_k - z_k)   (compression-only pad springs)
    where ``b`` (U,) are the commanded unilateral (buffer) positions, mm.

    names: labels of all declared parameters, bilateral first then unilateral: (B + U,).
    w0: (N,) skin normal displacement at a = 0 with no pad force (loads only).
    R: (N, B) skin response to a unit (1 mm) bilateral parameter.
    G: (N, S) skin response to a unit (1 N) pad spring force.
    z0: (S,), Sa: (S, B), H: (S, S) symmetric positive semi-definite pad compliance, mm/N.
    k: (S,) pad spring stiffness, N/mm. preload: (S,) mm. pad_of: (S,) int, index into the unilateral parameters.
    w0_3d, R_3d, G_3d: the same responses as 3D vectors, shapes (N, 3), (N, 3, B), (N, 3, S).
    parameter_states: "effective" or "commanded", the state an ensemble records for a lifted unilateral boundary
    (Ensemble.effective; the part model's ``parameter_states``).
    """

    model_id: str
    names: tuple[str, ...]
    n_bilateral: int
    w0: np.ndarray
    R: np.ndarray
    G: np.ndarray
    z0: np.ndarray
    Sa: np.ndarray
    H: np.ndarray
    k: np.ndarray
    preload: np.ndarray
    pad_of: np.ndarray
    w0_3d: np.ndarray
    R_3d: np.ndarray
    G_3d: np.ndarray
    parameter_states: str = "effective"


@dataclass(frozen=True)
class ParameterEstimate:
    """Estimated parameter state of one field (paper eqs. 4-5, plus the contact-aware estimator).

    names: (P,) parameter labels. values, std, lower, upper: (P,) mm. For a lifted unilateral boundary ``values`` is
    the part's position there (the commanded position lies at or below it) and ``lifted`` is True.
    reconstruction: (N,) mm. residual: (N,) mm, measured minus reconstruction, NaN where unseen.
    within_model: False when the residual is larger than the scan noise explains.
    method: "pca" (the paper's) or "contact" (contact-aware).
    """

    model_id: str
    names: tuple[str, ...]
    values: np.ndarray
    std: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    lifted: np.ndarray
    reconstruction: np.ndarray
    residual: np.ndarray
    residual_rms: float
    residual_max: float
    coverage: float
    within_model: bool
    method: str


@dataclass(frozen=True)
class EffectContribution:
    """One hierarchical effect e_i in a decomposition (paper eqs. 6-8).

    name: e.g. "LOCK_L & LOCK_R". parameters: the labels it involves.
    partial_displacement: (N,) mm, d_i = |c_i B_i + c_i^-1 B_i^-1| (eq. 6).
    contribution: (N,) 0..1, d_i / D (eq. 8); 0 where D = 0.
    share: this effect's part of sum over nodes of D, 0..1.
    """

    name: str
    parameters: tuple[str, ...]
    partial_displacement: np.ndarray
    contribution: np.ndarray
    share: float


@dataclass(frozen=True)
class Decomposition:
    """Per-effect decomposition of one field with the hierarchical basis.

    reconstruction: (N,) mm; residual: (N,) mm (NaN where unseen); reconstruction_rms: mm over seen nodes.
    """

    model_id: str
    effects: tuple[EffectContribution, ...]
    reconstruction: np.ndarray
    residual: np.ndarray
    reconstruction_rms: float


@dataclass(frozen=True)
class Ensemble:
    """One set of simulation members (the training set of section 3.1.1, or the validation set).

    names: (P,) parameter labels, bilateral first, then the U unilateral ones (buffers).
    n_bilateral: number of bilateral parameters B (P = B + U).
    lower, upper: (P,) declared ranges, mm.
    commanded: (M, P) commanded parameter states, mm.
    effective: (M, P) effective states, mm: equal to ``commanded`` except for a lifted unilateral boundary (no pad
        spring in contact), where it is the part's position there, min_k(z_k - preload_k) over that pad's springs,
        i.e. the commanded position at which the pad would just touch; commanded <= effective then. A model with
        ``parameter_states: commanded`` (the paper's convention, preset hood-paper) records the commanded state
        there too: effective == commanded, and contact_fraction == 0 keeps the lifted flag.
    contact_fraction: (M, U) fraction of each pad's springs in contact, 0 = lifted, 1 = full contact.
    reactions: (M, U) total pad force per unilateral boundary, N (>= 0).
    rank: (M,) number of non-zero commanded parameters (Table 1); -1 for random validation members.
    normal_displacement: (M, N) visible skin normal displacement, mm.
    displacement: (M, N, 3) visible skin 3D displacement, mm.
    """

    model_id: str
    names: tuple[str, ...]
    n_bilateral: int
    lower: np.ndarray
    upper: np.ndarray
    commanded: np.ndarray
    effective: np.ndarray
    contact_fraction: np.ndarray
    reactions: np.ndarray
    rank: np.ndarray
    normal_displacement: np.ndarray
    displacement: np.ndarray

    @property
    def n_members(self) -> int:
        return int(self.commanded.shape[0])


@dataclass(frozen=True)
class BoundaryCorrection:
    """The move that brings each boundary to nominal, for the fixture adjustment robot.

    names: (P,) labels. corrections: (P,) mm (the negated estimate; 0 for a lifted unilateral boundary, whose commanded
    position is not observable). safe_to_apply: False with a reason when coverage is low, the field is not within the
    model, an estimate lies outside its range, or an uncertainty is too large to act on.
    """

    model_id: str
    names: tuple[str, ...]
    corrections: np.ndarray
    safe_to_apply: bool
    reason: str
