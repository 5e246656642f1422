"""What a surface scan reads of a displacement: the displaced surface at the nominal node, not the displaced node.

The FE model and its bases give each skin node's own normal displacement u_n. A scan measures how far the displaced
*surface* lies from the nominal one along the nominal normal at the nominal node. Where the part moves in its own
plane by u_t, the surface has slid along itself, and the scan reads the surface point that came from x - u_t:

    s(x) = u_n(x - u_t) = u_n(x) - u_t . grad u_n(x) + O(|u_t|^2)                       (the slide)

a smooth term, an in-plane motion times a slope. On the built-in hood HINGE_Y moves the hood in its plane by up to
a millimetre; the slide is then most of a noise-free scan's error against the FE truth (issue 15 run 10: 0.0013 mm
RMS with it, 0.00034 mm without, default hood), state-driven, and the within-model test could only allow for it by
an allowance ten to a hundred times what a part that barely slides needs. So it is taken out instead: the estimator
adds u_t . grad u_n at its own estimate to a scanned field and estimates again (one Gauss-Newton step of a term
that is second order in the displacement; :func:`hood_decomp.core.method.bases.estimate_field`).

Left out, with their size on the built-in hood: the O(|u_t|^2) terms (the nominal surface's curvature times the
slide squared, about 1e-4 mm at a 1 mm slide on a 5 m radius), and the slide a part temperature adds (thermal
growth is in-plane, 0.02 mm per K over the hood, times slopes of 1e-3).

The scan step also smooths: on a curved displacement that biases what it reads (the kernel's second moment times
the curvature). The part of that bias a basis field's reading has inside the basis is a gain of the reading, which
moves the estimate and which no residual test sees; where the bases carry it (:class:`ScanReadingBias`, measured by
noise-free scans of the basis' fields, core.loop.scan_skin) it is taken out the same way.
"""

from __future__ import annotations

import dataclasses
from functools import cached_property

import numpy as np

from hood_decomp.core.method.estimation import valid_normal_matrix
from hood_decomp.core.method.pca import PCABasis
from hood_decomp.core.types import SkinSurface
from hood_decomp.errors import BasisError


@dataclasses.dataclass(frozen=True)
class SurfaceGradient:
    """The tangential gradient of node values on a skin: per node the area-weighted mean of the gradients of the
    piecewise-linear interpolant on the triangles around it, projected on the node's tangent plane.

    triangles: (T, 3) node indices; hats: (T, 3, 3) 1/mm, per triangle and corner the gradient of that corner's hat
    function; area: (T,) mm^2; around: (N,) mm^2, the area of the triangles around each node; normals: (N, 3) unit.
    """

    triangles: np.ndarray
    hats: np.ndarray
    area: np.ndarray
    around: np.ndarray
    normals: np.ndarray

    @classmethod
    def fit(cls, skin: SkinSurface) -> SurfaceGradient:
        """Prepare the gradient of ``skin``'s node values (one pass over its triangles)."""
        points = np.asarray(skin.points, dtype=float)
        triangles = np.asarray(skin.triangles, dtype=np.int64)
        corners = points[triangles]  # (T, 3, 3)
        normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        twice = np.linalg.norm(normal, axis=1)
        if not np.all(twice > 0):
            raise BasisError(f"the skin has {int(np.count_nonzero(twice <= 0))} degenerate triangles (zero area)")
        unit = normal / twice[:, None]
        # The hat function of corner k grows towards it across the opposite edge: grad = n x e_k / (2 A), with e_k the
        # opposite edge taken counter-clockwise.
        opposite = np.stack([corners[:, 2] - corners[:, 1], corners[:, 0] - corners[:, 2],
                             corners[:, 1] - corners[:, 0]], axis=1)
        hats = np.cross(unit[:, None, :], opposite) / twice[:, None, None]
        area = 0.5 * twice
        around = np.bincount(triangles.ravel(), weights=np.repeat(area, 3), minlength=skin.n_nodes)
        normals = np.asarray(skin.normals, dtype=float)
        return cls(triangles, hats, area, around, normals / np.linalg.norm(normals, axis=1, keepdims=True))

    def __call__(self, values: np.ndarray) -> np.ndarray:
        """(N, 3) 1, the tangential gradient of node values ``values`` (N,) mm (mm per mm); nodes on no triangle 0."""
        per_triangle = np.einsum("tk,tkd->td", values[self.triangles], self.hats) * self.area[:, None]
        n = self.around.shape[0]
        summed = np.stack([np.bincount(self.triangles.ravel(), weights=np.repeat(per_triangle[:, d], 3), minlength=n)
                           for d in range(3)], axis=1)
        gradient = summed / np.where(self.around > 0, self.around, 1.0)[:, None]
        return gradient - np.sum(gradient * self.normals, axis=1, keepdims=True) * self.normals


