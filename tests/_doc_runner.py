"""The documentation runner: every command in README.md and docs/*.md runs (issue 42, item 1).

The convention, for whoever writes a doc (stated for users at the top of docs/index.md):

* A fenced block marked ``bash`` (or ``sh``/``shell``) is a list of commands: each line (``\\`` continues it) runs
  and must exit 0. A ``trimag ...`` line runs as ``trimag`` would (a process forked from one that has imported trimag,
  tests/_zygote.py); any other line runs in ``bash -c`` (``python`` is this interpreter, ``trimag`` this tree's).
* A block marked ``console`` (or unmarked, ``text``) with lines starting ``$ `` shows commands with their output:
  each ``$`` line runs, and each line printed below it must appear in what the command printed (stdout or stderr; a
  line may match part of a printed line; ``...`` stands for anything, inside a line or as a line of its own; numbers
  agree within the tolerance: 1 % relative or one unit of the last digit shown, whichever is larger).
* A ``python`` block runs as a script (the blocks of one doc share their names, in order).
* Every doc's commands run in order, in a fresh temporary folder that looks like the repository's root (its
  top-level entries linked in: ``src/trimag/data/...``, ``tests/data/...``, ``benchmarks/...`` are there) with
  ``../shared/data`` beside it when the shared data are present; what the commands write stays there.
* An HTML comment directly above a fence says more (several may be stacked, or ``;``-separated in one):
  ``<!-- doc-test: skip REASON -->`` (hardware, a server, a long benchmark: skipped and listed with the reason),
  ``<!-- doc-test: exit=3 -->`` (every command of the block must end with that exit code),
  ``<!-- doc-test: rtol=0.05 -->`` (the numbers' tolerance), ``<!-- doc-test: timeout=300 -->`` (seconds per
  command; 120 by default), ``<!-- doc-test: output -->`` (an unmarked block that is the output of the doc's previous
  command: compared as above), ``<!-- doc-test: expect TEXT -->`` (the block's last command prints a line matching
  TEXT, e.g. a number the prose quotes), ``<!-- doc-test: file=NAME -->`` (the block's text is written to NAME in the
  folder, for the commands after it), ``<!-- doc-test: synopsis -->`` (an unmarked block of ``trimag`` grammar, not
  a command: the runner refuses unmarked blocks of ``trimag`` lines without it).
* A command that names ``../shared/`` is skipped, with that reason, when the shared data are absent; so is every
  command of a block marked ``<!-- doc-test: shared -->`` (it reads what an earlier command made from them).

``python -m pytest -q tests/test_docs.py`` prints the counts of executed, skipped and failing doc commands (``-v``
lists the skipped ones); a failure names the doc, the line, the command, and what differed.
"""

from __future__ import annotations

import math
import os
import re
import shlex
import subprocess
import sys
import textwrap
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

REPO_DIR = Path(__file__).resolve().parents[1]
SHELL_INFOS = {"bash", "sh", "shell"}
CONSOLE_INFOS = {"console", "", "text"}
DEFAULT_TIMEOUT_S = 120.0
DEFAULT_RTOL = 0.01
_ANNOTATION = re.compile(r"^\s*<!--\s*doc-test:\s*(.*?)\s*-->\s*$")
_FENCE = re.compile(r"^(\s*)(```+|~~~+)\s*([\w+-]*)")
_NUMBER = r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?"


def doc_files() -> list[Path]:
    """README.md and docs/*.md, the documents whose commands run."""
    return [REPO_DIR / "README.md", *sorted((REPO_DIR / "docs").glob("*.md"))]


@dataclass
class Step:
    """One thing the runner does: a command (shell, trimag or python), a file it writes, or the output it expects."""

    doc: str
    line: int  # 1-based line in the doc
    kind: str  # "shell" | "python" | "file" | "output"
    text: str
    exit_code: int = 0
    skip: str | None = None
    rtol: float = DEFAULT_RTOL
    timeout_s: float = DEFAULT_TIMEOUT_S
    expected: list[tuple[int, str]] = field(default_factory=list)  # (doc line, expected output line)
    filename: str | None = None
    shared: bool = False  # reads what an earlier command made from ../shared/data: skipped when that is absent


