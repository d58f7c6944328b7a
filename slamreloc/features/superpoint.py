"""SuperPoint (DeTone et al. 2018): MagicLeap's network, loaded from a local `superpoint_v1.pth`.

The layer names match the published state dict (`conv1a.weight` ... `convDb.bias`), so the file
shipped with MagicLeap's SuperPointPretrainedNetwork or with cvg/LightGlue loads as is. Nothing
is downloaded: `weights` must name a file on disk.

Post-processing follows the reference code: softmax over 65 channels, drop the dustbin,
pixel-shuffle to full resolution, max-pool NMS, border removal, threshold, top-k; descriptors are
L2-normalised, bilinearly sampled at the keypoints with the reference normalisation, and
L2-normalised again. Keypoints are returned in this package's convention (integer = pixel
centre), which is the reference's own before LightGlue's `+ 0.5`.

Images whose sides are not multiples of 8 are padded at the bottom/right by edge replication;
keypoints are only taken inside the original image (and `remove_borders` from its edges).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from slamreloc.errors import InputError
from slamreloc.features.base import Extractor, ExtractorConfig
from slamreloc.types import Features

CELL = 8  # the encoder's total stride


class SuperPointNet(nn.Module):
    """MagicLeap's SuperPointNet; attribute names fix the state-dict keys."""

    def __init__(self) -> None:
        super().__init__()
        c1, c2, c3, c4, c5, d1 = 64, 64, 128, 128, 256, 256
        self.relu = nn.ReLU(inplace=True)
        self.pool = nn.MaxPool2d(kernel_size=2, stride=2)
        self.conv1a = nn.Conv2d(1, c1, kernel_size=3, stride=1, padding=1)
        self.conv1b = nn.Conv2d(c1, c1, kernel_size=3, stride=1, padding=1)
        self.conv2a = nn.Conv2d(c1, c2, kernel_size=3, stride=1, padding=1)
        self.conv2b = nn.Conv2d(c2, c2, kernel_size=3, stride=1, padding=1)
        self.conv3a = nn.Conv2d(c2, c3, kernel_size=3, stride=1, padding=1)
        self.conv3b = nn.Conv2d(c3, c3, kernel_size=3, stride=1, padding=1)
        self.conv4a = nn.Conv2d(c3, c4, kernel_size=3, stride=1, padding=1)
        self.conv4b = nn.Conv2d(c4, c4, kernel_size=3, stride=1, padding=1)
        self.convPa = nn.Conv2d(c4, c5, kernel_size=3, stride=1, padding=1)
        self.convPb = nn.Conv2d(c5, 65, kernel_size=1, stride=1, padding=0)
        self.convDa = nn.Conv2d(c4, c5, kernel_size=3, stride=1, padding=1)
        self.convDb = nn.Conv2d(c5, d1, kernel_size=1, stride=1, padding=0)

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """image (B,1,H,W) in [0,1], H and W multiples of 8 -> (scores (B,H,W) in [0,1],
        dense descriptors (B,256,H/8,W/8) L2-normalised)."""
        x = self.relu(self.conv1a(image))
        x = self.pool(self.relu(self.conv1b(x)))
        x = self.relu(self.conv2a(x))
        x = self.pool(self.relu(self.conv2b(x)))
        x = self.relu(self.conv3a(x))
        x = self.pool(self.relu(self.conv3b(x)))
        x = self.relu(self.conv4a(x))
        x = self.relu(self.conv4b(x))

        scores = self.convPb(self.relu(self.convPa(x)))
        scores = F.softmax(scores, 1)[:, :-1]  # drop the dustbin
        b, _, h, w = scores.shape
        scores = scores.permute(0, 2, 3, 1).reshape(b, h, w, CELL, CELL)
        scores = scores.permute(0, 1, 3, 2, 4).reshape(b, h * CELL, w * CELL)

        desc = self.convDb(self.relu(self.convDa(x)))
        desc = F.normalize(desc, p=2, dim=1)
        return scores, desc


