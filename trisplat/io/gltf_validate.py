"""Run the Khronos glTF validator (npm package gltf-validator, through node) on a .glb and return its report."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

# Where scripts/ci_extras.sh installs npm packages (outside the package); TRISPLAT_NODE_MODULES overrides it.
DEFAULT_NODE_MODULES = Path(__file__).resolve().parents[2] / ".cache" / "node" / "node_modules"
VALIDATOR_TIMEOUT_S = 120.0

_SCRIPT = """
const fs = require('fs');
const validator = require('gltf-validator');
validator.validateBytes(new Uint8Array(fs.readFileSync(process.argv[1])), {maxIssues: 100})
  .then(r => { process.stdout.write(JSON.stringify(r.issues)); })
  .catch(e => { process.stderr.write(String(e)); process.exit(2); });
"""


@dataclass
class GltfReport:
    """The validator's verdict: counts by severity and the messages (code, message, severity, pointer)."""

    num_errors: int
    num_warnings: int
    num_infos: int
    num_hints: int
    messages: list[dict] = field(default_factory=list)

    def errors(self) -> list[dict]:
        return [m for m in self.messages if m.get("severity") == 0]


def find_validator() -> tuple[str, Path] | None:
    """(node executable, node_modules folder holding gltf-validator), or None when either is missing."""
    node = shutil.which("node")
    if node is None:
        return None
    candidates = [Path(p) for p in os.environ.get("TRISPLAT_NODE_MODULES", "").split(os.pathsep) if p]
    candidates.append(DEFAULT_NODE_MODULES)
    for c in candidates:
        if (c / "gltf-validator" / "package.json").is_file():
            return node, c
    return None


def validate_gltf(path: str | Path) -> GltfReport:
    """Validate a .glb/.gltf file. Raises FileNotFoundError when node or gltf-validator is not installed
    (scripts/ci_extras.sh installs it into .cache/node)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    found = find_validator()
    if found is None:
        raise FileNotFoundError(
            f"node or the gltf-validator npm package is missing (looked in $TRISPLAT_NODE_MODULES and "
            f"{DEFAULT_NODE_MODULES}); run scripts/ci_extras.sh"
        )
    node, modules = found
    env = dict(os.environ, NODE_PATH=str(modules))
    proc = subprocess.run(
        [node, "-e", _SCRIPT, str(path.resolve())],
        capture_output=True,
        text=True,
        env=env,
        timeout=VALIDATOR_TIMEOUT_S,
    )
    if proc.returncode != 0:
        raise ValueError(f"{path}: glTF validator failed to run: {proc.stderr.strip()[:500]}")
    issues = json.loads(proc.stdout)
    return GltfReport(
        num_errors=int(issues["numErrors"]),
        num_warnings=int(issues["numWarnings"]),
        num_infos=int(issues["numInfos"]),
        num_hints=int(issues["numHints"]),
        messages=list(issues.get("messages", [])),
    )
