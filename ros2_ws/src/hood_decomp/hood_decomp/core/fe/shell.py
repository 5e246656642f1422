"""Flat-facet linear shell triangle, vectorised over elements: CST membrane + DKT plate bending + drilling spring.

Each triangle carries 6 DOF per node in the global frame, ordered per node (ux, uy, uz, rx, ry, rz): translations mm,
rotations rad (right-hand rotation vector). In the element's own frame (x along edge 1-2, z along the normal) the
membrane (u, v) uses the constant-strain triangle, the bending (w, theta_x = dw/dy, theta_y = -dw/dx) uses the
discrete Kirchhoff triangle of Batoz, Bathe & Ho (1980), and the drilling rotation theta_z gets a small per-node spring
(a fraction of the plate bending stiffness) so that coplanar nodes are not singular; it carries no physical load.
Kirchhoff bending is the right model for 0.7-2 mm sheets whose element size is far larger than the thickness.

Quads are handled by :func:`quad_stiffness`: each quad is the four triangles of both diagonal splits at half weight,
so no diagonal direction is preferred.
"""

from __future__ import annotations

import numpy as np

#: drilling spring per element node as a fraction of the plate bending stiffness D = E t^3 / (12 (1 - nu^2)).
DRILLING_FACTOR = 1e-3


#: the four triangles of a quad (corner indices), both diagonal splits
QUAD_SPLITS = np.array([[0, 1, 2], [0, 2, 3], [0, 1, 3], [1, 2, 3]])


