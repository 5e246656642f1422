"""Shared result types of the numerical core: frozen dataclasses of numpy arrays.

These are the contracts between the layers: the FE side produces :class:`SkinSurface` and :class:`ReducedModel`, the
scan side produces :class:`DisplacementField`, the method produces :class:`ParameterEstimate` and
:class:`Decomposition`; the ROS adapters convert them to and from messages. Units are millimetres throughout. Every
per-node array is in the model's visible-skin node order (N nodes).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field, replace

import numpy as np

from hood_decomp.errors import FieldError


def side_by_side(*parts: np.ndarray) -> np.ndarray:
    """(N, k) the parts (N, k_i) side by side, each column contiguous in memory (a fields-first array, transposed).
    Node-by-mode arrays are stored so because the weighted Grams (core.method.residual.weighted_gram) read them column
    by column: a strided column costs a pass over the whole part's memory (paper scale, a scan's check: the unseen
    rows' Gram 4.2 -> 2.0 ms). A single part already stored so is returned as it is (no copy)."""
    parts = [np.asarray(part, float) for part in parts]
    if len(parts) == 1 and parts[0].T.flags.c_contiguous:
        return parts[0]
    stacked = np.empty((sum(part.shape[1] for part in parts), parts[0].shape[0]))  # (k, N), C order
    np.concatenate([part.T for part in parts], axis=0, out=stacked)
    return stacked.T


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
            digest.update(array.reshape(-1).view(np.uint8))  # the bytes of tobytes(), without copying them
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

    def triangle_areas(self) -> np.ndarray:
        """(T,) mm^2, the area of each triangle. By blocks of triangles, the cross product by components: the whole
        (T, 3, 3) corners and np.cross's temporaries were about 60 MB of fresh memory at paper resolution, 0.1-0.15 s
        of a one-off run in page faults."""
        points = np.asarray(self.points, dtype=np.float64)
        triangles = np.asarray(self.triangles)
        areas = np.empty(triangles.shape[0])
        for start in range(0, triangles.shape[0], 65_536):
            corners = triangles[start : start + 65_536]
            first = points[corners[:, 0]]
            a, b = points[corners[:, 1]] - first, points[corners[:, 2]] - first
            x = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
            y = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
            z = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
            areas[start : start + 65_536] = 0.5 * np.sqrt(x * x + y * y + z * z)
        return areas


#: kinds of field error model: made by the scan step, stated by a user (``--noise-mm``), or none (a simulated field)
ERROR_MODEL_KINDS = ("scan", "stated", "none")
#: node variance floor, mm^2: round-off of a noise-free field must not count as a model defect
VARIANCE_FLOOR_MM2 = 1e-16


def uniform(values: np.ndarray) -> bool:
    """Whether positive node values (n,) are one value to round-off (a white uniform error model)."""
    return bool(np.ptp(values) <= 1e-12 * values.max())


