"""Optional dependencies (not public API): which extra installs each one, and the one-line error a feature gives
when the package it needs is missing.

The core install (``pip install trimag``) reads and writes CSV, text, NPZ and MAT v4-v7.2 files, fits, applies,
evaluates, simulates and runs ``trimag batch`` on this machine. The extras add (``pyproject.toml``, docs/cli.md):

=============  ========================================  ====================================================
extra          packages                                   what needs them
=============  ========================================  ====================================================
``parquet``    pyarrow                                    Parquet files (read and write), the fast CSV reader
``mat``        h5py                                       MATLAB v7.3 (HDF5) files
``batch``      dask[distributed]                          ``trimag batch --scheduler`` (a Dask cluster)
``logs``       pymavlink, pyulog, rosbags                 autopilot and ROS logs, ``trimag live --mavlink``
``live``       pyserial                                   ``trimag live --serial``
``review``     plotly                                     ``trimag review``, ``fit --report report.html``
=============  ========================================  ====================================================
"""

from __future__ import annotations

import importlib
from typing import Any

from ..errors import MissingExtraError

__all__ = ["EXTRAS", "available", "missing_extra_message", "require"]

#: The extra that installs each optional top-level package.
EXTRAS: dict[str, str] = {
    "pyarrow": "parquet",
    "h5py": "mat",
    "dask": "batch",
    "distributed": "batch",
    "pymavlink": "logs",
    "pyulog": "logs",
    "rosbags": "logs",
    "serial": "live",
    "plotly": "review",
}


def missing_extra_message(module: str, feature: str | None = None) -> str:
    """One line: what needs the missing package ``module`` and the command that installs it."""
    top = module.split(".")[0]
    extra = EXTRAS.get(top)
    what = feature or "this feature"
    install = f'pip install "trimag[{extra}]"' if extra else f"pip install {top}"
    return f"{what} needs the optional package {top!r}, which is not installed: {install}"


def require(module: str, feature: str) -> Any:
    """Import and return ``module``, an optional dependency needed for ``feature``.

    Parameters
    ----------
    module : str
        Dotted module name (e.g. ``"pyarrow.parquet"``); its top-level package must be a key of :data:`EXTRAS`.
    feature : str
        What needs it, for the message (e.g. ``"reading Parquet files"``).

    Raises
    ------
    MissingExtraError
        The package is not installed (or cannot be imported): one line naming the extra (exit code 2).
    """
    try:
        return importlib.import_module(module)
    except ImportError:
        raise MissingExtraError(missing_extra_message(module, feature)) from None


def available(module: str) -> bool:
    """True when the optional package ``module`` can be imported (importing it if it was not yet)."""
    try:
        importlib.import_module(module)
    except ImportError:
        return False
    return True
