"""What a finished run says about itself: the test pixels its mesh covers, the scores by layer of a real capture
(trisplat.eval.layers), photos that do not fit, and the run's verdict (trisplat.train.health) with the connected
surface's statistics. The Trainer calls `run_verdict(trainer, metrics)` when it finishes."""
from __future__ import annotations

import numpy as np
import torch

@torch.no_grad()
def test_pixels(tr) -> tuple[float | None, dict | None]:
    """test_coverage, and for a real capture's connected surface the test PSNR by layer (trisplat.eval.layers:
    the piece of the surface that shows the most test pixels, its other pieces, the far-field soup, the
    background sphere; the opaque mesh at one sample per pixel centre, pooled over the test views), from one
    render of each test view."""
    from trisplat.eval.layers import LayerScores, face_layers, layer_labels, main_piece, surface_pieces
    from trisplat.render import rasterize_hard

    scene, covered, total = tr.ts.to_scene(), 0.0, 0.0
    layered = tr.connected and (tr.far_faces > 0 or not tr.has_alpha)
    shown = []  # (test view, face ids, render) for the layers
    for i in tr.data.test_indices:
        cam = tr.data.cameras[int(i)]
        out = rasterize_hard(scene.positions, scene.faces, scene.sh, torch.as_tensor(cam.world_to_camera,
                             dtype=torch.float32), torch.as_tensor(cam.K, dtype=torch.float32), cam.width,
                             cam.height, tr.background, near=tr.cfg.near, linear_light=scene.linear_light)
        hit = (out.alpha > 0.5).cpu().numpy()
        alpha = tr.data.load_alpha(int(i))
        content = np.ones_like(hit) if alpha is None else np.asarray(alpha) > 0.5
        covered += float((hit & content).sum())
        total += float(content.sum())
        if layered:
            shown.append((int(i), out.face_id.cpu().numpy().astype(np.int32), out.rgb.clamp(0, 1).cpu().numpy()))
    by_layer = None
    if layered and shown:
        piece = surface_pieces(scene.positions.numpy(), scene.faces.numpy(), scene.num_faces - tr.far_faces)
        of_face = face_layers(scene.num_faces, tr.far_faces, tr.background_faces, piece,
                              main_piece([fid for _, fid, _ in shown], piece) if len(piece) else 0)
        layers = LayerScores()
        for i, fid, rgb in shown:
            layers.add(layer_labels(fid, of_face), rgb, np.asarray(tr.data.load_image(i)))
        by_layer = layers.to_dict()
    return (covered / total if total else None), by_layer

def misfit_warnings(tr) -> list[str]:
    """Training photos whose learned colour correction no camera makes (trisplat.train.exposure.Exposure.misfits):
    the scene cannot show them, most often because their pose is wrong."""
    if tr.exposure is None:
        return []
    found = tr.exposure.misfits()
    if not found:
        return []
    names = [f"{tr.data.cameras[i].name} (gains {lo:.2f}-{hi:.2f})" for i, lo, hi in found]
    return [f"{len(found)} training photo(s) do not fit the scene: their colour correction scales a colour by "
            f"a factor no camera does, so the scene cannot show them (a wrong pose, something moving through, "
            f"another scene): {', '.join(names[:8])}{' ...' if len(names) > 8 else ''}"]

def run_verdict(tr, metrics: dict) -> dict:
    """What the run says about itself (trisplat.train.health.verdict): coverage of the test views, collapses,
    the final PSNR against the best seen; with a far field, the connected surface's own statistics."""
    from trisplat.train.health import MAX_FILE_LOSS, add_to_report, verdict

    coverage, by_layer = test_pixels(tr)
    extra = {"coverage": coverage, "switch_s": tr.switch_s, "far_field_faces": tr.far_faces,
             "psnr_by_layer": by_layer,
             "surface_pixels": None if by_layer is None else by_layer.get("surface", {}).get("pixels", 0.0),
             "background_faces": tr.background_faces,
             "exposure": None if tr.exposure is None else tr.exposure.summary(),
             "intrinsics": None if tr.intrinsics is None else tr.intrinsics.summary(),
             "history_faces_peak": tr.health.peak_faces}
    if tr.far_faces:
        from trisplat.mesh.stats import mesh_statistics
        from trisplat.train.switch import sub_scene

        scene = tr.ts.to_scene().to("cpu")
        surface = sub_scene(scene, np.arange(scene.num_faces) < scene.num_faces - tr.far_faces)
        st = mesh_statistics(surface.positions.numpy(), surface.faces.numpy()).to_dict()
        extra["mesh"] = {**metrics.get("mesh", {}), **{k: st[k] for k in metrics.get("mesh", {}) if k in st},
                         "of": "the connected surface (without the far-field layer)"}
        extra["surface_faces"] = surface.num_faces
    view_independent = None  # measured only when the file is far below the model (see health.verdict)
    if metrics.get("file_psnr") is not None and metrics.get("psnr") is not None and \
            metrics["file_psnr"] < metrics["psnr"] - MAX_FILE_LOSS:
        view_independent = tr.evaluate_hard(list(tr.data.test_indices), sh_degree=0)
        extra["psnr_sh_band_0"] = view_independent
    extra["health"] = verdict(tr.health, metrics.get("psnr"), coverage, metrics.get("file_psnr"),
                              misfit_warnings(tr), view_independent)
    if metrics.get("report"):
        add_to_report(tr.run_dir / metrics["report"], extra["health"], by_layer)
    return extra
