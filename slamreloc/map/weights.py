"""The regressor's weights in a map folder: the model's state as plain arrays (regressor.npz,
format 2) and back, and format 1's torch archive (regressor.pt) through torch's weights-only
unpickler. Weights are checked against the regressor config before a model is built."""

from __future__ import annotations

import hashlib
import io
import zipfile
from pathlib import Path

import numpy as np
import torch

from slamreloc.errors import InputError
from slamreloc.io.fileio import read_bytes
from slamreloc.map.format import LEGACY_WEIGHTS, MAX_ARRAY_BYTES, WEIGHTS, one_line, read_npz
from slamreloc.map.meta import MapMeta
from slamreloc.regressor.model import RegressorConfig, SceneCoordinateRegressor

BF16_SUFFIX = "::bfloat16"  # npz key suffix: a bfloat16 tensor stored as its int16 bits


def read_regressor(root: Path, meta: MapMeta,
                   digests: dict[str, str] | None = None) -> SceneCoordinateRegressor:
    """The map's regressor, its weights checked against the checksum (format 2) and the
    config in `meta` (the map's checked metadata). `digests`: receives the SHA-256 of the
    weights file as read (name -> hex)."""
    cfg = meta.regressor.to_config()
    if meta.format_version == 1:
        state = _read_legacy_weights(root / LEGACY_WEIGHTS, digests)
    else:
        state = _read_weights(root / WEIGHTS, meta.files[WEIGHTS], digests)
    return _build_regressor(cfg, state, root / meta.weights_file)


def _read_weights(path: Path, expected: str | None = None,
                  digests: dict[str, str] | None = None) -> dict[str, torch.Tensor]:
    arrays = read_npz(path, "regressor weights", expected, digests)
    state = {}
    for key, arr in arrays.items():
        if key.endswith(BF16_SUFFIX):
            if arr.dtype != np.int16:
                raise InputError(f"{path}: {key} must hold int16 bits of bfloat16 values")
            state[key[: -len(BF16_SUFFIX)]] = torch.from_numpy(arr.copy()).view(torch.bfloat16)
        elif arr.dtype.kind in "fiub":
            state[key] = torch.from_numpy(arr.copy())
        else:
            raise InputError(f"{path}: {key} has dtype {arr.dtype}; weights must be numbers")
    return state


def _read_legacy_weights(path: Path,
                         digests: dict[str, str] | None = None) -> dict[str, torch.Tensor]:
    """Format 1: a torch zip archive of tensors, read with the weights-only unpickler."""
    if not path.exists() and not path.is_symlink():
        raise InputError(f"{path}: map has no regressor weights")
    if tuple(int(p) for p in torch.__version__.split(".")[:2]) < (2, 6):
        raise InputError(f"{path}: reading a format-1 map safely needs torch >= 2.6 "
                         f"(have {torch.__version__}); re-create the map")
    data = read_bytes(path, "regressor weights", MAX_ARRAY_BYTES)
    if digests is not None:
        digests[path.name] = hashlib.sha256(data).hexdigest()
    if not zipfile.is_zipfile(io.BytesIO(data)):
        raise InputError(f"{path}: not a torch weights archive (format-1 maps store a zip)")
    try:
        state = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - any failure of torch's unpickler means: refuse
        kind = ("refused: it holds Python objects other than tensors, which could run code"
                if "weights_only" in str(err) or "Unpickl" in type(err).__name__ else
                "not a readable torch weights archive")
        raise InputError(f"{path}: {kind} ({type(err).__name__}: "
                         f"{one_line(err)[:200]})") from None
    if not isinstance(state, dict) or not all(
            isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state.items()):
        raise InputError(f"{path}: expected a dict of named tensors")
    return state


# the model's scales (descriptor spread, output scale, cluster offset scale): > 0 as trained
POSITIVE_BUFFERS = ("in_std", "out_scale", "offset_scale")
MIN_SCALE = 1e-9  # a scale below this blows a descriptor up past float32's range
MAX_WEIGHT = 1e9  # any weight or buffer (the output's mean and scale: metres, `Rigid3`'s bound)


def _build_regressor(cfg: RegressorConfig, state: dict[str, torch.Tensor],
                     path: Path) -> SceneCoordinateRegressor:
    """Check the weights against the config (on the meta device: no memory is allocated for
    a config that a corrupted file blew up), then build the model."""
    with torch.device("meta"):
        expected = {k: tuple(v.shape)
                    for k, v in SceneCoordinateRegressor(cfg).state_dict().items()}
    missing = sorted(set(expected) - set(state))
    extra = sorted(set(state) - set(expected))
    if missing or extra:
        what = f"missing {missing[0]}" if missing else f"unexpected {extra[0]}"
        raise InputError(f"{path}: weights do not fit the regressor config ({what})")
    for key, shape in expected.items():
        tensor = state[key]
        if tuple(tensor.shape) != shape:
            raise InputError(f"{path}: {key} has shape {tuple(tensor.shape)}, the config says "
                             f"{shape}")
        if not tensor.is_floating_point():
            raise InputError(f"{path}: {key} has dtype {tensor.dtype}, expected floats")
        tensor = tensor.float()  # as the model holds it: 1e300 in float64 is infinite there
        if not bool(torch.isfinite(tensor).all()):
            raise InputError(f"{path}: {key} holds NaN or infinite values (as float32)")
        if bool((tensor.abs() > MAX_WEIGHT).any()):
            raise InputError(f"{path}: {key} holds values beyond {MAX_WEIGHT:g}, which no "
                             "training makes (the regression would overflow)")
        if key in POSITIVE_BUFFERS and not bool((tensor >= MIN_SCALE).all()):
            raise InputError(f"{path}: {key} holds values below {MIN_SCALE:g}; it is a scale "
                             "the regressor divides or multiplies by, positive when trained")
    model = SceneCoordinateRegressor(cfg)
    model.load_state_dict({k: v.float() for k, v in state.items()})
    return model.eval()


def weight_arrays(model: SceneCoordinateRegressor) -> dict[str, np.ndarray]:
    """The model's state as plain arrays for regressor.npz: the MLP's float weights as
    float16, bfloat16 tensors as their int16 bits (key + BF16_SUFFIX)."""
    arrays = {}
    for key, v in model.state_dict().items():
        v = v.detach().cpu()
        if v.is_floating_point() and v.dim() > 0 and key.startswith("mlp"):
            v = v.half()
        if v.dtype == torch.bfloat16:
            arrays[key + BF16_SUFFIX] = v.view(torch.int16).numpy()
        else:
            arrays[key] = v.numpy()
    return arrays
