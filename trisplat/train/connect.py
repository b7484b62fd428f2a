"""The switch stage of training: at `connect_at`, the trained soup becomes one connected surface (the fusion switch,
`trisplat.train.switch`, or MeshSplatting's restricted Delaunay), inside a running Trainer; a switch that fails
leaves the run a soup and says why. The Trainer calls `connect(trainer)`; this module owns what it does."""
from __future__ import annotations

import dataclasses
import sys

import numpy as np
import torch

from trisplat import run as layout
from trisplat.strategy import ops
from trisplat.train.checkpoint import atomic_torch_save, checkpoint_state, restore_trainable
from trisplat.train.config import TrainConfig

# Fusion switch on captures without alpha (photos of a scene): the thickness of unseen space behind what the views
# measured, as a fraction of the fused box's side, is at least this. With the object default (0.01: 2 cm in the
# inner box) the bonsai's soup fused into 8,400 pieces and the table with the bonsai on it, seen by 33 views, was a
# piece apart from the floor's, below 2% of it, and dropped as a floater (its test views 5-13% covered by the
# surface); at 0.025 it is part of the largest piece (29-38% covered, as much as marching cubes gave at all).
UNBOUNDED_MAX_DEPTH = 0.025
# ... and where the surface fused with the object default (3 voxels) carves away more than 10% of what the views saw
# in the box, it is fused again with a truncation of 2%, then 4%, of the box's side (8 and 16.6 voxels on bonsai's
# 414). A real capture's soup can put a surface at depths that differ between views by more than 3 voxels; each view
# that sees past it votes its space free: bonsai's table and tree were carved out of the surface (marching cubes kept
# a 15,785-face piece of them, dropped as a floater below 2% of the floor's), and the room came out without the object
# at its centre (test views 15.8 dB straight after the switch; 19.2 dB at 8 voxels, 19.1 at 16). Not for every real
# capture: on fox a larger truncation rounds detail off (22.9 dB straight after the switch at 3 voxels, 22.6 at 8,
# 21.9 at 20), so it is tried only where the first surface lost what the views saw (docs/benchmarks.md, issue 24).
UNBOUNDED_RETRY_TRUNCATIONS = (0.02, 0.04)
# ... and with the whole scene fused (far_field 'fused'), where a floor is found under the cameras, what no view saw
# between it and something solid up to this far above it (normalised units: the cameras lie within the unit sphere)
# is solid: bonsai's stool, whose foot no photo shows, stands on the floor instead of hanging in a hole of it
# (trisplat.mesh.ground)
GROUND_REACH = 0.5


OBJECT_TRUNCATION_VOXELS = 6.0  # the fusion switch's truncation for captures with alpha (TrainConfig.surface_truncation)
REAL_TRUNCATION_VOXELS = 3.0  # and for real photos


def surface_truncation(cfg: TrainConfig, has_alpha: bool) -> float:
    """The fusion switch's truncation in voxels: cfg.surface_truncation, or its capture-dependent default."""
    if cfg.surface_truncation is not None:
        return float(cfg.surface_truncation)
    return OBJECT_TRUNCATION_VOXELS if has_alpha else REAL_TRUNCATION_VOXELS


def connect(tr) -> None:
    """The stage-2 switch: the soup becomes one connected surface (cfg.connect_method), then fine-tuning. The
    soup is kept first as checkpoints/soup.pt (a checkpoint like last.pt: the switch can be redone from it).

    A switch that fails, whatever the error (a MemoryError, a Numba or trimesh error, no surface found), does not
    end hours of training: the soup is restored, the run goes on as a soup and says why (see switch_failed).
    Only KeyboardInterrupt and SystemExit (not Exceptions) pass."""
    tr.sync_cameras()  # the fusion back-projects depth through the cameras
    soup = checkpoint_state(tr.ts, tr.step, tr.clock.total, tr.generator, tr._extra())
    atomic_torch_save(soup, tr.run_dir / layout.SOUP_CHECKPOINT)
    if tr.switched_p is None:
        tr.switched_p = tr.clock.p(tr.step)
    try:
        if tr.cfg.connect_method == "fusion":
            connect_fusion(tr)
        else:
            connect_restricted_delaunay(tr)
    except Exception as exc:  # noqa: BLE001 - any error of the switch: the soup goes on (module docstring)
        switch_failed(tr, exc, soup)


