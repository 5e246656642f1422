"""rosbag2 (MCAP) bags through ``rosbags``: I/O of raw CDR records, and a typestore that knows hood_decomp_msgs.

Records stay serialised bytes here; decoding is the caller's choice (rosbags' typestore, or rclpy's
``deserialize_message``). Every bag ``NAME/`` (a rosbag2 directory) has a sidecar ``NAME.json`` beside it that states
what is in it (true parameter states, undeclared effects, noise, malformed messages).
"""

from __future__ import annotations

import json
import pathlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from functools import cache
from typing import Any

import yaml
from rosbags.rosbag2 import Reader, ReaderError, StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from hood_decomp.errors import BagError
from hood_decomp.io.json_values import loads_strict

PROJECT_MESSAGES = ("DisplacementField", "BoundaryState", "BoundaryCorrection", "EffectField", "EffectFields",
                    "MoveVerification", "ZoneVerdict")


@dataclass(frozen=True)
class Record:
    """One serialised message: topic, type name (e.g. ``sensor_msgs/msg/PointCloud2``), time (ns), CDR bytes."""

    topic: str
    msgtype: str
    timestamp_ns: int
    data: bytes


def _message_dir() -> pathlib.Path:
    """The .msg files of hood_decomp_msgs: the install space when sourced, else the source tree."""
    try:
        from ament_index_python.packages import get_package_share_directory

        installed = pathlib.Path(get_package_share_directory("hood_decomp_msgs")) / "msg"
        if installed.is_dir():
            return installed
    except (ImportError, LookupError, ValueError):
        pass
    return pathlib.Path(__file__).resolve().parents[3] / "hood_decomp_msgs" / "msg"


@cache
def typestore() -> Typestore:
    """ROS 2 Kilted types plus hood_decomp_msgs, for writing connections and decoding records."""
    store = get_typestore(Stores.ROS2_KILTED)
    types: dict[str, Any] = {}
    directory = _message_dir()
    for name in PROJECT_MESSAGES:
        path = directory / f"{name}.msg"
        if not path.is_file():
            raise BagError(f"message definition {path} not found; build the workspace (scripts/setup.sh)")
        types.update(get_types_from_msg(path.read_text(), f"hood_decomp_msgs/msg/{name}"))
    store.register(types)
    return store


class BagWriter:
    """A new MCAP rosbag2 directory written record by record (for recording while messages arrive)::

        with BagWriter(path) as bag:
            bag.write(record)
    """

    def __init__(self, path: str | pathlib.Path) -> None:
        self.path = pathlib.Path(path)
        self.count = 0
        self._writer: Writer | None = None
        self._connections: dict[tuple[str, str], Any] = {}

    def __enter__(self) -> BagWriter:
        if self.path.exists():
            raise BagError(f"bag {self.path} exists already; remove it or choose another name")
        self._writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        self._writer.open()
        return self

    def write(self, record: Record) -> None:
        assert self._writer is not None, "BagWriter used outside its with-block"
        key = (record.topic, record.msgtype)
        if key not in self._connections:
            self._connections[key] = self._writer.add_connection(record.topic, record.msgtype, typestore=typestore())
        self._writer.write(self._connections[key], record.timestamp_ns, record.data)
        self.count += 1

    def __exit__(self, *exc: object) -> None:
        if self._writer is not None:
            self._writer.close()


def write_bag(path: str | pathlib.Path, records: Iterable[Record]) -> int:
    """Write records (in the given order) to a new MCAP rosbag2 directory ``path``; returns the count written."""
    with BagWriter(path) as bag:
        for record in records:
            bag.write(record)
    return bag.count


def read_bag(path: str | pathlib.Path, topics: Iterable[str] | None = None) -> Iterator[Record]:
    """The records of a rosbag2 directory in time order, optionally only those of ``topics``."""
    path = pathlib.Path(path)
    if not (path / "metadata.yaml").is_file():
        raise BagError(f"{path} is not a rosbag2 directory (no metadata.yaml)")
    _check_bag_files(path)
    wanted = set(topics) if topics is not None else None
    try:
        with Reader(path) as reader:
            connections = [c for c in reader.connections if wanted is None or c.topic in wanted]
            for connection, timestamp, data in reader.messages(connections=connections):
                yield Record(connection.topic, connection.msgtype, timestamp, bytes(data))
    except ReaderError as error:
        raise BagError(f"cannot read bag {path}: {error}") from error
    except Exception as error:  # a corrupt file makes the foreign reader fail in many ways: all mean a bad bag
        raise BagError(f"cannot read bag {path}: {type(error).__name__}: {' '.join(str(error).split())[:200]}"
                       ) from error


def _check_bag_files(path: pathlib.Path) -> None:
    """The files metadata.yaml names must lie in the bag directory: a bag from elsewhere must not make the reader open
    /etc/passwd or another user's file as a storage file."""
    try:
        document = yaml.safe_load((path / "metadata.yaml").read_text(errors="replace"))
        names = document["rosbag2_bagfile_information"]["relative_file_paths"]
    except (yaml.YAMLError, KeyError, TypeError) as error:
        raise BagError(f"{path}/metadata.yaml is not rosbag2 metadata: {type(error).__name__}") from error
    if not isinstance(names, list):
        raise BagError(f"{path}/metadata.yaml: relative_file_paths must be a list")
    directory = path.resolve()
    for name in names:
        if not isinstance(name, str) or pathlib.PurePath(name).is_absolute() or not (
                directory / name).resolve().is_relative_to(directory):
            raise BagError(f"{path}/metadata.yaml names the file {str(name)[:80]!r} outside the bag directory")


def sidecar_path(bag: str | pathlib.Path) -> pathlib.Path:
    bag = pathlib.Path(bag)
    return bag.with_name(bag.name + ".json")


def read_sidecar(bag: str | pathlib.Path) -> dict[str, Any]:
    path = sidecar_path(bag)
    if not path.is_file():
        raise BagError(f"bag {bag} has no sidecar file {path}")
    try:
        content = loads_strict(path.read_text())
    except ValueError as error:  # UnicodeDecodeError and JSONDecodeError are ValueErrors
        raise BagError(f"sidecar {path} is not JSON: {' '.join(str(error).split())[:120]}") from error
    if not isinstance(content, dict):
        raise BagError(f"sidecar {path}: expected a JSON object, got {type(content).__name__}")
    return content



def write_sidecar(bag: str | pathlib.Path, content: dict[str, Any]) -> pathlib.Path:
    path = sidecar_path(bag)
    path.write_text(json.dumps(content, indent=2) + "\n")
    return path