@dataclass(frozen=True)
class FieldErrorModel:
    """How wrong each node value of a field may be (DESIGN.md: "a field carries its error model").

    The node errors are e = s * x + U z: x a zero-mean unit-variance field correlated over the smoothing radius, z ~
    N(0, I_6) the registration error, U (N, 6) the pose covariance carried to the field through the rigid-body modes
    of the skin (:meth:`registration_modes`).

    kind: "scan" (made by the scan step), "stated" (a user's ``--noise-mm``: white, uniform) or "none" (a simulated
        field: no statement; the within-model test and the covariance then take the level from the residual).
    node_std: (N,) mm, one standard deviation per node (NaN where the field is NaN); empty (0,) for "none".
    correlation: (N,) >= 1, the sum of node i's correlation coefficients with all nodes, sum_k rho_ik: how many nodes
        one independent sample spans (1 for white noise). For a field that is smooth on the correlation scale, x's
        projection variance is sum_i x_i^2 s_i^2 correlation_i; the effective number of independent samples of the
        field is sum_i 1 / correlation_i.
    correlation_length_mm: the smoothing radius that makes the correlation (0 for white noise).
    pose_covariance: (6, 6) covariance of the registration twist [omega (rad, 3), t (mm, 3)] about ``pose_center``
        (part frame), symmetric positive semi-definite; zeros when the field has no registration.
    pose_center: (3,) mm, the point the twist's rotation is about.
    bias_correlation: the correlation sum (nodes, as ``correlation``) of the making's own bias, 0 for none. The scan
        step's smoothing biases node values where the displacement is curved below the smoothing radius (at pads,
        hinges, free edges); that bias is not noise: it shows as rough residual in excess of ``node_std`` and it is
        correlated over a wider area. Its level is measured on each residual as that excess; this number says how
        far it is correlated.
    bias_variance_floor: mm^2 per node, the least level of that bias (0 for none): the scan step's smoothing-bias
        variance per node measured on the part's own FE states (core.loop.scan_skin), as the test measures a level
        (core.method.residual.split_level). A residual's rough excess over ``node_std`` is lost in the noise at
        realistic point noise (issue 15 run 16 B) while the bias is the same whatever the noise, so the test uses the
        larger of the two. Used only with ``bias_correlation`` > 0.
    view_poses: a field fused from several views (:mod:`hood_decomp.core.scan.fusion`) has one independent
        registration error per view, each reaching only the nodes that view saw, with that view's fusion weight:
        :class:`ViewPoseError` per view. When present, :meth:`registration_modes` is built from them (N, 6 V) and
        ``pose_covariance`` about ``pose_center`` is only a conservative one-pose summary (the sum of the views'
        covariances moved to a common centre) for consumers that carry a single pose (field files). The
        DisplacementField message carries the views (``view_weight``, ``view_poses``), so a node downstream propagates
        them as the fusing process does.
    """

    kind: str
    node_std: np.ndarray
    correlation: np.ndarray
    correlation_length_mm: float = 0.0
    pose_covariance: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))
    pose_center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    bias_correlation: float = 0.0
    view_poses: tuple[ViewPoseError, ...] = ()
    bias_variance_floor: float = 0.0

    @staticmethod
    def none() -> FieldErrorModel:
        """The error model of a field that states none (a simulated field)."""
        return FieldErrorModel("none", np.zeros(0), np.zeros(0))

    @staticmethod
    def stated(noise_mm: float, n_nodes: int) -> FieldErrorModel:
        """White noise of ``noise_mm`` (mm, one sigma) on every node, as a user states it (``--noise-mm``)."""
        if not (np.isfinite(noise_mm) and noise_mm > 0):
            raise FieldError(f"a stated noise must be a finite number > 0 mm, got {noise_mm}")
        return FieldErrorModel("stated", np.full(n_nodes, float(noise_mm)), np.ones(n_nodes))

    @property
    def has_pose(self) -> bool:
        return bool(np.any(self.pose_covariance != 0.0)) or any(view.has_pose for view in self.view_poses)

    def validate(self, n_nodes: int) -> None:
        """Raise FieldError naming the problem: an unknown kind, arrays of the wrong shape, negative, infinite or NaN
        variances on seen nodes, correlation below 1, a pose covariance that is not symmetric positive semi-definite.
        Checked once per model and node count (an estimate asks four times; paper scale 0.5 ms each): the model is
        frozen and its arrays are taken as not written in place after it is made, as every decoded or fitted array.
        """
        if self.__dict__.get("_valid_nodes") == n_nodes:
            return
        if self.kind not in ERROR_MODEL_KINDS:
            raise FieldError(f"error model kind {self.kind!r} is not one of {ERROR_MODEL_KINDS}")
        expected = (0,) if self.kind == "none" else (n_nodes,)
        for name in ("node_std", "correlation"):
            shape = np.shape(getattr(self, name))
            if shape != expected:
                raise FieldError(f"error model {name} has shape {shape}, expected {expected} ({self.kind!r} model)")
        std, corr = np.asarray(self.node_std, float), np.asarray(self.correlation, float)
        known = ~np.isnan(std)
        if np.any(np.isinf(std)) or np.any(std[known] < 0):
            raise FieldError("error model node_std must be finite and >= 0 (NaN only on unseen nodes); found "
                             f"{int(np.sum(np.isinf(std) | (std < 0)))} negative or infinite values")
        if np.any(~(corr[known] >= 1.0 - 1e-9)) or np.any(np.isinf(corr)):
            raise FieldError("error model correlation (sum of correlation coefficients per node) must be a finite "
                             "number >= 1 on every node with a std")
        for name in ("correlation_length_mm", "bias_correlation", "bias_variance_floor"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise FieldError(f"error model {name} must be a finite number >= 0, got {value}")
        pose = np.asarray(self.pose_covariance, float)
        if pose.shape != (6, 6) or not np.all(np.isfinite(pose)):
            raise FieldError(f"error model pose_covariance must be a finite (6, 6) matrix, got shape {pose.shape}")
        scale = max(float(np.abs(pose).max()), 1e-300)
        if not np.allclose(pose, pose.T, rtol=0.0, atol=1e-9 * scale):
            raise FieldError("error model pose_covariance is not symmetric")
        if np.linalg.eigvalsh(pose)[0] < -1e-9 * scale:
            raise FieldError("error model pose_covariance is not positive semi-definite "
                             f"(smallest eigenvalue {np.linalg.eigvalsh(pose)[0]:.3g})")
        if np.shape(self.pose_center) != (3,) or not np.all(np.isfinite(self.pose_center)):
            raise FieldError(f"error model pose_center must be a finite (3,) point, got {np.shape(self.pose_center)}")
        for k, view in enumerate(self.view_poses):
            weight = np.asarray(view.weight, float)
            if weight.shape != (n_nodes,) or not np.all((weight >= 0) & (weight <= 1 + 1e-9)):
                raise FieldError(f"error model view {k}: weight must be (N,) = ({n_nodes},) values in [0, 1], got "
                                 f"shape {weight.shape}")
            FieldErrorModel("none", np.zeros(0), np.zeros(0), pose_covariance=view.covariance,
                            pose_center=view.center).validate(n_nodes)
        object.__setattr__(self, "_valid_nodes", n_nodes)  # frozen: the memo is not a field (eq, repr, replace)

    def __getstate__(self) -> dict:
        """The fields only: the memos of :meth:`validate` and :meth:`node_variance` are made again where the model
        lands (a pickled model kept its variances: twice the bytes, writeable again)."""
        return {name: value for name, value in self.__dict__.items() if not name.startswith("_")}

    def node_variance(self, n_nodes: int) -> tuple[np.ndarray, np.ndarray]:
        """(variance (N,) mm^2 = node_std^2 floored at VARIANCE_FLOOR_MM2 (unseen nodes: the floor), correlation (N,))
        of this model, validated (:meth:`validate`), read-only and made once (the estimate and its test read them
        four times). Not for a model of kind "none" (core.method.residual.node_variance states its unit weight)."""
        self.validate(n_nodes)
        made = self.__dict__.get("_node_variance")
        if made is None:
            variance = np.maximum(np.nan_to_num(np.asarray(self.node_std, float)) ** 2, VARIANCE_FLOOR_MM2)
            correlation = np.array(self.correlation, float)
            variance.flags.writeable = correlation.flags.writeable = False
            made = (variance, correlation)
            object.__setattr__(self, "_node_variance", made)
        return made

    def uniform_weight(self, n_nodes: int) -> float | None:
        """The node weight variance x correlation (mm^2, :meth:`node_variance`) when it is one value on every node to
        round-off (:func:`uniform`: a white uniform model, as :meth:`stated` makes), else None; found once per model.
        Any nodes' sums of the weights are then their count times it, so the estimate and its test make no pass for
        them. Not for a model of kind "none"."""
        made = self.__dict__.get("_uniform_weight")
        if made is None:
            variance, correlation = self.node_variance(n_nodes)
            weight = variance * correlation
            made = (float(weight[0]) if weight.size and uniform(weight) else None,)
            object.__setattr__(self, "_uniform_weight", made)
        return made[0]

    def node_sums(self, n_nodes: int) -> tuple[float, float, float]:
        """(sum of the node variances mm^2, the largest of them, sum of 1 / correlation: the effective number of
        independent samples) over every node (:meth:`node_variance`), found once per model: the within-model test of
        a field seen everywhere reads them (four passes over the nodes at each estimate otherwise). Not for a model
        of kind "none"."""
        made = self.__dict__.get("_node_sums")
        if made is None:
            variance, correlation = self.node_variance(n_nodes)
            made = (float(variance.sum()), float(variance.max()), float(np.sum(1.0 / correlation)))
            object.__setattr__(self, "_node_sums", made)
        return made

    def registration_modes(self, points: np.ndarray, normals: np.ndarray, rigid: np.ndarray | None = None
                           ) -> np.ndarray:
        """U (N, 6) mm: the normal field error of the pose error, e_reg = U z with z ~ N(0, I_6).

        points, normals: (N, 3) skin nodes (mm) and unit normals. A twist (omega, t) about c moves x by
        omega x (x - c) + t, whose normal part is omega . ((x - c) x n) + t . n: the rigid-body modes J (N, 6);
        U = J L with L L^T the pose covariance. rigid: :func:`rigid_modes` of these nodes when the caller keeps
        them (None: made here).
        """
        rigid = rigid_modes(points, normals) if rigid is None else rigid
        mixing = self.pose_mixing()
        if mixing is not None:
            return (mixing.T @ rigid.T).T  # column-major as the rigid modes (side_by_side)
        return side_by_side(*(view.weight[:, None] * (rigid @ _pose_mixing(view.covariance, view.center))
                              for view in self.view_poses))

    def pose_mixing(self) -> np.ndarray | None:
        """(6, 6) M with :meth:`registration_modes` = :func:`rigid_modes` @ M for a field of one pose; None for a
        fused field, whose views' modes are weighted node by node."""
        return None if self.view_poses else _pose_mixing(self.pose_covariance, self.pose_center)


@dataclass(frozen=True)
class ViewPoseError:
    """The registration error of one view of a fused field (:attr:`FieldErrorModel.view_poses`).

    covariance: (6, 6) of the view's registration twist [omega rad (3), t mm (3)] about ``center`` (3,) mm, part
    frame (zeros: the view's pose states none). weight: (N,) the view's share in each fused node value (0 where the
    view did not see the node; the views' weights sum to 1 on every seen node).
    """

    covariance: np.ndarray
    center: np.ndarray
    weight: np.ndarray

    @property
    def has_pose(self) -> bool:
        return bool(np.any(self.covariance != 0.0))


def rigid_modes(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(N, 6) the normal displacement of the nodes per unit twist (omega, t) about the origin: [x x n, n] (points,
    normals (N, 3) mm and unit); column-major (:func:`side_by_side`)."""
    return side_by_side(np.cross(points, normals), normals)


def _pose_mixing(covariance: np.ndarray, center: np.ndarray) -> np.ndarray:
    """(6, 6) M with rigid_modes @ M the normal field error per unit of a pose error with ``covariance`` about
    ``center`` (registration_modes): omega x (x - c) + t = omega x x + (t + [c]x omega), so the rigid modes about c
    are the origin's times [[I, 0], [[c]x, I]] (a 6 x 6 product instead of a pass over the nodes), then L with
    L L^T the covariance."""
    cx, cy, cz = np.asarray(center, float)
    about = np.eye(6)
    about[3:, :3] = [[0.0, -cz, cy], [cz, 0.0, -cx], [-cy, cx, 0.0]]
    values, vectors = np.linalg.eigh(np.asarray(covariance, float))
    return about @ (vectors * np.sqrt(np.clip(values, 0.0, None)))


#: how far a 3D displacement's normal part may differ from the field's normal value, per mm of the field's largest
#: displacement (at least 1 mm): the round-off of single precision, in which the ensemble store keeps both (an
#: exported member differed by 2.9e-8 mm at 1e-9, and was refused), never a measurement's difference
NORMAL_PART_RTOL = 1e-6


@dataclass(frozen=True)
class DisplacementField:
    """A signed normal displacement per visible skin node (paper: the condensed scalar field).

    normal_displacement: (N,) float64, mm, NaN where the scan gave no support.
    coverage: fraction of skin nodes with a finite value, 0..1.
    noise_rms: estimated scan noise per scan point, mm (NaN when unknown, e.g. a simulated field); informative only:
        the within-model test and the covariance use ``error_model``, with its level checked against the residual.
    error_model: the field's :class:`FieldErrorModel`; None means :meth:`FieldErrorModel.none`.
    displacement: (N, 3) float64, mm, the field's own 3D displacement where it has one (a simulated or FE field: the
        paper fits all three components, section 3.2), NaN rows where ``normal_displacement`` is NaN; its normal part
        is ``normal_displacement``. None for a field that measures normal distances only (a scan). Checked against a
        skin by :meth:`checked_displacement`.
    """

    model_id: str
    normal_displacement: np.ndarray
    coverage: float
    noise_rms: float
    error_model: FieldErrorModel | None = None
    displacement: np.ndarray | None = None

    @property
    def errors(self) -> FieldErrorModel:
        """The error model, "none" when the field states none."""
        return self.error_model if self.error_model is not None else FieldErrorModel.none()

    def checked_displacement(self, normals: np.ndarray | None) -> np.ndarray:
        """The field's 3D displacement (N, 3) mm, validated: its shape, finite exactly on the nodes whose normal value
        is (NaN rows elsewhere) and, given the skin's unit ``normals`` (N, 3) (None: not checked, a reader without
        the skin), its normal part equal to ``normal_displacement`` within :data:`NORMAL_PART_RTOL`. Raises
        FieldError naming the problem, and for a field without a 3D displacement."""
        if self.displacement is None:
            raise FieldError("the field carries no 3D displacement (a scan measures normal distances only; a field "
                             "file states one with displacement_3d, which files written before it lack): fit its "
                             "normal component (components 'normal')")
        values = np.asarray(self.normal_displacement, dtype=float)
        vectors = np.asarray(self.displacement, dtype=float)
        if vectors.shape != (values.size, 3):
            raise FieldError(f"3D displacement has shape {vectors.shape}, expected ({values.size}, 3)")
        seen = np.isfinite(values)
        if not np.all(np.isfinite(vectors[seen])) or not np.all(np.isnan(vectors[~seen])):
            wrong = int(np.sum(~np.all(np.isfinite(vectors), axis=1) & seen)
                        + np.sum(~np.all(np.isnan(vectors), axis=1) & ~seen))
            raise FieldError(f"3D displacement must be finite exactly where the normal displacement is (NaN rows "
                             f"elsewhere); {wrong} nodes differ")
        if normals is not None:
            part = np.einsum("na,na->n", vectors[seen], np.asarray(normals, float)[seen])
            gap = float(np.max(np.abs(part - values[seen]), initial=0.0))
            limit = NORMAL_PART_RTOL * max(1.0, float(np.max(np.abs(vectors[seen]), initial=0.0)))
            if gap > limit:
                raise FieldError(f"3D displacement's normal part differs from normal_displacement by up to {gap:.3g} "
                                 f"mm (round-off allows {limit:.3g} mm): not the same field")
        return vectors

    def vectors(self, normals: np.ndarray) -> np.ndarray:
        """The 3D displacement (N, 3) mm as normal times value, as the paper does."""
        return normals * self.normal_displacement[:, None]


#: the reduced model's arrays a sheet thickness changes (k, preload and pad_of do not depend on it)
SENSITIVE_ARRAYS = ("w0", "R", "G", "z0", "Sa", "H", "w0_3d", "R_3d", "G_3d")


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

    def on_nodes(self, nodes: np.ndarray) -> ReducedModel:
        """This model's normal skin responses on the kept skin ``nodes`` (n,) (a coarsened estimate, of the normal
        component: :mod:`hood_decomp.core.method.coarsening`), its 3D responses empty (0 nodes: at paper resolution
        they were 80 MB never read); the pad springs' arrays as they are."""
        return replace(self, w0=self.w0[nodes], R=np.ascontiguousarray(self.R[nodes]),
                       G=np.ascontiguousarray(self.G[nodes]), w0_3d=self.w0_3d[:0], R_3d=self.R_3d[:0],
                       G_3d=self.G_3d[:0])