@dataclass
class Annotations:
    skip: str | None = None
    exit_code: int = 0
    rtol: float = DEFAULT_RTOL
    timeout_s: float = DEFAULT_TIMEOUT_S
    output: bool = False
    synopsis: bool = False
    filename: str | None = None
    shared: bool = False
    expect: list[str] = field(default_factory=list)


class DocFormatError(ValueError):
    """A doc breaks the convention (an unknown annotation, a block of trimag lines that is neither run nor marked)."""


def _parse_annotations(comments: list[tuple[int, str]], doc: str) -> Annotations:
    notes = Annotations()
    for line, body in comments:
        parts: list[str] = []
        rest = body.strip()
        while rest:  # `;` separates annotations; `skip` and `expect` take the rest of the comment as their text
            if re.match(r"(skip|expect)\b", rest):
                parts.append(rest)
                break
            part, _, rest = rest.partition(";")
            parts.append(part.strip())
            rest = rest.strip()
        for part in parts:
            key, _, value = part.partition(" ")
            if "=" in key:
                key, _, rest = part.partition("=")
                value = rest.strip()
            key, value = key.strip(), value.strip()
            try:
                if key == "skip":
                    notes.skip = value or "marked skip"
                elif key == "exit":
                    notes.exit_code = int(value)
                elif key == "rtol":
                    notes.rtol = float(value)
                elif key == "timeout":
                    notes.timeout_s = float(value)
                elif key == "output":
                    notes.output = True
                elif key == "synopsis":
                    notes.synopsis = True
                elif key == "shared":
                    notes.shared = True
                elif key == "file":
                    notes.filename = value
                elif key == "expect":
                    notes.expect.append(value.strip("\"'"))
                else:
                    raise ValueError
            except ValueError:
                raise DocFormatError(f"{doc}:{line}: unknown or malformed doc-test annotation {part!r} (tests/"
                                     "_doc_runner.py lists them: skip REASON, exit=N, rtol=X, timeout=S, output, "
                                     "expect TEXT, file=NAME, synopsis, shared)") from None
    return notes


def _logical_lines(lines: list[tuple[int, str]]) -> list[tuple[int, str]]:
    """Join ``\\``-continued lines: (first line number, joined text)."""
    joined: list[tuple[int, str]] = []
    pending: tuple[int, str] | None = None
    for number, text in lines:
        if pending is not None:
            number, text = pending[0], pending[1] + " " + text.strip()
            pending = None
        if text.rstrip().endswith("\\"):
            pending = (number, text.rstrip()[:-1].rstrip())
            continue
        joined.append((number, text))
    if pending is not None:
        joined.append(pending)
    return joined


def parse_doc(path: Path, text: str | None = None) -> list[Step]:
    """The steps of one doc, in order (see the module's docstring for the convention)."""
    doc = str(path.relative_to(REPO_DIR)) if path.is_absolute() and path.is_relative_to(REPO_DIR) else str(path)
    lines = (path.read_text(encoding="utf-8") if text is None else text).splitlines()
    steps: list[Step] = []
    comments: list[tuple[int, str]] = []
    i = 0
    while i < len(lines):
        raw = lines[i]
        note = _ANNOTATION.match(raw)
        if note:
            comments.append((i + 1, note.group(1)))
            i += 1
            continue
        fence = _FENCE.match(raw)
        if not fence:
            if raw.strip():
                comments = []
            i += 1
            continue
        indent, marker, info = fence.group(1), fence.group(2), fence.group(3).lower()
        j = i + 1
        while j < len(lines) and not lines[j].strip().startswith(marker[:3]):
            j += 1
        body = [(k + 1, lines[k][len(indent):] if lines[k].startswith(indent) else lines[k].lstrip())
                for k in range(i + 1, j)]
        notes = _parse_annotations(comments, doc)
        comments = []
        steps.extend(_block_steps(doc, i + 1, info, body, notes))
        i = j + 1
    return steps


