"""The one atomic writer never replaces what is not a regular file (issue 33, item 5).

A character device, a FIFO, a symlink or a socket given as an output is refused (exit 2, one line) and left as it
was; a regular file is replaced atomically as before.
"""

from __future__ import annotations

import json
import os
import socket
import stat
from pathlib import Path

import numpy as np
import pytest

from trimag.cli import main
from trimag.errors import TrimagInputError
from trimag.io.atomic import atomic_path, atomic_write_text

from _helpers import simulate_ellipsoid


@pytest.fixture
def log(tmp_path: Path) -> Path:
    path = tmp_path / "log.csv"
    np.savetxt(path, simulate_ellipsoid(400, noise=20.0, seed=2), delimiter=",", header="x,y,z", comments="",
               fmt="%.3f")
    return path


def _special_outputs(tmp_path: Path, suffix: str = ".json") -> dict[str, Path]:
    """A FIFO, a symlink to a regular file, a dangling symlink and a socket in ``tmp_path`` (names ending in
    ``suffix``)."""
    fifo = tmp_path / f"fifo{suffix}"
    os.mkfifo(fifo)
    target = tmp_path / "precious.txt"
    target.write_text("keep me\n", encoding="utf-8")
    link = tmp_path / f"link{suffix}"
    link.symlink_to(target)
    dangling = tmp_path / f"dangling{suffix}"
    dangling.symlink_to(tmp_path / "nowhere" / "x.json")
    sock_path = tmp_path / f"sock{suffix}"
    sock = socket.socket(socket.AF_UNIX)
    sock.bind(str(sock_path))
    sock.close()
    return {"fifo": fifo, "symlink": link, "dangling symlink": dangling, "socket": sock_path}


def _char_device(tmp_path: Path) -> Path:
    """A character device (null's numbers, 1:3) made in ``tmp_path``: never the system's /dev/null, which a writer
    with the bug (the tree before the fix, run to see these tests fail) would replace by a regular file."""
    node = tmp_path / "null.dev"
    try:
        os.mknod(node, 0o666 | stat.S_IFCHR, os.makedev(1, 3))
    except (PermissionError, OSError) as exc:
        pytest.skip(f"cannot make a character device here ({exc}); mknod needs root")
    return node


def _unchanged(paths: dict[str, Path], tmp_path: Path) -> None:
    assert paths["fifo"].is_fifo()
    assert paths["symlink"].is_symlink() and (tmp_path / "precious.txt").read_text() == "keep me\n"
    assert paths["dangling symlink"].is_symlink() and not (tmp_path / "nowhere").exists()
    assert paths["socket"].is_socket()
    assert not list(tmp_path.glob(".*.tmp"))


def test_the_writer_refuses_what_is_not_a_regular_file(tmp_path: Path) -> None:
    paths = _special_outputs(tmp_path)
    for kind, path in [*paths.items(), ("character device", _char_device(tmp_path))]:
        with pytest.raises(TrimagInputError, match="not a regular file") as info:
            atomic_write_text(path, "x")
        assert kind.split()[-1] in str(info.value).lower(), str(info.value)
    _unchanged(paths, tmp_path)
    assert (tmp_path / "null.dev").is_char_device()
    regular = tmp_path / "out.json"
    atomic_write_text(regular, "one")
    with atomic_path(regular) as tmp:
        tmp.write_text("two", encoding="utf-8")
    assert regular.read_text() == "two"


@pytest.mark.parametrize("command", ["fit", "apply", "simulate"])
def test_commands_refuse_a_special_output_before_any_work(
    command: str, log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cal = tmp_path / "cal.json"
    assert main(["fit", str(log), "-o", str(cal), "-q"]) == 0
    work = tmp_path / "outputs"
    work.mkdir()
    paths = _special_outputs(work, ".json" if command == "fit" else ".csv")
    params = tmp_path / "params.json"
    params.write_text(json.dumps({"hard_iron_x": 10.0, "hard_iron_y": 0.0, "hard_iron_z": 0.0, "w11": 1.0, "w12": 0.0,
                                  "w13": 0.0, "w21": 0.0, "w22": 1.0, "w23": 0.0, "w31": 0.0, "w32": 0.0, "w33": 1.0}),
                      encoding="utf-8")
    for kind, out in [*paths.items(), ("character device", _char_device(work))]:
        argv = {"fit": ["fit", str(log), "-o", str(out), "-q"],
                "apply": ["apply", str(cal), str(log), "-o", str(out), "-q"],
                "simulate": ["simulate", "--model", "ellipsoid", "--params", str(params), "--n", "50",
                             "-o", str(out)]}[command]
        assert main(argv) == 2, (command, kind)
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "not a regular file" in err[0], (command, kind, err)
    _unchanged(paths, work)


def test_export_and_report_refuse_a_symlink(log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cal = tmp_path / "cal.json"
    assert main(["fit", str(log), "-o", str(cal), "-q"]) == 0
    target = tmp_path / "precious.txt"
    target.write_text("keep me\n", encoding="utf-8")
    for name, argv in (("p.params", ["export", str(cal), "--to", "px4", "-o"]),
                       ("r.png", ["fit", str(log), "-q", "--report"])):
        link = tmp_path / name
        link.symlink_to(target)
        assert main([*argv, str(link)]) == 2
        assert "not a regular file" in capsys.readouterr().err
        assert link.is_symlink() and target.read_text() == "keep me\n"
