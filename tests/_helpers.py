"""Helpers shared by the tests (import as `from _helpers import ...`)."""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

#: the tests' folder (``tests/``, where ``data/`` is) and the repository's root
TESTS_DIR = Path(__file__).resolve().parent
REPO_DIR = TESTS_DIR.parent

# the folder beside the repository (CI clones beside shared/), or where TRIMAG_SHARED_DATA points; nothing else
SHARED_DATA = Path(os.environ.get("TRIMAG_SHARED_DATA") or Path(__file__).resolve().parents[2] / "shared" / "data")

requires_shared = pytest.mark.skipif(
    not SHARED_DATA.exists(), reason="../shared/data absent (larger real logs are not bundled in the repo)"
)

#: The repository's benchmark harnesses (``python benchmarks/speed.py ...``); not part of the installed package.
BENCHMARKS_DIR = REPO_DIR / "benchmarks"


def load_benchmark(name: str) -> ModuleType:
    """Import the harness ``benchmarks/<name>.py`` from its path, once per process.

    ``benchmarks/`` is not a package and is not installed, so it is loaded by path, under the name
    ``_trimag_bench_<name>`` (the name ``benchmarks/speed.py`` loads its sibling ``accuracy.py`` under, so both
    share one module). Call it at the top of a test module: without the folder (tests run against an installed
    trimag, away from the repository) the whole module is skipped, with the reason.
    """
    path = BENCHMARKS_DIR / f"{name}.py"
    if not path.is_file():
        pytest.skip(f"{path} is absent: the benchmark harnesses live in the repository's benchmarks/ folder, "
                    "which is not installed with trimag", allow_module_level=True)
    module_name = f"_trimag_bench_{name}"
    module = sys.modules.get(module_name)
    if module is None:
        spec = importlib.util.spec_from_file_location(module_name, path)
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[module_name] = module
        try:
            spec.loader.exec_module(module)
        except BaseException:
            del sys.modules[module_name]
            raise
    return module


def trimag_command() -> list[str]:
    """The installed ``trimag`` command (end-to-end tests run it as a user would)."""
    exe = shutil.which("trimag")
    if exe is None:
        exe_dir = Path(sys.executable).parent
        candidate = exe_dir / "trimag"
        if candidate.exists():
            exe = str(candidate)
    if exe is None:
        pytest.fail("the `trimag` command is not installed; run the README's install command first")
    return [exe]


def run_trimag(*args: str, cwd: Path | None = None, timeout: float = 120,
               input: str | None = None) -> subprocess.CompletedProcess[str]:
    """Run the command as a process of its own; returns the completed process (text mode). ``input``: the text
    on its standard input.

    The process is forked from one that has already imported trimag and its dependencies (``_zygote.py``: the same
    ``trimag.cli.main`` with its own exit code, folder, environment and streams, without the 1.6 s of imports of
    every fresh start); ``TRIMAG_TEST_FRESH_PROCESS=1`` runs the installed command as a fresh process instead."""
    command = trimag_command()  # the command must be installed either way
    env = {**os.environ, "MPLBACKEND": "Agg"}
    argv = [str(a) for a in args]
    if os.environ.get("TRIMAG_TEST_FRESH_PROCESS") or not hasattr(os, "fork"):
        return subprocess.run([*command, *argv], capture_output=True, text=True, cwd=cwd, timeout=timeout, env=env,
                              input=input)
    from _zygote import run_forked

    return run_forked(argv, cwd=cwd, env=env, timeout=timeout, input=input)


def ellipsoid_truth() -> tuple[np.ndarray, np.ndarray]:
    """A realistic soft-iron correction (upper triangular) and hard iron, for field ~48000 nT."""
    W = np.array([[0.95, 0.03, -0.02], [0.0, 1.04, 0.05], [0.0, 0.0, 1.01]])
    b = np.array([1200.0, -850.0, 400.0])
    return W, b


def write_sphere_csv(path: Path, n: int = 300, seed: int = 0, header: str = "x,y,z") -> Path:
    """A CSV log of ``n`` readings on a sphere of radius 500 (uniform directions) with noise 2, under ``header``:
    a small log every command fits; returns ``path``."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    np.savetxt(path, u * 500 + rng.normal(0, 2, (n, 3)), delimiter=",", header=header, comments="")
    return path


def simulate_ellipsoid(n: int = 2000, noise: float = 0.0, seed: int = 0, F: float = 48000.0) -> np.ndarray:
    """Raw samples of a sensor with :func:`ellipsoid_truth` errors in a field of magnitude F (uniform sphere)."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    W, b = ellipsoid_truth()
    raw = np.linalg.solve(W, (F * u).T).T + b
    return raw + rng.normal(scale=noise, size=raw.shape) if noise else raw