def _block_steps(doc: str, fence_line: int, info: str, body: list[tuple[int, str]], notes: Annotations) -> list[Step]:
    common = dict(doc=doc, exit_code=notes.exit_code, skip=notes.skip, rtol=notes.rtol, timeout_s=notes.timeout_s,
                  shared=notes.shared)
    if notes.filename:
        return [Step(line=fence_line, kind="file", text="\n".join(t for _, t in body) + "\n",
                     filename=notes.filename, **common)]  # type: ignore[arg-type]
    if notes.output:
        return [Step(line=fence_line, kind="output", text="", expected=[(n, t) for n, t in body if t.strip()],
                     **common)]  # type: ignore[arg-type]
    steps: list[Step] = []
    if info in SHELL_INFOS:
        for number, text in _logical_lines(body):
            stripped = text.strip()
            if stripped and not stripped.startswith("#"):
                steps.append(Step(line=number, kind="shell", text=stripped, **common))  # type: ignore[arg-type]
    elif info == "python":
        source = "\n".join(t for _, t in body)
        steps.append(Step(line=fence_line + 1, kind="python", text=source, **common))  # type: ignore[arg-type]
    elif info in CONSOLE_INFOS:
        prompts = [(n, t) for n, t in body if t.startswith("$ ")]
        if not prompts:
            if not notes.synopsis and not notes.skip and any(
                    re.match(r"\s*(trimag|python3?) ", t) for _, t in body):
                raise DocFormatError(
                    f"{doc}:{fence_line}: an unmarked block of commands: mark it ```bash to run it, write its "
                    "commands as `$ trimag ...` lines followed by their output, or put <!-- doc-test: synopsis --> "
                    "above it if it is grammar (DATA, [--option ...]), not a command")
            return []
        current: Step | None = None
        logical = _logical_lines(body)
        for number, text in logical:
            if text.startswith("$ "):
                current = Step(line=number, kind="shell", text=text[2:].strip(), **common)  # type: ignore[arg-type]
                steps.append(current)
            elif current is not None and text.strip():
                current.expected.append((number, text))
    if notes.expect and steps:
        steps[-1].expected.extend((fence_line, e) for e in notes.expect)
    return steps


# ---------------------------------------------------------------------------------------------------------------
# output matching


def _line_pattern(expected: str) -> tuple[re.Pattern[str], list[str]]:
    """A regex for one expected line (numbers captured, ``...`` anything, runs of blanks any blanks) and its
    numbers as written."""
    parts: list[str] = []
    numbers: list[str] = []
    for piece in re.split(r"(\.\.\.|…)", expected.strip()):
        if piece in ("...", "…"):
            parts.append(".*?")
            continue
        pos = 0
        for m in re.finditer(_NUMBER, piece):
            literal = piece[pos:m.start()]
            parts.append(r"\s+".join(re.escape(w) for w in re.split(r"\s+", literal)) if literal else "")
            parts.append(f"({_NUMBER}|nan|inf|-inf)")
            numbers.append(m.group(0))
            pos = m.end()
        literal = piece[pos:]
        parts.append(r"\s+".join(re.escape(w) for w in re.split(r"\s+", literal)) if literal else "")
    return re.compile("".join(parts)), numbers


def _unit_of_last_digit(written: str) -> float:
    mantissa, _, exponent = written.lower().lstrip("+-").partition("e")
    decimals = len(mantissa.partition(".")[2])
    return 10.0 ** (-decimals + (int(exponent) if exponent else 0))


def _numbers_agree(written: str, printed: str, rtol: float) -> bool:
    try:
        a, b = float(written), float(printed)
    except ValueError:
        return False
    if math.isnan(a) or math.isnan(b):
        return math.isnan(a) and math.isnan(b)
    return abs(a - b) <= max(rtol * abs(a), _unit_of_last_digit(written) * 1.0000001)


def match_output(expected: list[tuple[int, str]], printed: str, rtol: float) -> list[str]:
    """What of ``expected`` (doc line, text) the printed text lacks: one message per line not found."""
    printed_lines = printed.splitlines()
    problems = []
    for number, text in expected:
        if text.strip() in ("...", "…", ""):
            continue
        pattern, written = _line_pattern(text)
        closest: str | None = None
        for candidate in printed_lines:
            m = pattern.search(candidate)
            if not m:
                continue
            if all(_numbers_agree(w, p, rtol) for w, p in zip(written, m.groups(), strict=True)):
                break
            closest = closest or candidate
        else:
            hint = (f"; printed with other numbers (tolerance {rtol:g} relative or one unit of the last digit "
                    f"shown): {closest.strip()!r}") if closest else "; no printed line has that text"
            problems.append(f"line {number}: expected output {text.strip()!r} not printed{hint}")
    return problems


