"""``trimag live`` saves what was recorded, every time (issue 33, item 1).

Each save writes one snapshot of the samples and the calibration fitted to exactly that snapshot, whatever arrives
meanwhile; SIGINT and SIGTERM both save and say so, a second signal waits for the save; an output that would replace
the replayed log, and flags that cannot work, are refused before the session starts (exit 2).
"""

from __future__ import annotations

import json
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from _live_helpers import get, post_save, sensor, start_live, write_log

import trimag
from trimag.app.requests import LiveRequest
from trimag.cli import main
from trimag.errors import TrimagInputError
from trimag.io import read_samples
from trimag.live import LiveServer, LiveSession, run_live
from trimag.live.sources import Batch
from trimag.simulate import uniform_directions

from _helpers import run_trimag


def _assert_saved_pair(written: dict[str, str], units: str = "counts") -> int:
    """The calibration written is the fit of exactly the samples written; returns their number."""
    assert set(written) == {"samples", "calibration"}, written
    recorded = read_samples(written["samples"]).field
    cal = trimag.Calibration.from_file(written["calibration"])
    assert cal.stats["n_samples"] == len(recorded)
    again = trimag.fit(recorded, units=units)
    assert np.allclose(cal.matrix, again.matrix, rtol=1e-9, atol=1e-12)
    assert np.allclose(cal.offset, again.offset, rtol=1e-9, atol=1e-9)
    return len(recorded)


def test_a_save_while_samples_arrive_writes_the_calibration_of_the_samples_written(tmp_path):
    """POST /save while a source floods: every save writes the samples and the calibration of exactly them (the
    tree before wrote one snapshot and refitted a later one: no calibration, in 10 of 10 tries at 2000 Hz)."""
    raw = sensor(uniform_directions(20_000, seed=11))
    session = LiveSession(units="counts", interval=0.05)
    enough, stop = threading.Event(), threading.Event()

    def feed() -> None:
        k = 0
        while not stop.is_set():
            session.add(Batch(raw[k % len(raw) : k % len(raw) + 10]))
            k += 10
            if k >= 3000:
                enough.set()
            stop.wait(0.0005)

    feeder = threading.Thread(target=feed, daemon=True)
    server = LiveServer(session, 0, save=lambda: session.save(tmp_path / "cal.json")).start()
    feeder.start()
    try:
        assert enough.wait(60)
        counts = [_assert_saved_pair(post_save(server.url)["written"]) for _ in range(3)]
    finally:
        stop.set()
        feeder.join()
        server.shutdown()
    assert counts == sorted(counts) and counts[0] >= 3000


@pytest.mark.slow
@pytest.mark.parametrize("signals", [("SIGINT",), ("SIGTERM",), ("SIGINT", "SIGTERM", "SIGINT")],
                         ids=["ctrl-c", "sigterm", "repeated"])
def test_a_signal_while_recording_saves_the_samples_and_their_calibration(tmp_path, signals):
    """Ctrl-C after "good enough" wrote no calibration in 7 of 12 replays, SIGTERM exited 143 without it (and
    without a word), a second signal during the save lost the recording. Now each saves both, exit 0."""
    log = write_log(tmp_path / "sphere.csv", sensor(uniform_directions(20_000, seed=12)))
    proc, url = start_live("--replay", str(log), "--rate", "4000", "--units", "counts", "-o",
                           str(tmp_path / "cal.json"), "--interval", "0.05", cwd=tmp_path)
    try:
        for _ in range(600):
            if get(url + "status?points=0")["good_enough"]:
                break
            threading.Event().wait(0.05)
        for name in signals:  # back to back: the later ones arrive during the stop or the save
            proc.send_signal(getattr(signal, name))
        out, err = proc.communicate(timeout=120)
    except BaseException:
        proc.kill()
        raise
    assert proc.returncode == 0, err
    assert "Traceback" not in err
    assert "saved samples" in out and "good enough" in out
    n = _assert_saved_pair({"samples": str(tmp_path / "cal-samples.csv"), "calibration": str(tmp_path / "cal.json")})
    assert np.array_equal(read_samples(tmp_path / "cal-samples.csv").field, read_samples(log).field[:n])


