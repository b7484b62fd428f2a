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


def test_final_line_puts_the_files_score_first_and_says_when_not_to_trust_it():
    from trisplat.commands.train import final_lines

    m = {"psnr": 27.44, "file_psnr": 25.99, "ssim": 0.941, "faces": 274803, "vertices": 141758, "connected": True,
         "coverage": 0.999, "health": {"ok": True, "problems": []}}
    line = final_lines(m, 1800.0, "runs/lego")[0]
    assert line.startswith("done in 30.0 min: mesh.glb 25.99 dB as a glTF viewer shows it (the model: 27.44 dB)")
    del m["file_psnr"]  # no file scored (e.g. --output soup without a GLB): the model's score, said as such
    assert "test PSNR 27.44 dB (hard)" in final_lines(m, 60.0, "r")[0]
    m["health"] = {"ok": False, "problems": ["the mesh covers 95.0% of the test pixels (holes; below 99%)"]}
    lines = final_lines(m, 60.0, "r")
    assert "NOT trustworthy" in lines[0] and lines[1] == "  problem: " + m["health"]["problems"][0]
    m["health"] = {"ok": True, "problems": [], "warnings": ["1 training photo(s) do not fit the scene: a.jpg"]}
    lines = final_lines(m, 60.0, "r")  # a warning does not make the result untrusted, but it is said
    assert lines[0].startswith("done") and lines[1] == "  warning: 1 training photo(s) do not fit the scene: a.jpg"


def test_final_line_says_how_many_pieces_a_surface_came_out_in():
    from trisplat.commands.train import result_shape

    m = {"connected": True, "mesh": {"connected_components": 1, "largest_component_fraction": 1.0}}
    assert result_shape(m) == "one connected surface"
    m["mesh"] = {"connected_components": 7, "largest_component_fraction": 0.366}
    assert result_shape(m) == "a connected surface in 7 pieces (the largest holds 37% of the faces)"
    assert result_shape({"connected": True}) == "one connected surface"  # older metrics.json without mesh stats