def slide(gradient: SurfaceGradient, normal: np.ndarray, displacement: np.ndarray) -> np.ndarray:
    """(N,) mm, u_t . grad u_n: what a scan of the part displaced by ``displacement`` (N, 3) mm, whose normal part is
    ``normal`` (N,) mm, reads less than ``normal`` (module docstring): s = u_n - slide."""
    tangential = displacement - np.sum(displacement * gradient.normals, axis=1, keepdims=True) * gradient.normals
    return np.sum(tangential * gradient(normal), axis=1)


#: the largest gain inside the basis a scan reading bias may have (ScanReadingBias.validate): the one-step
#: correction neglects the gain's square (0.024 on the coarse hood: 6e-4 of the field; 0.5 would leave a quarter)
MAX_READING_GAIN = 0.5


@dataclasses.dataclass(frozen=True)
class ScanReadingBias:
    """What the scan step's smoothing reads in excess of each field of a PCA basis: a noise-free scan of the basis'
    3D field through the scan step's own field path, less what a scan reads of it (its normal displacement less its
    slide; core.loop.scan_skin.state_bias). Linear in the field to the order the slide is taken out, so a basis
    field with pre-factors c reads ``mean + c @ components`` in excess.

    radius_mm: the smoothing radius it was measured with; it holds for fields whose error model states that radius
        (``FieldErrorModel.correlation_length_mm``), not for fields smoothed otherwise.
    mean: (N,) mm, of the basis' mean field; components: (K, N) mm per unit pre-factor of each basis field.
    """

    radius_mm: float
    mean: np.ndarray
    components: np.ndarray

    def validate(self, pca: PCABasis) -> None:
        """Raise BasisError naming the problem: a radius that is not a finite number > 0, arrays of other shapes than
        (N,) and (K, N) of ``pca``, values that are not finite, a mean bias larger than the mean field it reads (RMS),
        or a gain inside the basis of :data:`MAX_READING_GAIN` or more (largest singular value of the (K, K)
        pre-factor change per unit pre-factor; 0.024 on the coarse hood): a reading bias that large is no small bias
        of a scan step (a skin too coarse for its kernel), and the one-step correction
        (:meth:`ReadingOfBasis.bias_inside`) would not hold."""
        if not (np.isfinite(self.radius_mm) and self.radius_mm > 0):
            raise BasisError(f"scan reading bias radius must be a finite number > 0 mm, got {self.radius_mm}")
        n_components, n_nodes = pca.components_.shape
        for name, shape in (("mean", (n_nodes,)), ("components", (n_components, n_nodes))):
            value = np.asarray(getattr(self, name))
            if value.shape != shape:
                raise BasisError(f"scan reading bias {name} has shape {value.shape}, expected {shape}")
            if not np.all(np.isfinite(value)):
                raise BasisError(f"scan reading bias {name} holds {int(np.sum(~np.isfinite(value)))} values that are "
                                 "not finite")
        mean_rms, field_rms = (float(np.sqrt(np.mean(np.square(v)))) for v in (self.mean, pca.mean_field_))
        if mean_rms > field_rms:
            raise BasisError(f"scan reading bias of the mean field is {mean_rms:.3g} mm RMS, more than the mean field "
                             f"itself ({field_rms:.3g} mm)")
        gain = np.linalg.norm(np.linalg.solve(pca.gram_, pca.components_ @ self.components.T), 2)
        if not gain < MAX_READING_GAIN:
            raise BasisError(f"scan reading bias changes the basis' pre-factors by {gain:.3g} per unit (largest "
                             f"singular value), expected below {MAX_READING_GAIN}")

    def holds_for(self, radius_mm: float) -> bool:
        """Whether a field smoothed with ``radius_mm`` was read as this bias was measured."""
        return abs(radius_mm - self.radius_mm) <= 1e-9 * self.radius_mm


