"""Every `trisplat COMMAND --help` reads cleanly: no `--no-no-...` flags, no `{None}|TYPE` metavars, one
"(default: ...)" per option, no section comment as an option's help, docstrings as flowing text, and the top-level
usage lists every benchmark suite."""
from __future__ import annotations

import dataclasses
import importlib
import re
import typing

import docstring_parser
import pytest
import tyro

from trisplat.cli import COMMANDS, main


def _help(command: str, capsys, monkeypatch) -> str:
    # one column of option boxes (tyro sets boxes side by side from 130 columns), wide enough that few helps wrap
    monkeypatch.setenv("COLUMNS", "129")
    with pytest.raises(SystemExit) as exc:
        main([command, "--help"])
    assert exc.value.code == 0
    return capsys.readouterr().out


def _option_rows(text: str) -> dict[str, list[str]]:
    """Option -> the rows of its help, from a help printed by _help: `  --name METAVAR  help`, or the help on the
    next lines when the invocation is long, wrapped over as many rows as it takes."""
    out: dict[str, list[str]] = {}
    last = None
    for line in text.splitlines():
        m = re.match(r"^  (-\w|--\w[\w.-]*)(.*)$", line)
        if m:
            last, rest = m.group(1), m.group(2)
            if not re.match(r" {2,}", rest):  # a metavar first
                rest = rest.strip().split("  ", 1)[1] if "  " in rest.strip() else ""
            out[last] = [rest.strip()] if rest.strip() else []
        elif last and re.match(r"^ {4,}\S", line):
            out[last].append(line.strip())
        else:
            last = None
    return out


def _options(text: str) -> dict[str, str]:
    """Option -> its whole help text (wrapped rows joined with spaces)."""
    return {name: " ".join(rows) for name, rows in _option_rows(text).items()}


def _hard_breaks(text: str) -> list[tuple[str, str]]:
    """(row, next row) of an option's help where the row ends although the next row's first word would have fitted
    on it: a line break taken from the docstring, not made by the wrapping."""
    lines = [line.rstrip() for line in text.splitlines()]
    width = max(len(line) for line in lines if re.fullmatch(r" *-{20,}", line))  # a box's rule spans its width
    found = []
    for a, b in zip(lines, lines[1:]):
        in_help = (re.match(r"^  (-\w|--\w)", a) and "  " in a.strip()) or re.match(r"^ {4,}\S", a)
        if in_help and re.match(r"^ {4,}\S", b) and len(a) + 1 + len(b.split()[0]) < width - 2:
            found.append((a.strip(), b.strip()))
    return found


@pytest.mark.parametrize("command", [c for c in COMMANDS if c != "bench"])
def test_help_has_no_double_negatives_none_metavars_or_repeated_defaults(command, capsys, monkeypatch):
    text = _help(command, capsys, monkeypatch)
    assert "--no-no-" not in text
    assert "{None}" not in text
    options = _options(text)
    assert "-h" in options and len(options) > 1, text
    for name, help_ in options.items():
        assert len(re.findall(r"\(default", help_)) <= 1, (name, help_)


def test_view_has_one_browser_flag(capsys, monkeypatch):
    text = _help("view", capsys, monkeypatch)
    assert "--no-browser" in text and "--no-no-browser" not in text


def test_top_level_usage_lists_every_benchmark_suite(capsys):
    from trisplat.commands.bench import SUITES

    main(["--help"])
    line = next(l for l in capsys.readouterr().out.splitlines() if l.strip().startswith("bench"))
    for suite in [*SUITES, "all"]:
        assert suite in line, (suite, line)


@pytest.mark.parametrize("command", ["train", "mesh-stats", "slam"])
def test_no_option_help_is_a_section_comment_or_none_metavar(command, capsys, monkeypatch):
    text = _help(command, capsys, monkeypatch)
    assert "{None}|" not in text
    options = _options(text)
    assert len(options) >= 3, text
    for name, help_ in options.items():
        assert not help_.startswith("---"), (name, help_)


def test_every_train_option_has_its_own_help(capsys, monkeypatch):
    from trisplat.train.config import TrainConfig

    options = _options(_help("train", capsys, monkeypatch))
    for f in dataclasses.fields(TrainConfig):
        name = "--" + f.name.replace("_", "-")
        help_ = options[name]
        assert not help_.startswith("(default"), (name, help_)  # no help at all: only the default hint
        assert not help_.startswith("---"), (name, help_)
    # progress settings are said to be fractions of the run; optional values keep `None` possible, plainly shown
    assert "Progress (0-1)" in options["--prune-from"] and "Progress (0-1)" in options["--densify-until"]
    text = _help("train", capsys, monkeypatch)
    assert "--connect-at FLOAT|None" in text and "--surface-sigma FLOAT|None" in text and "--minutes FLOAT" in text


def test_train_help_says_what_minutes_covers_and_whose_defaults_are_shown(capsys, monkeypatch):
    options = _options(_help("train", capsys, monkeypatch))
    minutes = options["--minutes"]
    for on_top in ("compiling", "test evaluations", "exports", "scoring of the whole test split"):
        assert on_top in minutes, (on_top, minutes)
    assert "the defaults shown are the 'default' preset's; another preset changes them" in options["--preset"]


