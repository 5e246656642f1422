"""CalculiX (``ccx``) backend: the same mesh, patches and loads as an .inp deck, one linear job per unit response.

Each response the reduced model needs (the load case, one unit motion per bilateral parameter, one unit force per
pad spring) is an independent linear static job: S8R shells, one ``*SHELL SECTION`` per part, the constrained patch
DOFs by ``*BOUNDARY`` (value 1 mm for the moved boundary), the lumped gravity, gas spring and pad forces by ``*CLOAD``
with the embedded solver's nodal values, and ``*NODE PRINT`` of the model's nodes' translations, read back from the
.dat file. Jobs run through Dask (a LocalCluster by default, or a scheduler address); failed jobs are reported by
name.

Why S8R: ccx expands shells to one brick through the thickness. S4 becomes C3D8I, which bends poorly on coarse
quads: on the coarse hood (~28 mm quads, 0.7 mm skin) it differs from the embedded solver by 6-13 % of the peak unit
response. S8R becomes C3D20R, which does not lock: 1-4 % there, under 2 % from a 64 x 74 grid on (S3 would lock). It
costs about 5 times the solve time of S4. The mid-side nodes are the midpoints of the model's straight quad edges (the
embedded solver's facets are flat) and are numbered after the model's nodes, so these keep their numbers 1..n.

This module writes files and starts processes, so it lives beside the numerical core but only uses the core's
numpy data; nothing in the core imports it.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import re
import shutil
import subprocess
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hood_decomp.core.fe.model import AXES, PartModel, patch_nodes, validate_model
from hood_decomp.core.fe.solver import (
    PAD_LATTICE,
    STEEL_EXPANSION,
    condense,
    constrained_dofs,
    load_vector,
    pad_springs,
)
from hood_decomp.core.types import ReducedModel
from hood_decomp.errors import SolverError

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class LoadCase:
    """One linear job: nodal forces (n, 3) N and the value (mm) of every constrained translation DOF (C,);
    temperature_k: a uniform temperature rise (K) of the whole part, with the expansion coefficient ``expansion``
    (1/K) (0: no thermal load)."""

    name: str
    forces: np.ndarray
    prescribed: np.ndarray
    temperature_k: float = 0.0
    expansion: float = STEEL_EXPANSION


def ccx_executable() -> str | None:
    """Path of ``ccx`` (Debian package calculix-ccx) or None."""
    return shutil.which("ccx")


def load_cases(model: PartModel, pad_lattice: int = PAD_LATTICE) -> tuple[list[LoadCase], np.ndarray]:
    """The load case, one unit motion per bilateral parameter and one unit force per pad spring.

    Returns the cases and the constrained DOF indices (C,) (global 6*node + axis, translations only).
    """
    constrained = constrained_dofs(model)
    constrained = constrained[constrained % 6 < 3]
    n = len(model.nodes)
    cases = [LoadCase("load", load_vector(model).reshape(n, 6)[:, :3], np.zeros(len(constrained)))]
    for parameter in model.bilateral:
        dofs = 6 * patch_nodes(model, model.boundary(parameter.boundary)) + AXES[parameter.direction]
        prescribed = np.isin(constrained, dofs).astype(float)
        cases.append(LoadCase(f"unit_{parameter.label}", np.zeros((n, 3)), prescribed))
    pads = pad_springs(model, pad_lattice)
    for s in range(pads.loads.shape[1]):
        forces = pads.loads[:, s].toarray().reshape(n, 6)[:, :3]
        cases.append(LoadCase(f"pad_{s:03d}", forces, np.zeros(len(constrained))))
    return cases, constrained


def _real(value: float) -> str:
    """The shortest text that reads back as ``value`` exactly, if it fits ccx's 20-character number fields (ccx reads
    only the first 20 characters: a longer field loses digits, or is rejected when cut in its exponent); else the
    closest value that fits."""
    text, digits = repr(float(value)), 16
    while len(text) > 20:
        text, digits = f"{value:.{digits}g}", digits - 1
    return text


def _quad_edges(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The unique edges of quad cells (E, 4) and, per cell, the edge index of its sides 1-2, 2-3, 3-4, 4-1.

    Returns edges (M, 2) node pairs, ascending within a pair, and side (E, 4) indices into edges, in the
    CalculiX/Abaqus order of an 8-node shell's mid-side nodes.
    """
    pairs = np.sort(np.stack([cells, np.roll(cells, -1, axis=1)], axis=2), axis=2).reshape(-1, 2)
    edges, side = np.unique(pairs, axis=0, return_inverse=True)
    return edges, side.reshape(len(cells), 4)