def restore_sigint() -> None:
    """``preexec_fn`` of a subprocess a test interrupts with SIGINT: the default disposition, so that Python installs
    its KeyboardInterrupt handler. A shell without job control starts background commands (e.g. a CI job run with
    ``&``) with SIGINT ignored, and a child inherits that: Ctrl-C would then never reach trimag."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)


#: The site of the simulated boats (Berlin, 2026-06-01): IGRF-14 gives 500.77 mG, inclination 68.06 deg,
#: declination 5.12 deg (docs/autopilot.md, "Large vehicles").
BOAT_SITE = "52.5,13.3,40,2026-06-01"
#: The boat's compass: the symmetric correction (the firmware's DIA/ODI; its vertical scale equal to the horizontal
#: ones' mean, as a level turn holds it) and the hard iron, mG.
BOAT_MATRIX = np.array([[1.05, 0.02, -0.01], [0.02, 0.97, 0.015], [-0.01, 0.015, 1.01]])
BOAT_OFFSET = np.array([120.0, -80.0, 60.0])


def simulate_boat(
    seed: int = 0, n: int = 720, *, turns: float = 2.0, tilt_deg: float = 0.0, yaw_deg: np.ndarray | None = None,
    noise_mG: float = 2.0, matrix: np.ndarray | None = None, offset: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """A vehicle's compass (mG, body frame) turning level through ``turns`` circles (or at the true headings
    ``yaw_deg``), rolling and pitching by ``tilt_deg`` (amplitude, a wave's periods of 37 and 23 samples), with the
    errors :data:`BOAT_MATRIX` and :data:`BOAT_OFFSET` and ``noise_mG`` of white noise per axis, at :data:`BOAT_SITE`.

    Returns ``raw`` (N, 3), ``ypr`` (N, 3: true heading, pitch, roll in degrees), ``field_ned`` (3,, mG),
    ``matrix`` and ``offset``."""
    from scipy.spatial.transform import Rotation

    from trimag.fields.reference import igrf, parse_igrf_spec
    from trimag.simulate import body_field

    rng = np.random.default_rng(seed)
    M = BOAT_MATRIX if matrix is None else matrix
    b = BOAT_OFFSET if offset is None else offset
    ned = np.asarray(igrf(*parse_igrf_spec(BOAT_SITE)).ned_nT) / 100.0
    yaw = (np.linspace(0.0, 360.0 * turns, n, endpoint=False) + rng.normal(0, 1.0, n)) if yaw_deg is None else \
        np.broadcast_to(np.asarray(yaw_deg, dtype=float), (n,))
    t = np.arange(n)
    roll = tilt_deg * np.sin(2 * np.pi * t / 37.0)
    pitch = 0.6 * tilt_deg * np.sin(2 * np.pi * t / 23.0 + 1.0)
    ypr = np.column_stack([np.mod(yaw, 360.0), pitch, roll])
    h = body_field(Rotation.from_euler("ZYX", ypr, degrees=True), ned)
    raw = h @ np.linalg.inv(M).T + b + rng.normal(0, noise_mG, (n, 3))
    return {"raw": raw, "ypr": ypr, "field_ned": ned, "matrix": M, "offset": b}


def heading_rms_deg(field: np.ndarray, ypr: np.ndarray, declination_deg: float) -> float:
    """RMS (degrees) of the tilt-compensated true heading of a body-frame ``field`` against the true heading of
    ``ypr`` (yaw, pitch, roll), the down direction from the true pitch and roll."""
    from scipy.spatial.transform import Rotation

    from trimag.vehicle.heading import heading_difference, tilt_compensated_heading

    down = Rotation.from_euler("ZYX", ypr, degrees=True).inv().apply([0.0, 0.0, 1.0])
    heading = tilt_compensated_heading(field, -down, declination_deg=declination_deg)
    return float(np.sqrt(np.mean(heading_difference(heading, ypr[:, 0]) ** 2)))


#: a refusal's layout (docs/cli.md, "Errors"): its verdict line and each detail line at most this long
MAX_VERDICT_CHARS, MAX_DETAIL_CHARS = 200, 120


def refusal(stderr: str, *, ignore: Callable[[str], bool] = lambda line: False,
            max_verdict: int | None = MAX_VERDICT_CHARS) -> tuple[str, list[str]]:
    """The one refusal in ``stderr``: ``(its verdict line, the detail lines under it)``, after checking the layout
    every refusal keeps: each line a ``trimag: `` verdict (a warning's or the refusal's, <= 200 characters) or a
    detail under one (indented by two spaces, <= 120 characters); exactly one verdict that is not a warning; no
    traceback. ``ignore``: lines that are not trimag's (a library's own prints); ``max_verdict=None``: a verdict of
    any length (one that quotes a long path)."""
    assert "Traceback" not in stderr, stderr
    verdict, details, under = "", [], False
    for line in stderr.rstrip("\n").split("\n"):
        if ignore(line):
            continue
        if line.startswith("trimag: "):
            assert max_verdict is None or len(line) <= max_verdict, (len(line), line)
            under = not line.startswith("trimag: warning")
            if under:
                assert not verdict, stderr  # one refusal
                verdict = line
            continue
        assert line.startswith("  ") and len(line) <= MAX_DETAIL_CHARS, (len(line), line, stderr)
        if under:
            details.append(line)
    assert verdict, stderr
    return verdict, details


def refusal_text(stderr: str, max_verdict: int | None = MAX_VERDICT_CHARS) -> str:
    """The refusal's verdict and details (:func:`refusal`) as one text, the details' wrapped lines joined."""
    verdict, details = refusal(stderr, max_verdict=max_verdict)
    return " ".join([verdict, *(d.strip() for d in details)])