def test_an_output_that_would_replace_the_replayed_log_is_refused(tmp_path):
    """--samples-out equal to the replayed file overwrote the original log with its x, y, z columns only."""
    raw = sensor(uniform_directions(500, seed=13))
    log = tmp_path / "cal-samples.csv"
    np.savetxt(log, np.column_stack([np.arange(500), raw]), delimiter=",", header="t,x,y,z", comments="")
    before = log.read_bytes()
    for given in ({"samples_out": log}, {"samples_out": tmp_path / "." / "cal-samples.csv"},
                  {"out": tmp_path / "cal.json"}):  # the last: the default samples file is the replayed one
        request = LiveRequest(replay=log, rate=None, units="counts", port=0, open_browser=False, exit_at_end=True,
                              **{"out": tmp_path / "other.json", **given})
        with pytest.raises(TrimagInputError, match="replayed"):
            run_live(request, say=lambda m: None)
        assert log.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cal-samples.csv"]


@pytest.fixture
def small_log(tmp_path: Path) -> Path:
    return write_log(tmp_path / "log.csv", sensor(uniform_directions(400, seed=14)))


@pytest.mark.parametrize("flags", [
    ["--units", "furlongs"], ["--reference", "inf"], ["--reference", "-3"], ["--out", "/proc/x.json"],
    ["--port", "70000"], ["--port", "-1"], ["--interval", "inf"], ["--interval", "nan"], ["--interval", "-1"],
    ["--rate", "inf"], ["--rate", "nan"], ["--samples-out", "/proc/x.csv"],
    # a method live cannot feed: the gyroscope's rate, the attitudes, a known magnitude (review: these ran the
    # whole session and then ended "no calibration written", exit 3)
    ["--method", "gyro"], ["--model", "interference12"], ["--model", "zhang-cheng", "--method", "quadric"],
], ids=lambda f: " ".join(f))
def test_flags_that_cannot_work_are_refused_before_the_session_starts(tmp_path, small_log, capsys, flags):
    argv = ["live", "--replay", str(small_log), "--rate", "1e6", "--exit-at-end", "--no-browser", "--port", "0",
            "-o", str(tmp_path / "cal.json"), *flags]
    code = main(argv)
    out, err = capsys.readouterr()
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err and "internal error" not in err
    assert "the page is at" not in out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["log.csv"]


def test_the_header_unit_is_checked_as_fit_checks_it(tmp_path, capsys):
    raw = sensor(uniform_directions(400, seed=15))
    cases = [
        (write_log(tmp_path / "nT.csv", raw, "mx_nT,my_nT,mz_nT"), ["--units", "uT"]),  # the header says nT
        (write_log(tmp_path / "uT.csv", raw, "Bx (uT),By (uT),Bz (uT)"), ["--reference", "0.5"]),  # 1000x the F
    ]
    for log, flags in cases:
        code_fit = main(["fit", str(log), *flags, "-o", str(tmp_path / "fit.json"), "-q"])
        err_fit = capsys.readouterr().err
        code = main(["live", "--replay", str(log), "--rate", "1e6", "--exit-at-end", "--no-browser", "--port", "0",
                     "-o", str(tmp_path / "cal.json"), *flags])
        out, err = capsys.readouterr()
        assert code_fit == code == 2, (err_fit, err)
        assert err == err_fit and "the page is at" not in out
    assert not list(tmp_path.glob("cal*")) and not list(tmp_path.glob("fit*"))


def test_a_unit_in_the_header_of_standard_input_is_checked_too(tmp_path):
    """A header naming its unit (x_uT,y_uT,z_uT) is the unit of the samples: taken without --units, and a --units
    that contradicts it ends the source with fit's message (no samples recorded in the wrong unit)."""
    raw = sensor(uniform_directions(300, seed=16)) / 10.0
    text = "x_uT,y_uT,z_uT\n" + "\n".join(f"{x:.4f},{y:.4f},{z:.4f}" for x, y, z in raw) + "\n"
    runs = {}
    for name, flags in (("taken", []), ("contradicted", ["--units", "nT"])):
        runs[name] = run_trimag("live", "--stdin", "--no-browser", "--port", "0", "--exit-at-end", "--json", "-o",
                                tmp_path / f"{name}.json", *flags, input=text, cwd=tmp_path)
    taken = json.loads(runs["taken"].stdout.strip().splitlines()[-1])
    assert runs["taken"].returncode == 0 and taken["units"] == "uT" and taken["n_samples"] == 300
    assert trimag.Calibration.from_file(tmp_path / "taken.json").units == "uT"
    bad = runs["contradicted"]
    assert bad.returncode == 2, bad.stderr
    assert "the column headers say uT" in bad.stderr.strip().splitlines()[-1] and "Traceback" not in bad.stderr
    assert json.loads(bad.stdout.strip().splitlines()[-1])["n_samples"] == 0
    assert not (tmp_path / "contradicted.json").exists()


