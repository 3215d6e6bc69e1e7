"""The public surface is pinned: ``trimag.__all__`` and the ``__all__`` of every public module (a dotted path
without an underscore-prefixed part) equal ``tests/data/public_api.json``. A change of the public API shows up here
and is made deliberately: regenerate the file with ``python tests/test_public_api.py`` and review the diff.
Everything else (``trimag._core``, ``trimag.estimators._*``) is private and may change without notice."""

from __future__ import annotations

import importlib
import json
import pkgutil
import sys
from pathlib import Path

import trimag

PIN = Path(__file__).parent / "data" / "public_api.json"
#: Public modules that need an optional extra or are the command line itself.
SKIP: set[str] = set()


def public_surface() -> dict[str, list[str]]:
    surface = {"trimag": sorted(trimag.__all__)}
    for info in pkgutil.walk_packages(trimag.__path__, "trimag."):
        if any(part.startswith("_") for part in info.name.split(".")[1:]) or info.name in SKIP:
            continue
        module = importlib.import_module(info.name)
        surface[info.name] = sorted(getattr(module, "__all__", []))
    return surface


def test_public_api_is_pinned():
    pinned = json.loads(PIN.read_text(encoding="utf-8"))
    current = public_surface()
    assert sorted(current) == sorted(pinned), "public modules added or removed"
    changed = {m: (sorted(set(current[m]) - set(pinned[m])), sorted(set(pinned[m]) - set(current[m])))
               for m in current if current[m] != pinned[m]}
    assert changed == {}, f"public names (added, removed) per module: {changed}"


def test_every_public_name_exists():
    for name, names in public_surface().items():
        module = importlib.import_module(name)
        missing = [n for n in names if not hasattr(module, n)]
        assert missing == [], f"{name}.__all__ lists missing names {missing}"


def test_estimator_modules_export_only_their_estimator():
    from trimag.estimators import all_estimators

    for _, cls in all_estimators():
        module = sys.modules[cls.__module__]
        assert cls.__name__ in module.__all__
        assert len(module.__all__) <= 2, f"{module.__name__} exports {module.__all__}"


if __name__ == "__main__":
    PIN.write_text(json.dumps(public_surface(), indent=1, sort_keys=True) + "\n", encoding="utf-8")
    print(f"wrote {PIN}")
