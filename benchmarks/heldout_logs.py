"""Held-out real autopilot logs: the log's calibration, MAGFit and trimag on the half not fitted (issue 38).

    python benchmarks/heldout_logs.py DIR [--manifest benchmarks/heldout_logs.toml] [--out table.md]

``DIR`` holds the logs of the manifest (``benchmarks/heldout_logs.toml``: repository, commit, path, sha256 and
licence of each; none is in the repository). Each file is checked against its sha256, then every compass of every
ArduPilot log is put through :func:`magfit_compare.compare` (``benchmarks/magfit_compare.py``): MAGFit
(``magfit_WMM.py``, best of its variants) and ``trimag fit LOG --sensor N --target ardupilot --rows 0:HALF`` fitted
on the first half, each judged on the second half through ArduPilot's formula with the log's ``AHRS_TRIM``, as the
log's firmware loads them; and trimag's exit code and its own verdict against the log's calibration. A log without a
GPS fix is run through ``trimag fit`` only (MAGFit and the judge need the Earth's field at the log's site), and so is
a PX4 log (``firmware = "px4"`` in the manifest; ``--target px4``): MAGFit and the judge are ArduPilot's.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from magfit_compare import compare

HERE = Path(__file__).resolve().parent


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _compasses(log: Path) -> list[int]:
    from trimag.io.logs import read_log

    return sorted({m.number for m in read_log(log).magnetometers})


def _fit_only(log: Path, compass: int, target: str = "ardupilot") -> dict[str, Any]:
    """``trimag fit`` on the first half where nothing else can judge (no GPS fix; a PX4 log: MAGFit and the judge
    are ArduPilot's): its exit code and its own verdict on the rows left out (or its last line)."""
    from trimag.io.logs import read_log

    n = len(read_log(log).table(str(compass))[0])
    with tempfile.TemporaryDirectory() as tmp:
        proc = subprocess.run([sys.executable, "-m", "trimag", "fit", str(log), "--sensor", str(compass), "--target",
                               target, "--rows", f"0:{n // 2}", "-o", str(Path(tmp) / "cal.json")],
                              capture_output=True, text=True)
    errors = proc.stderr.strip().splitlines()
    verdict = ([line for line in proc.stdout.splitlines() if "the fit did not see" in line]
               or (errors[:1] if proc.returncode else errors[-1:]) or [""])
    return {"log": log.name, "compass": compass, "n_fit": n // 2, "n_heldout": n - n // 2,
            "trimag_exit": proc.returncode, "trimag": verdict[0]}


def _short(text: str, words: int = 12) -> str:
    text = text.replace("|", "/").removeprefix("trimag: ").removeprefix("cannot identify the model: ")
    if "another with --sensor N): " in text:
        text = text.split("another with --sensor N): ", 1)[1]
    parts = text.split()
    return " ".join(parts[:words]) + (" ..." if len(parts) > words else "")


def _cell(e: Any) -> str:
    return f"{e[0]:.1f} / {e[1]:.1f}" if isinstance(e, (tuple, list)) else str(e)


def table(rows: list[dict[str, Any]]) -> str:
    lines = ["| log | firmware | compass | fit / held-out samples | heading turned (fitted half), max tilt | "
             "log's calibration | MAGFit (best variant) | trimag | trimag's verdict (its residual, held-out rows) "
             "| exit |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        best = r.get("magfit_best")
        mf = f"{_cell(best[1])} ({best[0]})" if best else r.get("magfit_note", "failed" if "before" in r else "-")
        if isinstance(r.get("trimag"), (tuple, list)):
            tr = f"{_cell(r['trimag'])} ({r.get('trimag_level', '-')})"
        else:
            tr = "-"
        v = r.get("trimag_verdict")
        if isinstance(v, dict):
            verdict = f"{v.get('decision')}: {v.get('rms_fit', float('nan')):.4g} vs log's {v.get('rms_log', 0):.4g}"
        else:
            verdict = _short(str(r.get("trimag", r.get("note", ""))))
        span = (f"{r['yaw_span_deg']:.0f} deg, {r['tilt_max_deg']:.0f} deg" if "yaw_span_deg" in r else "-")
        lines.append(f"| {r['log']} | {r.get('vehicle') or '-'} | {r['compass']} | {r['n_fit']} / {r['n_heldout']} | "
                     f"{span} | {_cell(r.get('before', '-'))} | {mf} | {tr} | {verdict} | "
                     f"{r.get('trimag_exit', '-')} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dir", type=Path, help="the directory holding the manifest's logs")
    parser.add_argument("--manifest", type=Path, default=HERE / "heldout_logs.toml")
    parser.add_argument("--only", nargs="*", help="only these files of the manifest")
    parser.add_argument("--no-magfit", action="store_true", help="leave MAGFit out (an A/B of trimag alone)")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    entries = tomllib.loads(args.manifest.read_text())["log"]
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        for entry in entries:
            if args.only and entry["file"] not in args.only:
                continue
            log = args.dir / entry["file"]
            if not log.exists() or _sha256(log) != entry["sha256"]:
                print(f"skipped {entry['file']}: absent or not the manifest's sha256", file=sys.stderr)
                continue
            for compass in _compasses(log):
                if entry.get("firmware") == "px4":  # trimag's own verdict only (docs/autopilot.md)
                    row = {"vehicle": "PX4", **_fit_only(log, compass, "px4")}
                    print(json.dumps(row, default=str), flush=True)
                    rows.append(row)
                    continue
                row = compare(log, Path(tmp), compass, magfit=not args.no_magfit)
                if "note" in row:  # nothing to judge against: trimag's own answer only
                    row = {**row, **_fit_only(log, compass)}
                print(json.dumps(row, default=str), flush=True)
                rows.append(row)
    text = ("held-out (second half) field error, mGauss: MAGFit's cost (mean, heading from the corrected field) / "
            "vector RMS against IGRF rotated by ATT\n\n" + table(rows) + "\n")
    print(text)
    if args.out:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
