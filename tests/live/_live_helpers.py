"""Helpers of the ``trimag live`` tests: simulated recordings, the command in a subprocess, the page's requests."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import urllib.request
from importlib import resources
from pathlib import Path

import numpy as np

from _helpers import restore_sigint

DEMO = Path(str(resources.files("trimag") / "data" / "qmc5883l_noisy_raw_data.csv"))


def sensor(directions: np.ndarray, seed: int = 0) -> np.ndarray:
    """Raw counts of a sensor with hard and soft iron seeing ``directions`` (unit vectors) of a 500-count field."""
    W_inv = np.array([[1.1, 0.05, 0.0], [0.0, 0.9, -0.03], [0.0, 0.0, 1.0]])
    noise = np.random.default_rng(seed).normal(0.0, 2.0, directions.shape)
    return (500.0 * directions) @ W_inv.T + [30.0, -20.0, 10.0] + noise


def write_log(path: Path, raw: np.ndarray, header: str = "x,y,z") -> Path:
    """``raw`` as a CSV log with ``header``; returns the path."""
    np.savetxt(path, raw, delimiter=",", header=header, comments="", fmt="%.6f")
    return path


def start_live(*args: str, cwd: Path, stdin: int | None = None) -> tuple[subprocess.Popen, str]:
    """``trimag live ARGS --no-browser --port 0`` in a subprocess; returns it and the page's address."""
    env = {**os.environ, "MPLBACKEND": "Agg"}
    proc = subprocess.Popen([sys.executable, "-m", "trimag", "live", *args, "--no-browser", "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=cwd, env=env, stdin=stdin,
                            preexec_fn=restore_sigint)
    stream = proc.stderr if "--json" in args else proc.stdout  # --json keeps stdout for the JSON object
    assert stream is not None
    first = stream.readline()
    if "http://127.0.0.1:" not in first:
        proc.kill()
        raise AssertionError(f"no address printed: {first!r} {proc.stderr.read() if proc.stderr else ''}")
    return proc, first.split("the page is at ")[1].split()[0]


def get(url: str, timeout: float = 10.0) -> dict:
    """GET ``url`` as JSON."""
    with urllib.request.urlopen(url, timeout=timeout) as r:
        return json.loads(r.read())


def page_token(url: str) -> str:
    """The per-session token the page carries (``<meta name="trimag-token">``); empty when the page has none."""
    with urllib.request.urlopen(url, timeout=10) as r:
        page = r.read().decode()
    found = re.search(r'name="trimag-token" content="([^"]*)"', page)
    return found.group(1) if found else ""


def post_save(url: str, token: str | None = None) -> dict:
    """``POST /save`` as the page sends it: from the page's own origin, with the session's token."""
    origin = url.rstrip("/")
    headers = {"Origin": origin, "X-Trimag-Token": page_token(url) if token is None else token}
    request = urllib.request.Request(url + "save", method="POST", data=b"", headers=headers)
    with urllib.request.urlopen(request, timeout=60) as r:
        return json.loads(r.read())


def chromium() -> str | None:
    """The installed Chromium (or Chrome), if any."""
    import shutil

    for name in ("chromium", "chromium-browser", "google-chrome", "chrome"):
        found = shutil.which(name)
        if found:
            return found
    return None


#: Flags of headless Chromium that work in a container as root, on a machine without a GPU, offline.
CHROMIUM_FLAGS = ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--window-size=1400,1100")


def chrome(profile: Path, *flags: str):  # type: ignore[no-untyped-def]
    """A Selenium driver of headless Chromium with a new empty profile in ``profile``; skips the test, saying why,
    where no browser (or no Selenium, or no driver matching the browser) can be had."""
    import shutil

    import pytest

    browser = chromium()
    if browser is None:
        pytest.skip("no Chromium installed (apt-get install chromium chromium-driver; see README, 'trimag live')")
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed (pip install selenium)")
    options = webdriver.ChromeOptions()
    options.binary_location = browser
    profile.mkdir(parents=True, exist_ok=True)
    for arg in (*CHROMIUM_FLAGS, f"--user-data-dir={profile}", *flags):
        options.add_argument(arg)
    from selenium.webdriver.chrome.service import Service

    driver = shutil.which("chromedriver")  # the distribution's (else Selenium looks for one, online)
    service = Service(executable_path=driver) if driver else None
    try:
        return webdriver.Chrome(options=options, service=service)
    except Exception as exc:  # no chromedriver matching the browser
        pytest.skip(f"Chromium is installed but Selenium cannot drive it: {exc}")