def local_frames(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Element frames and 2D coordinates.

    xyz: (T, 3, 3) node coordinates, mm. Returns R (T, 3, 3) with rows (e1, e2, n) and xy (T, 3, 2) local coordinates
    of the nodes (node 1 at the origin), mm.
    """
    e1 = xyz[:, 1] - xyz[:, 0]
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    n = np.cross(xyz[:, 1] - xyz[:, 0], xyz[:, 2] - xyz[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    e2 = np.cross(n, e1)
    R = np.stack([e1, e2, n], axis=1)
    xy = np.einsum("tij,tkj->tki", R[:, :2], xyz - xyz[:, :1])
    return R, xy


def membrane_cst(xy: np.ndarray, thickness: np.ndarray, E: float, nu: float) -> np.ndarray:
    """CST membrane stiffness (T, 6, 6) on local DOFs (u1, v1, u2, v2, u3, v3). xy: (T, 3, 2) mm; thickness (T,) mm."""
    x, y = xy[..., 0], xy[..., 1]
    area2 = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (x[:, 2] - x[:, 0]) * (y[:, 1] - y[:, 0])
    b = np.stack([y[:, 1] - y[:, 2], y[:, 2] - y[:, 0], y[:, 0] - y[:, 1]], axis=1) / area2[:, None]
    c = np.stack([x[:, 2] - x[:, 1], x[:, 0] - x[:, 2], x[:, 1] - x[:, 0]], axis=1) / area2[:, None]
    B = np.zeros((len(xy), 3, 6))
    B[:, 0, 0::2] = b
    B[:, 1, 1::2] = c
    B[:, 2, 0::2] = c
    B[:, 2, 1::2] = b
    D = E / (1 - nu**2) * np.array([[1, nu, 0], [nu, 1, 0], [0, 0, (1 - nu) / 2]])
    return np.matmul(B.transpose(0, 2, 1) @ D, B) * (0.5 * area2 * thickness)[:, None, None]


def bending_dkt(xy: np.ndarray, thickness: np.ndarray, E: float, nu: float) -> np.ndarray:
    """DKT plate bending stiffness (T, 9, 9) on local DOFs (w, theta_x, theta_y) per node (Batoz et al. 1980).

    Three mid-side integration points, exact for the quadratic rotation fields of the element.
    """
    x, y = xy[..., 0], xy[..., 1]
    # edges k = 4, 5, 6 are 2-3, 3-1, 1-2 (x_ij = x_i - x_j)
    xij = np.stack([x[:, 1] - x[:, 2], x[:, 2] - x[:, 0], x[:, 0] - x[:, 1]], axis=1)
    yij = np.stack([y[:, 1] - y[:, 2], y[:, 2] - y[:, 0], y[:, 0] - y[:, 1]], axis=1)
    l2 = xij**2 + yij**2
    P = -6 * xij / l2
    q = 3 * xij * yij / l2
    t = -6 * yij / l2
    r = 3 * yij**2 / l2
    P4, P5, P6 = P.T
    q4, q5, q6 = q.T
    t4, t5, t6 = t.T
    r4, r5, r6 = r.T
    x31, y31 = x[:, 2] - x[:, 0], y[:, 2] - y[:, 0]
    x12, y12 = x[:, 0] - x[:, 1], y[:, 0] - y[:, 1]
    area2 = x31 * y12 - x12 * y31  # (x2-x1)(y3-y1) - (x3-x1)(y2-y1)
    Db = E * thickness**3 / (12 * (1 - nu**2))
    Dmat = np.array([[1, nu, 0], [nu, 1, 0], [0, 0, (1 - nu) / 2]])
    K = np.zeros((len(xy), 9, 9))
    for xi, eta in ((0.5, 0.0), (0.5, 0.5), (0.0, 0.5)):
        a, b = 1 - 2 * xi, 1 - 2 * eta
        hx_xi = np.stack([
            P6 * a + (P5 - P6) * eta, q6 * a - (q5 + q6) * eta, -4 + 6 * (xi + eta) + r6 * a - eta * (r5 + r6),
            -P6 * a + eta * (P4 + P6), q6 * a - eta * (q6 - q4), -2 + 6 * xi + r6 * a + eta * (r4 - r6),
            -eta * (P5 + P4), eta * (q4 - q5), -eta * (r5 - r4)], axis=1)
        hy_xi = np.stack([
            t6 * a + eta * (t5 - t6), 1 + r6 * a - eta * (r5 + r6), -q6 * a + eta * (q5 + q6),
            -t6 * a + eta * (t4 + t6), -1 + r6 * a + eta * (r4 - r6), -q6 * a - eta * (q4 - q6),
            -eta * (t4 + t5), eta * (r4 - r5), -eta * (q4 - q5)], axis=1)
        hx_eta = np.stack([
            -P5 * b - xi * (P6 - P5), q5 * b - xi * (q5 + q6), -4 + 6 * (xi + eta) + r5 * b - xi * (r5 + r6),
            xi * (P4 + P6), xi * (q4 - q6), -xi * (r6 - r4),
            P5 * b - xi * (P4 + P5), q5 * b + xi * (q4 - q5), -2 + 6 * eta + r5 * b + xi * (r4 - r5)], axis=1)
        hy_eta = np.stack([
            -t5 * b - xi * (t6 - t5), 1 + r5 * b - xi * (r5 + r6), -q5 * b + xi * (q5 + q6),
            xi * (t4 + t6), xi * (r4 - r6), -xi * (q4 - q6),
            t5 * b - xi * (t4 + t5), -1 + r5 * b + xi * (r4 - r5), -q5 * b - xi * (q4 - q5)], axis=1)
        B = np.stack([
            y31[:, None] * hx_xi + y12[:, None] * hx_eta,
            -x31[:, None] * hy_xi - x12[:, None] * hy_eta,
            -x31[:, None] * hx_xi - x12[:, None] * hx_eta + y31[:, None] * hy_xi + y12[:, None] * hy_eta,
        ], axis=1) / area2[:, None, None]
        # weight 1/6 per point, dA = 2A dxi deta
        K += np.matmul(B.transpose(0, 2, 1) @ Dmat, B) * (Db * area2 / 6.0)[:, None, None]
    return K


def drilling(xy: np.ndarray, thickness: np.ndarray, E: float, nu: float) -> np.ndarray:
    """Drilling springs (T, 18, 18) on local DOFs: energy 0.5 k sum_i (theta_z_i - omega)^2.

    omega = (dv/dx - du/dy) / 2 is the CST's in-plane rigid rotation, so a rigid rotation costs nothing; k is
    ``DRILLING_FACTOR`` times the plate bending stiffness.
    """
    x, y = xy[..., 0], xy[..., 1]
    area2 = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (x[:, 2] - x[:, 0]) * (y[:, 1] - y[:, 0])
    b = np.stack([y[:, 1] - y[:, 2], y[:, 2] - y[:, 0], y[:, 0] - y[:, 1]], axis=1) / area2[:, None]
    c = np.stack([x[:, 2] - x[:, 1], x[:, 0] - x[:, 2], x[:, 1] - x[:, 0]], axis=1) / area2[:, None]
    k = DRILLING_FACTOR * E * thickness**3 / (12 * (1 - nu**2))
    K = np.zeros((len(xy), 18, 18))
    for i in range(3):
        g = np.zeros((len(xy), 18))
        g[:, 6 * i + 5] = 1.0
        g[:, 0::6] = 0.5 * c  # -(-du/dy)/2 with du/dy = sum c_j u_j
        g[:, 1::6] = -0.5 * b
        K += k[:, None, None] * g[:, :, None] * g[:, None, :]
    return K


def triangle_stiffness(xyz: np.ndarray, thickness: np.ndarray, E: float, nu: float) -> np.ndarray:
    """Global stiffness of flat shell triangles, (T, 18, 18), DOFs per node (ux, uy, uz, rx, ry, rz).

    xyz: (T, 3, 3) mm; thickness: (T,) mm (a weight may be folded in); E MPa; nu.
    """
    R, xy = local_frames(xyz)
    Km = membrane_cst(xy, thickness, E, nu)
    Kb = bending_dkt(xy, thickness, E, nu)
    local = np.zeros((len(xyz), 18, 18))
    mem = np.array([[6 * i, 6 * i + 1] for i in range(3)]).ravel()
    ben = np.array([[6 * i + 2, 6 * i + 3, 6 * i + 4] for i in range(3)]).ravel()
    local[:, mem[:, None], mem[None, :]] = Km
    local[:, ben[:, None], ben[None, :]] = Kb
    local += drilling(xy, thickness, E, nu)
    # rotate 3-vector blocks (6 blocks: translation and rotation of each node) to the global frame
    T = np.zeros((len(xyz), 18, 18))
    for block in range(6):
        T[:, 3 * block : 3 * block + 3, 3 * block : 3 * block + 3] = R
    return np.matmul(T.transpose(0, 2, 1), np.matmul(local, T))


def quad_stiffness(xyz: np.ndarray, thickness: np.ndarray, E: float, nu: float) -> np.ndarray:
    """Global stiffness of flat shell quads, (Q, 24, 24), DOFs per corner (ux, uy, uz, rx, ry, rz).

    Each quad is the four triangles of both diagonal splits (:data:`QUAD_SPLITS`), each counted half.
    xyz: (Q, 4, 3) mm; thickness: (Q,) mm; E MPa; nu.
    """
    n_quads = len(xyz)
    triangles = 0.5 * triangle_stiffness(xyz[:, QUAD_SPLITS].reshape(4 * n_quads, 3, 3), np.repeat(thickness, 4), E, nu)
    triangles = triangles.reshape(n_quads, len(QUAD_SPLITS), 18, 18)
    K = np.zeros((n_quads, 24, 24))
    for split, corners in enumerate(QUAD_SPLITS):
        dofs = (6 * corners[:, None] + np.arange(6)).ravel()
        K[:, dofs[:, None], dofs[None, :]] += triangles[:, split]
    return K
