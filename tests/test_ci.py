"""CI runs the README's test command, with a browser for the live page's tests (issue 33, item 8)."""

from __future__ import annotations

import os
import re
import subprocess
import tomllib

import pytest

from _helpers import REPO_DIR

CI = REPO_DIR / ".ci"


def _readme_test_command() -> str:
    readme = (REPO_DIR / "README.md").read_text(encoding="utf-8")
    found = re.search(r"\(this is what CI runs\)\n(.+)\n", readme)
    assert found, "the README names the command CI runs"
    return found.group(1).strip()


def test_ci_installs_a_browser_then_runs_exactly_the_readme_test_command():
    if not (CI / "run").is_file():
        pytest.skip(".ci/ is absent (tests run away from the repository)")
    lines = [ln.strip() for ln in (CI / "run").read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    assert lines[-1] == _readme_test_command()
    install = [k for k, ln in enumerate(lines) if ".ci/install-browser" in ln]
    assert install and install[0] < len(lines) - 1, "the browser is installed before the tests"
    assert "||" in lines[install[0]], "a browser that cannot be installed does not fail the run"
    script = (CI / "install-browser").read_text()
    assert "apt-get install" in script and "chromium chromium-driver" in script
    extras = tomllib.loads((REPO_DIR / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert any(dep.startswith("selenium") for dep in extras["test"]), "selenium comes with the test extra"


def test_the_browser_install_step_passes_where_it_cannot_install(tmp_path):
    """Without apt-get (or not as root) the step says why and succeeds: the browser tests then skip."""
    if not (CI / "run").is_file():
        pytest.skip(".ci/ is absent (tests run away from the repository)")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for tool in ("bash", "id", "env"):  # the shell and its basics, no apt-get, no chromium
        for folder in ("/usr/bin", "/bin"):
            if os.path.exists(f"{folder}/{tool}"):
                (bin_dir / tool).symlink_to(f"{folder}/{tool}")
                break
    proc = subprocess.run(["bash", str(CI / "install-browser")], capture_output=True, text=True, timeout=60,
                          env={"PATH": str(bin_dir)})
    assert proc.returncode == 0, proc.stderr
    assert "apt-get" in proc.stderr and "skip" in proc.stderr


def test_the_browser_tests_skip_with_their_reason_where_no_browser_can_be_had(tmp_path, monkeypatch):
    import sys

    sys.path.insert(0, str(REPO_DIR / "tests" / "live"))
    try:
        from _live_helpers import chrome
    finally:
        sys.path.remove(str(REPO_DIR / "tests" / "live"))
    monkeypatch.setenv("PATH", str(tmp_path))  # no chromium on it
    with pytest.raises(pytest.skip.Exception, match=r"no Chromium installed.*apt-get install chromium chromium-driver"):
        chrome(tmp_path / "profile")