@dataclass(frozen=True)
class ModelCheck:
    """The one within-model test of a residual (:mod:`hood_decomp.core.method.residual`), as every result reports it.

    statistic: the test statistic (chi-square-like, in units of the smooth part's own covariance); dof: its degrees of
    freedom (smooth modes tested); denominator_dof: degrees of freedom of the noise level estimated from the rough
    part of the residual (inf when the level is not estimated). p_value, alpha (false-alarm rate), within_model
    (p_value >= alpha). noise_scale: residual-supported node variance over the error model's (1 when they agree;
    a stated noise that is too large gives < 1 and is not used). noise_source: "error model" (the field's level was
    supported by the residual), "residual" (the field states none, or the stated one is larger than the residual
    supports, and the level comes from the residual). n_effective: effective number of independent samples.
    bias_mm2: variance (mm^2) the making's bias adds to a smooth unit-norm field's coefficient (0 without a bias term:
    :func:`hood_decomp.core.method.residual.split_level`).
    """

    statistic: float
    dof: int
    denominator_dof: float
    p_value: float
    alpha: float
    within_model: bool
    noise_scale: float
    noise_source: str
    n_effective: float
    bias_mm2: float = 0.0


@dataclass(frozen=True)
class ParameterEstimate:
    """Estimated parameter state of one field (paper eqs. 4-5, plus the contact-aware estimator).

    names: (P,) parameter labels. values, std, lower, upper: (P,) mm. For a lifted unilateral boundary ``values`` is
    the part's position there (the commanded position lies at or below it) and ``lifted`` is True.
    reconstruction: (N,) mm. residual: (N,) mm, measured minus reconstruction, NaN where unseen.
    within_model: False when the one within-model test says the model lacks an effect (``check``).
    method: "pca" (the paper's) or "contact" (contact-aware).
    covariance: (P, P) mm^2, full covariance of ``values`` (the field's error model, the basis' approximation error
        and, for a light-touch pad, the range its commanded position may take); std = sqrt(diag). None when unknown
        (an estimate decoded from a message without it).
    check: the :class:`ModelCheck` behind ``within_model`` (None when unknown).
    measured_effect: (P,) bool, True for a measured effect (a parameter without a boundary: a basis field learned from
        recurring residuals, :mod:`hood_decomp.core.loop.measured_effects`); its value is an amplitude, never a
        boundary to move. None means every parameter is a boundary (bases without measured effects).
    model_factors: names of the model's physical factors considered (:mod:`hood_decomp.core.method.model_spread`).
    model_effects: (F, P) mm, each factor's one-sigma effect on ``values`` (the uncertainty the model's not being
        calibrated to the part adds, apart from ``std``: a softer pad looks like a moved pad; on calibrated bases
        a factor's read of a lifted pad's position through the pad springs is in ``std`` instead); None when not
        considered (the "pca" estimator, an estimate decoded from a message).
    weighting: how the field was fitted: "generalised" (least squares weighted by the field's error model, its node
        covariance with the registration's rigid-body modes: :mod:`hood_decomp.core.method.estimation`) or
        "ordinary" (a field without an error model, or one whose covariance is a multiple of the identity).
    components: the displacement components fitted: "normal" (the default; scans measure normal distances) or "xyz"
        (all three, stacked, as the paper does for FE fields: :func:`hood_decomp.core.method.bases.estimate_field`).
        For "xyz" ``reconstruction`` and ``residual`` are the normal part (N,) of the 3D ones, ``residual_rms`` and
        ``residual_max`` that normal residual's (as a normal fit's: the in-plane residual is not in them), and
        ``check`` is the skin's test on each component of the stacked residual
        (:meth:`hood_decomp.core.method.residual.ResidualTest.stacked`; its level from the rough part of all 3 N
        values, which ``covariance`` uses).
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
    covariance: np.ndarray | None = None
    check: ModelCheck | None = None
    measured_effect: np.ndarray | None = None
    model_factors: tuple[str, ...] = ()
    model_effects: np.ndarray | None = None
    weighting: str = "ordinary"
    components: str = "normal"

    @property
    def model_covariance(self) -> np.ndarray | None:
        """(P, P) mm^2, the considered factors' covariance of ``values``: sum of the effects' outer products."""
        return None if self.model_effects is None else self.model_effects.T @ self.model_effects

    @property
    def model_std(self) -> np.ndarray | None:
        """(P,) mm, sqrt of the diagonal of :attr:`model_covariance`."""
        return None if self.model_effects is None else np.sqrt(np.sum(self.model_effects**2, axis=0))

    @property
    def boundary(self) -> np.ndarray:
        """(P,) bool: True where the parameter is a boundary the robot can move (not a measured effect)."""
        if self.measured_effect is None:
            return np.ones(len(self.names), dtype=bool)
        return ~np.asarray(self.measured_effect, bool)


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
    std: (P,) mm, one standard deviation of each correction. applicable: (P,) bool, whether this boundary's correction
    may be applied on its own (its std below the limit, its estimate in range, not lifted, and the field within the
    model with enough coverage); None when unknown (decoded from a message without it).
    remaining: (P,) mm, the part of the move to nominal that a per-cycle step limit left for the next cycle (0 where
    the correction is the whole move); None means nothing was left.
    measured_effect: (P,) bool, True for a measured effect (no boundary: its correction is always 0 and never
        applicable); None means every parameter is a boundary.
    """

    model_id: str
    names: tuple[str, ...]
    corrections: np.ndarray
    safe_to_apply: bool
    reason: str
    std: np.ndarray | None = None
    applicable: np.ndarray | None = None
    remaining: np.ndarray | None = None
    measured_effect: np.ndarray | None = None


