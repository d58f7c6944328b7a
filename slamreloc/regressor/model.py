"""The scene-coordinate regressor: one MLP shared by all descriptors (Bui, Tran, Lee).

Maps a local descriptor (D,) to its world point (3,) in metres. Outputs are predicted in a
normalised frame (centred on the training points, scaled by their spread) and mapped back to
world coordinates inside `forward`, so callers only see metres.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn

PRESETS: dict[str, tuple[int, ...]] = {
    "paper": (512, 1024, 1024, 512),  # ~2.3 M parameters with 256-d input
    "tiny": (512, 512, 512, 128),  # ~0.7 M
}


@dataclass(frozen=True)
class RegressorConfig:
    in_dim: int = 128
    hidden: tuple[int, ...] = PRESETS["paper"]

    @staticmethod
    def preset(arch: str, in_dim: int) -> RegressorConfig:
        if arch not in PRESETS:
            raise ValueError(f"unknown architecture '{arch}' (known: {', '.join(PRESETS)})")
        return RegressorConfig(in_dim=in_dim, hidden=PRESETS[arch])

    def to_dict(self) -> dict:
        return {**asdict(self), "hidden": list(self.hidden)}


class SceneCoordinateRegressor(nn.Module):
    """(N, D) descriptors -> (N, 3) world points in metres."""

    def __init__(self, config: RegressorConfig) -> None:
        super().__init__()
        self.config = config
        layers: list[nn.Module] = []
        width = config.in_dim
        for h in config.hidden:
            layers += [nn.Linear(width, h), nn.ReLU(inplace=True)]
            width = h
        layers.append(nn.Linear(width, 3))
        self.mlp = nn.Sequential(*layers)
        self.register_buffer("in_mean", torch.zeros(config.in_dim))
        self.register_buffer("in_std", torch.ones(config.in_dim))
        self.register_buffer("out_mean", torch.zeros(3))
        self.register_buffer("out_scale", torch.ones(()))

    def set_normalisation(self, descriptors: torch.Tensor, points: torch.Tensor) -> None:
        """Standardise inputs per dimension; centre and scale outputs on the training points."""
        self.in_mean.copy_(descriptors.mean(0))
        self.in_std.copy_(descriptors.std(0).clamp_min(1e-4))
        self.out_mean.copy_(points.mean(0))
        self.out_scale.copy_((points - points.mean(0)).norm(dim=1).mean().clamp_min(1e-3))

    def normalise_input(self, desc: torch.Tensor) -> torch.Tensor:
        return (desc - self.in_mean) / self.in_std

    def forward_normalised(self, desc_normalised: torch.Tensor) -> torch.Tensor:
        """Standardised descriptors -> outputs in the normalised point frame."""
        return self.mlp(desc_normalised)

    def forward(self, desc: torch.Tensor) -> torch.Tensor:
        return self.mlp(self.normalise_input(desc)).float() * self.out_scale + self.out_mean

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())
