"""Property-based fuzzing of the readers and the CLI (issue 22, item 9).

Invariant for any input file: the exit code is 0, 2 or 3 (never 1, an internal error), stderr has no traceback,
and a failed command leaves no output file. `apply` keeps every row. Runs in-process (cli.main) with few examples.
"""

from __future__ import annotations

import string
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from trimag.cli import main

_SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def _run(argv: list[str], capsys) -> tuple[int, str]:
    code = main(argv)
    err = capsys.readouterr().err
    return code, err


def _assert_clean(code: int, err: str, out: Path) -> None:
    assert code in (0, 2, 3), err
    assert "Traceback" not in err and "internal error" not in err
    if code != 0:
        assert not out.exists()
        assert not list(out.parent.glob(f".{out.name}*"))


@_SETTINGS
@given(data=st.binary(max_size=2000))
def test_random_bytes(tmp_path: Path, capsys, data: bytes) -> None:
    path = tmp_path / "fuzz.csv"
    path.write_bytes(data)
    out = tmp_path / "cal.json"
    out.unlink(missing_ok=True)
    code, err = _run(["fit", str(path), "-o", str(out), "-q"], capsys)
    _assert_clean(code, err, out)


_cell = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=32).map(lambda v: repr(float(v))),
    st.integers(-10**6, 10**6).map(str),
    st.text(alphabet=string.ascii_letters + " -_.", max_size=6),
    st.just(""),
)


@_SETTINGS
@given(
    header=st.lists(st.text(alphabet=string.ascii_letters + "_ ()", min_size=1, max_size=8), min_size=1, max_size=6),
    rows=st.lists(st.lists(_cell, min_size=1, max_size=6), min_size=0, max_size=30),
    sep=st.sampled_from([",", ";", "\t", " "]),
)
def test_random_tables(tmp_path: Path, capsys, header: list[str], rows: list[list[str]], sep: str) -> None:
    path = tmp_path / "t.csv"
    path.write_text("\n".join(sep.join(r) for r in [header, *rows]) + "\n", encoding="utf-8")
    out = tmp_path / "cal.json"
    out.unlink(missing_ok=True)
    code, err = _run(["fit", str(path), "-o", str(out), "-q"], capsys)
    _assert_clean(code, err, out)


@_SETTINGS
@given(n_bad=st.integers(0, 40), order=st.permutations(["x", "y", "z", "t"]), seed=st.integers(0, 10**6))
def test_apply_keeps_every_row_with_nan_and_inf_anywhere(tmp_path: Path, capsys, n_bad: int, order: list[str],
                                                         seed: int) -> None:
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(400, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    B = 50.0 * u + [3.0, -2.0, 1.0]
    table = {"x": B[:, 0].astype(object), "y": B[:, 1].astype(object), "z": B[:, 2].astype(object),
             "t": np.arange(400) * 0.1}
    for _ in range(n_bad):
        table[str(rng.choice(["x", "y", "z"]))][rng.integers(400)] = rng.choice(["nan", "inf", "", "-inf", "abc"])
    path = tmp_path / "log.csv"
    lines = [",".join(order)] + [",".join(str(table[c][i]) for c in order) for i in range(400)]
    path.write_text("\n".join(lines) + "\n")
    cal = tmp_path / "cal.json"
    cal.unlink(missing_ok=True)
    code, err = _run(["fit", str(path), "--units", "uT", "-o", str(cal), "-q"], capsys)
    _assert_clean(code, err, cal)
    if code != 0:
        return
    out = tmp_path / "out.csv"
    out.unlink(missing_ok=True)
    code, err = _run(["apply", str(cal), str(path), "-o", str(out), "-q"], capsys)
    _assert_clean(code, err, out)
    if code == 0:
        assert len(out.read_text().splitlines()) == len(lines)


@_SETTINGS
@given(data=st.binary(max_size=4000), head=st.sampled_from([b"", b"\xa3\x95", b"\xa3\x95\x80", b"FMT, "]))
def test_random_dataflash_bin(tmp_path: Path, capfd, data: bytes, head: bytes) -> None:
    """A random ``.bin`` (issue 32, item 6): one line on stderr, nothing printed by pymavlink."""
    path = tmp_path / "fuzz.bin"
    path.write_bytes(head + data)
    out = tmp_path / "cal.json"
    out.unlink(missing_ok=True)
    code = main(["fit", str(path), "-o", str(out), "-q"])
    captured = capfd.readouterr()
    _assert_clean(code, captured.err, out)
    assert code != 0 and len(captured.err.strip().splitlines()) == 1, captured.err[:2000]
    assert captured.out == ""
