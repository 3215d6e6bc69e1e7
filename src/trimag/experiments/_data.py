"""Where the experiments find the larger real logs (not bundled): ``$TRIMAG_SHARED_DATA``, else ``shared/data``
beside the repository (for a source checkout) or beside / in the current folder. Parts that need them are
skipped, with the reason in the summary, when the folder is absent."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["shared_data_dir"]


def shared_data_dir() -> Path:
    """The folder holding the shared real logs (it may not exist)."""
    env = os.environ.get("TRIMAG_SHARED_DATA")
    if env:
        return Path(env)
    candidates = (
        Path(__file__).resolve().parents[4] / "shared" / "data",  # beside the repository of a source checkout
        Path.cwd().parent / "shared" / "data",
        Path.cwd() / "shared" / "data",
    )
    for candidate in candidates:
        if candidate.is_dir():
            return candidate
    return candidates[0]
