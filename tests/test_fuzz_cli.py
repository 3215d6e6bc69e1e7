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


# ------------------------------------------------------------------ issue 33: limits, wild rows, policies, nesting, TL
_FEW = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def _sphere_lines(n: int, seed: int) -> list[str]:
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    B = 48000.0 * u / np.linalg.norm(u, axis=1, keepdims=True) + [900.0, -300.0, 400.0]
    return [f"{x:.2f},{y:.2f},{z:.2f}" for x, y, z in B]


@_FEW
@given(width=st.integers(1, 300), at=st.integers(0, 250), max_fields=st.integers(3, 120),
       cell=st.sampled_from(["1", "a", "", "1e5"]), seed=st.integers(0, 10**6))
def test_a_wide_line_anywhere_is_refused_by_its_limit_or_read(tmp_path: Path, capsys, width: int, at: int,
                                                               max_fields: int, cell: str, seed: int) -> None:
    """A line of ``width`` fields at line ``at``: beyond ``--max-fields`` within the sniffed head it is refused
    naming the flag; anywhere else the usual rules hold (exit 0, 2 or 3; never 1, never a traceback)."""
    lines = ["x,y,z", *_sphere_lines(300, seed)]
    lines.insert(min(at, len(lines)), ",".join([cell] * width))
    path = tmp_path / "wide.csv"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    out = tmp_path / "cal.json"
    out.unlink(missing_ok=True)
    code, err = _run(["fit", str(path), "--max-fields", str(max_fields), "-o", str(out), "-q"], capsys)
    _assert_clean(code, err, out)
    if width > max_fields and at < 200:
        assert code == 2 and "--max-fields" in err, err


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(spikes=st.lists(st.tuples(st.integers(0, 399), st.sampled_from([1e3, -1e4, 1e308, 3.0, 0.5])),
                       max_size=8), seed=st.integers(0, 10**6))
def test_spikes_are_dropped_and_counted_or_refused_never_an_internal_error(tmp_path: Path, capsys,
                                                                          spikes: list[tuple[int, float]],
                                                                          seed: int) -> None:
    import json

    lines = _sphere_lines(400, seed)
    scale = np.ones(400)
    for row, factor in spikes:
        with np.errstate(over="ignore"):  # 1e308 twice: inf, a non-finite row
            scale[row] *= factor
        lines[row] = ",".join(f"{float(v) * factor:.6g}" for v in lines[row].split(","))
    finite = np.array([all(np.isfinite(float(v)) for v in line.split(",")) for line in lines])
    path = tmp_path / "spiky.csv"
    path.write_text("x,y,z\n" + "\n".join(lines) + "\n", encoding="utf-8")
    code = main(["fit", str(path), "--json", "-q"])
    captured = capsys.readouterr()
    _assert_clean(code, captured.err, tmp_path / "none.json")
    if code == 0:
        s = json.loads(captured.out)
        wild = int((finite & (np.abs(scale) > 10)).sum())  # products of these are 9x or less, or 27x or more
        assert s["n_wild"] == wild and s["n_used"] == int(finite.sum()) - wild


_limit_value = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(lambda v: repr(v).replace("inf", "inf").lower()),
    st.integers(-5, 10**6).map(str), st.booleans().map(lambda b: str(b).lower()),
    st.text(alphabet=string.ascii_letters + "0123456789.", max_size=6).map(lambda t: f'"{t}"'),
    st.just("[1, 2]"),
)


@_FEW
@given(rule=st.sampled_from(["max_rms_after", "max_field_error_pct", "min_coverage", "max_offset",
                             "max_heading_sigma_deg", "max_inclination_error_deg"]), value=_limit_value)
def test_policy_limits_of_any_type_are_read_or_refused(tmp_path: Path, capsys, rule: str, value: str) -> None:
    import tomllib

    policy = tmp_path / "p.toml"
    policy.write_text(f"[limits]\n{rule} = {value}\n", encoding="utf-8")
    log = tmp_path / "log.csv"
    log.write_text("x,y,z\n" + "\n".join(_sphere_lines(300, 1)) + "\n", encoding="utf-8")
    out = tmp_path / "cal.json"
    out.unlink(missing_ok=True)
    code = main(["fit", str(log), "--policy", str(policy), "-o", str(out), "-q"])
    err = capsys.readouterr().err
    assert code in (0, 2, 4), err
    assert "Traceback" not in err and "internal error" not in err
    try:
        parsed = tomllib.loads(policy.read_text())["limits"][rule]
    except tomllib.TOMLDecodeError:
        parsed = None
    usable = (not isinstance(parsed, bool) and isinstance(parsed, int | float) and np.isfinite(parsed)
              and parsed >= 0 and (rule != "min_coverage" or parsed <= 1))
    assert (code != 2) == usable, (value, code, err)


