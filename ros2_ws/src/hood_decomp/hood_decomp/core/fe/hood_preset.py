"""The built-in hood: an engine hood like the paper's (section 4.1, Fig. 7, Table 2) at a chosen mesh resolution.

Geometry (X rearward, Y to the right, Z up; left = -Y as in a vehicle body frame; mm):
- outer skin, 0.7 mm: doubly curved (crowned across and along, rising towards the windscreen), 1250 mm long (X) and
  1450 mm wide at the rear (Y), slightly narrower at the front;
- inner panel, 0.7 mm: a frame along the perimeter plus two longitudinal and one transverse rib, each a closed hat
  section 30 mm deep under the skin. Along the perimeter (hem) and along the inner edges of frame and ribs (adhesive
  beads) the inner panel shares its nodes with the skin, so both solvers see one joined structure; elsewhere the
  windows between frame and ribs leave the skin unsupported;
- four reinforcements, 2 mm: hinge L/R and lock L/R areas of the inner panel (flush tailored patches).
Boundaries (all on the inner structure, never on skin nodes): hinge R fixed in X, Y, Z; hinge L prescribed in X, Y, Z
(HINGE_X, HINGE_Y adjustable, Z held); locks L/R prescribed in Z (LOCK_L, LOCK_R, push and pull); buffers L/R rubber
pads in Z (BUFFER_L, BUFFER_R: compression-only, preloaded, may lift off partly or entirely); gas springs L/R pushing
580 N rearward-up in the X-Z plane near the hinges; gravity -Z. All six ranges [-1, 1] mm.

Two presets share this geometry (same mesh, same ``model_id``) and differ in the buffers' physics and the state
convention (:data:`PRESETS`):
- ``hood`` (the default): preloaded rubber pads (600 N/mm, 0.15 mm) and effective states (a lifted buffer's state is
  the part's position there);
- ``hood-paper``: the paper's boundary physics (section 4.1, Table 2): buffers are rigid unilateral displacement
  boundaries without preload (the hood rests on them or lifts off), states are the commanded ones (the lifted flag is
  kept beside them). "Rigid" is a pad of :data:`RIGID_PAD_STIFFNESS`; the member fields move by less than
  1e-5 mm when it is made 10 times stiffer (tests/core/fe/test_hood_paper.py).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from hood_decomp.core.fe.model import Boundary, Material, Parameter, Part, PartModel, Patch, validate_model
from hood_decomp.errors import ModelError

#: skin grid (nodes along X, nodes along Y) per resolution; paper: >= 188,559 visible skin nodes (section 4.1)
RESOLUTIONS: dict[str, tuple[int, int]] = {
    "coarse": (64, 74),  # ~19 mm: both solvers within ~2 % of the converged unit responses (44 x 51: 4-7 %)
    "default": (161, 187),
    "paper": (405, 466),
}
LENGTH = 1250.0  # X, mm
WIDTH = 1450.0  # Y at the rear, mm
TAPER = 0.06  # relative width loss at the front
DEPTH = 30.0  # inner panel depth under the skin, mm
RAMP = 40.0  # distance over which the inner panel drops from the bond line to full depth, mm
FRAME = 150.0  # frame width from the perimeter, mm
RIB = 120.0  # rib width, mm
RIBS_Y = (-260.0, 260.0)  # longitudinal ribs
RIBS_X = (0.55 * LENGTH,)  # transverse rib
GAS_SPRING_FORCE = 580.0  # N (section 4.1)
GAS_SPRING_AXIS = (np.cos(np.radians(30.0)), 0.0, np.sin(np.radians(30.0)))  # rearward-up, X-Z plane
#: pad (rubber buffer) stiffness N/mm and preload mm, chosen so the ensemble has lifted, partly and fully seated pads
#: and the pad pressure distribution adds fields beyond the 7 that point buffers would give (~0.01 mm, coarse)
PAD_STIFFNESS = 600.0
PAD_PRELOAD = 0.15
#: hood-paper: total stiffness of a rigid buffer, N/mm. The fields converge as 1/k (edge contact concentrates the
#: reaction on a few of the 36 springs): on the coarse hood's 729 members 1e7 differs from 1e13 by 1.5e-3 mm, 1e10 by
#: 1.5e-6 mm; the pad compliance 1/k stays 1e-6 of the structure's (cond(H) ~ 400), so the LCP is as well posed.
RIGID_PAD_STIFFNESS = 1.0e10
PATCH_RADIUS = 30.0  # hinges, locks, gas springs, mm
PAD_RADIUS = 40.0  # buffers, mm


#: the 2 mm reinforcements: site -> how far (mm, in plan) they reach from it
REINFORCEMENT_REACH = {"hinge_L": 120.0, "hinge_R": 120.0, "lock_L": 90.0, "lock_R": 90.0}


def half_width(x: np.ndarray) -> np.ndarray:
    """Half width (mm) of the hood's plan at X = x."""
    return 0.5 * WIDTH * (1.0 - TAPER * (1.0 - x / LENGTH))


