"""What a shift is made of: the parts in bags (rosbag2 directories with their sidecars), scan files (.ply) and field
files (.vtu), given as paths or directories holding them, as :class:`~hood_decomp.shift.part.PartTask` s.

A bag's clouds are its ``sensor_msgs/msg/PointCloud2`` messages on the sidecar's topic (all PointCloud2 topics when
there is no sidecar), each registered with the sidecar's scanner pose and reference markers as the scan node does.
A part's id is the sidecar's ``part_id`` for that scan when it states one, else ``<bag>#<message index>``; a file's
part id is its stem. A bag whose sidecar names one part in several views (``part_id`` and ``expected_views`` > 1) is
one part, which the shift does not fuse: it is recorded as failed with the reason (``hood-decomp replay`` inspects it
through the nodes), never as one part per view. Tasks are produced lazily: a bag's clouds are read one at a time
while the batch runs.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import yaml

from hood_decomp.errors import BagError, FieldError
from hood_decomp.io.bags import read_bag, sidecar_path
from hood_decomp.shift.part import PartTask

CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
FILE_KINDS = {".vtu": "field", ".ply": "scan"}


@dataclass(frozen=True)
class Source:
    """One input: a bag (``kind`` "bag", with the number of clouds it holds) or a file ("field" or "scan")."""

    path: Path
    kind: str
    count: int


def _is_bag(path: Path) -> bool:
    return path.is_dir() and (path / "metadata.yaml").is_file()


def _sidecar(bag: Path) -> dict:
    path = sidecar_path(bag)
    if not path.is_file():
        return {}
    try:
        content = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise BagError(f"sidecar {path} is not readable JSON: {error}") from error
    if not isinstance(content, dict):
        raise BagError(f"sidecar {path} must hold a JSON object, got {type(content).__name__}")
    return content


def _cloud_topics(bag: Path) -> dict[str, int]:
    """PointCloud2 topic -> message count from the bag's metadata.yaml (the sidecar's topic only, when it names one)."""
    try:
        info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        topics = {t["topic_metadata"]["name"]: int(t["message_count"]) for t in info["topics_with_message_count"]
                  if t["topic_metadata"]["type"] == CLOUD_TYPE}
    except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError) as error:
        raise BagError(f"bag {bag}: unreadable metadata.yaml ({error})") from error
    wanted = _sidecar(bag).get("topic")
    return {wanted: topics.get(wanted, 0)} if isinstance(wanted, str) else topics


def find_sources(paths: Sequence[str | Path]) -> list[Source]:
    """Expand bags, files and directories (their bags, .vtu and .ply files, sorted by name, not recursive below a
    bag) into sources; FieldError for a path that is none of these or holds nothing."""
    sources: list[Source] = []
    for raw in paths:
        path = Path(raw)
        if _is_bag(path):
            sources.append(Source(path, "bag", sum(_cloud_topics(path).values())))
        elif path.is_file() and path.suffix.lower() in FILE_KINDS:
            sources.append(Source(path, FILE_KINDS[path.suffix.lower()], 1))
        elif path.is_dir():
            found = find_sources([p for p in sorted(path.iterdir())
                                  if _is_bag(p) or (p.is_file() and p.suffix.lower() in FILE_KINDS)])
            if not found:
                raise FieldError(f"directory {path} holds no bag, field (.vtu) or scan (.ply)")
            sources.extend(found)
        else:
            raise FieldError(f"{path} is neither a bag directory, a field (.vtu), a scan (.ply) nor a directory "
                             "of them")
    return sources


def iter_tasks(sources: Sequence[Source]) -> Iterator[PartTask]:
    """The parts of the sources in order, one task each (a bag's clouds read as they are asked for)."""
    for source in sources:
        if source.kind != "bag":
            stat = source.path.stat()
            yield PartTask(str(source.path), source.path.stem, 0, stat.st_mtime_ns, source.kind, str(source.path))
            continue
        sidecar = _sidecar(source.path)
        views = sidecar.get("expected_views")
        if sidecar.get("part_id") and isinstance(views, int) and not isinstance(views, bool) and views > 1:
            yield PartTask(str(source.path), str(sidecar["part_id"]), 0, source.path.stat().st_mtime_ns, "multiview",
                           str(source.path))
            continue
        entries = sidecar.get("scans", []) if isinstance(sidecar.get("scans"), list) else []
        pose = sidecar.get("scanner_pose_mm")
        pose_flat = None if pose is None else tuple(float(v) for row in pose for v in row)
        if pose_flat is not None and len(pose_flat) != 16:
            raise BagError(f"sidecar of {source.path}: scanner_pose_mm must be 4 x 4, got {len(pose_flat)} numbers")
        markers = tuple((int(k), *(float(c) for c in v)) for k, v in sidecar.get("marker_positions_mm", {}).items())
        for index, record in enumerate(read_bag(source.path, _cloud_topics(source.path))):
            entry = entries[index] if index < len(entries) and isinstance(entries[index], dict) else {}
            part_id = str(entry.get("part_id") or f"{source.path.name}#{index}")
            yield PartTask(str(source.path), part_id, index, record.timestamp_ns, "cloud", str(source.path),
                           record.data, pose_flat, markers)
