"""How every `trisplat COMMAND --help` reads: one tyro configuration shared by the commands.

- `DisallowNone`: optional values show their type (`--out PATH`), not `{None}|PATH`; leaving one out means None.
- `FlagCreatePairsOff`: a boolean option is the one flag that changes its default (`--force`, `--no-browser`),
  not a pair such as `--no-browser, --no-no-browser`.
- `HelptextFromCommentsOff`: a `# --- section` comment above a field is not that field's help text.
`NO_DEFAULT_HINT` marks a field whose help already says what its default means (no second "(default: None)").
"""
from __future__ import annotations

import tyro

CLI_STYLE = (tyro.conf.DisallowNone, tyro.conf.FlagCreatePairsOff, tyro.conf.HelptextFromCommentsOff)
NO_DEFAULT_HINT = tyro.conf.arg(help_behavior_hint=lambda default: "")
