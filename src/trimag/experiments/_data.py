"""Where the experiments find the larger real logs (not bundled): ``$TRIMAG_SHARED_DATA``, else
``../shared/data`` beside the current folder, else ``/work/shared/data``. Parts that need them are skipped,
with the reason in the summary, when the folder is absent."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["shared_data_dir"]


def shared_data_dir() -> Path:
    """The folder holding the shared real logs (it may not exist)."""
    env = os.environ.get("TRIMAG_SHARED_DATA")
    if env:
        return Path(env)
    for candidate in (Path.cwd().parent / "shared" / "data", Path.cwd() / "shared" / "data"):
        if candidate.is_dir():
            return candidate
    return Path("/work/shared/data")
