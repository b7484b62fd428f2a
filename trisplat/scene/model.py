"""TriangleScene: the vertex table and face table being optimised (positions, SH colour, opacity, faces)."""
from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from trisplat.scene.sh import num_sh_bases, sh_dc_to_rgb, sh_degree_from_bases


@dataclass
class TriangleScene:
    """Vertices and faces, as torch tensors on one device.

    positions: float32 [V,3], world (normalised) frame.
    sh: float32 [V,K,3] SH coefficients, K = (d+1)^2, band order as 3DGS; colour = eval_sh(...) (+0.5 inside).
    opacity_logit: float32 [V]; vertex opacity = floor + (1 - floor) * sigmoid(logit).
    faces: int32 [F,3] vertex indices; counter-clockwise seen from outside = outward normal.
    opacity_floor: the current floor in [0, 1).
    linear_light: the vertex colours are blended in linear light when rendered (render.RenderOptions.linear_light):
    the connected surface of a run with surface_linear_light, rendered as a glTF viewer renders its vertex colours.
    """

    positions: torch.Tensor
    sh: torch.Tensor
    opacity_logit: torch.Tensor
    faces: torch.Tensor
    opacity_floor: float = 0.0
    linear_light: bool = False

    def __post_init__(self) -> None:
        V = self.positions.shape[0]
        if self.positions.ndim != 2 or self.positions.shape[1] != 3:
            raise ValueError(f"positions must be [V,3], got {tuple(self.positions.shape)}")
        if self.sh.ndim != 3 or self.sh.shape[0] != V or self.sh.shape[2] != 3:
            raise ValueError(f"sh must be [V,K,3] with V={V}, got {tuple(self.sh.shape)}")
        sh_degree_from_bases(self.sh.shape[1])
        if self.opacity_logit.shape != (V,):
            raise ValueError(f"opacity_logit must be [V]={V}, got {tuple(self.opacity_logit.shape)}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise ValueError(f"faces must be [F,3], got {tuple(self.faces.shape)}")

    @property
    def num_vertices(self) -> int:
        return int(self.positions.shape[0])

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_bases(self.sh.shape[1])

    def opacities(self) -> torch.Tensor:
        """Vertex opacities [V] in [floor, 1]."""
        return self.opacity_floor + (1.0 - self.opacity_floor) * torch.sigmoid(self.opacity_logit)

    def base_colors(self) -> torch.Tensor:
        """View-independent RGB [V,3] from the DC term (what plain-colour exports carry)."""
        return sh_dc_to_rgb(self.sh[:, 0, :]).clamp(max=1.0)

    def to(self, device: torch.device | str) -> TriangleScene:
        """The scene with its tensors on `device` (itself when they are there already)."""
        if self.positions.device == torch.device(device):
            return self
        return replace(self, positions=self.positions.to(device), sh=self.sh.to(device),
                       opacity_logit=self.opacity_logit.to(device), faces=self.faces.to(device))

    def detached(self) -> TriangleScene:
        return replace(
            self,
            positions=self.positions.detach().clone(),
            sh=self.sh.detach().clone(),
            opacity_logit=self.opacity_logit.detach().clone(),
            faces=self.faces.detach().clone(),
        )

    @staticmethod
    def from_rgb(positions, faces, rgb, opacity: float = 0.5, sh_degree: int = 0) -> TriangleScene:
        """A scene with constant vertex opacity and colour `rgb` [V,3] in the DC band (higher bands zero)."""
        from trisplat.scene.sh import rgb_to_sh_dc

        positions = torch.as_tensor(positions, dtype=torch.float32)
        V = positions.shape[0]
        sh = torch.zeros(V, num_sh_bases(sh_degree), 3)
        sh[:, 0, :] = rgb_to_sh_dc(torch.as_tensor(rgb, dtype=torch.float32))
        o = torch.full((V,), float(opacity)).clamp(1e-6, 1 - 1e-6)
        return TriangleScene(
            positions=positions,
            sh=sh,
            opacity_logit=torch.log(o / (1 - o)),
            faces=torch.as_tensor(faces, dtype=torch.int32),
        )