@dataclass(frozen=True)
class MoveVerification:
    """Did a correction happen? The measured change of each boundary between the inspection that produced the
    correction and the next inspection of the same part, against the predicted change (the correction sent).

    names: (P,) labels. predicted, measured, std: (P,) mm (std: one standard deviation of measured - predicted, the
    two estimates' stds combined). fraction: (P,) measured / predicted (NaN where nothing was commanded).
    outcome: (P,) one of NOT_COMMANDED, ACHIEVED, PARTIAL, FAILED (the codes of hood_decomp_msgs/MoveVerification).
    tolerance: (P,) mm, the band around the prediction that counts as achieved. summary: the failed and slipped moves
    named, "" when every commanded move was achieved.
    """

    NOT_COMMANDED = 0
    ACHIEVED = 1
    PARTIAL = 2
    FAILED = 3
    OUTCOMES = ("NOT_COMMANDED", "ACHIEVED", "PARTIAL", "FAILED")

    model_id: str
    names: tuple[str, ...]
    predicted: np.ndarray
    measured: np.ndarray
    std: np.ndarray
    fraction: np.ndarray
    outcome: np.ndarray
    tolerance: np.ndarray
    summary: str

    @property
    def all_achieved(self) -> bool:
        commanded = self.outcome != self.NOT_COMMANDED
        return bool(np.all(self.outcome[commanded] == self.ACHIEVED))