# ---------------------------------------------------------------------------------------------------------------
# running


@dataclass
class Outcome:
    step: Step
    status: str  # "passed" | "failed" | "skipped"
    message: str = ""
    seconds: float = 0.0


def make_workdir(root: Path, shared_data: Path) -> Path:
    """``root/repo`` (returned), where every top-level entry of the repository is linked, and ``root/shared/data``
    linked to the shared data when present; ``root/bin`` holds ``trimag`` and ``python`` of this tree."""
    repo = root / "repo"
    repo.mkdir()
    for entry in REPO_DIR.iterdir():
        if entry.name not in {".git", ".venv", "__pycache__", ".pytest_cache", ".mypy_cache", ".ruff_cache"}:
            (repo / entry.name).symlink_to(entry)
    if shared_data.is_dir():
        (root / "shared").mkdir()
        (root / "shared" / "data").symlink_to(shared_data.resolve())
    bin_dir = root / "bin"
    bin_dir.mkdir()
    for name, script in (("trimag", f'exec "{sys.executable}" -m trimag "$@"\n'),
                         ("python", f'exec "{sys.executable}" "$@"\n'),
                         ("python3", f'exec "{sys.executable}" "$@"\n')):
        path = bin_dir / name
        path.write_text("#!/bin/sh\n" + script)
        path.chmod(0o755)
    return repo


def command_env(root: Path) -> dict[str, str]:
    src = str(REPO_DIR / "src")
    pythonpath = os.pathsep.join(p for p in (src, os.environ.get("PYTHONPATH", "")) if p)
    return {**os.environ, "PATH": f"{root / 'bin'}{os.pathsep}{os.environ.get('PATH', '')}",
            "PYTHONPATH": pythonpath, "MPLBACKEND": "Agg"}


_SHELL_OPERATORS = set("|&;<>()")


def _trimag_argv(text: str, cwd: Path, env: dict[str, str]) -> list[str] | None:
    """The argv of a plain ``trimag ...`` line after the shell's quoting, globbing and comments (None: not plain)."""
    try:
        lexer = shlex.shlex(text, posix=True, punctuation_chars=True)
        lexer.whitespace_split = True
        lexer.commenters = "#"
        tokens = list(lexer)
    except ValueError:
        return None
    if not tokens or tokens[0] != "trimag" or any(t and set(t) <= _SHELL_OPERATORS for t in tokens):
        return None
    if "`" in text or "$(" in text:
        return None
    expanded = subprocess.run(["bash", "-c", f"printf '%s\\0' {text[len('trimag'):]}"], capture_output=True,
                              cwd=cwd, env=env, timeout=30)
    if expanded.returncode != 0:
        return None
    return [a.decode() for a in expanded.stdout.split(b"\0")[:-1]]


#: commands the runner never runs unless the doc marks them skip: they change the machine, need the network or serve
#: until stopped (``trimag live`` without ``--exit-at-end``)
_NEVER_RUN = re.compile(r"^(sudo|pip3?|apt-get|apt|git|curl|wget|ssh)\b|-m\s+venv\b|\bpip3? install\b"
                        r"|^trimag live\b(?!.*--exit-at-end)")


def refusal(text: str) -> str | None:
    """Why the runner will not run this command unmarked (None: it runs)."""
    if _NEVER_RUN.search(text.strip()):
        return ("it installs, changes the machine, reaches the network or serves until stopped: mark it "
                "<!-- doc-test: skip REASON --> (or give `trimag live` --exit-at-end)")
    return None