#: a name ccx reads as one token on a keyword line: a letter, then letters, digits, "_" or "-"; ccx keeps 80 characters
CCX_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_-]{0,79}")


def ccx_names(names: list[str] | tuple[str, ...], prefix: str) -> list[str]:
    """The names to write for ``names`` on ccx keyword lines (``ELSET=``): each name itself when it follows
    :data:`CCX_NAME` and is unique ignoring case (ccx upper-cases names), else the generated ``{prefix}{index}``.
    User text (a model.yaml part name holding a newline and ``*INCLUDE, INPUT=...``) so never reaches a deck line."""
    upper = [n.upper() for n in names]
    generated = {f"{prefix}{i}".upper() for i in range(len(names))}
    return [n if CCX_NAME.fullmatch(n) and upper.count(n.upper()) == 1 and n.upper() not in generated
            else f"{prefix}{i}" for i, n in enumerate(names)]


def _heading_text(text: str) -> str:
    """Free text for the *HEADING data line: only letters, digits and ``_.-``, at most 80 characters."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", text)[:80]


def write_deck(model: PartModel, case: LoadCase, constrained: np.ndarray, path: str | Path) -> Path:
    """Write one linear static job as a CalculiX .inp deck.

    Nodes and elements are numbered from 1 in model order; S8R elements (4 corners, then the mid-side nodes of sides
    1-2, 2-3, 3-4, 4-1) come in one ELSET per part, named like the part (``PART_<index>`` when the name is not a
    ccx name, :func:`ccx_names`; the heading's text is reduced to ``[A-Za-z0-9_.-]``: no user text reaches a keyword
    line), so the deck is also a mesh file that model.yaml can name (io.mesh reads the corners of .inp meshes). The
    mid-side nodes (straight-edge midpoints) are numbered n+1.. in a set of their own; one whose two end nodes are
    both held in a translation is held there too, at the mean of the two values, so a moved patch moves as a whole.
    Forces stay on the model's nodes.
    """
    if not (np.all(np.isfinite(case.forces)) and np.all(np.isfinite(case.prescribed))):
        raise SolverError(f"load case {case.name}: forces and prescribed values must be finite")
    if case.prescribed.shape != constrained.shape:
        raise SolverError(f"load case {case.name}: {len(constrained)} prescribed values expected, got "
                          f"{case.prescribed.shape}")
    n = len(model.nodes)
    edges, side = _quad_edges(model.cells)
    elsets = ccx_names([part.name for part in model.parts], "PART_")
    lines = ["*HEADING", f"hood_decomp {_heading_text(model.name)} {_heading_text(case.name)}", "*NODE, NSET=NALL"]
    lines += [f"{i + 1}," + ",".join(map(_real, xyz)) for i, xyz in enumerate(model.nodes)]
    lines.append("*NODE, NSET=NMID")
    lines += [f"{n + m + 1}," + ",".join(map(_real, xyz)) for m, xyz in enumerate(model.nodes[edges].mean(axis=1))]
    for p in range(len(model.parts)):
        members = np.flatnonzero(model.cell_part == p)
        if not len(members):
            continue
        lines.append(f"*ELEMENT, TYPE=S8R, ELSET={elsets[p]}")
        connectivity = np.hstack([model.cells[members], n + side[members]]) + 1
        lines += [f"{e + 1}," + ",".join(map(str, row)) for e, row in zip(members, connectivity, strict=True)]
    lines += ["*MATERIAL, NAME=STEEL", "*ELASTIC", f"{model.material.E:.9g},{model.material.nu:.9g}",
              "*DENSITY", f"{model.material.density:.9g}"]
    thermal = bool(np.isfinite(case.temperature_k) and case.temperature_k != 0.0)
    if thermal:
        lines += ["*EXPANSION", f"{case.expansion:.9g}"]
    for p, part in enumerate(model.parts):
        if np.any(model.cell_part == p):
            lines += [f"*SHELL SECTION, ELSET={elsets[p]}, MATERIAL=STEEL", f"{part.thickness:.9g}"]
    if thermal:
        lines += ["*INITIAL CONDITIONS, TYPE=TEMPERATURE", "NALL, 0.", "NMID, 0."]
    lines += ["*STEP", "*STATIC"]
    if thermal:
        lines += ["*TEMPERATURE", f"NALL, {case.temperature_k:.9g}", f"NMID, {case.temperature_k:.9g}"]
    lines += ["*BOUNDARY"]
    node, axis = np.divmod(constrained, 6)
    lines += [f"{a + 1},{b + 1},{b + 1},{v:.12g}" for a, b, v in zip(node, axis, case.prescribed, strict=True)]
    held = np.full((n, 3), np.nan)
    held[node, axis] = case.prescribed
    mean = held[edges].mean(axis=1)  # NaN unless both end nodes hold that translation
    lines += [f"{n + m + 1},{b + 1},{b + 1},{mean[m, b]:.12g}" for m, b in np.argwhere(np.isfinite(mean))]
    loaded = np.argwhere(np.abs(case.forces) > 0)
    if len(loaded):
        lines.append("*CLOAD")
        lines += [f"{i + 1},{a + 1},{case.forces[i, a]:.12g}" for i, a in loaded]
    lines += ["*NODE PRINT, NSET=NALL", "U", "*END STEP", ""]
    path = Path(path)
    path.write_text("\n".join(lines))
    return path


def read_dat_displacements(path: str | Path, n_nodes: int) -> np.ndarray:
    """Nodal translations (n, 3) mm from the last 'displacements' block of a ccx .dat file."""
    text = Path(path).read_text().splitlines()
    starts = [i for i, line in enumerate(text) if line.strip().startswith("displacements")]
    if not starts:
        raise SolverError(f"{path}: no displacement block (did ccx finish?)")
    out = np.full((n_nodes, 3), np.nan)
    for line in text[starts[-1] + 1:]:
        fields = line.split()
        if not fields:
            if np.isfinite(out).all():
                break
            continue
        if len(fields) != 4:
            break
        node = int(fields[0]) - 1
        if node < n_nodes:
            out[node] = [float(v) for v in fields[1:]]
    if not np.isfinite(out).all():
        raise SolverError(f"{path}: displacements missing for {int((~np.isfinite(out).any(axis=1)).sum())} nodes")
    return out


def run_job(deck: str, name: str, n_nodes: int, workdir: str | None = None, timeout: float = 3600.0,
            executable: str | None = None) -> np.ndarray:
    """Run one ccx job from deck text in a fresh directory; returns translations (n, 3). Raises SolverError."""
    with tempfile.TemporaryDirectory(prefix=f"ccx_{_heading_text(name)}_", dir=workdir) as directory:
        job = _run_ccx(deck, name, directory, timeout, executable)
        return read_dat_displacements(job.with_suffix(".dat"), n_nodes)


def _run_ccx(deck: str, name: str, directory: str, timeout: float, executable: str | None) -> Path:
    """Write ``deck`` as ``directory/name.inp`` and run ccx on it; returns the job path (without suffix)."""
    executable = executable or ccx_executable()
    if executable is None:
        raise SolverError("ccx not found: install the Debian package calculix-ccx")
    name = _heading_text(name)  # the job's file name: no path separator or shell-special character from a label
    job = Path(directory) / name
    job.with_suffix(".inp").write_text(deck)
    result = subprocess.run([executable, "-i", name], cwd=directory, capture_output=True, text=True,
                            timeout=timeout, env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"})
    if result.returncode != 0 or "*ERROR" in result.stdout:
        errors = [line for line in result.stdout.splitlines() if "ERROR" in line][:3]
        raise SolverError(f"ccx job {name} failed (exit {result.returncode}): {' | '.join(errors)}")
    return job


def _deck_text(model: PartModel, case: LoadCase, constrained: np.ndarray) -> str:
    with tempfile.TemporaryDirectory() as directory:
        return write_deck(model, case, constrained, Path(directory) / "deck.inp").read_text()


def run_case(model: PartModel, case: LoadCase, constrained: np.ndarray, workdir: str | None = None,
             timeout: float = 3600.0) -> np.ndarray:
    """Run one case in this process (no Dask: for jobs too large to run two at a time); translations (n, 3) mm."""
    return run_job(_deck_text(model, case, constrained), case.name, len(model.nodes), workdir, timeout)


@contextlib.contextmanager
def holding(lock: Path | None) -> Iterator[None]:
    """Hold an exclusive flock on ``lock`` (the same lock as ``flock FILE command``: large jobs of several users run
    one at a time); None: no lock."""
    if lock is None:
        yield
        return
    with open(lock, "a") as handle:
        start = time.perf_counter()
        fcntl.flock(handle, fcntl.LOCK_EX)
        logger.info("holding %s (waited %.0f s)", lock, time.perf_counter() - start)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def run_cases(model: PartModel, cases: list[LoadCase], constrained: np.ndarray, scheduler: str | None = None,
              workdir: str | None = None, executable: str | None = None) -> dict[str, np.ndarray]:
    """Run the cases as independent Dask jobs; returns name -> translations (n, 3). Failed jobs raise SolverError
    naming every failed case. ``executable`` overrides the ccx binary (path, e.g. a wrapper script)."""
    from dask.distributed import Client, LocalCluster, as_completed

    cluster = None
    if scheduler is None:
        cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None)
        client = Client(cluster)
    else:
        client = Client(scheduler)
    try:
        futures = {
            client.submit(run_job, _deck_text(model, case, constrained), case.name, len(model.nodes), workdir,
                          executable=executable, key=f"ccx-{case.name}-{id(case)}", pure=False): case.name
            for case in cases
        }
        results: dict[str, np.ndarray] = {}
        failed: dict[str, str] = {}
        for done, future in enumerate(as_completed(futures), start=1):
            name = futures[future]
            try:
                results[name] = future.result()
            except Exception as error:  # a worker error of any kind is reported by job name
                failed[name] = str(error)
            logger.info("ccx jobs %d/%d (%d failed)", done, len(futures), len(failed))
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    if failed:
        raise SolverError(f"{len(failed)} ccx job(s) failed: " + "; ".join(f"{k}: {v}" for k, v in failed.items()))
    return results


def reduce_model_calculix(model: PartModel, scheduler: str | None = None, pad_lattice: int = PAD_LATTICE,
                          workdir: str | None = None) -> ReducedModel:
    """The ReducedModel from CalculiX responses (same patches, loads and pad springs as the embedded solver)."""
    validate_model(model)
    cases, constrained = load_cases(model, pad_lattice)
    results = run_cases(model, cases, constrained, scheduler, workdir)
    columns = np.stack([results[c.name] for c in cases if not c.name.startswith("pad_")], axis=2)
    pad_columns = np.stack([results[c.name] for c in cases if c.name.startswith("pad_")], axis=2) if any(
        c.name.startswith("pad_") for c in cases) else np.zeros((len(model.nodes), 3, 0))
    names = tuple(p.label for p in model.bilateral) + tuple(p.label for p in model.unilateral)
    return condense(model, pad_springs(model, pad_lattice), columns, pad_columns, names, len(model.bilateral))


def write_member_deck(model: PartModel, state: np.ndarray, path: str | Path, buffers: str = "unilateral",
                      nlgeom: bool = True, gap_stiffness: float = 1.0e7, springs: np.ndarray | None = None,
                      pad_lattice: int = PAD_LATTICE) -> Path:
    """One ensemble member as a CalculiX deck with the buffers as ccx sees them: the load case with the bilateral
    parameters at ``state`` (P,) mm (model.names order) and each unilateral boundary either

    - ``"unilateral"``: one GAPUNI element per patch node (gap stiffness ``gap_stiffness`` N/mm) between the node and
      a ground node held at the commanded position along the pad axis, so the node may lift off but not sink below it
      (ccx's gap elements act only with NLGEOM, so ``nlgeom`` must be True); or
    - ``"held"``: held at the commanded position along the axis (bilateral, no contact): every patch node when
      ``springs`` is None (geometric nonlinearity alone, ``nlgeom`` True or False); else the pad springs
      (:func:`~hood_decomp.core.fe.solver.pad_springs` with ``pad_lattice``, in its order) where ``springs`` (S,)
      is True, each as the embedded solver's rigid spring: one ``*EQUATION`` holds the area-weighted mean axial
      displacement of its nodes at the commanded position (against a reference node of set ``NSPRING`` held there;
      the equation spreads the spring's force with the same weights), its nodes otherwise free. Holding the
      springs an LCP solution says push gives a linear job whose spring reactions and free springs certify that
      contact state (Signorini: reactions push, free springs do not sink below the buffer) at any mesh resolution.
    The deck prints the translations of every node and the reactions of the pad nodes (``NPAD``: with held springs,
    the element forces their equations balance).

    GAPUNI and all-nodes holding are like-for-like with the embedded solver only where each pad spring holds one node
    (the coarse hood: 14 springs on 14 nodes per buffer); on finer meshes a spring averages several nodes and
    node-wise gaps are stiffer. ``springs`` is like for like at every resolution.
    """
    if buffers not in ("unilateral", "held"):
        raise SolverError(f"buffers must be 'unilateral' or 'held', got {buffers!r}")
    if buffers == "unilateral" and not nlgeom:
        raise SolverError("ccx gap elements act only with NLGEOM: unilateral buffers need nlgeom=True")
    state = np.asarray(state, dtype=float)
    if state.shape != (len(model.names),) or not np.all(np.isfinite(state)):
        raise SolverError(f"expected {len(model.names)} finite parameter values {model.names}, got {state.shape}")
    constrained = constrained_dofs(model)
    constrained = constrained[constrained % 6 < 3]
    prescribed = np.zeros(len(constrained))
    for parameter, value in zip(model.bilateral, state, strict=False):
        dofs = 6 * patch_nodes(model, model.boundary(parameter.boundary)) + AXES[parameter.direction]
        prescribed[np.isin(constrained, dofs)] = value
    n = len(model.nodes)
    case = LoadCase("member", load_vector(model).reshape(n, 6)[:, :3], prescribed)
    text = _deck_text(model, case, constrained)
    pads = []  # (nodes, axis, commanded position)
    for u, parameter in enumerate(model.unilateral):
        boundary = model.boundary(parameter.boundary)
        axis = np.asarray(boundary.axis, dtype=float)
        if np.count_nonzero(axis) != 1:
            raise SolverError(f"buffer {boundary.name!r}: ccx decks need a pad axis along X, Y or Z, got {axis}")
        pads.append((patch_nodes(model, boundary), axis, state[len(model.bilateral) + u]))
    n_mid = len(_quad_edges(model.cells)[0])
    nodes_lines, element_lines, boundary_lines = [], [], []
    first_ground = n + n_mid + 1
    count = 0
    if springs is not None:
        if buffers != "held":
            raise SolverError("held springs need buffers='held'")
        equation_lines, reference_lines = _held_springs(model, state, springs, pad_lattice, first_ground)
        boundary_lines += reference_lines
        if equation_lines:
            text = text.replace("*STEP\n*STATIC", "\n".join(equation_lines) + "\n*STEP\n*STATIC", 1)
    for nodes, axis, position in pads if springs is None else ():
        a = int(np.flatnonzero(axis)[0])
        sign = float(axis[a])
        for node in nodes:
            if buffers == "held":
                boundary_lines.append(f"{node + 1},{a + 1},{a + 1},{sign * position:.12g}")
                continue
            ground = first_ground + count
            nodes_lines.append(f"{ground}," + ",".join(map(_real, model.nodes[node])))
            element_lines.append(f"{len(model.cells) + count + 1},{node + 1},{ground}")
            boundary_lines += [f"{ground},{b + 1},{b + 1},{(sign * position if b == a else 0.0):.12g}"
                               for b in range(3)]
            count += 1
    if element_lines:
        direction = ",".join(f"{-c:.12g}" for c in pads[0][1])  # ccx: the gap closes when (u2 - u1) . n < -d
        nodes_block = "\n".join(["*NODE, NSET=NGROUND", *nodes_lines])
        gap_block = "\n".join(["*ELEMENT, TYPE=GAPUNI, ELSET=EGAP", *element_lines, "*GAP, ELSET=EGAP",
                               f"0.0,{direction},,{gap_stiffness:.6g}"])
        text = text.replace("*MATERIAL, NAME=STEEL", f"{nodes_block}\n{gap_block}\n*MATERIAL, NAME=STEEL", 1)
    step = "*STEP, NLGEOM, INC=1000\n*STATIC\n0.05,1.0,1e-6,0.1" if nlgeom else "*STEP\n*STATIC"
    text = text.replace("*STEP\n*STATIC", step, 1).replace("*BOUNDARY\n", "*BOUNDARY\n" + "".join(
        line + "\n" for line in boundary_lines), 1)
    pad_nodes = np.concatenate([nodes for nodes, _, _ in pads]) if pads else np.zeros(0, dtype=np.int64)
    if len(pad_nodes):
        pad_set = "\n".join(["*NSET, NSET=NPAD", *(f"{node + 1}," for node in pad_nodes)])
        text = text.replace("*MATERIAL, NAME=STEEL", f"{pad_set}\n*MATERIAL, NAME=STEEL", 1)
        text = text.replace("*END STEP", "*NODE PRINT, NSET=NPAD\nRF\n*END STEP", 1)
    path = Path(path)
    path.write_text(text)
    return path


def _held_springs(model: PartModel, state: np.ndarray, springs: np.ndarray, pad_lattice: int,
                  first_reference: int) -> tuple[list[str], list[str]]:
    """Deck lines holding pad springs ``springs`` (S,) bool like the embedded solver's rigid springs: the reference
    nodes (``NSPRING``, numbered from ``first_reference``, at each spring's weighted centre) and one ``*EQUATION``
    per held spring (sum_i w_i u_i . axis - u_ref . axis = 0, the reference held at the commanded position), then
    their ``*BOUNDARY`` lines. Returns (lines before the step, boundary lines)."""
    pads = pad_springs(model, pad_lattice)
    springs = np.asarray(springs, dtype=bool)
    if springs.shape != pads.k.shape:
        raise SolverError(f"springs must hold {len(pads.k)} flags (the pad springs), got {springs.shape}")
    n_bilateral = len(model.bilateral)
    nodes_lines, equations, boundary = ["*NODE, NSET=NSPRING"], ["*EQUATION"], []
    for count, s in enumerate(np.flatnonzero(springs)):
        column = pads.loads[:, s].tocoo()
        axis = np.asarray(model.boundary(model.unilateral[pads.pad_of[s]].boundary).axis, dtype=float)
        a = int(np.flatnonzero(axis)[0])
        along = column.row % 6 == a
        nodes, weights = column.row[along] // 6, column.data[along]  # weights w_i * axis[a], summing to axis[a]
        order = np.argsort(-np.abs(weights))  # the largest weight is ccx's dependent term
        nodes, weights = nodes[order], weights[order]
        reference = first_reference + count
        centre = (np.abs(weights) @ model.nodes[nodes]) / np.abs(weights).sum()
        nodes_lines.append(f"{reference}," + ",".join(map(_real, centre)))
        terms = [f"{node + 1},{a + 1},{_real(w)}" for node, w in zip(nodes, weights, strict=True)]
        terms.append(f"{reference},{a + 1},-1.0")
        equations.append(str(len(terms)))
        equations += [",".join(terms[i:i + 4]) for i in range(0, len(terms), 4)]  # ccx: at most 4 terms a line
        position = state[n_bilateral + pads.pad_of[s]]
        boundary += [f"{reference},{b + 1},{b + 1},{(position if b == a else 0.0):.12g}" for b in range(3)]
    if len(equations) == 1:
        return [], []
    return nodes_lines + equations, boundary


def read_dat_reactions(path: str | Path) -> dict[int, np.ndarray]:
    """Reaction forces (3,) N by node index (0-based) from the 'forces' blocks of a ccx .dat file: every printed node
    set, the last increment's value where a node is printed in several increments."""
    text = Path(path).read_text().splitlines()
    starts = [i for i, line in enumerate(text) if line.strip().startswith("forces")]
    if not starts:
        raise SolverError(f"{path}: no reaction force block")
    out: dict[int, np.ndarray] = {}
    for start in starts:
        read = 0
        for line in text[start + 1:]:
            fields = line.split()
            if not fields:
                if read:
                    break
                continue
            if len(fields) != 4:
                break
            out[int(fields[0]) - 1] = np.array([float(v) for v in fields[1:]])
            read += 1
    return out


def run_member_job(deck: str, n_nodes: int, workdir: str | None = None, timeout: float = 7200.0
                   ) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """Run a :func:`write_member_deck` deck: translations (n, 3) mm and the pad nodes' reactions (node -> (3,) N)."""
    with tempfile.TemporaryDirectory(prefix="ccx_member_", dir=workdir) as directory:
        job = _run_ccx(deck, "member", directory, timeout, None)
        return read_dat_displacements(job.with_suffix(".dat"), n_nodes), read_dat_reactions(job.with_suffix(".dat"))


@dataclass(frozen=True)
class ContactCheck:
    """A member solved by CalculiX with the contact set of an LCP solution held (:func:`check_contact_set`).

    normal: (N,) mm skin normal displacement; skin_displacement: (N, 3) mm skin translations. touching: per unilateral
    boundary, (patch nodes,) bool, the nodes of its held springs. spring_reaction: (S,) N, CalculiX's reaction of each
    held pad spring along its axis (NaN: free). spring_gap: (S,) mm, each free spring's clearance (weighted mean axial
    displacement minus the commanded position; NaN: held).
    reaction: (U,) N, CalculiX's total reaction of each buffer along its axis. held_reaction_min: (U,) N, the
    smallest reaction of a held spring (NaN: none held). free_gap_min: (U,) mm, the smallest clearance of a free pad
    spring above its buffer (NaN: none free). The contact set is CalculiX's solution too when held springs push and
    free springs clear (Signorini); ``certified(tolerance_n, tolerance_mm)`` says whether they do.
    """

    normal: np.ndarray
    skin_displacement: np.ndarray
    touching: tuple[np.ndarray, ...]
    spring_reaction: np.ndarray
    spring_gap: np.ndarray
    reaction: np.ndarray
    held_reaction_min: np.ndarray
    free_gap_min: np.ndarray

    def certified(self, tolerance_n: float, tolerance_mm: float = 1e-3) -> bool:
        """True when no held spring pulls by more than ``tolerance_n`` N and no free one sinks by ``tolerance_mm``."""
        pulls = np.nan_to_num(self.held_reaction_min, nan=0.0) >= -tolerance_n
        sinks = np.nan_to_num(self.free_gap_min, nan=0.0) >= -tolerance_mm
        return bool(np.all(pulls & sinks))


def check_contact_set(model: PartModel, state: np.ndarray, pad_forces: np.ndarray, normals: np.ndarray,
                      pad_lattice: int = PAD_LATTICE, workdir: str | None = None) -> ContactCheck:
    """Solve member ``state`` (P,) mm with CalculiX (linear, S8R) holding every pad spring that pushes in
    ``pad_forces`` (S,) N (an LCP solution of the embedded solver) at the commanded buffer position as the embedded
    solver's rigid spring does (its nodes' weighted mean, :func:`write_member_deck`), the other springs free: like
    for like at every mesh resolution. ``normals`` (N, 3): the skin's unit normals. Raises SolverError."""
    pads = pad_springs(model, pad_lattice)
    pad_forces = np.asarray(pad_forces, dtype=float)
    if pad_forces.shape != pads.k.shape:
        raise SolverError(f"expected {len(pads.k)} pad spring forces, got {pad_forces.shape}")
    held = pad_forces > 0
    with tempfile.TemporaryDirectory(dir=workdir) as directory:
        deck = write_member_deck(model, state, Path(directory) / "deck.inp", "held", nlgeom=False, springs=held,
                                 pad_lattice=pad_lattice).read_text()
    u, reactions = run_member_job(deck, len(model.nodes), workdir)
    # ccx reports a node's reaction as the elements' force on it, so an unattached reference node shows none; a
    # spring's force is what its equation puts on its pad nodes: their element forces less the applied load (gravity)
    load = load_vector(model).reshape(-1, 6)[:, :3]
    axes = [np.asarray(model.boundary(p.boundary).axis, dtype=float) for p in model.unilateral]
    spring_reaction = np.full(len(held), np.nan)
    for s in np.flatnonzero(held):
        nodes = np.unique(pads.loads[:, s].indices // 6)
        spring_reaction[s] = sum(float((reactions[node] - load[node]) @ axes[pads.pad_of[s]]) for node in nodes)
    full = np.zeros(6 * len(model.nodes))
    full.reshape(-1, 6)[:, :3] = u
    n_bilateral = len(model.bilateral)
    spring_gap = pads.loads.T @ full - state[n_bilateral + pads.pad_of]
    spring_gap[held] = np.nan
    touching, reaction, held_min, gap_min = [], [], [], []
    for index, parameter in enumerate(model.unilateral):
        nodes = patch_nodes(model, model.boundary(parameter.boundary))
        mine = pads.pad_of == index
        pushing = [pads.loads[:, k].indices // 6 for k in np.flatnonzero(mine & held)]
        touching.append(np.isin(nodes, np.concatenate(pushing)) if pushing else np.zeros(len(nodes), dtype=bool))
        rz, gap = spring_reaction[mine & held], spring_gap[mine & ~held]
        reaction.append(rz.sum() if rz.size else 0.0)
        held_min.append(rz.min() if rz.size else np.nan)
        gap_min.append(gap.min() if gap.size else np.nan)
    normal = np.einsum("na,na->n", u[model.skin_nodes], normals)
    return ContactCheck(normal, u[model.skin_nodes], tuple(touching), spring_reaction, spring_gap,
                        np.array(reaction), np.array(held_min), np.array(gap_min))
