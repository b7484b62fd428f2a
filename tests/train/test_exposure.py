"""Per-photo colour corrections: applied as specified, learned from photos with known exposure and white balance,
kept in their gauge, and implausible corrections named (a photo the scene cannot show)."""
import pytest
import torch

from trisplat.train.exposure import PARAMS_PER_IMAGE, Exposure
from trisplat.train.health import RunHealth, verdict


def test_apply_is_the_identity_at_start_and_the_affine_map_after():
    e = Exposure(3, lr=0.01)
    rgb = torch.rand(4, 5, 3)
    assert torch.equal(e.apply(rgb, 1), rgb)
    p = torch.zeros(3, PARAMS_PER_IMAGE)
    p[2, :9] = torch.tensor([[0.1, 0.0, 0.2], [0.0, -0.3, 0.0], [0.05, 0.0, 0.0]]).flatten()
    p[2, 9:] = torch.tensor([0.01, -0.02, 0.03])
    e = Exposure(3, lr=0.01, values=p)
    M = torch.eye(3) + p[2, :9].reshape(3, 3)
    expect = torch.einsum("ij,hwj->hwi", M, rgb) + p[2, 9:]
    torch.testing.assert_close(e.apply(rgb, 2), expect)
    with pytest.raises(ValueError, match=r"\[3,12\]"):
        Exposure(3, lr=0.01, values=torch.zeros(2, PARAMS_PER_IMAGE))


def test_corrections_are_learned_from_photos_with_known_gains_and_stay_in_their_gauge():
    torch.manual_seed(0)
    scene = torch.rand(16, 16, 3)
    gains = torch.tensor([[0.8, 0.9, 1.1], [1.2, 1.1, 0.9], [1.0, 1.0, 1.0]])  # mean 1: the scene is the common colour
    photos = [scene * g for g in gains]
    e = Exposure(3, lr=0.01)
    losses = []
    for _ in range(600):
        loss = sum(((e.apply(scene, i) - photos[i]) ** 2).mean() for i in range(3))
        loss.backward()
        e.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 1e-3 * losses[0]
    learned = 1 + e.state()[:, [0, 4, 8]]
    torch.testing.assert_close(learned, gains, atol=0.02, rtol=0)
    torch.testing.assert_close(e.state().mean(0), torch.zeros(PARAMS_PER_IMAGE), atol=1e-6, rtol=0)  # the gauge
    assert e.misfits() == []


def test_a_correction_no_camera_makes_is_named_and_reported_as_a_warning():
    p = torch.zeros(5, PARAMS_PER_IMAGE)
    diag = torch.tensor([[0.13, 0.10, 0.03], [-1.01, -0.08, -0.57], [-0.04, -0.04, -0.55], [0.30, 0.12, 0.10],
                         [-0.10, 0.00, 0.05]])  # bonsai's gains: rows 0, 3, 4 normal; row 1 (red 0), row 2 (blue 0.45) not
    p[:, [0, 4, 8]] = diag
    e = Exposure(5, lr=0.01, values=p)
    found = e.misfits()
    assert [i for i, _, _ in found] == [1, 2]
    assert found[0][1] < 0.05 and found[1][1] == pytest.approx(0.45, abs=0.01)
    # only the training photos are judged (a test photo's correction is never learned)
    assert Exposure(5, lr=0.01, values=p, train_indices=[0, 2, 3]).misfits()[0][0] == 2
    v = verdict(RunHealth(), 25.0, 1.0, warnings=["2 training photo(s) do not fit the scene"])
    assert v["ok"] and v["warnings"] == ["2 training photo(s) do not fit the scene"]


def test_the_report_shows_problems_and_warnings(tmp_path):
    from trisplat.train.health import add_to_report

    page = tmp_path / "report.html"
    page.write_text("<html><body><h1>Run</h1><p>scores</p></body></html>")
    add_to_report(page, verdict(RunHealth(), 25.0, 0.9, warnings=["photo <b>x</b> does not fit"]))
    text = page.read_text()
    assert "not trustworthy" in text and "90.0%" in text
    assert "photo &lt;b&gt;x&lt;/b&gt; does not fit" in text  # escaped
    assert text.index("</h1>") < text.index("health-warnings") < text.index("<p>scores")
    assert "id='layers'" not in text  # no far field, no table of layers
    page.write_text("<html><body><h1>Run</h1><p>scores</p></body></html>")
    add_to_report(page, verdict(RunHealth(), 25.0, 1.0), {"surface": {"pixels": 0.316, "psnr": 23.28},
                                                          "far_field": {"pixels": 0.684, "psnr": 24.1}})
    text = page.read_text()
    assert "<td>the connected surface (its piece that shows the most)</td><td>31.6%</td><td>23.28 dB</td>" in text
    assert "<td>far-field layer (independent triangles)</td><td>68.4%</td><td>24.10 dB</td>" in text
    assert text.index("</h1>") < text.index("id='layers'") < text.index("<p>scores")


