"""Migration of calibration files written in older format versions.

trimag's first public format is 1.0.0, so no older major version exists yet; this is the one place where
a future 2.x will upgrade 1.x files (emitting a warning), as imucal's ``legacy`` module does.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from ..errors import CalibrationFormatError

__all__ = ["migrate"]


def migrate(data: Mapping[str, Any]) -> Mapping[str, Any]:
    """Upgrade an older calibration dict to the current format, or explain why it cannot be."""
    raise CalibrationFormatError(
        f"calibration file has format_version {data.get('format_version')!r}, older than any trimag "
        "release (1.0.0 is the first); it cannot be migrated"
    )
