"""skelid: identify the geometry of articulated bodies from noisy motion capture."""

from importlib.metadata import PackageNotFoundError, version

from skelid.data import MarkerData
from skelid.errors import (
    DataError,
    FormatError,
    IdentifiabilityError,
    ModelError,
    NotFittedError,
    SettingError,
    SkelidError,
    SkelidWarning,
    StreamError,
)
from skelid.loading import load_model
from skelid.model import Model

try:
    __version__ = version("skelid")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0+unknown"

__all__ = [
    "MarkerData", "Model", "load_model", "SkelidError", "FormatError", "ModelError",
    "DataError", "IdentifiabilityError", "SettingError", "NotFittedError", "SkelidWarning", "StreamError",
    "__version__",
]