def run_shell(step: Step, cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    argv = _trimag_argv(step.text, cwd, env)
    if argv is not None and hasattr(os, "fork") and not os.environ.get("TRIMAG_TEST_FRESH_PROCESS"):
        import _zygote

        try:
            return _zygote.run_forked(argv, cwd=cwd, env=env, timeout=step.timeout_s)
        except (TimeoutError, RuntimeError, OSError):
            # the zygote did not answer in time (a loaded machine): its replies may now be out of step, so it is
            # stopped (the next command starts another) and this command runs as a fresh process instead
            if _zygote._zygote is not None:
                _zygote._zygote.kill()
                _zygote._zygote.wait()
                _zygote._zygote = None
    return subprocess.run(["bash", "-c", step.text], capture_output=True, text=True, cwd=cwd, env=env,
                          timeout=step.timeout_s)


def _short(text: str, limit: int = 600) -> str:
    text = text.strip()
    return text if len(text) <= limit else text[:limit // 2] + " ... " + text[-limit // 2:]


def run_doc(steps: list[Step], root: Path, shared_data: Path) -> list[Outcome]:
    """Run one doc's steps in order in a fresh folder under ``root``."""
    cwd = make_workdir(root, shared_data)
    env = command_env(root)
    namespace: dict[str, object] = {"__name__": "__doc__"}
    outcomes: list[Outcome] = []
    last: Outcome | None = None
    last_printed = ""
    for step in steps:
        where = f"{step.doc}:{step.line}"
        if step.skip:
            outcomes.append(Outcome(step, "skipped", step.skip))
            last = None
            continue
        if ("../shared/" in step.text or step.shared) and not shared_data.is_dir():
            outcomes.append(Outcome(step, "skipped", "../shared/data absent (the larger real logs are not in the "
                                                     "repository)"))
            last = None
            continue
        if step.kind == "file":
            assert step.filename is not None
            (cwd / step.filename).write_text(step.text)
            continue
        if step.kind == "output":
            if last is None:
                outcomes.append(Outcome(step, "skipped", "the command whose output it shows was skipped"))
                continue
            problems = match_output(step.expected, last_printed, step.rtol)
            if problems:
                last.status = "failed"
                last.message += (f"{where}: the output shown below `{last.step.text}` differs from what it "
                                 f"printed:\n  " + "\n  ".join(problems) + f"\n  printed: {_short(last_printed)}\n")
            continue
        start = time.perf_counter()
        outcome = Outcome(step, "passed")
        refused = refusal(step.text) if step.kind == "shell" else None
        if refused:
            outcome.status, outcome.message = "failed", f"{where}: `{step.text}` not run: {refused}\n"
            outcomes.append(outcome)
            last = None
            continue
        if step.kind == "python":
            outcome.message = _run_python(step, cwd, namespace)
            printed = ""
        else:
            try:
                done = run_shell(step, cwd, env)
                printed = (done.stdout or "") + "\n" + (done.stderr or "")
                if done.returncode != step.exit_code:
                    outcome.message = (f"{where}: `{step.text}` exited {done.returncode}, the doc expects "
                                       f"{step.exit_code} (<!-- doc-test: exit=N --> above the fence for a "
                                       f"documented failure)\n  stderr: {_short(done.stderr or '')}\n")
            except subprocess.TimeoutExpired:
                printed = ""
                outcome.message = (f"{where}: `{step.text}` ran longer than {step.timeout_s:g} s (<!-- doc-test: "
                                   "timeout=S --> or skip REASON for a long benchmark)\n")
            problems = match_output(step.expected, printed, step.rtol)
            if problems:
                outcome.message += (f"{where}: `{step.text}` printed other than the doc shows:\n  "
                                    + "\n  ".join(problems) + f"\n  printed: {_short(printed)}\n")
            last_printed = printed
        outcome.seconds = time.perf_counter() - start
        if outcome.message:
            outcome.status = "failed"
        outcomes.append(outcome)
        last = outcome
    return outcomes


def _run_python(step: Step, cwd: Path, namespace: dict[str, object]) -> str:
    source = "\n" * (step.line - 1) + textwrap.dedent(step.text)
    old = Path.cwd()
    os.chdir(cwd)
    try:
        exec(compile(source, step.doc, "exec"), namespace)
    except BaseException as exc:
        frames = [f for f in traceback.extract_tb(exc.__traceback__) if f.filename == step.doc]
        line = frames[-1].lineno if frames else step.line
        return f"{step.doc}:{line}: the python block raised {type(exc).__name__}: {_short(str(exc), 300)}\n"
    finally:
        os.chdir(old)
    return ""
