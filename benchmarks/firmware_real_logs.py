"""What ``trimag fit LOG --target T`` gives on real autopilot logs, compass by compass (issue 30, docs/autopilot.md).

    python benchmarks/firmware_real_logs.py LOG [LOG ...] [--out table.md]

For each log (the target from its format: ArduPilot DataFlash and telemetry logs -> ``ardupilot``, PX4 ULog and
sdlog2 -> ``px4``) and each of its magnetometers, as a user runs them:

    trimag fit LOG --target T --sensor N --json -o cal.json
    trimag export cal.json --to T -o compass.param

and a markdown table row: the exit code, the level chosen (+ motor term), the residual the levels were judged by,
the firmware's field RMS before (the log's own calibration) -> after (the fit), the warnings (their first words),
and what export did; a refusal is given by its reason's first words.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

_ARDUPILOT = (".bin", ".tlog", ".log")


def _target(log: Path) -> str:
    return "ardupilot" if log.suffix.lower() in _ARDUPILOT else "px4"


def _compasses(log: Path) -> list[str]:
    """The log's magnetometers as ``--sensor`` takes them (1-based numbers), or [] when the log cannot be read."""
    from trimag.errors import TrimagError
    from trimag.io.logs import read_log

    try:
        vlog = read_log(log)
    except TrimagError:
        return []
    seen: set[int] = set()
    out = []
    for m in vlog.magnetometers:  # a number taken twice (PX4's vehicle_magnetometer) is asked for by its name
        out.append(str(m.number) if m.number not in seen else m.name)
        seen.add(m.number)
    return out


def _short(text: str, words: int = 14) -> str:
    text = text.replace("|", "/").strip()
    for prefix in ("trimag: ", "error: ", "cannot identify the model: "):
        text = text.removeprefix(prefix)
    text = re.sub(r"^.*?another with --sensor N\): ", "", text)  # the compass list before the reason
    parts = text.split()
    return " ".join(parts[:words]) + (" ..." if len(parts) > words else "")


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "trimag", *map(str, args)], capture_output=True, text=True)


def fit_one(log: Path, sensor: str | None, work: Path) -> dict[str, Any]:
    """One compass (or the whole log when it lists none): the fit, then the export."""
    target = _target(log)
    cal, param = work / "cal.json", work / "compass.param"
    cal.unlink(missing_ok=True)
    param.unlink(missing_ok=True)
    fit = _run("fit", log, "--target", target, *(["--sensor", sensor] if sensor else []), "--json", "-o", cal)
    row: dict[str, Any] = {"log": log.name, "compass": sensor or "-", "target": target, "exit": fit.returncode}
    if fit.returncode != 0:
        lines = fit.stderr.strip().splitlines()
        row["result"] = _short(lines[-1] if lines else "(no message)")
        return row
    summary = json.loads(fit.stdout)
    fw = summary["firmware"]
    row["level"] = fw["level"] + (f" + {fw['motor_type']}" if fw.get("motor_type") else "")
    row["residual"] = fw["residual"]
    row["rms"] = f"{fw['rms_before']:.4g} -> {fw['rms_after']:.4g} {fw['unit']}"
    row["warnings"] = "; ".join(_short(w, 8) for w in summary.get("warnings") or [])
    export = _run("export", cal, "--to", target, "-o", param)
    row["result"] = ("parameters" if export.returncode == 0 else
                     f"export exit {export.returncode}: {_short(export.stderr.strip().splitlines()[-1])}")
    return row


def table(rows: list[dict[str, Any]]) -> str:
    head = "| log | compass | exit | result | level | residual | RMS before -> after | warnings |\n"
    head += "|---|---|---|---|---|---|---|---|\n"
    return head + "".join(
        f"| `{r['log']}` | {r['compass']} | {r['exit']} | {r.get('result', '')} | {r.get('level', '')} | "
        f"{r.get('residual', '')} | {r.get('rms', '')} | {r.get('warnings', '')} |\n" for r in rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("logs", nargs="+", type=Path)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for log in args.logs:
            for sensor in _compasses(log) or [None]:
                rows.append(fit_one(log, sensor, Path(tmp)))
                print(json.dumps(rows[-1]), file=sys.stderr)
    text = table(rows)
    if args.out:
        args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