def skin_height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Skin Z (mm): crown across (45 mm), crown along (20 mm) and a rise towards the rear (0.12)."""
    eta = y / half_width(x)
    xi = 2.0 * x / LENGTH - 1.0
    return 45.0 * (1.0 - eta**2) + 20.0 * (1.0 - xi**2) + 0.12 * x


def _smoothstep(t: np.ndarray) -> np.ndarray:
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _graded_axis(n: int, breaks: list[float]) -> np.ndarray:
    """n points from breaks[0] to breaks[-1] that include every break, evenly spaced within each segment."""
    lengths = np.diff(breaks)
    counts = np.maximum(1, np.round(lengths / lengths.sum() * (n - 1)).astype(int))
    while counts.sum() != n - 1:  # fix rounding on the longest segment
        counts[np.argmax(lengths / counts)] += 1 if counts.sum() < n - 1 else -1
    parts = [np.linspace(a, b, c, endpoint=False) for a, b, c in zip(breaks[:-1], breaks[1:], counts, strict=True)]
    return np.concatenate([*parts, [breaks[-1]]])


def build_hood(resolution: str = "default", pad_stiffness: float = PAD_STIFFNESS,
               pad_preload: float = PAD_PRELOAD, grid: tuple[int, int] | None = None,
               parameter_states: str = "effective", stem: str = "hood") -> PartModel:
    """Generate the built-in hood model at ``resolution`` (coarse | default | paper); validated.

    grid: (nodes along X, nodes along Y) of the skin, overriding the resolution's (mesh convergence studies).
    parameter_states: "effective" or "commanded" (PartModel.parameter_states). stem: the model name's first part.
    """
    if resolution not in RESOLUTIONS:
        raise ModelError(f"resolution must be one of {sorted(RESOLUTIONS)}, got {resolution!r}")
    nx, ny = grid if grid is not None else RESOLUTIONS[resolution]
    if nx < 20 or ny < 20:
        raise ModelError(f"the hood needs at least 20 x 20 skin nodes, got {nx} x {ny}")
    # grid lines run along the frame and rib edges, so the bond lines sit at the same place at every resolution
    hw_mean = float(half_width(np.array(LENGTH / 2)))
    eta_frame, eta_ribs = 1.0 - FRAME / hw_mean, [y / hw_mean for y in RIBS_Y]
    x_breaks = [0.0, FRAME, *[x + d for x in RIBS_X for d in (-RIB / 2, RIB / 2)], LENGTH - FRAME, LENGTH]
    eta_breaks = [-1.0, -eta_frame, *[e + d for e in eta_ribs for d in (-RIB / 2 / hw_mean, RIB / 2 / hw_mean)],
                  eta_frame, 1.0]
    x_line = _graded_axis(nx, x_breaks)
    eta = _graded_axis(ny, eta_breaks)
    X = x_line[:, None] * np.ones(ny)
    Y = eta[None, :] * half_width(X)
    Z = skin_height(X, Y)
    skin_xyz = np.stack([X, Y, Z], axis=-1).reshape(-1, 3)
    index = np.arange(nx * ny).reshape(nx, ny)
    quads = np.stack([index[:-1, :-1], index[1:, :-1], index[1:, 1:], index[:-1, 1:]], axis=-1)  # CCW from +Z

    # inner region on the cell grid: frame + ribs (cell centres, in the grid's own coordinates)
    cx = 0.5 * (x_line[:-1] + x_line[1:])[:, None] * np.ones(ny - 1)
    ce = 0.5 * (eta[:-1] + eta[1:])[None, :] * np.ones((nx - 1, 1))
    inner = (np.minimum(cx, LENGTH - cx) < FRAME) | (np.abs(ce) > eta_frame)
    for e in eta_ribs:
        inner |= np.abs(ce - e) < RIB / 2 / hw_mean
    for x_rib in RIBS_X:
        inner |= np.abs(cx - x_rib) < RIB / 2
    cy = ce * half_width(cx)
    # nodes whose four cells are all inner lie below the skin; all other inner nodes are bond (hem/adhesive) nodes
    padded = np.pad(inner, 1, constant_values=False)
    interior = padded[:-1, :-1] & padded[1:, :-1] & padded[:-1, 1:] & padded[1:, 1:]
    inner_nodes = padded[:-1, :-1] | padded[1:, :-1] | padded[:-1, 1:] | padded[1:, 1:]
    bond = inner_nodes & ~interior
    plan = np.stack([X, Y], axis=-1)
    distance, _ = cKDTree(plan[bond]).query(plan[interior])
    depth = np.zeros((nx, ny))
    depth[interior] = DEPTH * _smoothstep(distance / RAMP)
    inner_id = index.copy()
    inner_id[interior] = nx * ny + np.arange(interior.sum())
    inner_xyz = np.stack([X[interior], Y[interior], Z[interior] - depth[interior]], axis=-1)
    nodes = np.concatenate([skin_xyz, inner_xyz])
    inner_quads = np.stack([inner_id[:-1, :-1], inner_id[1:, :-1], inner_id[1:, 1:], inner_id[:-1, 1:]], axis=-1)
    below = interior[:-1, :-1] | interior[1:, :-1] | interior[1:, 1:] | interior[:-1, 1:]
    inner_cells = inner & below  # a cell on bond nodes only would lie on the skin: none is made
    # reinforcements: inner cells near hinges and locks
    hw_rear, hw_front = float(half_width(np.array(LENGTH))), float(half_width(np.array(0.0)))
    sites = {
        "hinge_L": (LENGTH - 75.0, -(hw_rear - 110.0)),
        "hinge_R": (LENGTH - 75.0, hw_rear - 110.0),
        "gas_spring_L": (LENGTH - 260.0, -(hw_rear - 75.0)),
        "gas_spring_R": (LENGTH - 260.0, hw_rear - 75.0),
        "lock_L": (75.0, -220.0),
        "lock_R": (75.0, 220.0),
        "buffer_L": (75.0, -(hw_front - 72.0)),
        "buffer_R": (75.0, hw_front - 72.0),
    }
    parts = [Part("outer_skin", 0.7), Part("inner_panel", 0.7)]
    cell_part_inner = np.ones(inner_cells.sum(), dtype=np.int64)
    ccx, ccy = cx[inner_cells], cy[inner_cells]
    for name, reach in REINFORCEMENT_REACH.items():
        x0, y0 = sites[name]
        mine = np.hypot(ccx - x0, ccy - y0) < reach
        parts.append(Part(f"reinf_{name}", 2.0))
        cell_part_inner[mine] = len(parts) - 1
    cells = np.concatenate([quads.reshape(-1, 4), inner_quads[inner_cells]])
    cell_part = np.concatenate([np.zeros(quads.shape[0] * quads.shape[1], dtype=np.int64), cell_part_inner])

    inner_names = tuple(p.name for p in parts[1:])
    radius_floor = 1.1 * max(np.diff(x_line).max(), np.diff(eta).max() * WIDTH / 2)

    def patch(site: str, radius: float) -> Patch:
        x0, y0 = sites[site]
        # centred under the skin at the full inner depth: the same place at every resolution
        center = (x0, y0, float(skin_height(np.array(x0), np.array(y0))) - DEPTH)
        return Patch(center=tuple(float(c) for c in center), radius=max(radius, radius_floor), parts=inner_names,
                     exclude_parts=("outer_skin",))

    up = (0.0, 0.0, 1.0)
    boundaries = (
        Boundary("hinge_R", "fixed", patch("hinge_R", PATCH_RADIUS), dofs=("x", "y", "z")),
        Boundary("hinge_L", "prescribed", patch("hinge_L", PATCH_RADIUS), dofs=("x", "y", "z")),
        Boundary("lock_L", "prescribed", patch("lock_L", PATCH_RADIUS), dofs=("z",)),
        Boundary("lock_R", "prescribed", patch("lock_R", PATCH_RADIUS), dofs=("z",)),
        Boundary("buffer_L", "unilateral", patch("buffer_L", PAD_RADIUS), axis=up, stiffness=pad_stiffness,
                 preload=pad_preload),
        Boundary("buffer_R", "unilateral", patch("buffer_R", PAD_RADIUS), axis=up, stiffness=pad_stiffness,
                 preload=pad_preload),
        Boundary("gas_spring_L", "force", patch("gas_spring_L", PATCH_RADIUS), axis=GAS_SPRING_AXIS,
                 force=GAS_SPRING_FORCE),
        Boundary("gas_spring_R", "force", patch("gas_spring_R", PATCH_RADIUS), axis=GAS_SPRING_AXIS,
                 force=GAS_SPRING_FORCE),
    )
    parameters = (
        Parameter("HINGE_X", "hinge_L", "x", -1.0, 1.0),
        Parameter("HINGE_Y", "hinge_L", "y", -1.0, 1.0),
        Parameter("LOCK_L", "lock_L", "z", -1.0, 1.0),
        Parameter("LOCK_R", "lock_R", "z", -1.0, 1.0),
        Parameter("BUFFER_L", "buffer_L", "z", -1.0, 1.0),
        Parameter("BUFFER_R", "buffer_R", "z", -1.0, 1.0),
    )
    model = PartModel(
        name=f"{stem}-{resolution}" if grid is None else f"{stem}-{nx}x{ny}",
        nodes=nodes,
        cells=cells.astype(np.int64),
        cell_part=cell_part,
        parts=tuple(parts),
        material=Material(),  # steel
        boundaries=boundaries,
        parameters=parameters,
        skin_part="outer_skin",
        parameter_states=parameter_states,
    )
    validate_model(model)
    return model


def build_hood_paper(resolution: str = "default", pad_stiffness: float = RIGID_PAD_STIFFNESS,
                     grid: tuple[int, int] | None = None) -> PartModel:
    """The hood with the paper's boundary physics (preset ``hood-paper``): rigid unilateral buffers (stiffness
    ``pad_stiffness`` N/mm, no preload), commanded parameter states. Same mesh and model_id as :func:`build_hood`."""
    return build_hood(resolution, pad_stiffness=pad_stiffness, pad_preload=0.0, grid=grid,
                      parameter_states="commanded", stem="hood-paper")


#: the built-in presets by name (``hood-decomp model --preset NAME``): resolution -> validated model
PRESETS = {"hood": build_hood, "hood-paper": build_hood_paper}


def build_preset(preset: str, resolution: str = "default") -> PartModel:
    """The built-in model ``preset`` (a key of :data:`PRESETS`) at ``resolution``. Raises ModelError."""
    if preset not in PRESETS:
        raise ModelError(f"preset must be one of {sorted(PRESETS)}, got {preset!r}")
    return PRESETS[preset](resolution)
