"""The one errors module of hood_decomp.

Every error raised at a public boundary derives from :class:`HoodDecompError`, so the command line and the nodes can
turn it into a one-line message (CLI) or a diagnostic (nodes) without catching programming errors by accident.
Messages name what was expected and what was found.
"""


class HoodDecompError(Exception):
    """Base class: bad input or a state the system refuses to compute from."""


class ModelError(HoodDecompError):
    """A part model (model.yaml and mesh) is invalid: unknown boundary, empty patch, min > max, missing thickness,
    degenerate element, under-constrained part."""


class MeshError(HoodDecompError):
    """A mesh file cannot be read or is inconsistent."""


class SolverError(HoodDecompError):
    """A finite-element solve failed (singular stiffness, complementarity not converged, external solver failure)."""


class EnsembleError(HoodDecompError):
    """An ensemble store is missing, incomplete or of an unknown schema version."""


class BasisError(HoodDecompError):
    """A basis cannot be built or loaded (too few members, unsupported component count, wrong schema)."""


class FieldError(HoodDecompError):
    """A displacement field is unusable: wrong length, wrong model_id, all NaN, inf values, coverage too low."""


class ModelIdMismatchError(FieldError):
    """A field and a basis (or model) come from different models."""


class ScanError(HoodDecompError):
    """A scan is unusable: empty, all NaN, wrong unit scale, no overlap with the part, too little coverage."""


class PointCloudError(HoodDecompError):
    """A sensor_msgs/PointCloud2 cannot be decoded: no x/y/z, inconsistent sizes, unsupported datatype."""


class BagError(HoodDecompError):
    """A bag or its sidecar file is missing or inconsistent."""


class OutputError(HoodDecompError):
    """An output path is unusable: its directory is missing or not writable, it is a directory where a file is
    wanted (or a file where a directory is), or it is one of the command's inputs."""


class HistoryError(HoodDecompError):
    """A results history database is unreadable, of an unknown schema version, or inconsistent."""


class ShiftError(HoodDecompError):
    """A shift cannot be analysed: no input part, too few parts for a control chart, a baseline without spread."""


class CalibrationError(HoodDecompError):
    """A calibration cannot be made or used: too few entries for what is fitted, an entry whose known setting
    disagrees with the others, a reference or calibration file that is malformed."""
