"""Packaging: torch is a range in the package's dependencies (installing trisplat never replaces a user's torch,
e.g. a CUDA build); the exact tested version is pinned only where this project installs it (README, scripts/test.sh)."""
from __future__ import annotations

import re
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _torch_requirement() -> str:
    deps = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    found = [d for d in deps if re.match(r"torch\b", d)]
    assert len(found) == 1, found
    return found[0]


def test_torch_is_a_range_in_the_package():
    req = _torch_requirement().replace(" ", "")
    assert "==" not in req and "~=" not in req, f"pyproject.toml pins {req}: a user's torch would be replaced"
    assert re.fullmatch(r"torch>=2\.\d+(,<\d+(\.\d+)*)?", req), req


def test_readme_and_test_script_pin_the_same_exact_version_inside_the_range():
    readme = re.findall(r"pip install torch==([\d.]+)", (REPO / "README.md").read_text())
    script = re.findall(r"pip install -q torch==([\d.]+)", (REPO / "scripts" / "test.sh").read_text())
    assert readme and script and set(readme) == set(script), (readme, script)
    low = _torch_requirement().replace(" ", "").split(">=")[1].split(",")[0]
    as_tuple = lambda v: tuple(int(x) for x in v.split("."))  # noqa: E731
    assert as_tuple(readme[0]) >= as_tuple(low)
