"""SuperPoint extractor: weights are made here (seeded random network), never downloaded."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from torch import nn

from slamreloc.errors import InputError
from slamreloc.features.superpoint import (SuperPoint, SuperPointConfig, SuperPointNet,
                                           sample_descriptors)

H, W = 240, 320


def _random_net(seed: int = 0) -> SuperPointNet:
    # He init with zero biases keeps activations O(1) through the layers, so the random
    # detector head gives a peaky, image-dependent score map (PyTorch's default init gives an
    # almost uniform softmax, which would make the geometric checks meaningless).
    torch.manual_seed(seed)
    net = SuperPointNet()
    for m in net.modules():
        if isinstance(m, nn.Conv2d):
            nn.init.kaiming_normal_(m.weight, nonlinearity="relu")
            nn.init.zeros_(m.bias)
    return net


@pytest.fixture(scope="module")
def weights(tmp_path_factory) -> str:
    path = tmp_path_factory.mktemp("sp") / "superpoint_random.pth"
    torch.save(_random_net().state_dict(), path)
    return str(path)


@pytest.fixture(scope="module")
def image() -> np.ndarray:
    return _textured(H, W, seed=0)


def _textured(h: int, w: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.full((h, w), 128, np.uint8)
    for _ in range(80):
        colour = int(rng.integers(0, 256))
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        if rng.random() < 0.5:
            cv2.circle(img, (x, y), int(rng.integers(4, 30)), colour, -1)
        else:
            cv2.rectangle(img, (x, y), (x + int(rng.integers(4, 50)), y + int(rng.integers(4, 50))),
                          colour, -1)
    return img


def _check_features(f, h: int, w: int, border: int, max_kp: int) -> None:
    n = len(f)
    assert 0 < n <= max_kp
    assert f.keypoints.dtype == np.float32 and f.keypoints.shape == (n, 2)
    assert f.descriptors.dtype == np.float32 and f.descriptors.shape == (n, 256)
    assert f.scores.shape == (n,)
    x, y = f.keypoints[:, 0], f.keypoints[:, 1]
    assert x.min() >= border and x.max() <= w - 1 - border
    assert y.min() >= border and y.max() <= h - 1 - border
    np.testing.assert_allclose(np.linalg.norm(f.descriptors, axis=1), 1.0, atol=1e-5)
    assert np.all(np.diff(f.scores) <= 0), "strongest first"
    assert len(np.unique(f.keypoints, axis=0)) == n


def test_extract_textured_image(weights, image):
    sp = SuperPoint(weights=weights, max_keypoints=300)
    assert sp.name == "superpoint" and sp.dim == 256
    f = sp(image)
    _check_features(f, H, W, border=4, max_kp=300)
    assert len(f) == 300  # the random net finds far more than 300 candidates
    assert np.all(f.scores > sp.config.detection_threshold)
    # Top-k keeps the strongest: a prefix of the unlimited result.
    full = SuperPoint(weights=weights, max_keypoints=0)(image)
    assert len(full) > 300
    np.testing.assert_array_equal(full.keypoints[:300], f.keypoints)
    np.testing.assert_allclose(full.descriptors[:300], f.descriptors, atol=1e-6)
    # RGB input goes through the same grey path.
    rgb = np.repeat(image[:, :, None], 3, axis=2)
    np.testing.assert_array_equal(sp(rgb).keypoints, f.keypoints)


def test_keypoints_follow_dense_scores(weights, image):
    sp = SuperPoint(weights=weights, max_keypoints=0)
    f = sp(image)
    with torch.inference_mode():
        dense, _ = sp.net(torch.from_numpy(image).float()[None, None] / 255)
    dense = dense[0].numpy()
    assert dense.shape == (H, W)
    xi, yi = f.keypoints[:, 0].astype(int), f.keypoints[:, 1].astype(int)
    np.testing.assert_array_equal(f.keypoints, np.stack([xi, yi], 1).astype(np.float32))
    np.testing.assert_allclose(f.scores, dense[yi, xi], rtol=1e-6)
    r, b, t = sp.config.nms_radius, sp.config.remove_borders, sp.config.detection_threshold
    # Every strict local maximum of the dense map (inside the borders, above threshold) is
    # detected: the first NMS pass keeps them all.
    pooled = cv2.dilate(dense, np.ones((2 * r + 1, 2 * r + 1), np.uint8),
                        borderType=cv2.BORDER_CONSTANT, borderValue=-1.0)
    strict = (dense == pooled) & (dense > t)
    strict[:b], strict[:, :b], strict[H - b:], strict[:, W - b:] = False, False, False, False
    ys, xs = np.nonzero(strict)
    assert len(ys) > 100
    found = {(int(x), int(y)) for x, y in zip(xi, yi)}
    assert {(int(x), int(y)) for x, y in zip(xs, ys)} <= found
    # No two kept keypoints lie within the NMS radius of each other (no exact ties here).
    cheb = np.abs(f.keypoints[:, None] - f.keypoints[None]).max(axis=2)
    np.fill_diagonal(cheb, np.inf)
    assert cheb.min() > r


def test_pixel_shuffle_layout(tmp_path):
    # Detector that puts all mass on channel 8*2 + 5 whatever the image: every keypoint must
    # then sit at row 2, column 5 of its 8x8 cell (the reference layout: channel = 8*row + col).
    net = _random_net(1)
    state = net.state_dict()
    state["convPb.weight"].zero_()
    state["convPb.bias"].zero_()
    state["convPb.bias"][8 * 2 + 5] = 12.0
    path = tmp_path / "shuffle.pth"
    torch.save(state, path)
    f = SuperPoint(weights=str(path), max_keypoints=0)(_textured(H, W, seed=3))
    xs = np.arange(5, W - 4, 8)
    ys = np.arange(2, H - 4, 8)
    ys = ys[ys >= 4]
    assert len(f) == len(xs) * len(ys)
    assert np.all(f.keypoints[:, 0] % 8 == 5) and np.all(f.keypoints[:, 1] % 8 == 2)


def test_translation_by_one_cell(weights, image):
    # Shifting the content by 8 px (one descriptor cell) shifts the network's output by one cell,
    # exactly, away from the receptive field of the image border.
    sp = SuperPoint(weights=weights, max_keypoints=0)
    f = sp(image)
    g = sp(np.pad(image, ((8, 0), (8, 0)), mode="edge"))
    margin = 48

    def interior(k, off):
        return ((k[:, 0] >= off + margin) & (k[:, 0] < off + W - margin)
                & (k[:, 1] >= off + margin) & (k[:, 1] < off + H - margin))

    ia, ib = interior(f.keypoints, 0), interior(g.keypoints, 8)
    a, b = f.keypoints[ia] + 8, g.keypoints[ib]
    assert len(a) > 100
    dist = np.linalg.norm(a[:, None] - b[None], axis=2)
    nn_b = dist.argmin(1)
    close = dist.min(1) <= 1.0
    assert close.mean() >= 0.95 and (dist.min(0) <= 1.0).mean() >= 0.95
    # Descriptors at the same content agree (the sampling normalisation depends slightly on the
    # map width, so not bit-exact)...
    da, db = f.descriptors[ia][close], g.descriptors[ib][nn_b[close]]
    cos = np.sum(da * db, axis=1)
    assert np.median(cos) > 0.999 and cos.min() > 0.99
    # ... and they are discriminative: the most similar descriptor is the same point.
    sim = f.descriptors[ia] @ g.descriptors[ib].T
    assert (sim.argmax(1) == nn_b).mean() >= 0.9


def test_sample_descriptors_convention():
    # A ramp map: channel 0 / channel 1 recovers the sampled grid coordinate, which must be
    # (x - s/2 + 0.5) / (w*s - s/2 - 0.5) * (w - 1) as in MagicLeap's / LightGlue's code.
    h, w, s = 5, 7, 8
    gx = torch.arange(w, dtype=torch.float32)[None, :].expand(h, w)
    gy = torch.arange(h, dtype=torch.float32)[:, None].expand(h, w)
    desc = torch.stack([gx + 1, gy + 1, torch.ones(h, w)])
    kp = torch.tensor([[3.5, 3.5], [8 * w - 1, 8 * h - 1], [20.0, 11.0], [0.0, 0.0]])
    out = sample_descriptors(kp, desc, s)
    assert out.shape == (4, 3)
    torch.testing.assert_close(out.norm(dim=1), torch.ones(4))
    got_x, got_y = out[:, 0] / out[:, 2] - 1, out[:, 1] / out[:, 2] - 1
    exp_x = (kp[:, 0] - s / 2 + 0.5) / (w * s - s / 2 - 0.5) * (w - 1)
    exp_y = (kp[:, 1] - s / 2 + 0.5) / (h * s - s / 2 - 0.5) * (h - 1)
    exp_x[3], exp_y[3] = 0.0, 0.0  # outside the first cell centre: zeros padding is not used
    mask = torch.tensor([True, True, True, False])
    torch.testing.assert_close(got_x[mask], exp_x[mask], atol=1e-5, rtol=0)
    torch.testing.assert_close(got_y[mask], exp_y[mask], atol=1e-5, rtol=0)
    torch.testing.assert_close(got_x[:2], torch.tensor([0.0, w - 1.0]), atol=1e-5, rtol=0)


def test_odd_image_size(weights):
    h, w = 241, 323
    img = _textured(h, w, seed=1)
    sp = SuperPoint(weights=weights, max_keypoints=0)
    f = sp(img)
    _check_features(f, h, w, border=4, max_kp=10**9)
    # The odd image is padded at the bottom/right by edge replication: away from those edges
    # (NMS can reach 2*radius), it gives exactly what the explicitly padded image gives.
    g = sp(np.pad(img, ((0, -h % 8), (0, -w % 8)), mode="edge"))
    lim = 4 + 2 * sp.config.nms_radius

    def keep(ft):
        m = (ft.keypoints[:, 0] < w - lim) & (ft.keypoints[:, 1] < h - lim)
        order = np.lexsort((ft.keypoints[m, 0], ft.keypoints[m, 1]))
        return ft.keypoints[m][order], ft.descriptors[m][order]

    (ka, da), (kb, db) = keep(f), keep(g)
    assert len(ka) > 100
    np.testing.assert_array_equal(ka, kb)
    np.testing.assert_allclose(da, db, atol=1e-5)
    # A tiny image (smaller than one cell) still works.
    tiny = SuperPoint(weights=weights, remove_borders=0, nms_radius=1)(img[:5, :6])
    assert tiny.descriptors.shape[1] == 256
    assert np.all(tiny.keypoints[:, 0] <= 5) and np.all(tiny.keypoints[:, 1] <= 4)


def test_no_keypoints_above_threshold(weights, image):
    f = SuperPoint(weights=weights, detection_threshold=1.0)(image)
    assert f.keypoints.shape == (0, 2) and f.descriptors.shape == (0, 256)
    assert f.scores.shape == (0,)
    assert f.keypoints.dtype == np.float32 and f.descriptors.dtype == np.float32


def test_wrapped_state_dicts_load(weights, image, tmp_path):
    ref = SuperPoint(weights=weights, max_keypoints=100)(image)
    state = torch.load(weights, map_location="cpu", weights_only=True)
    for key in ("model", "state_dict"):
        path = tmp_path / f"{key}.pth"
        torch.save({key: state, "epoch": 3}, path)
        f = SuperPoint(SuperPointConfig(weights=str(path), max_keypoints=100))(image)
        np.testing.assert_array_equal(f.keypoints, ref.keypoints)
        np.testing.assert_array_equal(f.descriptors, ref.descriptors)


def test_bad_weights_raise_input_error(weights, tmp_path):
    with pytest.raises(InputError, match="weights=''"):
        SuperPoint()
    with pytest.raises(InputError, match="weights=''"):
        SuperPoint(weights="")

    missing = tmp_path / "nope" / "superpoint_v1.pth"
    with pytest.raises(InputError) as e:
        SuperPoint(weights=str(missing))
    assert str(missing) in str(e.value) and "\n" not in str(e.value)

    wrong = tmp_path / "wrong_keys.pth"
    torch.save({"foo.weight": torch.zeros(3)}, wrong)
    with pytest.raises(InputError) as e:
        SuperPoint(weights=str(wrong))
    assert str(wrong) in str(e.value) and "conv1a.weight" in str(e.value)

    state = torch.load(weights, map_location="cpu", weights_only=True)
    extra = tmp_path / "extra_key.pth"
    torch.save({**state, "convX.weight": torch.zeros(1)}, extra)
    with pytest.raises(InputError) as e:
        SuperPoint(weights=str(extra))
    assert str(extra) in str(e.value) and "convX.weight" in str(e.value)

    shape = tmp_path / "bad_shape.pth"
    torch.save({**state, "convDb.bias": torch.zeros(128)}, shape)
    with pytest.raises(InputError) as e:
        SuperPoint(weights=str(shape))
    assert str(shape) in str(e.value) and "convDb.bias" in str(e.value)

    garbage = tmp_path / "garbage.pth"
    garbage.write_bytes(b"this is not a checkpoint\n" * 10)
    with pytest.raises(InputError) as e:
        SuperPoint(weights=str(garbage))
    assert str(garbage) in str(e.value) and "\n" not in str(e.value)

    with pytest.raises(InputError) as e:
        SuperPoint(weights=str(tmp_path))  # a folder
    assert str(tmp_path) in str(e.value)
