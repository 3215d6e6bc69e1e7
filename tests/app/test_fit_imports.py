"""What ``trimag fit`` of a plain table imports (issue 42 item 5: the whole command is a fixed cost around a 0.5 s
floor, and its imports are most of it)."""

from __future__ import annotations

import subprocess
import sys

from _helpers import TESTS_DIR

_CODE = """
import sys
from trimag.cli import main
code = main(["fit", sys.argv[1], "--units", "counts", "-q", "-o", sys.argv[2]])
print(code, sorted(m for m in ("scipy.spatial", "trimag.models.firmware", "trimag.app._firmware") if m in sys.modules))
"""


def test_fitting_a_table_imports_neither_scipy_spatial_nor_the_firmware_models(tmp_path) -> None:
    """A CSV without attitudes has no rotation and no autopilot: ``scipy.spatial`` (its import pulls scipy.sparse and
    the k-d tree, ~0.1 s idle) and the firmware models were imported by every fit (app._inputs, the input
    orientation record of a log's fit)."""
    data = TESTS_DIR.parent / "src" / "trimag" / "data" / "qmc5883l_noisy_raw_data.csv"
    out = subprocess.run([sys.executable, "-c", _CODE, str(data), str(tmp_path / "cal.json")], capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split()[0] == "0" and out.stdout.strip().endswith("[]"), out.stdout