@dataclass(frozen=True)
class ToleranceZone:
    """An acceptance criterion on the skin (``tolerance_zones`` in model.yaml): the normal displacement of every
    node of the zone must lie in [lower_mm, upper_mm], judged only when at least ``min_coverage`` of its nodes are seen.

    name: the zone's name. nodes: (M,) int64, M >= 1, indices of the zone's skin nodes (the bases' node order).
    lower_mm < upper_mm: allowed normal displacement, mm. min_coverage: 0..1. region: the zone's definition in part
    coordinates as model.yaml gave it (JSON text: box and/or sphere, mm), for people.
    """

    name: str
    nodes: np.ndarray
    lower_mm: float
    upper_mm: float
    min_coverage: float
    region: str


@dataclass(frozen=True)
class ZoneVerdict:
    """The verdict on one :class:`ToleranceZone` for one field.

    ok: at least ``min_coverage`` of the zone seen and every seen node within [lower_mm, upper_mm].
    worst_deviation_mm: the seen node's normal displacement farthest outside the limits (or, when all are inside,
    nearest to one), NaN when no node of the zone is seen; worst_node: its skin index (-1 when none is seen).
    coverage: seen fraction of the zone's nodes. outside: how many seen nodes lie outside the limits. reason: why
    not ok, "" when ok.
    """

    name: str
    ok: bool
    lower_mm: float
    upper_mm: float
    worst_deviation_mm: float
    worst_node: int
    coverage: float
    outside: int
    reason: str
