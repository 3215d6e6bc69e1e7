"""A process that has imported trimag and forks one child per ``trimag`` command a test runs (issue 32, item 9).

Running ``trimag fit`` as a fresh process spends ~1.6 of its ~2 s importing numpy, pandas, scipy and trimag (python
-X importtime, this 2-core machine under load); the suite ran ~250 such commands. Here one process per test worker
imports them once, then forks a child per command: the child is a process of its own (its own exit code, working
folder, environment, standard streams, signal handlers, ``atexit`` handlers run at its exit), runs
``trimag.cli.main(argv)`` as the ``trimag`` entry point does, and exits; only the interpreter start, the imports and
the first calls (a warm-up run of the usual commands) are shared. Set
``TRIMAG_TEST_FRESH_PROCESS=1`` to run every command as a fresh ``trimag`` process instead (the tests that start
the command themselves, e.g. to send it signals, always do).

Protocol on the zygote's stdin/stdout: one JSON request per line (``argv``, ``cwd``, ``env``, ``stdout``,
``stderr``: paths the child writes its streams to); the zygote answers ``{"pid": ...}`` at once, then
``{"status": ...}`` (``os.waitpid``'s status) when the child ends.
"""

from __future__ import annotations

import atexit
import json
import os
import select
import subprocess
import sys
import tempfile
from pathlib import Path

_SERVER = r"""
import json, os, signal, sys
os.environ.setdefault("MPLBACKEND", "Agg")
import numpy, pandas, scipy.linalg, scipy.optimize, scipy.signal, scipy.spatial.transform, scipy.io  # noqa: E401
import matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot
import trimag, trimag.cli, trimag.app, trimag.app.fit, trimag.app.apply, trimag.app.evaluate, trimag.io.tables
import trimag.io.stream, trimag.app.tolles_lawson, trimag.fields.reference
try:
    import pyarrow, pyarrow.csv, pyarrow.compute  # the `parquet` extra, when installed
except ImportError:
    pass
def warm_up():
    # one run of the usual commands on a small log: every module they import lazily is then loaded before the fork
    import contextlib, io, tempfile
    import numpy as np
    with tempfile.TemporaryDirectory() as tmp, contextlib.redirect_stdout(io.StringIO()), \
            contextlib.redirect_stderr(io.StringIO()):
        rng = np.random.default_rng(0)
        u = rng.normal(size=(300, 3))
        B = 48000.0 * u / np.linalg.norm(u, axis=1, keepdims=True) + [900.0, -300.0, 400.0]
        t = np.arange(300) * 0.1
        np.savetxt(f"{tmp}/log.csv", np.column_stack([t, B, t, t, t]), delimiter=",", comments="",
                   header="t,x,y,z,yaw,pitch,roll", fmt="%.3f")
        for argv in (["fit", "log.csv", "--columns", "x,y,z", "-o", "cal.json", "--report", "r.png"],
                     ["apply", "cal.json", "log.csv", "--columns", "x,y,z", "-o", "out.csv"],
                     ["evaluate", "cal.json", "log.csv", "--columns", "x,y,z", "--json"],
                     ["export", "cal.json", "--to", "ardupilot", "-o", "x.param"],
                     ["fit", "log.csv", "--model", "interference12", "--columns", "x,y,z",
                      "--attitude-columns", "yaw,pitch,roll", "--background-ned", "18000,0,45000"]):
            cwd = os.getcwd()
            os.chdir(tmp)
            try:
                trimag.cli.main(argv)
            except BaseException:
                pass
            finally:
                os.chdir(cwd)


warm_up()
requests, replies = sys.stdin, sys.stdout
for line in iter(requests.readline, ""):
    job = json.loads(line)
    replies.flush()
    sys.stderr.flush()
    pid = os.fork()
    if pid == 0:  # the child: a `trimag` process of its own
        code = 1
        try:
            os.setpgid(0, 0)
            for fd, path, flags in ((0, job.get("stdin") or os.devnull, os.O_RDONLY), (1, job["stdout"], os.O_WRONLY),
                                    (2, job["stderr"], os.O_WRONLY)):
                opened = os.open(path, flags)
                os.dup2(opened, fd)
                os.close(opened)
            sys.stdin = open(0, closefd=False)
            os.chdir(job["cwd"])
            os.environ.clear()
            os.environ.update(job["env"])
            signal.signal(signal.SIGINT, signal.default_int_handler)
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
            sys.argv = ["trimag", *job["argv"]]
            code = trimag.cli.main(job["argv"])
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        finally:  # as a normal exit: atexit handlers run, streams are flushed (without tearing down every module)
            import atexit
            atexit._run_exitfuncs()
            for stream in (sys.stdout, sys.stderr):
                try:
                    stream.flush()
                except Exception:
                    pass
            os._exit(code)
    replies.write(json.dumps({"pid": pid}) + "\n")
    replies.flush()
    _, status = os.waitpid(pid, 0)
    replies.write(json.dumps({"status": status}) + "\n")
    replies.flush()
"""

