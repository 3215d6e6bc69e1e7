"""Does ``trimag live`` save what was recorded, whatever stops it and whenever? (issue 33, item 1)

Each run replays the bundled demo log (QMC5883L, 22 743 samples) at 2 000 samples/s through the real command and
stops it at a random moment between the first "good enough" on ``/status`` and one second after the replay's end, by
a random one of: SIGINT (Ctrl-C), SIGTERM, two or three signals back to back (the later ones arrive during the stop
or the save), or the page's ``POST /save`` followed by SIGINT. A run passes when the command exits 0 and the files
hold a prefix of the log and the calibration of exactly that prefix (``trimag.fit`` of the samples file gives the
same matrix and offset to 1e-9), and, for ``POST /save``, when the pair it wrote was such a pair too.

    python benchmarks/live_signals.py                       # 50 runs, two at a time (about 5 min)
    python benchmarks/live_signals.py --runs 4 --rate 8000 --seed 3
"""

from __future__ import annotations

import argparse
import json
import re
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request
from concurrent.futures import ThreadPoolExecutor
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

import trimag
from trimag.io import read_samples

DEMO = Path(str(resources.files("trimag") / "data" / "qmc5883l_noisy_raw_data.csv"))
#: The ways a run is stopped: signals sent back to back, or "save" (the page's POST /save) then a signal.
STOPS = ("SIGINT", "SIGTERM", "SIGINT SIGINT", "SIGTERM SIGINT SIGTERM", "save SIGINT")


def _get(url: str) -> dict[str, Any]:
    with urllib.request.urlopen(url, timeout=30) as r:
        return dict(json.loads(r.read()))


def _post_save(url: str) -> dict[str, str]:
    """The page's POST /save: its origin, and the token it carries."""
    with urllib.request.urlopen(url, timeout=30) as r:
        found = re.search(r'name="trimag-token" content="([^"]*)"', r.read().decode())
    headers = {"Origin": url.rstrip("/"), "X-Trimag-Token": found.group(1) if found else ""}
    request = urllib.request.Request(url + "save", method="POST", data=b"", headers=headers)
    with urllib.request.urlopen(request, timeout=120) as r:
        return dict(json.loads(r.read())["written"])


def check_pair(samples_path: Path, calibration_path: Path, log: np.ndarray) -> int:
    """The samples file holds a prefix of ``log`` and the calibration is the fit of exactly it; returns its length
    (raises AssertionError otherwise)."""
    recorded = read_samples(samples_path).field
    n = len(recorded)
    assert np.array_equal(recorded, log[:n]), "the samples are not the log's first rows"
    cal = trimag.Calibration.from_file(calibration_path)
    assert cal.stats["n_samples"] == n, f"calibration of {cal.stats['n_samples']} samples beside {n} samples"
    again = trimag.fit(recorded, units="counts")
    assert np.allclose(cal.matrix, again.matrix, rtol=1e-9, atol=1e-12), "the matrix is not the samples' fit"
    assert np.allclose(cal.offset, again.offset, rtol=1e-9, atol=1e-9), "the offset is not the samples' fit"
    return n


def one_run(stop: str, fraction: float, rate: float, folder: Path, log: np.ndarray) -> dict[str, Any]:
    """One replay stopped by ``stop`` at ``fraction`` of the way from the first "good enough" to one second after
    the replay's end; returns what happened (``ok`` and, when not, ``why``)."""
    out = folder / "cal.json"
    proc = subprocess.Popen([sys.executable, "-m", "trimag", "live", "--replay", str(DEMO), "--rate", str(rate),
                             "--units", "counts", "--no-browser", "--port", "0", "-o", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    result: dict[str, Any] = {"stop": stop, "fraction": round(fraction, 3), "ok": False}
    try:
        assert proc.stdout is not None
        first = proc.stdout.readline()
        url = first.split("the page is at ")[1].split()[0]
        t0 = time.monotonic()
        while not _get(url + "status?points=0")["good_enough"]:
            time.sleep(0.05)
        good = time.monotonic()
        end = t0 + len(log) / rate + 1.0
        time.sleep(max(0.0, good + fraction * max(0.0, end - good) - time.monotonic()))
        result["stopped_at_s"] = round(time.monotonic() - t0, 2)
        for what in stop.split():
            if what == "save":
                written = _post_save(url)
                result["saved_by_post"] = check_pair(Path(written["samples"]), Path(written["calibration"]), log)
            else:
                proc.send_signal(getattr(signal, what))
        _, stderr = proc.communicate(timeout=180)
        result["exit"] = proc.returncode
        assert proc.returncode == 0, f"exit {proc.returncode}: {stderr.strip()[-200:]}"
        assert "Traceback" not in stderr
        result["n_saved"] = check_pair(folder / "cal-samples.csv", out, log)
        result["ok"] = True
    except (AssertionError, OSError, IndexError, KeyError, ValueError, subprocess.TimeoutExpired) as exc:
        result["why"] = f"{type(exc).__name__}: {exc}"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return result


def run(runs: int, seed: int, rate: float, jobs: int) -> list[dict[str, Any]]:
    """``runs`` replays with random stops and moments (``seed``), ``jobs`` at a time."""
    rng = np.random.default_rng(seed)
    plan = [(STOPS[int(rng.integers(len(STOPS)))], float(rng.uniform())) for _ in range(runs)]
    log = read_samples(DEMO).field
    with tempfile.TemporaryDirectory() as tmp, ThreadPoolExecutor(jobs) as pool:
        folders = [Path(tmp) / f"run{k}" for k in range(runs)]
        for folder in folders:
            folder.mkdir()
        return list(pool.map(lambda k: one_run(*plan[k], rate, folders[k], log), range(runs)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=50)
    parser.add_argument("--seed", type=int, default=33)
    parser.add_argument("--rate", type=float, default=2000.0, help="replay rate, samples/s")
    parser.add_argument("--jobs", type=int, default=2, help="replays at a time")
    args = parser.parse_args()
    results = run(args.runs, args.seed, args.rate, args.jobs)
    for r in results:
        print(json.dumps(r))
    print("| stop | runs | saved (samples + their calibration, exit 0) |\n|---|---|---|")
    for stop in STOPS:
        mine = [r for r in results if r["stop"] == stop]
        if mine:
            print(f"| {stop} | {len(mine)} | {sum(r['ok'] for r in mine)} |")
    print(f"| all | {len(results)} | {sum(r['ok'] for r in results)} |")
    sys.exit(0 if all(r["ok"] for r in results) else 1)


if __name__ == "__main__":
    main()
