"""The scene-coordinate regressor: one MLP shared by all descriptors (Bui, Tran, Lee).

Maps a local descriptor (D,) to its world point (3,) in metres. Outputs are predicted in a
normalised frame (centred on the training points, scaled by their spread) and mapped back to
world coordinates inside `forward`, so callers only see metres.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from math import sqrt

import torch
from torch import nn

from slamreloc.registry import PRESETS
from slamreloc.regressor.regions import kmeans, nearest_centres


@dataclass(frozen=True)
class RegressorConfig:
    in_dim: int = 128
    hidden: tuple[int, ...] = PRESETS["paper"]["hidden"]
    # First-layer weights start as (standardised, unit-norm) training descriptors and its bias
    # as -threshold, so each first-layer unit starts as a detector of descriptors whose cosine
    # to its prototype exceeds the threshold: a nearest-neighbour-like start that trains far
    # faster than a random one (docs/history.md).
    prototype_init: bool = True
    prototype_threshold: float = 0.45
    # Output head. "regression": 3 outputs (x, y, z). "clusters": the training points are
    # k-means-clustered; the head classifies a descriptor into one of `n_clusters` scene
    # regions and regresses its offset from that region's centre (hierarchical scene
    # coordinate classification, Li et al. 2020). A descriptor that looks like two places then
    # gets one of them, not their average, and the class probability is a confidence.
    head: str = "regression"
    n_clusters: int = 512

    @staticmethod
    def preset(arch: str, in_dim: int) -> RegressorConfig:
        if arch not in PRESETS:
            raise ValueError(f"unknown architecture '{arch}' (known: {', '.join(PRESETS)})")
        return RegressorConfig(in_dim=in_dim, **PRESETS[arch])

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
        if config.head not in ("regression", "clusters"):
            raise ValueError(f"unknown head '{config.head}' (known: regression, clusters)")
        k = config.n_clusters if config.head == "clusters" else 0
        layers.append(nn.Linear(width, 4 * k if k else 3))  # k logits + k offsets, or xyz
        self.mlp = nn.Sequential(*layers)
        self.register_buffer("in_mean", torch.zeros(config.in_dim))
        self.register_buffer("in_std", torch.ones(config.in_dim))
        self.register_buffer("out_mean", torch.zeros(3))
        self.register_buffer("out_scale", torch.ones(()))
        self.register_buffer("centres", torch.zeros(k, 3))  # cluster centres, normalised frame
        self.register_buffer("offset_scale", torch.ones(()))  # mean point-to-centre distance

    def set_normalisation(self, descriptors: torch.Tensor, points: torch.Tensor) -> None:
        """Standardise inputs per dimension; centre and scale outputs on the training points."""
        self.in_mean.copy_(descriptors.mean(0))
        self.in_std.copy_(descriptors.std(0).clamp_min(1e-4))
        self.out_mean.copy_(points.mean(0))
        self.out_scale.copy_((points - points.mean(0)).norm(dim=1).mean().clamp_min(1e-3))

    @torch.no_grad()
    def reset_parameters(self, generator: torch.Generator) -> None:
        """Draw every layer's weights and biases anew from `generator`, as `nn.Linear` does
        (uniform in +-1/sqrt(fan_in)). Building the model draws them from torch's global
        generator, in whatever state the process left it: training from scratch calls this so
        that its seed alone fixes the initial model."""
        for layer in self.mlp:
            if isinstance(layer, nn.Linear):
                nn.init.kaiming_uniform_(layer.weight, a=sqrt(5), generator=generator)
                bound = 1 / sqrt(layer.in_features)
                nn.init.uniform_(layer.bias, -bound, bound, generator=generator)

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

    @torch.no_grad()
    def set_clusters(self, points_normalised: torch.Tensor, generator: torch.Generator,
                     iterations: int = 20) -> torch.Tensor:
        """k-means of the (normalised) training points; returns each point's cluster."""
        self.centres.copy_(kmeans(points_normalised, len(self.centres), generator, iterations))
        assign = self.assign_clusters(points_normalised)
        self.offset_scale.copy_((points_normalised - self.centres[assign]).norm(dim=1).mean()
                                .clamp_min(1e-6))
        return assign

    @torch.no_grad()
    def assign_clusters(self, points_normalised: torch.Tensor) -> torch.Tensor:
        """Index of the nearest cluster centre for each (normalised) point."""
        return nearest_centres(points_normalised, self.centres)[1]

    def hidden(self, desc_normalised: torch.Tensor) -> torch.Tensor:
        return self.mlp[:-1](desc_normalised)

    def head_outputs(self, hidden: torch.Tensor, cluster: torch.Tensor | None = None):
        """Hidden features -> (points (N, 3) in the normalised frame, logits (N, K) or None).

        The output layer runs in float32 even under bf16 autocast: bf16's 8-bit mantissa would
        round world points to ~1 % of the scene's size. `cluster` (N,) picks the cluster whose
        offset is used (training: the true one); by default the most probable one."""
        out = self.mlp[-1]
        with torch.autocast(hidden.device.type, enabled=False):
            hidden = hidden.float()
            if self.config.head == "regression":
                return out(hidden), None
            k = len(self.centres)
            logits = nn.functional.linear(hidden, out.weight[:k], out.bias[:k])
            if cluster is None:
                cluster = logits.argmax(1)
            # only the chosen cluster's 3 offset rows are evaluated; index_select, not
            # indexing: the latter's backward adds rows from all threads in racing order, so
            # one seed gave other weights from run to run
            w = out.weight[k:].view(k, 3, -1).index_select(0, cluster)
            b = out.bias[k:].view(k, 3).index_select(0, cluster)
            offset = torch.bmm(w, hidden.unsqueeze(2)).squeeze(2) + b
            return self.centres[cluster] + offset * self.offset_scale, logits

    def predict(self, desc: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(N, D) descriptors -> world points (N, 3), metres, and a confidence (N,) in [0, 1]
        (the cluster's probability; None for the regression head)."""
        points, logits = self.head_outputs(self.hidden(self.normalise_input(desc)))
        confidence = None if logits is None else logits.softmax(1).amax(1)
        return points * self.out_scale + self.out_mean, confidence

    def forward(self, desc: torch.Tensor) -> torch.Tensor:
        """(N, D) descriptors -> (N, 3) world points, metres."""
        return self.predict(desc)[0]

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())
