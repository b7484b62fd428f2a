"""The train command: preset values as defaults, any config field overridable, bad input rejected clearly."""
import pytest

from trisplat.commands import train as cmd


def _parse(argv):
    import tyro

    preset = cmd._preset_in(argv)
    default = cmd.TrainArgs(data=tyro.MISSING, out=tyro.MISSING, preset=preset, config=cmd.make_config(preset))
    return tyro.cli(cmd.TrainArgs, args=argv, default=default, config=(tyro.conf.OmitArgPrefixes,))


def test_preset_defaults_and_overrides(tmp_path):
    a = _parse([str(tmp_path), "--out", str(tmp_path / "run"), "--preset", "fast"])
    assert a.config.steps == cmd.make_config("fast").steps and a.config.sh_degree == 1
    a = _parse([str(tmp_path), "--out", "r", "--preset", "fast", "--steps", "77", "--init-random-size", "1.5"])
    assert a.config.steps == 77 and a.config.init_random_size == 1.5 and a.config.sh_degree == 1
    a = _parse([str(tmp_path), "--out", "r", "--minutes", "3"])
    assert a.config.minutes == 3.0 and a.config.steps == cmd.make_config("default").steps


def test_missing_capture_is_named(tmp_path, capsys):
    from trisplat.cli import main

    rc = main(["train", str(tmp_path / "nope"), "--out", str(tmp_path / "run"), "--steps", "5", "--quiet"])
    assert rc == 1
    assert "nope" in capsys.readouterr().err


def test_resume_without_checkpoint(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothing to resume"):
        cmd.prepare_run_dir(tmp_path / "run", resume=True, force=False)
