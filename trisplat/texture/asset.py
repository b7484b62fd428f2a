"""The deliverable surface: the run's opaque mesh, optionally decimated to a face budget (level of detail), with its
base-colour texture fitted to the photos."""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np

from trisplat.io.gltf import TextureMap


@dataclass
class MeshAsset:
    """positions [V,3] (the run's normalised frame), faces [F,3], colors [V,3] sRGB (vertex colours, what PLY holds),
    texture (None: vertex colours only) and what texturing and the vertex-colour fit reported (metrics.json's
    `texture` and `vertex_colours`)."""

    positions: np.ndarray
    faces: np.ndarray
    colors: np.ndarray
    texture: TextureMap | None = None
    texture_report: dict | None = None
    colour_report: dict | None = None


def decimate(positions: np.ndarray, faces: np.ndarray, colors: np.ndarray, target_faces: int):
    """Quadric edge-collapse decimation (fast-simplification) to about `target_faces` faces; each new vertex takes
    the colour of the nearest original vertex. Returns the mesh unchanged when it already has at most that many."""
    if target_faces <= 0:
        raise ValueError(f"target_faces must be > 0, got {target_faces}")
    if len(faces) <= target_faces:
        return positions, faces, colors
    import fast_simplification
    from scipy.spatial import cKDTree

    p, f = fast_simplification.simplify(np.asarray(positions, np.float32), np.asarray(faces, np.int32),
                                        target_reduction=1.0 - target_faces / len(faces))
    _, nearest = cKDTree(positions).query(p)
    return np.asarray(p, np.float32), np.asarray(f, np.int64), np.asarray(colors)[nearest]


MIN_TEXTURE_SIZE = 64


def photo_texture_cap(data) -> int:
    """The largest useful texture side for a capture: the power of two at or above sqrt(pixels of all training
    photos), at least MIN_TEXTURE_SIZE. A texture with more texels than the photos have pixels holds nothing they
    say, and fitting it costs time (a 2048 texture for six 40x40 views took most of a test's minutes)."""
    pixels = sum(int(data.cameras[int(i)].width) * int(data.cameras[int(i)].height) for i in data.train_indices)
    side = MIN_TEXTURE_SIZE
    while side * side < pixels:
        side *= 2
    return side


def build_asset(scene, data, texture_size: int = 2048, faces: int | None = None, supersample: int = 2,
                near: float = 0.01, fit_colours: bool = True) -> MeshAsset:
    """The mesh files' content for a TriangleScene trained on `data` (SceneData): vertex colours, decimated to
    `faces` when given, textured over the training views when texture_size > 0.

    The vertex colours are fitted to the training photos as a glTF viewer shows them (fit_colours; trisplat.texture.
    vertex_colours), starting from and pulled towards the model's SH band 0; the texture is fitted with them as its
    prior. With enough training views (holdout_views) some are held out of both fits, and the file gets whichever
    scores best on them: the texture, the fitted vertex colours or the model's band-0 colours (choose_colours)."""
    from trisplat.scene.sh import sh_dc_to_rgb
    from trisplat.texture import texture_mesh
    from trisplat.texture.fit import NoViewSeesMesh
    from trisplat.texture.vertex_colours import VertexRows, fit_vertex_colors, solve_vertex_colors

    positions = scene.positions.detach().cpu().numpy()
    fc = scene.faces.detach().cpu().numpy().astype(np.int64)
    colors = sh_dc_to_rgb(scene.sh[:, 0].detach().cpu()).clamp(0, 1).numpy()
    if faces is not None:
        positions, fc, colors = decimate(positions, fc, colors, int(faces))
    asset = MeshAsset(positions=positions, faces=fc, colors=colors)
    if not len(fc) or not (texture_size or fit_colours):
        return asset
    train = [int(i) for i in data.train_indices]
    held = holdout_views(train)
    fit = [i for i in train if i not in set(held)]
    model_colors = colors
    size = min(int(texture_size), photo_texture_cap(data)) if texture_size else 0
    if fit_colours and size:  # one rasterisation of each view feeds both fits
        vrows = VertexRows(len(positions), fc, data.background)

        def fitted_colours() -> np.ndarray:  # after the shared pass, before the texture's solve (its prior)
            t = time.perf_counter()
            try:
                asset.colors, stats = solve_vertex_colors(vrows.finish(model_colors), t)
                asset.colour_report = {**{f"fit_{k}": v for k, v in asdict(stats).items()},
                                       "fit_rows": "from the texture fit's pass over the views"}
            except NoViewSeesMesh as exc:  # no fitting view sees the mesh (the texture's fit then says so too)
                asset.colour_report = {"chosen": "model", "reason": str(exc)}
            return asset.colors

        try:
            asset.texture, rep = texture_mesh(positions, fc, fitted_colours, data, size, supersample, near,
                                              indices=fit, also=(vrows,))
            asset.texture_report = rep.to_dict()
        except NoViewSeesMesh as exc:  # no fitting view sees the mesh: no texture, and why
            asset.texture_report = {"chosen": "vertex colours", "reason": str(exc)}
        fit_colours = asset.colour_report.get("chosen") != "model"
    elif fit_colours:
        views = ((data.cameras[i], np.asarray(data.load_image(i), np.float32)) for i in fit)
        try:
            asset.colors, stats = fit_vertex_colors(positions, fc, views, data.background, model_colors,
                                                    supersample, near)
            asset.colour_report = {f"fit_{k}": v for k, v in asdict(stats).items()}
        except NoViewSeesMesh as exc:  # no fitting view sees the mesh: the model's colours, and why
            asset.colour_report = {"chosen": "model", "reason": str(exc)}
            fit_colours = False
    if size and asset.texture_report is None:
        try:
            asset.texture, rep = texture_mesh(positions, fc, asset.colors, data, size, supersample, near, indices=fit)
            asset.texture_report = rep.to_dict()
        except NoViewSeesMesh as exc:
            asset.texture_report = {"chosen": "vertex colours", "reason": str(exc)}
    if held and (fit_colours or asset.texture is not None):
        choose_colours(asset, data, held, supersample, near, model_colors if fit_colours else None)
    return asset


