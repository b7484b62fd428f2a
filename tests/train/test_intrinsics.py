"""Focal length and principal point refined through the renderer (trisplat.train.intrinsics)."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import trimesh

from trisplat.cameras import Camera
from trisplat.render import rasterize
from trisplat.synth.orbit import intrinsics, look_at
from trisplat.train.intrinsics import FILE, Intrinsics, apply_saved, camera_groups, refined_K

W, H = 48, 40


def _scene(seed: int = 0):
    """A coloured icosphere (one colour per vertex, fully opaque), and three cameras sharing one K."""
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.6)
    # turned off the axes: no vertex in a camera's centre plane, so no pixel centre lies exactly on an edge (where
    # the two renderers may break the tie differently)
    mesh.apply_transform(trimesh.transformations.random_rotation_matrix(np.random.default_rng(seed + 7).random(3)))
    rng = np.random.default_rng(seed)
    pos = torch.tensor(mesh.vertices, dtype=torch.float32)
    faces = torch.tensor(mesh.faces, dtype=torch.int32)
    rgb = torch.tensor(rng.uniform(0.1, 0.9, (len(pos), 3)), dtype=torch.float32)
    K = intrinsics(W, H, 50.0)
    cams = [Camera(look_at((2.2 * np.cos(a), 2.2 * np.sin(a), 0.6), (0.0, 0.0, 0.0)), K, W, H)
            for a in (0.0, 1.3, 2.6)]
    return pos, faces, rgb, cams


def _render(pos, faces, rgb, cam, K, sigma=1.0):
    return rasterize(pos, faces, rgb, torch.full((len(pos),), 0.95), sigma,
                     torch.as_tensor(cam.world_to_camera, dtype=torch.float32),
                     torch.as_tensor(K, dtype=torch.float32), cam.width, cam.height,
                     background=torch.tensor([1.0, 1.0, 1.0])).rgb


def test_the_warp_leaves_the_render_unchanged_and_its_gradient_is_the_intrinsics_gradient():
    """Rendered through the warp (Numba kernels), a view is the same image, and the gradient the warp carries out of
    the kernels' position gradients equals the torch reference renderer's autograd gradient with respect to K itself
    (chain rule: dL/ds = fx dL/dfx + fy dL/dfy, dL/ddx = dL/dcx, dL/ddy = dL/dcy). (Finite differences are no
    oracle here: the soft renderer's thresholds make the loss jagged at the scale of a hundredth of a pixel.)"""
    pos, faces, rgb, cams = _scene()
    cam = cams[0]
    intr = Intrinsics(cams, 1e-3, 0.1, values=torch.tensor([[0.02, 1.37, -0.81]]))
    K = intr.K(0)
    weights = torch.rand(H, W, 3, generator=torch.Generator().manual_seed(1))
    w2c = torch.as_tensor(cam.world_to_camera, dtype=torch.float32)
    warped = intr.warp(pos, w2c, 0)
    assert torch.equal(warped, pos)
    image = _render(warped, faces, rgb, cam, K)
    torch.testing.assert_close(image, _render(pos, faces, rgb, cam, K), rtol=0, atol=0)
    (image * weights).sum().backward()
    grad = torch.cat([intr.focal.grad, intr.shift.grad], 1)[0].double()
    Kt = torch.as_tensor(K, dtype=torch.float32).clone().requires_grad_(True)
    ref = rasterize(pos, faces, rgb, torch.full((len(pos),), 0.95), 1.0, w2c, Kt, W, H,
                    background=torch.tensor([1.0, 1.0, 1.0]), backend="reference").rgb
    (ref * weights).sum().backward()
    gK = Kt.grad.double()
    want = torch.stack([K[0, 0] * gK[0, 0] + K[1, 1] * gK[1, 1], gK[0, 2], gK[1, 2]])
    torch.testing.assert_close(grad, want, rtol=2e-3, atol=2e-3 * float(want.abs().max()))
    assert bool((want.abs() > 0.5).all())  # each parameter moves the picture


def test_a_wrong_focal_length_and_principal_point_are_recovered_from_the_photos():
    """Photos rendered with the true K; the scene known; the intrinsics start 4% too long and 2.5 px off: refining
    them through the renderer brings them back.

    The window is the soft one training starts with (1.0): there the photometric error is smooth in K, and the
    result does not depend on the last bits of the arithmetic. At sharper windows Adam's path is chaotic on these 48x40
    images: at 0.3, positions moved by 1e-6 end anywhere from 0.01% to 1.4% off the true focal length (and a change of
    the kernels' summation order, gradients equal to 1e-8, took this test from 0.01% to 1.4%); at 0.6 one start in
    four ended 5% off. At 1.0, 300 steps at two learning rates and four perturbed starts all end within 0.001%."""
    pos, faces, rgb, cams = _scene()
    photos = [_render(pos, faces, rgb, c, c.K, sigma=1.0).detach() for c in cams]
    wrong = [Camera(c.world_to_camera, refined_K(c.K, (np.log(1.04), 2.5, -2.0)), W, H) for c in cams]
    intr = Intrinsics(wrong, 3e-3, 0.1)
    steps = 300
    for it in range(steps):
        i = it % len(cams)
        w2c = torch.as_tensor(wrong[i].world_to_camera, dtype=torch.float32)
        out = _render(intr.warp(pos, w2c, i), faces, rgb, wrong[i], intr.K(i), sigma=1.0)
        ((out - photos[i]) ** 2).mean().backward()
        intr.step(1.0 - 0.95 * it / steps)  # the learning rate decays, as in training
    K = intr.K(0)
    true = cams[0].K
    assert K[0, 0] == pytest.approx(true[0, 0], rel=0.002) and K[1, 1] == pytest.approx(true[1, 1], rel=0.002)
    assert abs(K[0, 2] - true[0, 2]) < 0.1 and abs(K[1, 2] - true[1, 2]) < 0.1, (K, true)
    summary = intr.summary()["groups"][0]
    assert summary["cameras"] == 3 and summary["focal_change_percent"] == pytest.approx(100 * (1 / 1.04 - 1), abs=0.2)


def test_groups_saving_and_loading_into_the_capture(tmp_path):
    """Cameras group by intrinsics and size; the run's intrinsics.json gives a reloaded capture the refined K;
    a capture that does not match it is refused, naming the file."""
    from types import SimpleNamespace

    _, _, _, cams = _scene()
    other = Camera(cams[0].world_to_camera, intrinsics(W, H, 70.0), W, H)
    cams = [cams[0], other, cams[1], cams[2]]
    assert camera_groups(cams).tolist() == [0, 1, 0, 0]
    intr = Intrinsics(cams, 1e-3, 0.1, values=torch.tensor([[0.01, 0.5, 0.0], [-0.02, 0.0, 1.0]]))
    intr.save(tmp_path)
    saved = json.loads((tmp_path / FILE).read_text())
    assert saved["group"] == [0, 1, 0, 0] and len(saved["groups"]) == 2
    data = SimpleNamespace(cameras=list(cams))
    apply_saved(tmp_path, data)
    for i in range(4):
        np.testing.assert_allclose(data.cameras[i].K, intr.K(i))
    assert data.cameras[1].K[0, 0] == pytest.approx(other.K[0, 0] * np.exp(-0.02))
    with pytest.raises(ValueError, match=f"{FILE}.*3 cameras"):
        apply_saved(tmp_path, SimpleNamespace(cameras=list(cams[:3])))
    (tmp_path / FILE).write_text("{not json")
    with pytest.raises(ValueError, match="malformed refined intrinsics"):
        apply_saved(tmp_path, SimpleNamespace(cameras=list(cams)))
    apply_saved(tmp_path / "elsewhere", data)  # no file: nothing to apply
    with pytest.raises(ValueError, match=r"\[2,3\]"):
        Intrinsics(cams, 1e-3, 0.1, values=torch.zeros(1, 3))


def test_training_refines_a_wrong_focal_length_and_the_run_keeps_it(tmp_path):
    """The tiny demo capture with its focal length written 5% too long: a run with --refine-intrinsics on moves it
    toward the true one, keeps it in intrinsics.json and metrics.json, and the run's capture reloads with it;
    resuming restores it."""
    import math

    from tests.train.test_trainer import _trainer
    from trisplat import run as layout
    from trisplat.synth import demo_mesh, write_blender_scene

    scene = write_blender_scene(tmp_path / "scene", demo_mesh(), n_train=8, n_test=2, width=40, height=40,
                                samples_per_pixel=1, n_points=0)
    true_angle = None
    for split in ("train", "test"):
        path = scene / f"transforms_{split}.json"
        meta = json.loads(path.read_text())
        true_angle = meta["camera_angle_x"]
        meta["camera_angle_x"] = 2 * math.atan(math.tan(true_angle / 2) / 1.05)  # focal length x 1.05
        path.write_text(json.dumps(meta))
    true_f = 20.0 / math.tan(true_angle / 2)
    over = dict(refine_intrinsics="on", intrinsics_from=0.0, lr_focal=3e-3, lr_principal_point=0.05, steps=60)
    tr = _trainer(scene, tmp_path / "run", **over)
    assert tr.data.cameras[0].K[0, 0] == pytest.approx(1.05 * true_f, rel=1e-6)
    tr.train()
    f = tr.data.cameras[0].K[0, 0]
    assert abs(f / true_f - 1) < 0.5 * 0.05, (f, true_f)  # at least half of the error gone
    m = json.loads((tmp_path / "run" / layout.METRICS).read_text())
    g = m["intrinsics"]["groups"][0]
    assert g["cameras"] == 10 and g["fx_after"] == pytest.approx(f) and g["focal_change_percent"] < -2.3
    data = layout.open_run(tmp_path / "run").load_scene_data()
    np.testing.assert_allclose(data.cameras[3].K, tr.data.cameras[3].K, rtol=1e-6)
    resumed = _trainer(scene, tmp_path / "run", resume=True, **over)
    np.testing.assert_allclose(resumed.intrinsics.K(0), tr.intrinsics.K(0), rtol=1e-6)
    # a rollback in the same process (its cameras already refined) restores the saved refinement on the capture's
    # own K, not on the refined one
    saved = torch.load(tmp_path / "run" / layout.CHECKPOINT, weights_only=True)
    tr._restore(saved)
    assert tr.intrinsics.base[0][0, 0] == pytest.approx(1.05 * true_f, rel=1e-9)
    want = refined_K(tr.intrinsics.base[0], saved["extra"]["intrinsics"][0])
    np.testing.assert_allclose(tr.data.cameras[5].K, want, rtol=1e-9)
    np.testing.assert_allclose(tr.intrinsics.K(5), want, rtol=1e-9)