def simple_nms(scores: torch.Tensor, nms_radius: int) -> torch.Tensor:
    """Reference max-pool NMS on (B,H,W) scores: non-maxima set to 0."""
    if nms_radius <= 0:
        return scores

    k = nms_radius * 2 + 1

    def max_pool(x: torch.Tensor) -> torch.Tensor:  # separable: same result, ~k/2 times faster
        x = F.max_pool2d(x, kernel_size=(1, k), stride=1, padding=(0, nms_radius))
        return F.max_pool2d(x, kernel_size=(k, 1), stride=1, padding=(nms_radius, 0))

    zeros = torch.zeros_like(scores)
    max_mask = scores == max_pool(scores)
    for _ in range(2):
        supp_mask = max_pool(max_mask.float()) > 0
        supp_scores = torch.where(supp_mask, zeros, scores)
        new_max_mask = supp_scores == max_pool(supp_scores)
        max_mask = max_mask | (new_max_mask & (~supp_mask))
    return torch.where(max_mask, scores, zeros)


def sample_descriptors(keypoints: torch.Tensor, descriptors: torch.Tensor,
                       s: int = CELL) -> torch.Tensor:
    """Bilinear descriptors at keypoints, the reference convention.

    keypoints (N,2) x/y pixels (integer = pixel centre); descriptors (C,h,w), one cell = s pixels.
    Pixel x maps to grid coordinate (x - s/2 + 0.5) / (w*s - s/2 - 0.5) * (w - 1) with
    align_corners=True, exactly as MagicLeap's / LightGlue's `sample_descriptors`.
    Returns (N,C), L2-normalised.
    """
    c, h, w = descriptors.shape
    if len(keypoints) == 0:
        return descriptors.new_zeros((0, c))
    kp = keypoints - s / 2 + 0.5
    kp = kp / kp.new_tensor([w * s - s / 2 - 0.5, h * s - s / 2 - 0.5])
    kp = kp * 2 - 1
    out = F.grid_sample(descriptors[None], kp.view(1, 1, -1, 2), mode="bilinear",
                        align_corners=True)
    return F.normalize(out.reshape(c, -1), p=2, dim=0).t()


def load_superpoint_state(path: str | Path) -> dict[str, torch.Tensor]:
    """The state dict in `path`, checked against SuperPointNet's keys; InputError otherwise."""
    if not str(path).strip():
        raise InputError("SuperPoint needs weights: set weights='' to the path of "
                         "superpoint_v1.pth (nothing is downloaded)")
    p = Path(path).expanduser()
    from slamreloc.io.fileio import open_regular

    try:
        with open_regular(p, "SuperPoint weights") as f:
            obj = torch.load(f, map_location="cpu", weights_only=True)
    except InputError:
        raise
    except Exception as e:  # noqa: BLE001 - any unreadable file is the same user error
        first = (str(e).strip().splitlines() or [""])[0][:200]
        raise InputError(f"SuperPoint weights {path}: not a readable PyTorch checkpoint "
                         f"({type(e).__name__}: {first})") from None
    if isinstance(obj, dict):
        for key in ("model", "state_dict"):
            if isinstance(obj.get(key), dict):
                obj = obj[key]
                break
    if not isinstance(obj, dict):
        raise InputError(f"SuperPoint weights {path}: expected a state dict, "
                         f"got {type(obj).__name__}")
    state = {(k[len("module."):] if isinstance(k, str) and k.startswith("module.") else k): v
             for k, v in obj.items()}
    expected = SuperPointNet().state_dict()
    missing = [k for k in expected if k not in state]
    if missing:
        raise InputError(f"SuperPoint weights {path}: not a SuperPoint state dict, "
                         f"missing key {missing[0]!r} ({len(missing)} missing)")
    unexpected = [k for k in state if k not in expected]
    if unexpected:
        raise InputError(f"SuperPoint weights {path}: not a SuperPoint state dict, "
                         f"unexpected key {unexpected[0]!r} ({len(unexpected)} unexpected)")
    for k, ref in expected.items():
        v = state[k]
        if not isinstance(v, torch.Tensor) or tuple(v.shape) != tuple(ref.shape):
            shape = tuple(v.shape) if isinstance(v, torch.Tensor) else type(v).__name__
            raise InputError(f"SuperPoint weights {path}: {k} has shape {shape}, "
                             f"expected {tuple(ref.shape)}")
    return state


