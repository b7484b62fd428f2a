"""Every `trisplat COMMAND --help` reads cleanly: no `--no-no-...` flags, no `{None}|TYPE` metavars, one
"(default: ...)" per option, and the top-level usage lists every benchmark suite."""
from __future__ import annotations

import re

import pytest

from trisplat.cli import COMMANDS, main


def _help(command: str, capsys, monkeypatch) -> str:
    monkeypatch.setenv("COLUMNS", "400")  # one line per option: no wrapping to confuse the checks
    with pytest.raises(SystemExit) as exc:
        main([command, "--help"])
    assert exc.value.code == 0
    return capsys.readouterr().out


# commands whose modules have not adopted trisplat.commands.style.CLI_STYLE yet (owned by other work in progress);
# strict: the test fails as soon as one of them is fixed, so the entry is removed then
NOT_YET = {"mesh-stats": "`{None}|FLOAT` metavars", "slam": "`{None}|...` metavars",
           # train keeps `{None}|FLOAT`: `--connect-at None` must stay possible; TrainConfig could set metavars
           "train": "`{None}|FLOAT` metavars of optional TrainConfig fields"}


@pytest.mark.parametrize("command", [
    pytest.param(c, marks=pytest.mark.xfail(strict=True, reason=NOT_YET[c])) if c in NOT_YET else c
    for c in COMMANDS if c != "bench"])
def test_help_has_no_double_negatives_none_metavars_or_repeated_defaults(command, capsys, monkeypatch):
    text = _help(command, capsys, monkeypatch)
    assert "--no-no-" not in text
    assert "{None}" not in text
    for line in text.splitlines():
        assert len(re.findall(r"\(default", line)) <= 1, line


def test_view_has_one_browser_flag(capsys, monkeypatch):
    text = _help("view", capsys, monkeypatch)
    assert "--no-browser" in text and "--no-no-browser" not in text


def test_top_level_usage_lists_every_benchmark_suite(capsys):
    from trisplat.commands.bench import SUITES

    main(["--help"])
    line = next(l for l in capsys.readouterr().out.splitlines() if l.strip().startswith("bench"))
    for suite in [*SUITES, "all"]:
        assert suite in line, (suite, line)