# Texture or vertex colours: a texture fitted to the photos is not always the better file. On fox's surface it wins
# (24.29 against 23.61 dB on the test views); on bonsai's noisy 354k-face surface, whose atlas is mostly one-face
# charts and gutters, it loses (14.22 against 17.09). Every HOLDOUT_EVERY-th training view is kept out of the fit and
# the two files are compared on those views, as a glTF viewer shows them (trisplat.eval.spec_render).
HOLDOUT_EVERY = 10
HOLDOUT_MIN_VIEWS = 20  # fewer training views: all of them fit the texture, and the texture is kept


def holdout_views(train: list[int]) -> list[int]:
    """The training views held out of the texture fit to choose between texture and vertex colours."""
    if len(train) < HOLDOUT_MIN_VIEWS:
        return []
    return list(train[HOLDOUT_EVERY // 2 :: HOLDOUT_EVERY])


def file_psnr(positions: np.ndarray, faces: np.ndarray, colors: np.ndarray, texture: TextureMap | None, data,
              views: list[int], supersample: int, near: float) -> float:
    """Mean PSNR over `views` of the GLB these arrays make (normalised frame), rendered as the glTF specification
    defines it, against the photos."""
    from trisplat.eval.image_metrics import psnr
    from trisplat.eval.spec_render import mesh_asset, render_asset

    asset = mesh_asset(positions, faces, colors, texture)
    scores = []
    for i in views:
        cam = data.cameras[i]
        rgb = render_asset(asset, cam.world_to_camera, cam.K, cam.width, cam.height, data.background, supersample,
                           near)
        scores.append(psnr(rgb, np.asarray(data.load_image(i), np.float32)[..., :3]))
    return float(np.mean(scores))


# Fitted vertex colours or the model's band 0: the held-out views cannot judge this fairly. The model trained on them,
# the fit did not, so band 0 scores higher there than on views neither saw: on fox's 4 held-out views band 0 beat the
# fit by 0.40 dB where the test views gave the fit +0.38 dB. On the test views of five surfaces (the demo scene, Spot,
# lego, fox, bonsai) the fit won every time, by 0.06-0.93 dB. So the fitted colours are kept unless they lose by more
# than this on the held-out views: a fit that went wrong, not a close call.
FIT_MAX_HOLDOUT_LOSS_DB = 1.0


def choose_colours(asset: MeshAsset, data, held: list[int], supersample: int, near: float,
                   model_colors: np.ndarray | None = None) -> None:
    """Score the file's candidates on the held-out training views as a glTF viewer shows them and keep the best:
    the fitted vertex colours unless the model's band-0 colours (`model_colors`, when the vertex colours were
    fitted) beat them by more than FIT_MAX_HOLDOUT_LOSS_DB (the model trained on those views: a fair comparison
    needs more than a small win), then the texture against the vertex colours kept (a tie keeps the texture). What
    was compared and chosen goes into the reports (metrics.json's `vertex_colours` and `texture`)."""
    plain = file_psnr(asset.positions, asset.faces, asset.colors, None, data, held, supersample, near)
    if model_colors is not None:
        model = file_psnr(asset.positions, asset.faces, model_colors, None, data, held, supersample, near)
        fitted = plain >= model - FIT_MAX_HOLDOUT_LOSS_DB
        asset.colour_report = {**(asset.colour_report or {}), "holdout_views": len(held),
                               "holdout_psnr_fitted": plain, "holdout_psnr_model": model,
                               "chosen": "fitted" if fitted else "model"}
        if not fitted:
            asset.colors, plain = model_colors, model
    if asset.texture is None:
        return
    textured = file_psnr(asset.positions, asset.faces, asset.colors, asset.texture, data, held, supersample, near)
    keep = textured >= plain
    asset.texture_report = {**(asset.texture_report or {}), "holdout_views": len(held),
                            "holdout_psnr_texture": textured, "holdout_psnr_vertex_colours": plain,
                            "chosen": "texture" if keep else "vertex colours"}
    if not keep:
        asset.texture = None


def choice_message(report: dict | None) -> str | None:
    """One line for the log when the file got vertex colours instead of its texture (choose_colours), else None."""
    if not report or report.get("chosen") != "vertex colours":
        return None
    if "reason" in report:
        return f"texture: none ({report['reason']}); the mesh files keep vertex colours"
    return (f"texture: the mesh files keep vertex colours ({report['holdout_psnr_vertex_colours']:.2f} dB against "
            f"the texture's {report['holdout_psnr_texture']:.2f} dB on {report['holdout_views']} training views held "
            "out of the fit)")