def test_a_live_source_whose_fitted_field_contradicts_the_reference_gives_no_calibration(tmp_path):
    """A serial or stdin session cannot be checked before it starts: the session judges the unit on each fit, as
    ``trimag fit`` does (the correction's gain 1000x off the reference), and shows fit's message instead of a
    calibration; the save then writes the samples only (before the trust merge's post-fit unit check reached
    live, the session saved a calibration with gain 0.001)."""
    from trimag.live import LiveSession
    from trimag.live.sources import Batch

    session = LiveSession(units="uT", reference=0.5, source="test")
    session.add(Batch(sensor(uniform_directions(400, seed=17))))
    assert session.refit() is None
    status = session.status(points=False)
    assert "not in uT" in status["fit_message"], status["fit_message"]
    written = session.save(tmp_path / "cal.json")
    assert set(written) == {"samples"} and not (tmp_path / "cal.json").exists()
    # the same samples with the right reference give a calibration
    right = LiveSession(units="uT", reference=500.0, source="test")
    right.add(Batch(sensor(uniform_directions(400, seed=17))))
    assert right.refit() is not None


@pytest.mark.parametrize("failing", ["cal-samples.csv", "cal.json"])
def test_a_save_that_fails_keeps_the_recording_and_names_the_file(tmp_path, small_log, capsys, monkeypatch, failing):
    """Issue 41, item 7: a full disk at the final save said "cannot read or write: No space left on device", named
    no file and kept nothing. The failed file is named, and the samples are kept in a second, named place (the
    temporary folder) when their own file fails, or named where they were written when the calibration fails."""
    import errno
    import tempfile

    import trimag.live.session as session_module

    real = session_module.atomic_write_text

    def full_disk(path, text):
        if Path(path).name == failing:
            raise OSError(errno.ENOSPC, "No space left on device")  # as the write of a full disk raises it
        return real(path, text)

    monkeypatch.setattr(session_module, "atomic_write_text", full_disk)
    rescue = tmp_path / "rescue"
    rescue.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(rescue))
    out = tmp_path / "out"
    code = main(["live", "--replay", str(small_log), "--rate", "1e6", "--exit-at-end", "--no-browser", "--port", "0",
                 "--units", "counts", "-o", str(out / "cal.json")])
    _, err = capsys.readouterr()
    assert code == 2, err
    line = err.strip().splitlines()[-1]
    assert str(out / failing) in line and "No space left on device" in line, err
    kept = out / "cal-samples.csv" if failing == "cal.json" else next(rescue.glob("trimag-live-*samples.csv"))
    assert str(kept) in line
    assert np.array_equal(read_samples(kept).field, read_samples(small_log).field)
    assert not (out / "cal.json").exists()


def test_a_second_session_with_the_same_output_is_refused(tmp_path, small_log, capsys):
    """Issue 41, item 15: two sessions with the same ``-o`` each saved, leaving one's calibration beside the other's
    samples. The first session locks its outputs; a second one exits 2 naming them, before serving anything; the
    lock goes with the first session (no lock file left)."""
    log = write_log(tmp_path / "slow.csv", sensor(uniform_directions(5000, seed=16)))
    out = tmp_path / "out" / "cal.json"
    out.parent.mkdir()
    proc, url = start_live("--replay", str(log), "--rate", "50", "--units", "counts", "-o", str(out), cwd=tmp_path)
    try:
        for samples_out in (None, str(out.with_name("cal-samples.csv"))):  # the same calibration; the same samples
            argv = ["live", "--replay", str(small_log), "--rate", "1e6", "--exit-at-end", "--no-browser", "--port",
                    "0", "--units", "counts", "-o", str(out if samples_out is None else tmp_path / "other.json")]
            code = main(argv + ([] if samples_out is None else ["--samples-out", samples_out]))
            captured = capsys.readouterr()
            assert code == 2, captured.err
            assert len(captured.err.strip().splitlines()) == 1 and "another" in captured.err, captured.err
            assert "the page is at" not in captured.out
        deadline = time.monotonic() + 60  # the first session has what a calibration needs (30 samples) when stopped
        while get(url + "status?points=0")["n_samples"] < 60 and time.monotonic() < deadline:
            time.sleep(0.1)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    except BaseException:
        proc.kill()
        raise
    assert proc.returncode in (0, 3), err
    assert sorted(p.name for p in out.parent.iterdir()) in (["cal-samples.csv", "cal.json"], ["cal-samples.csv"])
    # the first session's lock is gone with it: a new session may write there
    assert main(["live", "--replay", str(small_log), "--rate", "1e6", "--exit-at-end", "--no-browser", "--port", "0",
                 "--units", "counts", "-o", str(out)]) == 0