def switch_failed(tr, exc: BaseException, soup: dict) -> None:
    """The switch raised `exc`: back to the soup it started from (`soup`, a checkpoint state), marked failed,
    said on stderr and in the history, and recorded at once in checkpoints/last.pt (the last good state with the
    failure noted: a resumed run replays the same soup steps and does not try the same switch again; a
    --resume with another --connect-at tries again there, --resume --output soup finishes as a soup)."""
    tr.ts = restore_trainable(soup, tr.device)
    tr.connected, tr.far_faces, tr.background_faces = False, 0, 0
    error = f"{type(exc).__name__}: {str(exc).strip() or 'no message'}"
    tr.switch_failed = True
    tr.switch_failure = {"step": tr.step, "progress": tr.clock.p(tr.step),
                         "connect_at": tr.cfg.connect_at, "error": error}
    msg = (f"the switch to a connected surface at step {tr.step} failed ({error}); training goes on with the "
           f"soup, which the run will end as. To finish otherwise, stop it (Ctrl-C) and continue with "
           f"`trisplat train DATA --out {tr.run_dir} --resume --connect-at P` (P after "
           f"{tr.clock.p(tr.step):.2f}: the switch is tried again there) or `--resume --output soup`")
    tr._log({"step": tr.step, "switch_failed": msg, "error": error})
    print(f"warning: {msg}", file=sys.stderr, flush=True)
    for key in ("switch_failed", "switch_failure", "switched_p"):
        tr._last_good["extra"][key] = getattr(tr, key)
    atomic_torch_save(tr._last_good, tr.run_dir / layout.CHECKPOINT)

def connect_restricted_delaunay(tr) -> None:
    from trisplat.mesh.connect import ConnectConfig, connect_scene

    # layered soups make the restricted Delaunay keep several faces per edge: keep the two best-shaped ones
    connected, _report = connect_scene(tr.ts.to_scene(), ConnectConfig(repair_non_manifold_edges=True))
    if len(connected.faces) == 0:
        raise RuntimeError(
            f"the switch to a connected mesh at step {tr.step} produced no faces (from {tr.ts.num_faces} "
            f"soup faces); the last good checkpoint is {tr.run_dir / layout.CHECKPOINT}. The soup may be "
            "too sparse or too transparent at connect_at: try a later --connect-at.")
    ops.set_faces(tr.ts, connected.faces)
    ops.remove_orphan_vertices(tr.ts)
    tr.connected = True
    tr.ts.linear_light = tr.cfg.surface_linear_light
    tr._log({"step": tr.step, "switch": {"method": "restricted_delaunay", "faces": tr.ts.num_faces,
                                             "vertices": tr.ts.num_vertices}})