def test_minutes_and_connect_at_none_still_parse(tmp_path):
    from trisplat.commands import train as cmd

    default = cmd.TrainArgs(data=tyro.MISSING, out=tyro.MISSING, config=cmd.make_config("default"))
    args = tyro.cli(cmd.TrainArgs, default=default, config=(tyro.conf.OmitArgPrefixes,),
                    args=[str(tmp_path), "--out", "r", "--minutes", "2.5", "--output", "soup", "--connect-at", "None",
                          "--surface-sigma", "None"])
    assert args.config.minutes == 2.5 and args.config.connect_at is None and args.config.surface_sigma is None


def _cli_class(command: str, monkeypatch) -> type:
    """The dataclass a command hands to tyro.cli (caught before any parsing)."""
    class Caught(Exception):
        pass

    def fake_cli(cls, *args, **kwargs):
        raise Caught(cls)

    monkeypatch.setattr(tyro, "cli", fake_cli)
    with pytest.raises(Caught) as exc:
        importlib.import_module(COMMANDS[command][0]).main(["--help"])
    return exc.value.args[0]


def _wrapped_docstrings(cls: type, seen: set | None = None):
    """(class, field) of every field (nested dataclasses included) whose docstring spans several source lines."""
    seen = set() if seen is None else seen
    if cls in seen or not dataclasses.is_dataclass(cls):
        return
    seen.add(cls)
    docs = {p.arg_name: p.description for p in docstring_parser.parse_from_object(cls).params if p.description}
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if "\n" in docs.get(f.name, ""):
            yield cls, f
        yield from _wrapped_docstrings(hints.get(f.name), seen)


@pytest.mark.parametrize("command", [c for c in COMMANDS if c != "bench"])
def test_wrapped_docstrings_are_flowing_help(command, monkeypatch):
    """tyro keeps a wrapped docstring's line breaks ("the alpha" / "silhouettes"); flowing_help joins them."""
    cls = _cli_class(command, monkeypatch)
    for owner, f in _wrapped_docstrings(cls):
        help_ = f.metadata.get("help")
        assert help_ and "\n" not in help_ and "  " not in help_, (owner.__name__, f.name, help_)


@pytest.mark.parametrize("command", [c for c in COMMANDS if c != "bench"])
def test_help_rows_break_only_where_the_column_is_full(command, capsys, monkeypatch):
    """No "the alpha" / "silhouettes" rows: a help breaks where the terminal's column is full, not where its
    docstring's source line ended."""
    assert _hard_breaks(_help(command, capsys, monkeypatch)) == []


def test_hard_breaks_are_seen(capsys, monkeypatch):
    """The check above finds the breaks tyro keeps from a docstring wrapped in the source."""
    @dataclasses.dataclass
    class Wrapped:
        init: str = "auto"
        """'auto' | 'delaunay' | 'hull' (surface of the visual hull of the alpha
        silhouettes) | 'random' (points in the scene box)."""

    monkeypatch.setenv("COLUMNS", "129")
    with pytest.raises(SystemExit):
        tyro.cli(Wrapped, args=["--help"])
    breaks = _hard_breaks(capsys.readouterr().out)
    assert [b.split()[0] for _, b in breaks] == ["silhouettes)"], breaks


def test_train_description_flows(capsys, monkeypatch):
    text = _help("train", capsys, monkeypatch)
    assert "Every field of the preset's\n" not in text  # the docstring's own line break, indented, was shown
    assert "configuration can be overridden" in text and "\n    configuration" not in text


def test_flow_and_help_description(monkeypatch):
    from trisplat.commands.style import flow, help_description

    assert flow("a wrapped\n    docstring (with a\n    'quote')\n\n    second paragraph") == \
        "a wrapped docstring (with a 'quote')\n\nsecond paragraph"
    monkeypatch.setenv("COLUMNS", "61")  # the description is wrapped to the terminal, without the source's indentation
    lines = help_description("A description\n    wrapped in the source, " + "word " * 40).splitlines()
    assert len(lines) > 1 and all(len(line) <= 60 and not line.startswith(" ") for line in lines)
    assert lines[0].startswith("A description wrapped in the source,")


@pytest.mark.parametrize("command", [c for c in COMMANDS if c != "bench"])
def test_every_command_names_itself_in_its_usage(command, capsys, monkeypatch):
    """`trisplat COMMAND --help` starts with `usage: trisplat COMMAND`, not the path of the script that ran it."""
    text = _help(command, capsys, monkeypatch)
    assert text.startswith(f"usage: trisplat {command} "), text[:200]


def _suites() -> list[str]:
    from trisplat.commands.bench import LONG_SUITES, SUITES

    return [*SUITES, *LONG_SUITES]


@pytest.mark.parametrize("suite", _suites())
def test_every_bench_suite_names_itself_in_its_usage(suite, capsys, monkeypatch):
    """`trisplat bench SUITE --help` starts with `usage: trisplat bench SUITE` (bench render once printed
    `usage: .../bin/trisplat [-h]`); `trisplat bench --help` and `trisplat bench all --help` print the suites."""
    monkeypatch.setenv("COLUMNS", "129")
    with pytest.raises(SystemExit) as exc:
        main(["bench", suite, "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    assert text.startswith(f"usage: trisplat bench {suite} "), text[:200]
    for argv in (["bench", "--help"], ["bench", "all", "--help"]):
        assert main(argv) == 0
        assert capsys.readouterr().out.startswith("usage: trisplat bench {")