def test_one_photo_per_step_moves_only_that_photos_correction_and_learns_the_gains():
    """Training sees one photo per step. A step moves that photo's correction alone (every row then shifts by the
    same gauge amount), and corrections learned from a photo every 20 steps, against a render that is still
    changing, end close to the photos' real gains: with dense Adam the rows not seen kept moving on stale momentum
    and ended far off."""
    torch.manual_seed(0)
    n = 20
    scene = torch.rand(8, 8, 3) * 0.8 + 0.1
    gains = 1 + 0.15 * torch.randn(n, 3)
    gains = gains / gains.mean(0)  # mean 1: the scene is the common colour
    e = Exposure(n, lr=0.01)
    for step in range(4000):
        i = step % n
        render = scene + 0.02 * torch.randn_like(scene)  # the scene is being learned too: a noisy render
        ((e.apply(render, i) - scene * gains[i]) ** 2).mean().backward()
        e.step()
    before = e.state()
    ((e.apply(scene, 3) - scene * gains[3]) ** 2).mean().backward()
    e.step()
    moved = e.state() - before
    others = torch.cat([moved[:3], moved[4:]])
    torch.testing.assert_close(others, others[:1].expand_as(others), atol=1e-7, rtol=0)  # the gauge shift only
    assert (moved[3] - moved[0]).abs().max() > 1e-3
    learned = torch.stack([torch.diagonal(torch.eye(3) + e.state()[i, :9].reshape(3, 3)) for i in range(n)])
    assert (learned - gains).abs().max() < 0.03


def test_a_held_out_photo_gets_its_neighbours_correction_interpolated_in_photo_order(tmp_path):
    import json

    import numpy as np

    from trisplat.train.exposure import FILE, apply_correction, load_saved, neighbour_correction

    params = np.zeros((6, PARAMS_PER_IMAGE))
    params[1, [0, 4, 8]] = -0.2  # photo 1: gain 0.8
    params[4, [0, 4, 8]] = 0.4  # photo 4: gain 1.4
    params[4, 9:] = [0.03, 0.0, -0.03]
    train = np.array([4, 1])  # any order
    # a training photo keeps its own; photo 2 lies a third of the way from 1 to 4, photo 3 two thirds
    np.testing.assert_allclose(neighbour_correction(params, train, 1), params[1])
    np.testing.assert_allclose(neighbour_correction(params, train, 2)[[0, 4, 8]], [0.0] * 3, atol=1e-12)
    np.testing.assert_allclose(neighbour_correction(params, train, 3)[[0, 4, 8, 9, 11]], [0.2, 0.2, 0.2, 0.02, -0.02])
    # before the first and after the last training photo: the nearest one's
    np.testing.assert_allclose(neighbour_correction(params, train, 0), params[1])
    np.testing.assert_allclose(neighbour_correction(params, train, 5), params[4])
    # applied as Exposure.apply does, then clipped to what a display shows
    rgb = np.random.default_rng(0).random((4, 5, 3))
    e = Exposure(6, lr=0.01, values=torch.as_tensor(params, dtype=torch.float32))
    expect = e.apply(torch.as_tensor(rgb, dtype=torch.float32), 4).clamp(0, 1).detach().numpy()
    np.testing.assert_allclose(apply_correction(rgb, params[4]), expect, atol=1e-6)

    # saved with the run, read back; a file for another capture is refused by name
    e = Exposure(6, lr=0.01, values=torch.as_tensor(params, dtype=torch.float32), train_indices=[1, 4])
    assert load_saved(tmp_path, 6) is None
    e.save(tmp_path, [f"p{i}.jpg" for i in range(6)])
    got, tr = load_saved(tmp_path, 6)
    np.testing.assert_allclose(got, params, atol=1e-7)
    assert tr.tolist() == [1, 4]
    with pytest.raises(ValueError, match=rf"{FILE}.*6 photos.*capture has 7"):
        load_saved(tmp_path, 7)
    (tmp_path / FILE).write_text(json.dumps({"params": [[0.0] * 12] * 6}))
    with pytest.raises(ValueError, match="malformed colour corrections"):
        load_saved(tmp_path, 6)