@torch.no_grad()
def connect_fusion(tr) -> None:
    from trisplat.train.switch import (
        SurfaceConfig,
        append_scene,
        cut_pieces_last,
        far_field_mask,
        inner_box,
        soup_to_surface,
        sub_scene,
    )

    cfg, p = tr.cfg, tr.clock.p(tr.step)
    train = [int(i) for i in tr.data.train_indices]
    # voxels finer than about half a pixel of the training images add nothing but time
    side = max(max(tr.data.cameras[i].width, tr.data.cameras[i].height) for i in train)
    # a pixel the soup leaves empty is free space only where the photos have a background (alpha): in a real
    # photo every pixel sees something, so an empty pixel is a hole in the soup and says nothing (carving along
    # it could cut through what other views see; issue 26, item 5)
    masked = tr.has_alpha
    # a real capture's soup is noisier across views than an object's: its unseen shells need more thickness to
    # stay joined (UNBOUNDED_MAX_DEPTH)
    max_depth = cfg.surface_max_depth if masked else max(cfg.surface_max_depth, UNBOUNDED_MAX_DEPTH)
    scfg = SurfaceConfig(resolution=int(min(cfg.surface_resolution, max(2 * side, 32))),
                         face_ratio=cfg.surface_face_ratio, max_depth_fraction=max_depth,
                         truncation_voxels=surface_truncation(cfg, masked),
                         max_faces=cfg.surface_max_faces, opacity=cfg.surface_opacity,
                         unseen_faces=cfg.surface_unseen_faces, empty_is_free=masked,
                         retry_truncations=() if masked else UNBOUNDED_RETRY_TRUNCATIONS)
    say = (lambda m: print(f"switch: {m}", file=sys.stderr, flush=True)) if tr.show_progress else None
    if say:
        say(f"step {tr.step}: fusing the soup's depth in {len(train)} training views into one surface")
    # an object capture (alpha masks) has its content box. A real capture has none: its walls, floor and
    # distant content reach far beyond the cameras. By default (far_field 'fused') the whole scene is fused on a
    # sparse grid over the contracted scene; with far_field 'soup' the surface is fused in the inner box (the
    # unit cube of the normalised frame, where the cameras are) and the soup beyond it is kept as a far-field
    # layer behind it
    soup = tr.ts.to_scene().to("cpu")  # (the switch works on the CPU; the surface goes back to the device)
    contracted = not masked and cfg.far_field == "fused"
    box = tr.data.bounds if masked else inner_box()
    if contracted:
        from trisplat.scene.background import background_radius

        # everything inside the background sphere (its radius is beyond 99.9% of the soup's faces) is fused
        # unseen faces: the back of every wall goes (it faces nothing), the hidden sides that face something seen
        # and join seen pieces stay (a stool's foot no photo shows, between its seen sides and the floor): the room
        # and what stands in it stay one piece, and the face budget goes to what the photos see (bonsai: 79% of
        # the faces seen by a training view, against 67% keeping every unseen group that joins seen pieces)
        radius = background_radius(soup) / 1.05
        scfg = dataclasses.replace(scfg, space="contracted", outer_radius=radius, unseen_faces="drop_but_bridges",
                                   hidden_side_reach=2.0 * radius, ground_reach=GROUND_REACH)
    surface, report = soup_to_surface(
        soup, [tr.data.cameras[i] for i in train], lambda n: tr.render(train[n], p), box, scfg, say,
        images=lambda n: tr.data.load_image(train[n]))
    tr.far_faces = 0
    if not masked and not contracted:
        # pieces of the fused surface that reach the inner box's faces apart from the main one are walls and
        # furniture cut off by the box (bonsai: 5 pieces at x = +-1 and y = 1, 17-32% of the fused faces): far-field content,
        # kept behind the connected surface with the rest of the far field
        surface, tr.far_faces = cut_pieces_last(surface, box, 2.0 * report.voxel)
        if tr.far_faces:
            report.faces = surface.num_faces - tr.far_faces
            report.vertices = int(surface.faces[:report.faces].max()) + 1  # the cut pieces' vertices come after
            report.notes.append(f"{tr.far_faces} faces of the surface in pieces cut off by the inner box's "
                                "faces moved to the far field")
    far = far_field_mask(soup, box) if not masked and not contracted else np.zeros(soup.num_faces, bool)
    if far.any():
        surface = append_scene(surface, sub_scene(soup, far))
        report.notes.append(f"{int(far.sum())} soup faces outside the inner box kept as the far field")
    tr.far_faces += int(far.sum())
    if not masked and cfg.background_sphere:
        # behind it all, a background sphere coloured from the photos closes the gaps (trisplat.scene.background)
        from trisplat.scene.background import background_radius, background_sphere

        radius = background_radius(soup)
        sky = background_sphere(radius, [tr.data.cameras[i] for i in train],
                                lambda n: tr.data.load_image(train[n]), cfg.background, soup.sh_degree,
                                surface.opacity_floor)
        surface = append_scene(surface, sky)
        tr.far_faces += sky.num_faces
        tr.background_faces = sky.num_faces
        report.notes.append(f"a background sphere of {sky.num_faces} faces at radius {radius:.2f}")
    ops.replace_scene(tr.ts, surface.to(tr.device))
    tr.connected = True
    tr.ts.linear_light = tr.cfg.surface_linear_light
    tr._log({"step": tr.step, "wall_s": round(tr.wall_s, 3), "switch": report.to_dict(),
               "far_faces": tr.far_faces})
    if say:
        say(report.summary() + (f"; far-field layer: {tr.far_faces} faces" if tr.far_faces else ""))