@dataclasses.dataclass(frozen=True)
class ReadingOfBasis:
    """What a scan reads of the fields a PCA basis makes, less than their node displacements: their slide (a basis
    field's in-plane displacement is the same combination of the basis' 3D fields, mean_field_3d_ + c @
    components_3d_, c its pre-factors) and, when measured (``bias``), the scan step's smoothing bias inside the
    basis."""

    gradient: SurfaceGradient
    mean_field: np.ndarray
    components: np.ndarray
    gram: np.ndarray
    mean_field_3d: np.ndarray
    components_3d: np.ndarray
    bias: ScanReadingBias | None = None

    @classmethod
    def of(cls, pca: PCABasis, skin: SkinSurface, bias: ScanReadingBias | None = None) -> ReadingOfBasis:
        """The reading of ``pca``'s fields on ``skin`` (its nodes the basis' field nodes), with the scan step's
        ``bias`` of those fields where measured."""
        if skin.n_nodes != pca.components_.shape[1]:
            raise BasisError(f"skin has {skin.n_nodes} nodes, the PCA basis' fields {pca.components_.shape[1]}")
        if bias is not None:
            bias.validate(pca)
        return cls(SurfaceGradient.fit(skin), pca.mean_field_, pca.components_, pca.gram_, pca.mean_field_3d_,
                   pca.components_3d_, bias)

    def __call__(self, values: np.ndarray, radius_mm: float) -> np.ndarray:
        """(N,) mm, what to add to a scanned field ``values`` (N,) mm (NaN where unseen), smoothed with
        ``radius_mm``, to read the node displacement of the basis field that fits it best in ordinary least
        squares: that field's slide u_t . grad u_n, less :meth:`bias_inside`.

        The OLS fit is enough: both terms are small beside the field (an error of 0.01 mm in the fitted field
        changes the slide by about 1e-4 mm), and it costs a K x K solve where the estimator's own generalised fit,
        run twice, would double the estimate's time (117 -> 243 ms on a default-hood scan)."""
        seen, normal_matrix, coeff = self._fit(values)
        return self._combined(coeff, self._inside(seen, normal_matrix, coeff, radius_mm))

    def prepare(self) -> None:
        """Make now what the first scan's reading makes (:attr:`terms`, the bias' projection on the basis)."""
        self.terms  # noqa: B018 (made now, kept)
        if self.bias is not None:
            self._bias_projection  # noqa: B018

    def slide_of(self, coeff: np.ndarray) -> np.ndarray:
        """(N,) mm, the slide u_t . grad u_n (:func:`slide`) of the basis field with pre-factors ``coeff`` (K,),
        mean_field + coeff @ components with its 3D field, from the kept :attr:`terms`."""
        return self._combined(np.asarray(coeff, float), np.zeros(self.components.shape[0]))

    def _combined(self, coeff: np.ndarray, inside: np.ndarray) -> np.ndarray:
        """(N,) mm: the slide of the basis field with pre-factors ``coeff`` (K,) less the basis field with
        pre-factors ``inside`` (K,), one pass over :attr:`terms`."""
        weights = np.r_[1.0, coeff]
        first, second = np.triu_indices(weights.size)
        combination = np.r_[weights[first] * weights[second], -inside].astype(np.float32)
        return (combination @ self.terms).astype(float)

    @cached_property
    def terms(self) -> np.ndarray:
        """(P + K, N) float32: per pair i <= j of the basis' fields (P = (K + 1)(K + 2) / 2 pairs of the mean field,
        then the components), field i's 3D displacement times field j's tangential gradient plus the same with i and
        j swapped (once for i = j); then the K components themselves. The slide u_t . grad u_n (:func:`slide`) of
        the field w~ @ [mean, components], w~ = (1, c), is quadratic in w~: sum over the pairs of w~_i w~_j times
        their term, so a scan's reading takes no gradient of its own and, with the bias inside the basis
        (:meth:`bias_inside`, a combination of the components), is one pass over these rows. In float32: the
        reading is a small term beside the field (a slide of 0.01 mm at a millimetre of in-plane motion) and its
        round-off (1e-7 of it) is nothing, while the pass is most of a paper-resolution scan's reading (half the
        bytes: 50 + 8 MB at K = 10). The gradients being tangential, the 3D field's normal part does not count.
        Made at the first scan (11 gradients, about 0.3 s at paper resolution: a node's warm-up and `estimate
        --scan` while it reads the scan make them, :meth:`~.bases.Bases.prepare_estimation`)."""
        moved = (self.mean_field_3d, *self.components_3d)
        slopes = [self.gradient(field) for field in (self.mean_field, *self.components)]
        first, second = np.triu_indices(len(moved))
        terms = np.empty((first.size + len(self.components), self.mean_field.shape[0]), dtype=np.float32)
        for row, (i, j) in enumerate(zip(first, second, strict=True)):
            term = np.einsum("nd,nd->n", moved[i], slopes[j])
            if i != j:
                term += np.einsum("nd,nd->n", moved[j], slopes[i])
            terms[row] = term
        terms[first.size:] = self.components
        return terms

    def bias_inside(self, values: np.ndarray, radius_mm: float) -> np.ndarray:
        """(N,) mm, the part inside the basis of the smoothing bias (:class:`ScanReadingBias`) of the basis field that
        fits ``values`` (N,) mm best; zeros without a measured bias or for a field smoothed with another
        ``radius_mm`` than it was measured with.

        Only the part inside the basis: it is what moves the estimate (a gain of the reading: on the default hood
        a noise-free scan's HINGE_X error is 0.58-0.68 of a 0.02 mm scan's std RMS, linear in the state, R^2 0.99;
        issue 15 run 17), and the within-model test cannot see it. The part outside the basis stays the test's bias
        allowance (``FieldErrorModel.bias_correlation`` is measured outside the basis); taking it out as well, from
        a bias that is linear in the field only to about 75 %, raised the default false alarms from 2.0 to 3.2 %."""
        return self._inside(*self._fit(values), radius_mm) @ self.components

    def _fit(self, values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The OLS fit of the basis to ``values`` (N,) mm: seen (N,), the normal matrix (K, K), pre-factors (K,)."""
        values = np.asarray(values, dtype=float)
        if values.shape != self.mean_field.shape:
            raise BasisError(f"field must have {self.mean_field.shape[0]} node values, got shape {values.shape}")
        seen = np.isfinite(values)
        normal_matrix = valid_normal_matrix(self.components, self.gram, seen)
        centred = values - self.mean_field
        centred[~seen] = 0.0  # in place: np.where made a second (N,) array (0.3 of 1.3 ms at paper resolution)
        coeff = np.linalg.solve(normal_matrix, self.components @ centred)
        return seen, normal_matrix, coeff

    @cached_property
    def _bias_projection(self) -> tuple[np.ndarray, np.ndarray]:
        """(components @ bias mean (K,), components @ bias components^T (K, K)) over every node: the projection of
        the bias of a basis field on the basis, linear in its pre-factors."""
        assert self.bias is not None
        return self.components @ self.bias.mean, self.components @ self.bias.components.T

    def _inside(self, seen: np.ndarray, normal_matrix: np.ndarray, coeff: np.ndarray, radius_mm: float
                ) -> np.ndarray:
        """(K,) the pre-factors of :meth:`bias_inside` of the basis field with pre-factors ``coeff`` fitted on the
        ``seen`` nodes (its normal matrix there): the bias' projection over every node less the unseen nodes' share
        (no pass over the seen nodes)."""
        if self.bias is None or not self.bias.holds_for(radius_mm):
            return np.zeros(self.components.shape[0])
        mean, gain = self._bias_projection
        projected = mean + gain @ coeff
        unseen = np.flatnonzero(~seen)
        if unseen.size:
            bias = self.bias.mean[unseen] + coeff @ self.bias.components[:, unseen]
            projected = projected - self.components[:, unseen] @ bias
        return np.linalg.solve(normal_matrix, projected)