@_FEW
@given(depth=st.integers(1, 3000), opener=st.sampled_from(["[", '{"a":']))
def test_json_of_any_depth_is_read_or_refused_in_one_line(tmp_path: Path, capsys, depth: int, opener: str) -> None:
    closer = "]" if opener == "[" else "}"
    cal = tmp_path / "deep.json"
    cal.write_text(opener * depth + ("1" if opener != "[" else "") + closer * depth, encoding="utf-8")
    log = tmp_path / "log.csv"
    log.write_text("x,y,z\n" + "\n".join(_sphere_lines(50, 2)) + "\n", encoding="utf-8")
    out = tmp_path / "out.csv"
    code, err = _run(["apply", str(cal), str(log), "-o", str(out)], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    _assert_clean(code, err, out)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rate=st.floats(1e-3, 1e12), gap=st.integers(0, 30), segments=st.sampled_from(
    [None, "0:100,100:300", "0:50,60:200", "5:5.5", "-10:1e9"]))
def test_tolles_lawson_rates_gaps_and_segments_never_an_internal_error(tmp_path: Path, capsys, rate: float, gap: int,
                                                                      segments: str | None) -> None:
    from trimag.simulate import simulate_aircraft

    sim = simulate_aircraft(25.0, seed=3, terms="p,i5,e8")
    cols = np.column_stack([sim.time_s, sim.vector_nT, sim.scalar_nT])
    cols = np.delete(cols, np.arange(300, 300 + gap), axis=0)
    data = tmp_path / "box.csv"
    np.savetxt(data, cols, delimiter=",", header="time,fx,fy,fz,mag", comments="", fmt="%.6f")
    out = tmp_path / "tl.json"
    out.unlink(missing_ok=True)
    argv = ["fit", str(data), "--model", "tolles-lawson", "--columns", "fx,fy,fz", "--scalar-column", "mag",
            "--rate", repr(rate), "--option", "bootstrap=0", "-o", str(out), "-q"]
    code, err = _run(argv + ([f"--segments={segments}"] if segments else []), capsys)
    _assert_clean(code, err, out)


_EXPORT_TARGETS = ["ardupilot", "px4", "c-header", "json", "ros-yaml", "matlab"]


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(created=st.text(max_size=60), method=st.text(max_size=60), source=st.text(max_size=40),
       target=st.sampled_from(_EXPORT_TARGETS))
def test_export_writes_numbers_whatever_text_the_calibration_holds(tmp_path: Path, capsys, created: str,
                                                                   method: str, source: str, target: str) -> None:
    """Issue 33 item 3, fuzzed: any text in the calibration file's string fields (newlines, comment terminators,
    control characters, another parameter's line) gives an output whose every line is a number line or one comment
    line of the target's syntax, or a one-line refusal (exit 2, no file)."""
    import json

    import yaml

    from trimag.calibration import Calibration

    data = Calibration.from_matrix_offset(np.diag([1.02, 0.98, 1.0]), [12.0, -7.0, 20.0], units="uT").as_dict()
    data.update({"created": created, "method": method})
    data.setdefault("reference", {})
    if isinstance(data["reference"], dict):
        data["reference"] = {**data["reference"], "source": source}
    cal = tmp_path / "cal.json"
    cal.write_text(json.dumps(data))
    suffix = {"ardupilot": "param", "px4": "txt", "c-header": "h", "json": "json", "ros-yaml": "yaml",
              "matlab": "mat"}[target]
    out = tmp_path / f"out.{suffix}"
    code, err = _run(["export", str(cal), "--to", target, "-o", str(out)], capsys)
    _assert_clean(code, err, out)
    if code != 0:
        assert len(err.strip().splitlines()) == 1, err
        return
    if target == "matlab":  # a MAT file: binary, loaded by scipy with the numbers
        from scipy.io import loadmat

        assert np.allclose(loadmat(str(out))["b"].ravel(), [12.0, -7.0, 20.0])
        return
    text = out.read_text(encoding="utf-8")
    assert "\r" not in text and "\x1b" not in text
    lines = [ln for ln in text.splitlines() if ln.strip()]
    if target == "ardupilot":
        for ln in lines:
            assert ln.startswith("#") or (ln.count(",") == 1 and float(ln.split(",")[1]) == float(ln.split(",")[1]))
        assert {ln.split(",")[0] for ln in lines if not ln.startswith("#")} == {
            "COMPASS_DIA_X", "COMPASS_DIA_Y", "COMPASS_DIA_Z", "COMPASS_ODI_X", "COMPASS_ODI_Y", "COMPASS_ODI_Z",
            "COMPASS_OFS_X", "COMPASS_OFS_Y", "COMPASS_OFS_Z", "COMPASS_SCALE", "COMPASS_ORIENT"} or all(
            ln.split(",")[0].startswith("COMPASS_") for ln in lines if not ln.startswith("#"))
    elif target == "px4":
        for ln in lines:
            assert ln.startswith("#") or (ln.split()[:2] == ["param", "set"] and len(ln.split()) == 4)
    elif target == "c-header":
        for ln in lines:
            if ln.lstrip().startswith(("/*", "*")) and "*/" in ln:
                assert ln.rstrip().endswith("*/") and ln.count("*/") == 1, ln
    elif target == "ros-yaml":
        assert set(yaml.safe_load(text)["magnetometer_calibration"]) == {"unit", "offset", "matrix"}
    elif target == "json":
        assert json.loads(text)["offset"] == [12.0, -7.0, 20.0]
