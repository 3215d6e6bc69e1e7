"""Every command in README.md and docs/*.md runs, as written, on real files (issue 42, item 1).

Convention (details in tests/_doc_runner.py; for users at the top of docs/index.md):
- ```bash blocks: each line is a command run from the repository's root and must exit 0; `$ command` lines in
  ```console (or unmarked) blocks run too, and the lines below them must be printed (numbers within 1 % or one unit of
  the last digit shown). ```python blocks run as scripts.
- Each doc runs in order in a fresh temporary copy of the root (entries linked; ../shared/data beside it when
  present): outputs stay there. Name real files (src/trimag/data/..., tests/data/..., ../shared/data/...).
- Above a fence: <!-- doc-test: skip REASON -->, <!-- doc-test: exit=3 -->, <!-- doc-test: rtol=0.05 -->,
  <!-- doc-test: timeout=300 -->, <!-- doc-test: output --> (the block is the previous command's output),
  <!-- doc-test: expect TEXT -->, <!-- doc-test: file=NAME -->, <!-- doc-test: synopsis --> (grammar, not run).
- The run prints "doc commands: N executed, N skipped, N failing" (conftest.py; -v lists the skipped ones).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

from _doc_runner import (
    REPO_DIR,
    DocFormatError,
    Step,
    doc_files,
    match_output,
    parse_doc,
    run_doc,
)

from _helpers import SHARED_DATA

DOCS = doc_files()


@pytest.mark.parametrize("doc", DOCS, ids=[str(p.relative_to(REPO_DIR)) for p in DOCS])
def test_documented_commands_run(doc: Path, tmp_path: Path, request: pytest.FixtureRequest) -> None:
    try:
        steps = parse_doc(doc)
    except DocFormatError as exc:
        pytest.fail(str(exc), pytrace=False)
    outcomes = run_doc(steps, tmp_path, SHARED_DATA)
    counted = [o for o in outcomes if o.step.kind in ("shell", "python")]
    counts = {status: sum(o.status == status for o in counted) for status in ("passed", "skipped", "failed")}
    skipped = [f"{o.step.doc}:{o.step.line}: `{o.step.text.splitlines()[0][:90]}`: {o.message}"
               for o in counted if o.status == "skipped"]
    request.node.user_properties.append(("doc_commands", {**counts, "skipped_list": skipped}))
    if os.environ.get("TRIMAG_DOC_TIMES"):  # a file to append each command's seconds to (finding the slow ones)
        with open(os.environ["TRIMAG_DOC_TIMES"], "a", encoding="utf-8") as times:
            times.writelines(f"{o.seconds:8.2f} s  {o.step.doc}:{o.step.line}  {o.step.text.splitlines()[0][:100]}\n"
                             for o in counted if o.status != "skipped")
    failures = [o.message for o in outcomes if o.status == "failed"]
    if failures:
        pytest.fail(f"{len(failures)} of the {len(counted)} commands in {doc.relative_to(REPO_DIR)} failed "
                    f"(convention: tests/_doc_runner.py):\n" + "".join(failures), pytrace=False)
    if counted and not counts["passed"]:
        pytest.skip(f"every command of {doc.relative_to(REPO_DIR)} is skipped: " + "; ".join(skipped)[:400])


# ---------------------------------------------------------------------------------------------------------------
# the runner itself


def _steps(text: str) -> list[Step]:
    return parse_doc(REPO_DIR / "docs" / "example.md", text)


def test_parser_reads_commands_prompts_outputs_and_annotations() -> None:
    steps = _steps(
        "intro\n"
        "```bash\n"
        "trimag fit src/trimag/data/qmc5883l_noisy_raw_data.csv \\\n"
        "    --units counts   # a comment\n"
        "# a comment line\n"
        "```\n"
        "<!-- doc-test: exit=2 -->\n"
        "```console\n"
        "$ trimag fit nothing.csv\n"
        "trimag: error: ... not found\n"
        "```\n"
        "<!-- doc-test: skip needs a serial port -->\n"
        "```bash\n"
        "trimag live --serial /dev/ttyUSB0\n"
        "```\n"
        "<!-- doc-test: synopsis -->\n"
        "```\n"
        "trimag fit DATA [--units U]\n"
        "```\n"
    )
    assert [(s.line, s.kind, s.exit_code, s.skip) for s in steps] == [
        (3, "shell", 0, None), (9, "shell", 2, None), (14, "shell", 0, "needs a serial port")]
    assert steps[0].text.endswith("--units counts   # a comment")
    assert steps[1].expected == [(10, "trimag: error: ... not found")]


def test_an_unmarked_block_of_commands_is_refused_naming_its_line() -> None:
    with pytest.raises(DocFormatError, match=r"docs/example.md:2: an unmarked block of commands"):
        _steps("text\n```\ntrimag fit log.csv\n```\n")
    with pytest.raises(DocFormatError, match=r"docs/example.md:1: unknown or malformed doc-test annotation"):
        _steps("<!-- doc-test: skipp x -->\n```bash\ntrimag --version\n```\n")


def test_output_matching_compares_numbers_within_the_tolerance() -> None:
    printed = "field RMS 17.77 -> 8.593 mG\nlevel offsets: held COMPASS_DIA_X = 1.027, ... more\n"
    assert match_output([(1, "field RMS 17.77 -> 8.59 mG")], printed, 0.01) == []
    assert match_output([(1, "RMS 17.8 -> 8.6")], printed, 0.01) == []  # one unit of the last digit shown
    assert match_output([(1, "held COMPASS_DIA_X = 1.027, ...")], printed, 0.01) == []
    problems = match_output([(7, "field RMS 17.77 -> 9.593 mG")], printed, 0.01)
    assert len(problems) == 1 and "line 7" in problems[0] and "printed with other numbers" in problems[0]
    assert "no printed line" in match_output([(3, "coverage 95 %")], printed, 0.01)[0]


def test_runner_reports_exit_codes_outputs_and_shared_skips(tmp_path: Path) -> None:
    steps = _steps(
        "```console\n"
        "$ trimag --version\n"
        "trimag 999.0\n"
        "```\n"
        "<!-- doc-test: exit=2 -->\n"
        "```bash\n"
        "trimag fit no-such-file.csv\n"
        "```\n"
        "```bash\n"
        "trimag fit no-such-file.csv\n"
        "python -c 'import pathlib; pathlib.Path(\"made.txt\").write_text(\"x\")' && test -f made.txt\n"
        "trimag fit ../shared/data/none.csv\n"
        "```\n"
    )
    outcomes = run_doc(steps, tmp_path, tmp_path / "no-shared-data")
    assert [o.status for o in outcomes] == ["failed", "passed", "failed", "passed", "skipped"]
    assert "docs/example.md:2: `trimag --version` printed other than the doc shows" in outcomes[0].message
    assert "docs/example.md:10: `trimag fit no-such-file.csv` exited 2, the doc expects 0" in outcomes[2].message
    assert "../shared/data absent" in outcomes[4].message
    assert (tmp_path / "repo" / "made.txt").is_file() and not (REPO_DIR / "made.txt").exists()


def test_a_block_marked_shared_is_skipped_without_the_shared_data(tmp_path: Path) -> None:
    """A command that reads what an earlier command made from ../shared/data (README's `export broad.json`) failed
    on a clone without ../shared ("broad.json does not exist"): a block marked `shared` is skipped there."""
    steps = _steps(
        "<!-- doc-test: shared -->\n"
        "```bash\n"
        "trimag export made-from-shared.json --to json -o out.json\n"
        "```\n"
    )
    outcomes = run_doc(steps, tmp_path, tmp_path / "no-shared-data")
    assert [o.status for o in outcomes] == ["skipped"] and "../shared/data absent" in outcomes[0].message


# ---------------------------------------------------------------------------------------------------------------
# what the docs say (issue 42, item 2)


def _outside_fences(lines: list[str]) -> list[tuple[int, str]]:
    kept, fenced = [], False
    for number, line in enumerate(lines, 1):
        if line.lstrip().startswith(("```", "~~~")):
            fenced = not fenced
            continue
        if not fenced:
            kept.append((number, line))
    return kept


def _is_row(line: str) -> bool:
    stripped = line.strip()
    return stripped.startswith("|") and stripped.endswith("|") and stripped.count("|") >= 3


@pytest.mark.parametrize("doc", DOCS, ids=[str(p.relative_to(REPO_DIR)) for p in DOCS])
def test_every_table_row_belongs_to_a_table(doc: Path) -> None:
    """A row (`| ... |`) follows its table's header or another row: a paragraph between rows breaks the table
    (docs/cli.md's `fit --json` table had its `time_sync` row after a paragraph, shown as text)."""
    lines = _outside_fences(doc.read_text(encoding="utf-8").splitlines())
    stray = []
    for (_, before), (number, line), after in zip(lines, lines[1:], [*lines[2:], (0, "")], strict=False):
        is_row = _is_row(line)
        starts_table = _is_row(after[1]) and set(after[1].replace("|", "").strip()) <= set("-: ")
        if is_row and not _is_row(before) and not starts_table:
            stray.append(f"{doc.relative_to(REPO_DIR)}:{number}: {line[:80]}")
    assert not stray, "table rows outside a table:\n" + "\n".join(stray)


def test_docs_and_benchmarks_name_no_path_outside_the_repository() -> None:
    """The docs, the README and the benchmarks name files in the repository or ../shared/data, never a folder of
    this machine (/work/notes/..., a venv, a worktree under /work)."""
    machine = re.compile(r"/work/|/home/\w+|/Users/\w+")
    found = []
    for path in [*DOCS, *sorted((REPO_DIR / "benchmarks").glob("*.py"))]:
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if machine.search(line):
                found.append(f"{path.relative_to(REPO_DIR)}:{number}: {line.strip()[:100]}")
    assert not found, "paths outside the repository:\n" + "\n".join(found)


def test_tests_read_no_file_outside_the_repository() -> None:
    """A test's data live in tests/data or ../shared/data (issue 42, item 4: two tests skipped for files in a notes
    folder of this machine and never ran)."""
    found = []
    for path in sorted(REPO_DIR.joinpath("tests").rglob("*.py")):
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if re.search(r"[\"']/work/|/notes/", line) and path.name != "test_docs.py":
                found.append(f"{path.relative_to(REPO_DIR)}:{number}: {line.strip()[:100]}")
    assert not found, "tests reading files outside the repository:\n" + "\n".join(found)