#: pyarrow's jemalloc starts a background thread (``jemalloc_bg_thd``) that wakes to purge memory, taking the
#: allocator's locks: a fork while it holds one leaves the child waiting forever (one run in four of a few test files
#: saw a forked command never answer). Without it the zygote has only idle pool threads when it forks.
_NO_BACKGROUND_THREADS = {"JE_ARROW_MALLOC_CONF": "background_thread:false"}

_zygote: subprocess.Popen[str] | None = None


def _start() -> subprocess.Popen[str]:
    global _zygote
    if _zygote is None or _zygote.poll() is not None:
        _zygote = subprocess.Popen([sys.executable, "-c", _SERVER], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                   text=True, env={**os.environ, "MPLBACKEND": "Agg", **_NO_BACKGROUND_THREADS})
        atexit.register(_zygote.kill)
    return _zygote


def _reply(proc: subprocess.Popen[str], timeout: float | None) -> dict:
    assert proc.stdout is not None
    ready, _, _ = select.select([proc.stdout], [], [], timeout)
    if not ready:
        raise TimeoutError
    line = proc.stdout.readline()
    if not line:
        raise RuntimeError("the trimag zygote process ended")
    return json.loads(line)


def run_forked(argv: list[str], *, cwd: Path | None, env: dict[str, str], timeout: float | None,
               input: str | None = None) -> subprocess.CompletedProcess[str]:
    """``trimag ARGV`` in a child forked from the zygote; as ``subprocess.run(..., capture_output=True, text=True)``
    (``subprocess.TimeoutExpired`` after ``timeout`` s, the child killed); ``input`` is the child's standard input
    (a file it reads to its end; else the null device)."""
    proc = _start()
    assert proc.stdin is not None
    with tempfile.TemporaryDirectory(prefix="trimag-zygote-") as tmp:
        out, err, given = Path(tmp) / "stdout", Path(tmp) / "stderr", Path(tmp) / "stdin"
        out.touch()
        err.touch()
        if input is not None:
            given.write_text(input)
        proc.stdin.write(json.dumps({"argv": argv, "cwd": str(cwd or Path.cwd()), "env": env,
                                     "stdout": str(out), "stderr": str(err),
                                     "stdin": str(given) if input is not None else None}) + "\n")
        proc.stdin.flush()
        pid = _reply(proc, 60)["pid"]
        try:
            status = _reply(proc, timeout)["status"]
        except TimeoutError:
            try:
                os.killpg(pid, 9)
            except ProcessLookupError:  # no group yet: the child is still between its fork and its setpgid
                try:
                    os.kill(pid, 9)
                except ProcessLookupError:  # it has ended since: its status is on its way
                    pass
            _reply(proc, 60)
            raise subprocess.TimeoutExpired(["trimag", *argv], timeout or 0.0,
                                            out.read_text(errors="replace"), err.read_text(errors="replace")) from None
        return subprocess.CompletedProcess(["trimag", *argv], os.waitstatus_to_exitcode(status),
                                           out.read_text(errors="replace"), err.read_text(errors="replace"))