@dataclass(frozen=True)
class SuperPointConfig(ExtractorConfig):
    weights: str = ""  # path to superpoint_v1.pth (MagicLeap / LightGlue); required
    nms_radius: int = 4
    detection_threshold: float = 0.005
    remove_borders: int = 4
    device: str = "cpu"  # "cpu", "cuda", "cuda:1", or "auto" (cuda when available)

    def __post_init__(self) -> None:
        super().__post_init__()
        self.check_range("nms_radius", 0, 64)
        self.check_range("detection_threshold", 0.0, 1.0)
        self.check_range("remove_borders", 0, 64)


class SuperPoint(Extractor):
    name = "superpoint"
    dim = 256
    Config = SuperPointConfig
    bytes_per_pixel = 750  # float32 activations of the full-resolution layers (1.9 MP: 744 B)

    def __init__(self, config: SuperPointConfig | None = None, **overrides) -> None:
        super().__init__(config, **overrides)
        c = self.config
        if c.nms_radius < 0 or c.remove_borders < 0:
            raise InputError(f"SuperPoint: nms_radius and remove_borders must be >= 0, "
                             f"got {c.nms_radius} and {c.remove_borders}")
        device = c.device
        if device == "auto":
            device = "cuda" if torch.cuda.is_available() else "cpu"
        self.device = torch.device(device)
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise InputError(f"SuperPoint: device {c.device!r} requested but CUDA is not "
                             f"available (use 'cpu' or 'auto')")
        state = load_superpoint_state(c.weights)
        net = SuperPointNet()
        net.load_state_dict(state, strict=True)
        self.net = net.eval().requires_grad_(False).to(self.device)

    def extract_grey(self, grey: np.ndarray) -> Features:
        grey = np.asarray(grey)
        if grey.ndim != 2 or grey.size == 0:
            raise InputError(f"SuperPoint expects a non-empty (H, W) grey image, "
                             f"got shape {grey.shape}")
        if grey.dtype == np.uint8:
            scale = 255.0
        elif grey.dtype == np.uint16:
            scale = 65535.0
        elif np.issubdtype(grey.dtype, np.floating):
            scale = 1.0  # already in [0, 1]
        else:
            raise InputError(f"SuperPoint expects a uint8 grey image, got {grey.dtype}")
        c = self.config
        height, width = grey.shape
        with torch.inference_mode():
            img = torch.from_numpy(grey.astype(np.float32)).to(self.device)
            img = (img / scale if scale != 1.0 else img)[None, None]
            pad_h, pad_w = -height % CELL, -width % CELL
            if pad_h or pad_w:
                img = F.pad(img, (0, pad_w, 0, pad_h), mode="replicate")
            dense, desc = self.net(img)

            # Only the original image: the padded rows/columns neither detect nor suppress.
            scores = simple_nms(dense[:, :height, :width], c.nms_radius)[0]
            b = c.remove_borders
            if b:
                scores[:b] = -1
                scores[:, :b] = -1
                scores[-b:] = -1
                scores[:, -b:] = -1
            ys, xs = torch.where(scores > c.detection_threshold)
            kp_scores = scores[ys, xs]
            n = len(kp_scores)
            if n:  # strongest first; max_keypoints <= 0 means no limit
                k = n if c.max_keypoints <= 0 else min(c.max_keypoints, n)
                kp_scores, order = torch.topk(kp_scores, k, sorted=True)
                ys, xs = ys[order], xs[order]
            keypoints = torch.stack([xs, ys], dim=-1).float()
            descriptors = sample_descriptors(keypoints, desc[0], CELL)
            return Features(keypoints.cpu().numpy().astype(np.float32, copy=False),
                            descriptors.cpu().numpy().astype(np.float32, copy=False),
                            kp_scores.cpu().numpy().astype(np.float32, copy=False))
