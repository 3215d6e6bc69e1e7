"""Byte-damaged copies of every log format (issue 41, item 4): `trimag fit` ends with exit 0, 2 or 3, its error in
one verdict line (then its indented detail lines, docs/cli.md "Errors"), never a traceback or an internal error
(exit 1), and leaves no output behind.

Fixed seeds, a few hundred copies, each log cut to its first 48 kB (the FMT/definition messages, parameters and
the first data, where damage changes most) so that the whole test takes well under a minute on one core. The bundled
logs (and a simulated telemetry log) run everywhere; the shared ones (`../shared/data/flight-logs`) where present.
Before the fix 11 of 80 DataFlash copies, 1 of 30 tlogs and 6 of 30 ULogs ended in exit 1 (KeyError 'MOZ' / 'Lat' /
'Id' / '_timestamp' from an FMT without that column, LinAlgError from a logged compass matrix, a parameter's type).
"""

from __future__ import annotations

import re
import struct
from pathlib import Path

import numpy as np
import pytest

from _helpers import SHARED_DATA, TESTS_DIR, refusal, run_trimag

LOGS = TESTS_DIR / "data" / "logs"
FLIGHT = SHARED_DATA / "flight-logs"
HEAD_BYTES = 48 * 1024
COPIES = 24  # per log: 168 copies in all
#: pymavlink's compiled DataFlash indexer writes these to the process's stderr itself, one per damaged byte (issue
#: 41 item 11, another branch's): not trimag's lines, left out here.
_INDEXER_LINE = re.compile(r"^(bad header 0x[0-9a-f]+ at \d+|unknown msg type 0x[0-9a-f]+ \(\d+\) at \d+)$")


def _simulated_tlog(path: Path) -> Path:
    """A telemetry log of a tumble (RAW_IMU, ATTITUDE, PARAM_VALUE, GLOBAL_POSITION_INT), written with pymavlink."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    link = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    rng = np.random.default_rng(5)
    u = rng.normal(size=(120, 3))
    u = 450.0 * u / np.linalg.norm(u, axis=1, keepdims=True) + np.array([80.0, -40.0, 25.0])
    with path.open("wb") as fh:
        def put(t: float, msg) -> None:
            fh.write(struct.pack(">Q", int(t * 1e6)) + msg.pack(link))

        for k, (name, value) in enumerate({"COMPASS_OFS_X": 10.0, "COMPASS_OFS_Y": -5.0}.items()):
            put(1.7e9, link.param_value_encode(name.encode(), value, 9, 2, k))
        for i, m in enumerate(np.round(u).astype(int)):
            t = 1.7e9 + 0.1 * i
            put(t, link.raw_imu_encode(int(t * 1e6), 0, 0, -1000, 0, 0, 0, *m.tolist()))
            put(t, link.attitude_encode(i * 100, 0.01 * i, 0.02, 0.03 * i, 0.0, 0.0, 0.0))
            if i % 10 == 0:
                put(t, link.global_position_int_encode(i * 100, 525_000_000, 134_000_000, 50_000, 0, 0, 0, 0, 0))
    return path


SOURCES = {
    "ardusub_small.BIN": LOGS / "ardusub_small.BIN",
    "pyulog_sample_log_small.ulg": LOGS / "pyulog_sample_log_small.ulg",
    "px4tools_01_07_59.px4log": LOGS / "px4tools_01_07_59.px4log",
    "simulated.tlog": None,  # written by _simulated_tlog
    "shared ardusub_small.tlog": FLIGHT / "ardusub_small.tlog",
    "shared methodicconfigurator_backend_log_80k.bin": FLIGHT / "methodicconfigurator_backend_log_80k.bin",
    "shared pymavlink_test.BIN": FLIGHT / "pymavlink_test.BIN",
}


@pytest.mark.parametrize("name", list(SOURCES))
def test_byte_damaged_logs_end_cleanly(name: str, tmp_path: Path):
    source = SOURCES[name]
    if source is None:
        source = _simulated_tlog(tmp_path / "simulated.tlog")
    elif not source.exists():
        pytest.skip(f"{source.relative_to(SHARED_DATA.parent)} absent: the shared logs are not in the repository")
    head = source.read_bytes()[:HEAD_BYTES]
    rng = np.random.default_rng(sum(name.encode()))  # one fixed seed per log
    out = tmp_path / "cal.json"
    failures = []
    for copy in range(COPIES):
        data = bytearray(head)
        for at in rng.integers(0, len(data), rng.integers(1, 9)):  # 1 to 8 bytes set to random values
            data[at] = int(rng.integers(0, 256))
        damaged = tmp_path / f"damaged{source.suffix}"
        damaged.write_bytes(bytes(data))
        r = run_trimag("fit", damaged, "-o", out, timeout=60)
        clean = r.returncode in (0, 2, 3) and "Traceback" not in r.stderr and "internal error" not in r.stderr
        if r.returncode != 0:
            try:  # one verdict line, then short indented detail lines
                refusal(r.stderr, ignore=lambda line: bool(_INDEXER_LINE.match(line)), max_verdict=None)
            except AssertionError:
                clean = False
            clean = clean and not out.exists()
        if not clean:
            failures.append(f"copy {copy}: exit {r.returncode}: {r.stderr.strip()[-300:]}")
        out.unlink(missing_ok=True)
    assert not failures, "\n".join(failures)


def _small_dataflash(path: Path, params: dict[str, float], mag_format: tuple[str, str]) -> Path:
    import sys

    sys.path.insert(0, str(TESTS_DIR / "io"))
    from _dataflash import write_dataflash

    rng = np.random.default_rng(2)
    u = rng.normal(size=(300, 3))
    u = 450.0 * u / np.linalg.norm(u, axis=1, keepdims=True)
    fmt, columns = mag_format
    rows = [(1000 + 100_000 * i, *np.round(m).astype(int).tolist(), 0, 0, 0, 1)[:len(fmt)] for i, m in enumerate(u)]
    return write_dataflash(path, {
        "PARM": ("QNf", "TimeUS,Name,Value", [(100, k, v) for k, v in params.items()]),
        "MAG": (fmt, columns, rows),
    })


@pytest.mark.parametrize("case", ["singular matrix", "motor term without MOZ", "no TimeUS"])
def test_a_dataflash_log_the_reader_cannot_trust_is_refused_in_one_line(case: str, tmp_path: Path):
    """The exit-1 cases of issue 41 item 4, written on purpose: a logged compass matrix that is singular
    (``LinAlgError``), an FMT of MAG with MOX and MOY but no MOZ, a MAG without its time stamp (``KeyError``)."""
    params = {"COMPASS_OFS_X": 10.0, "COMPASS_DIA_X": 1.0, "COMPASS_DIA_Y": 1.0, "COMPASS_DIA_Z": 1.0}
    mag = ("QhhhhhhH", "TimeUS,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,Health")
    if case == "singular matrix":
        params["COMPASS_ODI_X"] = 1.0  # [[1, 1, 0], [1, 1, 0], [0, 0, 1]]
    elif case == "motor term without MOZ":
        mag = ("QhhhhhH", "TimeUS,MagX,MagY,MagZ,MOX,MOY,Health")
    else:
        mag = ("ihhhhhhH", "Tick,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,Health")
    log = _small_dataflash(tmp_path / "log.bin", params, mag)
    out = tmp_path / "cal.json"
    r = run_trimag("fit", log, "-o", out)
    assert r.returncode == 2, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "the log is damaged" in r.stderr, r.stderr
    assert not out.exists()
