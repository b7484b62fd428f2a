"""TrainConfig: every knob of the soft-to-hard optimisation, with named presets (fast, default, full, meshsplatting)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Annotated, Literal

import tyro

PAPER_STEPS = 30_000  # the Triangle Splatting+ schedule is specified for 30k iterations; we scale it by progress
# Progress at which the soup becomes one connected surface (trisplat.train.switch): the default of every preset with
# the fusion switch (the paper's ~11k/30k is for its restricted Delaunay switch, the meshsplatting preset's; the fusion
# switch comes after the densification window, which ends at 13k/30k in the paper's schedule).
# lego at 200x200, one 12-minute soup saved at 0.5 / 0.65 / 0.8, each fused and fine-tuned for the rest of the run
# (2x2 samples, first 16 test views; the soup itself ends at 26.15): 25.5 / 25.48 / 25.16 dB (docs/benchmarks.md).
SURFACE_SWITCH_AT = 0.6


@dataclass
class TrainConfig:
    """Soft-to-hard triangle splatting (Triangle Splatting+ defaults, scaled to `steps`).

    Every schedule is a function of progress p = step / steps (0 at the start, 1 at the end), so a short run keeps the
    shape of the paper's 30k-step schedule: settings of when something happens (`*_from`, `*_until`, `*_at`, ...) and
    how often (`*_interval`, `eval_every`) are in progress 0-1. Each field's docstring is its `trisplat train --help`
    text; the `# -- section` comments are not (tyro is told not to read comments, and every field has a docstring).
    """

    steps: int = 7_000
    """Total optimisation steps; every schedule is a function of progress = step / steps (0-1). With --minutes the
    step count is re-planned from the measured step rate."""
    minutes: Annotated[float | None, tyro.conf.arg(metavar="FLOAT")] = None
    """Wall-time budget, in minutes, for the optimisation steps: the step count is planned from the step rate measured
    over the first 10 steps and re-planned every 25 steps (with a 10% margin), so the steps, with their pruning,
    densification and switch to a connected surface, end within it (a resumed run counts the time already spent).
    Not in the budget, so on top: loading (or posing) the capture, the initialisation, compiling the kernels (first
    run only, then cached), checkpoint writes, the test evaluations during training (eval_every), and after the last
    step the final pruning or surface pass, the model and mesh exports, the test renders and the scoring of the whole
    test split. None: no budget, the run takes `steps` steps."""
    seed: int = 0
    """Random seed of the initialisation, the order of the training views and the faces densification picks."""

    # -- data
    downscale: int = 1
    """Image downscale factor applied by the loader (1, 2, 4, 8)."""
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    """Background RGB the ground truth is composited over and the renderer draws behind the triangles."""
    data_format: str = "auto"
    """Capture format for the loader: auto | colmap | blender | ngp | rgbd (a folder holding several picks ngp)."""
    test_every: int = 8
    """For captures without splits, every n-th image is held out for testing."""

    # -- initialisation
    init: str = "auto"
    """'auto' | 'delaunay' (TS+) | 'soup' (MeshSplatting) | 'hull' (surface of the visual hull of the alpha
    silhouettes) | 'random' (points in the scene box). auto: soup for sparse points of an unbounded scene (content
    reaching over 1.3x farther than the cameras), delaunay for other sparse points, else hull when the training
    images have alpha, else random."""
    init_soup_planes: bool = False
    """Lay each soup triangle in the plane of its 12 nearest sparse points where they are flat (PCA), instead of at
    a random angle (TS v1's rule). On the synthetic room seen from inside: walls nearer the truth and +0.45 dB at
    3000 steps; not yet measured on a full-length real capture, so off by default (docs/benchmarks.md, issue 49)."""
    init_max_points: int = 50_000
    """Subsample the sparse points to at most this many before initialisation."""
    init_random_points: int = 10_000
    """Triangles for the hull and random initialisations (scenes without sparse points)."""
    init_random_size: float = 2.23
    """Random initialisation: triangle circumradius / RMS distance to the 3 nearest random points."""
    init_opacity: float = 0.28
    """Vertex opacity (0-1) of the initial triangles."""
    sh_degree: int = 3
    """Maximum spherical-harmonics degree of the colours (0-3); the active degree rises by one every 1/30 of the run
    (1k of the paper's 30k steps)."""

    # -- learning rates (Adam, eps 1e-15)
    lr_position: float = 1.5e-3
    """Vertex position learning rate, times the scene extent; after position_hold it decays exponentially to
    lr_position x lr_position_final_ratio at the end."""
    lr_position_final_ratio: float = 0.01
    """Position learning rate at the end / at the start of its decay (the paper's 0.01)."""
    position_hold: float = 1_000 / PAPER_STEPS
    """Progress (0-1) until which vertex positions stay frozen (learning rate 0)."""
    lr_sh_dc: float = 1.6e-3
    """Learning rate of the SH DC coefficients (the base colour)."""
    lr_sh_rest_ratio: float = 1 / 20
    """Learning rate of the higher SH bands, as a fraction of lr_sh_dc."""
    lr_opacity: float = 0.03
    """Learning rate of the vertex opacity logits."""

    # -- soft-to-hard: window sharpness sigma and opacity floor
    sigma_start: float = 1.0
    """Window sharpness sigma at the start (1: a soft tent; towards 0: hard, opaque-looking triangles); it falls
    linearly to sigma_end over the run."""
    sigma_end: float = 1e-4
    """Window sharpness sigma at the end of the run (the hard, opaque mesh)."""
    floor_start: float = 0.1
    """Opacity floor set at floor_begin: no vertex opacity falls below it (the logits are re-solved when it rises, so
    opacities do not jump)."""
    floor_end: float = 0.9999
    """Opacity floor reached at floor_full and kept to the end (nearly opaque)."""
    floor_begin: float = 5_000 / PAPER_STEPS
    """Progress (0-1) of the first opacity-floor raise (from no floor to floor_start)."""
    floor_full: float = 24_000 / PAPER_STEPS
    """Progress (0-1) at which the opacity floor, rising linearly in steps, reaches floor_end."""
    floor_interval: float = 500 / PAPER_STEPS
    """Progress (0-1) between two raises of the opacity floor."""

    # -- losses
    lambda_dssim: float = 0.2
    """Photometric loss (1 - lambda) L1 + lambda (1 - SSIM): the weight of the D-SSIM part."""
    lambda_opacity: float = 1.9e-6
    """Weight of the opacity penalty (mean vertex opacity) until opacity_penalty_until."""
    opacity_penalty_until: float = 5_000 / PAPER_STEPS
    """Progress (0-1) until which the opacity penalty applies."""
    lambda_normal: float = 5e-5
    """Weight of the normal-consistency term (rendered normals vs normals of the rendered depth) from normal_from."""
    normal_from: float = 5_000 / PAPER_STEPS
    """Progress (0-1) from which the normal-consistency term applies."""
    lambda_vertex_depth: float = 2.5e-4
    """Weight of MeshSplatting's vertex-depth term (each vertex's view depth vs the rendered depth at its pixel) from
    vertex_depth_from."""
    vertex_depth_from: float = 12_000 / PAPER_STEPS
    """Progress (0-1) from which the vertex-depth term applies."""
    vertex_depth_max_diff: float = 0.5
    """Vertex-depth term only for |vertex depth - rendered depth| below this (scene units, normalised frame)."""

    # -- per-photo colour (trisplat.train.exposure)
    exposure: Literal["auto", "on", "off"] = "off"
    """Learn an affine colour correction per training photo (exposure, white balance), applied to the render in the
    loss only; test scores and files use the uncorrected scene, and evaluation adds psnr_exposure_matched (each
    test photo with its neighbours' correction). auto: on for captures without alpha (real photos), off for object
    captures (alpha). Off by default: the corrections hold the scene in the photos' common colour, and a held-out
    photo keeps the exposure of its place in the capture; on bonsai (auto exposure drifting about +-13% along the
    capture) they cost 1.1 dB of test PSNR and 0.36 dB on mesh.glb (docs/benchmarks.md). On: a consistent colour
    across a capture whose exposure changes, and a warning naming photos whose correction no camera makes."""
    lr_exposure: float = 5e-3
    """Adam learning rate of the per-photo colour corrections."""

    # -- the camera's intrinsics (trisplat.train.intrinsics)
    refine_intrinsics: Literal["auto", "on", "off"] = "off"
    """Refine focal length and principal point through the renderer (one set per group of cameras with equal
    intrinsics: 3 numbers for a one-camera capture); evaluation, the switch, texturing and file scoring then use the
    refined K (kept in RUN/intrinsics.json). auto: on for captures without alpha (real photos). Off by default: not
    yet measured on the bench scenes (docs/benchmarks.md)."""
    lr_focal: float = 2e-5
    """Adam learning rate of the focal length's log scale (per step, times the position learning rate's decay)."""
    lr_principal_point: float = 2e-3
    """Adam learning rate of the principal point's shift, pixels (per step, times the same decay)."""
    intrinsics_from: float = 0.1
    """Progress (0-1) from which the intrinsics are refined (the first triangles are too rough to say)."""

    # -- pruning (of the soup; none after the switch to a connected surface)
    prune_from: float = 4_000 / PAPER_STEPS
    """Progress (0-1) of the first pruning event: faces whose min vertex opacity or max blending weight is at or
    below the threshold, and oversized faces, are removed (events at least one epoch apart)."""
    prune_until: float = 25_000 / PAPER_STEPS
    """Progress (0-1) from which no more pruning events happen (the final max-weight pass aside)."""
    prune_interval: float = 500 / PAPER_STEPS
    """Progress (0-1) between two pruning events."""
    prune_threshold_start: float = 0.235
    """Opacity and max-blending-weight threshold of the first pruning event."""
    prune_threshold_step: float = 0.01
    """Added to the pruning threshold every prune_interval after prune_from."""
    prune_max_screen_frac: float = 0.875
    """Faces whose projected longest edge exceeds this fraction of the image's larger side are pruned
    (TS+ uses 1400 px on ~1600 px images)."""
    prune_max_fraction: float = 0.5
    """At most this fraction of the faces is removed by one pruning event (a guard for short schedules)."""
    final_max_weight_pass: bool = True
    """After training, render all training views and drop faces whose max blending weight <= final_max_weight
    (a soup only: a connected surface gets its own clean-up pass)."""
    final_max_weight: float = 0.5
    """Max-blending-weight threshold (0-1) of the final pass."""

    # -- densification (of the soup; none after the switch to a connected surface)
    densify_from: float = 500 / PAPER_STEPS
    """Progress (0-1) of the first densification event: chosen faces are split into 4 at their edge midpoints
    (events at least one epoch apart)."""
    densify_until: float = 13_000 / PAPER_STEPS
    """Progress (0-1) from which densification stops."""
    densify_interval: float = 500 / PAPER_STEPS
    """Progress (0-1) between two densification events."""
    densify_growth: float = 1.23
    """Each densification event grows the vertex count towards min(max_vertices, this x the current count), splitting
    faces sampled by their max blending weight."""
    densify_largest: int = 100
    """Besides the sampled faces, this many faces with the largest area are split at every densification event."""
    max_vertices: int = 300_000
    """Densification stops growing the vertex table beyond this cap."""
    min_face_px: float = 1.0
    """Faces smaller than this (longest edge, px) are never sampled for subdivision."""

    # -- anti-aliasing
    supersample_2x_from: float = 0.85
    """Progress (0-1) from which training renders 2x2 samples per pixel (4x the pixels per step; >1 disables)."""
    supersample_4x_from: float = 1.01
    """Progress (0-1) from which training renders 4x4 samples per pixel (>1 disables; 16x the pixels per step,
    costly on CPU)."""
    coarse_until: float = 0.0
    """Coarse to fine: until this progress (0-1) training renders at 1/coarse_factor of the training resolution and
    compares with the photo area-averaged to it (about 1/coarse_factor^2 of the pixels per step); 0 disables. Choose
    it below prune_from, so that pruning judges faces by full-resolution renders (a face that covers no pixel centre
    of the coarse image has a blending weight of 0 there)."""
    coarse_factor: int = 2
    """Resolution divisor of the coarse steps (2 or 4)."""
    coarse_min_px: int = 96
    """The coarse steps only when the coarse image keeps at least this many pixels on its short side (smaller
    images are cheap at full resolution)."""

    # -- MeshSplatting (soup -> connected mesh)
    output: Literal["surface", "soup"] = "surface"
    """'surface': the soup becomes ONE connected surface at `connect_at` and training fine-tunes it (the mesh a
    game or physics engine wants); 'soup': independent triangles to the end (no switch; connect_at is ignored). May
    change on --resume until the run has switched (`--resume --output soup` finishes a run whose switch failed)."""
    connect_at: Annotated[float | None, tyro.conf.arg(metavar="FLOAT|None")] = SURFACE_SWITCH_AT
    """Progress (0-1) at which the soup is replaced by a connected mesh (stage 2). None only with --output soup (a
    surface run must switch). May change on --resume until the run has switched (a later point, or an earlier one:
    then it switches at once)."""
    connect_method: Literal["fusion", "restricted_delaunay"] = "fusion"
    """'fusion': depth of the soup's renders fused into a TSDF, marching cubes, decimated (trisplat.train.switch);
    'restricted_delaunay': MeshSplatting's restricted Delaunay of the soup's vertices (thin soups only)."""
    surface_resolution: int = 512
    """Fusion grid: voxels along the longest side of the soup's box (fusion switch; lowered to at most 48M voxels
    and to about two voxels per pixel of the training images)."""
    # lego trials (docs/benchmarks.md, "connected surface"): one soup saved at the switch, fused and fine-tuned for
    # 1,500 steps, hard 2x2 PSNR on every 12th test view: ratio 4 -> 8: +0.6 dB; unseen space bounded at 0.03 ->
    # 0.01 of the box: +0.3 dB; smoothness 0.1 -> 0.03: +0.2 dB.
    surface_face_ratio: float = 8.0
    """Face budget of the surface: this many times the soup's faces at the switch (fusion switch)."""
    surface_max_faces: int = 400_000
    """Upper bound on the surface's face budget (fusion switch)."""
    # Re-switched from one soup each (docs/benchmarks.md, "The switch wore the silhouettes away"): 3 / 6 / 9 voxels,
    # model PSNR: Spot 35.13 / 36.18 / 36.69, lego 27.54 / 27.55 / 27.08; fox (real photos) 3 / 6: 25.33 / 25.20.
    surface_truncation: Annotated[float | None, tyro.conf.arg(metavar="FLOAT|None")] = None
    """Fusion switch: the TSDF's truncation distance, in voxels (None: 6 for a capture whose photos have alpha, an
    object, and 3 for real photos). The soup's depth differs a little from view to view; where two views disagree by
    more than this, the farther one votes the nearer one's surface free, which wears the outline away (Spot at 3
    voxels: 1.6% of the object's pixels lost, more than half the final error); a wider band rounds off fine
    detail."""
    surface_max_depth: float = 0.01
    """Fusion switch: space no camera saw (behind every view's surface) is solid only this far from what the views
    measured, as a fraction of the fused box's longest side; farther it is free (unseen undersides and insides get
    this thickness instead of filling the box)."""
    surface_unseen_faces: Literal["keep", "drop_enclosed", "drop"] = "drop_enclosed"
    """Fusion switch: faces of the fused surface that no training view sees. 'drop_enclosed' drops those facing the
    surface itself (an object's inside wall, joined to its outside where its underside was never seen), 'drop'
    every one, 'keep' none (trisplat.train.switch.SurfaceConfig.unseen_faces)."""
    far_field: Literal["fused", "soup"] = "fused"
    """Captures without alpha (real photos of a room, a table, a street) at the fusion switch: 'fused' fuses the
    whole scene, from the table at the centre to the floor and the walls, into ONE connected surface, on a sparse
    grid over the contracted scene (trisplat.mesh.contraction: voxels grow with the distance); 'soup' fuses only the
    inner box [-1, 1]^3 where the cameras are and keeps the soup beyond it as independent triangles behind the
    surface (a far-field layer; the default before issue 49)."""
    background_sphere: bool = True
    """Captures without alpha (real photos): at the switch, put an opaque sphere coloured from the photos behind
    everything (trisplat.scene.background), so no gap shows the flat background colour (sky, a window, what no
    photo saw twice); it is exported with the mesh as its last faces."""
    surface_opacity: float = 0.9
    """Vertex opacity the fused surface starts with (fusion switch)."""
    surface_sigma: Annotated[float | None, tyro.conf.arg(metavar="FLOAT|None")] = 0.1
    """After the switch the window sharpness is at most this, decaying geometrically to sigma_end (None: the
    linear schedule throughout). A soft window leaves a connected mesh's shared edges see-through."""
    # Spot trials of surface_smoothness, 2,000 fine-tuning steps: 0 / 0.01 / 0.03 / 0.1 / 1 gave folded edges
    # (> 90 degrees) 5.8 / 0.17 / 0.07 / 0.07 / 0.04 %, normal consistency with the true surface
    # 0.905 / 0.937 / 0.945 / 0.953 / -, PSNR 32.68 / 32.45 / 32.29 / 32.16 / 31.45 dB.
    surface_smoothness: float = 0.03
    """Weight of the normal-smoothness term after the switch (mean 1 - cos between the normals of faces sharing an
    edge): keeps the fine-tuned surface from crumpling where the photos do not say otherwise."""
    surface_refine_growth: float = 1.0
    """After the switch, at each refinement event (every densify_interval, at least one epoch apart, until
    surface_refine_until) the surface's faces grow towards this x their count (at most surface_max_faces): the faces
    whose vertices get the largest colour gradients are split in 4, conformingly (the surface stays welded).
    1 = no refinement."""
    surface_refine_until: float = 0.85
    """Progress (0-1) from which the connected surface is no longer refined."""
    surface_lr_position: float = 0.0
    """After the switch, the position learning rate starts again at this x lr_position and decays exponentially to
    the schedule's final rate at the end (0: the soup's decay goes on, by the switch about 1% of lr_position).
    For experiments: at 0.1 the synthetic room's surface scored +0.37 dB (its walls did not move), bonsai's 30-minute
    run -0.9 dB (docs/benchmarks.md, issue 49)."""
    surface_linear_light: bool = True
    """After the switch, blend the vertex colours in linear light (render.RenderOptions.linear_light), as every glTF
    viewer blends a mesh's vertex colours and texels: the fine-tuned colours are then the ones the exported files
    show. False: blend the sRGB values, as the soup does (the surface then looks smoother in the run than in a
    viewer)."""

    # -- asset export
    texture_size: int = 2048
    """Side (texels) of the base-colour texture fitted to the training photos at the end of the run (UV atlas +
    least squares, trisplat.texture) and written into mesh.glb (baseColorTexture) and mesh.obj (map_Kd); 0: no
    texture (vertex colours only)."""
    fit_colours: bool = True
    """Fit the mesh files' vertex colours to the training photos as a glTF viewer shows them (trisplat.texture.
    vertex_colours), kept unless the model's band-0 colours beat them by more than 1 dB on held-out photos;
    False: band 0 as it is."""
    export_faces: Annotated[int | None, tyro.conf.arg(metavar="INT")] = None
    """Decimate the exported mesh files (mesh.ply/obj/glb) to about this many faces before texturing (the model
    keeps its faces); None: export every face."""

    # -- renderer
    near: float = 0.01
    """Near plane (view depth, normalised scene units): faces with a vertex nearer to the camera are not drawn."""
    tile_size: int = 16
    """Screen tile edge (px) of the renderer: faces are depth-sorted per tile."""
    backend: str = "numba"
    """Renderer kernels: 'numba' (CPU), 'cuda' (numba-cuda kernels on an NVIDIA GPU; gpu extra) or 'reference'
    (dense PyTorch, slow; for tests). --device cuda turns numba into cuda."""

    # -- bookkeeping
    log_every: int = 10
    """Steps between the training records (loss, PSNR, faces, sigma) appended to RUN/history.jsonl."""
    eval_every: float = 0.25
    """Progress (0-1) between test-PSNR evaluations during training (the whole test split is scored at the end)."""
    eval_max_views: int = 8
    """Test views rendered at intermediate evaluations (all of them at the end)."""
    checkpoint_every_s: float = 120.0
    """Wall time of training (seconds) between checkpoints; one is also written at the end."""
    num_renders: int = 4
    """Test renders written to RUN/renders at the end."""
    eval_supersample: int = 2
    """Samples per pixel side when the test split is scored (final metrics, test renders, intermediate test PSNR):
    photographs (and Blender's renders) integrate light over each pixel's area, so the mesh is scored as an
    anti-aliased renderer shows it (2: 4 samples per pixel). The final metrics also record one sample per pixel
    (psnr_1spp, ...)."""

    def __post_init__(self):
        from trisplat.render.inputs import check_supersample

        check_supersample(self.eval_supersample, "eval_supersample")  # now, not when scoring after the training
        if self.coarse_factor not in (2, 4):
            raise ValueError(f"coarse_factor must be 2 or 4, got {self.coarse_factor}")
        if not 0.0 <= self.coarse_until < 1.0:
            raise ValueError(f"coarse_until must be a progress in [0, 1) (0 disables the coarse steps), got "
                             f"{self.coarse_until}")
        if self.output not in ("surface", "soup"):
            raise ValueError(f"output must be 'surface' or 'soup', got {self.output!r}")
        if self.connect_method not in ("fusion", "restricted_delaunay"):
            raise ValueError(f"connect_method must be 'fusion' or 'restricted_delaunay', got {self.connect_method!r}")
        if self.exposure not in ("auto", "on", "off"):
            raise ValueError(f"exposure must be 'auto', 'on' or 'off', got {self.exposure!r}")
        if self.connect_at is not None and not 0.0 <= self.connect_at < 1.0:
            raise ValueError(f"connect_at must be a progress in [0, 1) (the last step's progress is below 1: a switch "
                             f"at 1 never happens) or None, got {self.connect_at}")
        if self.surface_truncation is not None and not self.surface_truncation > 0:
            raise ValueError(f"surface_truncation must be > 0 voxels (or None: 6 for objects, 3 for real photos), got "
                             f"{self.surface_truncation}")
        if self.output == "surface" and self.connect_at is None:
            raise ValueError("connect_at is None but output is 'surface': a surface run must switch from the soup to "
                             f"a connected surface; give --connect-at P (progress 0-1, default {SURFACE_SWITCH_AT}) "
                             "or --output soup for a soup to the end")

    @property
    def switch_at(self) -> float | None:
        """Progress of the stage-2 switch, or None when the run stays a soup."""
        return self.connect_at if self.output == "surface" else None

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @staticmethod
    def from_dict(d: dict) -> TrainConfig:
        names = {f.name for f in dataclasses.fields(TrainConfig)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown config keys: {sorted(unknown)}")
        d = dict(d)
        if "background" in d:
            d["background"] = tuple(d["background"])
        return TrainConfig(**d)


PRESETS: dict[str, dict] = {
    # Sized for a CPU (measured on 2 cores, docs/benchmarks.md). The TS+ densification window (until 13k of 30k
    # steps) followed by ~12k steps of pruning left lego and fox at 9-11k faces; densifying until 70% of the run with
    # a 150k vertex cap ends at ~70k faces and, in 30 minutes, lifted fox from 20.95 to 23.55 dB and lego from 25.0
    # to 25.6 dB (half the steps, each dearer). Pruning more gently or not at all, and 8k instead of 3k Delaunay
    # points, scored lower in short trials. The 2x anti-aliasing phase (4x the pixels per step) is left to `full`.
    # A few minutes on a 2-core CPU: small images, modest triangle budget, SH degree 1.
    "fast": dict(steps=1_500, sh_degree=1, max_vertices=60_000, init_random_points=4_000, init_max_points=3_000,
                 supersample_2x_from=1.01, eval_every=0.5, eval_max_views=4, connect_at=SURFACE_SWITCH_AT),
    # A good CPU run (use with --minutes N): the fast preset's scene budget, full SH, a longer schedule.
    # Position learning rate decaying to 1/1000 (not the paper's 1/100) and densification until half the run (was
    # 70%): in 10-minute lego trials (docs/benchmarks.md) Adam's late position steps were noise that the hardening
    # could not absorb (final ratio 0.1: -4.6 dB; 0.01 -> 0.001: +0.3 dB), and the shorter window leaves more,
    # cheaper steps for the hardening (+0.5 dB). 30-minute bench, one sample per pixel: lego 25.33 -> 27.37 dB, but
    # fox 24.24 -> 23.13 dB (35k instead of 69k faces at the end; a scene-dependent face budget is not built yet).
    # Test PSNR every 10% of the run (8 views): the run's watch for collapses (trisplat.train.health) reads it.
    "default": dict(steps=7_000, sh_degree=3, max_vertices=150_000, densify_until=0.5, lr_position_final_ratio=1e-3,
                    init_random_points=4_000, init_max_points=3_000, supersample_2x_from=1.01,
                    connect_at=SURFACE_SWITCH_AT, eval_every=0.1),
    # The paper's schedule.
    "full": dict(steps=30_000, sh_degree=3, max_vertices=2_000_000, supersample_4x_from=0.95,
                 connect_at=SURFACE_SWITCH_AT),
    # MeshSplatting: soup initialisation, stage 2 restricted Delaunay at ~11k/30k, fine-tuning after.
    # No pruning after the switch and no final max-weight pass: both would open holes in the connected surface.
    "meshsplatting": dict(steps=7_000, init="soup", connect_at=11_000 / PAPER_STEPS, connect_method="restricted_delaunay",
                          densify_until=10_000 / PAPER_STEPS, max_vertices=300_000, final_max_weight_pass=False),
}


def make_config(preset: str = "default", **overrides) -> TrainConfig:
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of {sorted(PRESETS)}")
    values = {**PRESETS[preset], **{k: v for k, v in overrides.items() if v is not None}}
    return TrainConfig.from_dict(values)
