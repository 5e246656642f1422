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
"""

from __future__ import annotations

import dataclasses

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


@dataclasses.dataclass(frozen=True)
class SlideOfBasis:
    """The slide of the fields a PCA basis makes: a basis field's in-plane displacement is the same combination of
    the basis' 3D fields (mean_field_3d_ + c @ components_3d_, c its pre-factors)."""

    gradient: SurfaceGradient
    mean_field: np.ndarray
    components: np.ndarray
    gram: np.ndarray
    mean_field_3d: np.ndarray
    components_3d: np.ndarray

    @classmethod
    def of(cls, pca: PCABasis, skin: SkinSurface) -> SlideOfBasis:
        """The slide of ``pca``'s fields on ``skin`` (its nodes the basis' field nodes)."""
        if skin.n_nodes != pca.components_.shape[1]:
            raise BasisError(f"skin has {skin.n_nodes} nodes, the PCA basis' fields {pca.components_.shape[1]}")
        return cls(SurfaceGradient.fit(skin), pca.mean_field_, pca.components_, pca.gram_, pca.mean_field_3d_,
                   pca.components_3d_)

    def __call__(self, values: np.ndarray) -> np.ndarray:
        """(N,) mm, the slide u_t . grad u_n of the basis field that fits ``values`` (N,) mm (NaN where unseen) best
        in ordinary least squares. That fit is enough: the slide is second order (an error of 0.01 mm in the fitted
        field changes it by about 1e-4 mm), and it costs a K x K solve where the estimator's own generalised fit,
        run twice, would double the estimate's time (117 -> 243 ms on a default-hood scan)."""
        values = np.asarray(values, dtype=float)
        if values.shape != self.mean_field.shape:
            raise BasisError(f"field must have {self.mean_field.shape[0]} node values, got shape {values.shape}")
        seen = np.isfinite(values)
        coeff = np.linalg.solve(valid_normal_matrix(self.components, self.gram, seen),
                                self.components @ np.where(seen, values - self.mean_field, 0.0))
        normal = self.mean_field + coeff @ self.components
        return slide(self.gradient, normal, self.mean_field_3d + np.tensordot(coeff, self.components_3d, axes=1))
