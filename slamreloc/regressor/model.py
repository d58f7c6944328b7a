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
    # slamreloc's CPU default: a wide first (prototype) layer, then the tiny net's tail (~1.6 M
    # with 128-d SIFT); on CPU it beats both paper presets for the same training time
    "wide": (2048, 512, 512, 128),
}


@dataclass(frozen=True)
class RegressorConfig:
    in_dim: int = 128
    hidden: tuple[int, ...] = PRESETS["paper"]
    # First-layer weights start as (standardised, unit-norm) training descriptors and its bias
    # as -threshold, so each first-layer unit starts as a detector of descriptors whose cosine
    # to its prototype exceeds the threshold: a nearest-neighbour-like start that trains far
    # faster than a random one (see BENCHMARKS.md).
    prototype_init: bool = True
    prototype_threshold: float = 0.45

    @staticmethod
    def preset(arch: str, in_dim: int) -> RegressorConfig:
        if arch not in PRESETS:
            raise ValueError(f"unknown architecture '{arch}' (known: {', '.join(PRESETS)})")
        return RegressorConfig(in_dim=in_dim, hidden=PRESETS[arch])

    def to_dict(self) -> dict:
        return {**asdict(self), "hidden": list(self.hidden)}

    @staticmethod
    def from_dict(d: dict) -> RegressorConfig:
        return RegressorConfig(**{**d, "hidden": tuple(d["hidden"])})


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

    @torch.no_grad()
    def init_prototypes(self, desc_normalised: torch.Tensor, generator: torch.Generator) -> None:
        """Set the first layer from random training descriptors (already standardised)."""
        first = self.mlp[0]
        pick = torch.randperm(len(desc_normalised), generator=generator,
                              device=desc_normalised.device)[: first.out_features]
        protos = desc_normalised[pick]
        protos = protos / protos.norm(dim=1, keepdim=True).clamp_min(1e-6)
        gain = 3.0  # activations of about 3 * (cosine - threshold)
        first.weight[: len(protos)] = gain * protos / desc_normalised.norm(dim=1).mean()
        first.bias.fill_(-gain * self.config.prototype_threshold)

    def normalise_input(self, desc: torch.Tensor) -> torch.Tensor:
        return (desc - self.in_mean) / self.in_std

    def forward_normalised(self, desc_normalised: torch.Tensor) -> torch.Tensor:
        """Standardised descriptors -> outputs in the normalised point frame. Under bf16
        autocast the hidden layers run in bf16 but the output layer in float32: bf16's 8-bit
        mantissa would otherwise round world points to ~1 % of the scene's size."""
        hidden = self.mlp[:-1](desc_normalised)
        with torch.autocast(desc_normalised.device.type, enabled=False):
            return self.mlp[-1](hidden.float())

    def forward(self, desc: torch.Tensor) -> torch.Tensor:
        return self.forward_normalised(self.normalise_input(desc)) * self.out_scale + self.out_mean

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())
