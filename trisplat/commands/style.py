"""How every `trisplat COMMAND --help` reads: one tyro configuration shared by the commands.

- `DisallowNone`: optional values show their type (`--out PATH`), not `{None}|PATH`; leaving one out means None.
- `FlagCreatePairsOff`: a boolean option is the one flag that changes its default (`--force`, `--no-browser`),
  not a pair such as `--no-browser, --no-no-browser`.
- `HelptextFromCommentsOff`: a `# --- section` comment above a field is not that field's help text.
`NO_DEFAULT_HINT` marks a field whose help already says what its default means (no second "(default: None)").
`flowing_help` makes a field docstring wrapped over several source lines one paragraph of help;
`help_description` does the same for a command's description (tyro prints that as given).
"""
from __future__ import annotations

import dataclasses
import re
import shutil
import textwrap
import types
import typing

import tyro

CLI_STYLE = (tyro.conf.DisallowNone, tyro.conf.FlagCreatePairsOff, tyro.conf.HelptextFromCommentsOff)
NO_DEFAULT_HINT = tyro.conf.arg(help_behavior_hint=lambda default: "")


def flow(text: str) -> str:
    """`text` as flowing prose: the line breaks and indentation of a wrapped docstring become single spaces (a blank
    line still separates paragraphs)."""
    return "\n\n".join(" ".join(par.split()) for par in re.split(r"\n\s*\n", text.strip()) if par.strip())


def help_description(text: str) -> str:
    """A docstring as a command's description: flowing text wrapped to the terminal's width (tyro prints the
    description as given, so a docstring's own line breaks and indentation would show)."""
    width = max(shutil.get_terminal_size().columns - 1, 40)
    return "\n\n".join(textwrap.fill(par, width) for par in flow(text).split("\n\n"))


def flowing_help(cls: type) -> type:
    """Class decorator for a command's dataclass: each field's docstring (also in nested dataclasses) becomes its help
    as flowing text.

    tyro keeps a docstring's line break wherever the next source line does not start with a letter, and its
    indentation, so a docstring wrapped over several lines showed breaks mid-sentence ("the alpha" / "silhouettes").
    The flowed text goes into the field's metadata["help"], which tyro takes before the docstring; a field with its own
    metadata help or `tyro.conf.arg(help=...)` keeps that. Idempotent; the dataclass behaves as before otherwise.
    """
    _flow_fields(cls, set())
    return cls


def _flow_fields(cls: type, seen: set) -> None:
    import docstring_parser  # tyro's own docstring reader (a tyro dependency)

    if cls in seen or not dataclasses.is_dataclass(cls):
        return
    seen.add(cls)
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):  # a subclass's docstring wins over its base's
        if dataclasses.is_dataclass(klass):
            docs.update({p.arg_name: p.description for p in docstring_parser.parse_from_object(klass).params
                         if p.description})
    try:
        hints = typing.get_type_hints(cls)
    except Exception:  # noqa: BLE001 - an unresolvable annotation only means no nested dataclasses are followed
        hints = {}
    for f in dataclasses.fields(cls):
        if f.name in docs and "help" not in f.metadata:
            f.metadata = types.MappingProxyType({**f.metadata, "help": flow(docs[f.name])})
        nested = hints.get(f.name)
        if isinstance(nested, type) and dataclasses.is_dataclass(nested):
            _flow_fields(nested, seen)
