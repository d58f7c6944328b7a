"""A map holds each frame once, by name or by picture (`slamreloc.map.joining`): a picture is
the frame's decoded pixels (`io.images.picture_digest`), recorded in the map
(`MapMeta.frame_pictures`), so the map's own frames are known under any name, file bytes or
dataset location. Also the Python API's argument checks (attack round 37)."""

from __future__ import annotations

import json
import os
import resource
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from slamreloc.errors import InputError
from slamreloc.io.images import picture_digest, read_image
from tests.fuzzing import run_cli

REFUSED = "(by name, or the same picture): a map holds each frame once"


def _pseudo_label(small_map, dataset: Path, tmp_path: Path) -> tuple[int, str]:
    return run_cli([str(a) for a in ("pseudo-label", small_map.root, dataset, "--out",
                                     tmp_path / "new", "--report", tmp_path / "r.json",
                                     "--rounds", "1", "--epochs", "1")])


def _project(scene_dir: Path, root: Path, n: int = 3) -> tuple[Path, list[Path]]:
    """A COLMAP project of the map's first `n` frames (their pictures under other names);
    returns it and its image files."""
    from slamreloc.datasets import load_dataset
    from tests.colmap_project import write_colmap_project

    frames = load_dataset(scene_dir).frames("seq-01")[:n]
    project = write_colmap_project(frames, root)
    return project, sorted((project / "images").rglob("*.png"))


def test_a_map_records_each_frames_picture(small_map, scene_dir):
    from slamreloc.datasets import load_dataset, read_frame_image

    names, pictures = small_map.info.frame_names, small_map.info.frame_pictures
    assert pictures is not None and len(pictures) == len(names)
    by_name = {f.name: f for f in load_dataset(scene_dir).frames("all")}
    for name, picture in list(zip(names, pictures))[::10]:
        assert picture == picture_digest(read_frame_image(by_name[name]))
    assert len(set(pictures)) == len(pictures)  # no two frames of the scene look alike


@pytest.mark.parametrize("change", ["trailing bytes", "recompressed", "as jpeg quality 100"])
def test_the_maps_pictures_in_other_bytes_are_held(small_map, scene_dir, tmp_path, change):
    """V1: one byte after the PNG's end (the readers skip it) gave the map's own pictures a
    new file hash, and pseudo-label added them again; the same pixels in other bytes are one
    picture. A lossy re-encoding is another picture (it is refused only if lossless)."""
    project, images = _project(scene_dir, tmp_path / "col")
    for path in images:
        if change == "trailing bytes":
            path.write_bytes(path.read_bytes() + b"\0")
        else:  # the file's name kept, its bytes those of another encoding
            pixels = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            ok, data = (cv2.imencode(".png", pixels, [cv2.IMWRITE_PNG_COMPRESSION, 9])
                        if change == "recompressed"
                        else cv2.imencode(".jpg", pixels, [cv2.IMWRITE_JPEG_QUALITY, 100]))
            assert ok
            path.write_bytes(data.tobytes())
    if change == "as jpeg quality 100":  # same name, JPEG bytes: no longer the same pixels
        assert picture_digest(read_image(images[0])) not in small_map.info.frame_pictures
        return
    code, err = _pseudo_label(small_map, project, tmp_path)
    assert code == 2 and REFUSED in err.strip().splitlines()[-1], err
    assert not (tmp_path / "new").exists()


def test_the_maps_pictures_are_held_when_its_dataset_has_moved(small_map, scene_dir, tmp_path):
    """V2: with the map's recorded dataset moved away (or a pipe in its place), there was
    nothing to compare a picture with; the map records its frames' pictures."""
    moved = tmp_path / "map"
    shutil.copytree(small_map.root, moved)
    meta_path = moved / "slamreloc_map.json"
    meta = json.loads(meta_path.read_text())
    meta["dataset"]["root"] = str(tmp_path / "moved_away")
    meta_path.write_text(json.dumps(meta))
    project, _ = _project(scene_dir, tmp_path / "col")
    code, err = run_cli([str(a) for a in ("pseudo-label", moved, project, "--out",
                                          tmp_path / "new", "--report", tmp_path / "r.json")])
    assert code == 2 and REFUSED in err.strip().splitlines()[-1], err


def test_a_huge_image_to_add_is_refused_by_its_bound_not_read(small_map, scene_dir, tmp_path):
    """V3: the picture check read whole files before the image bound: a 6 GB sparse file ran
    out of memory under a 4 GB cap ("error: out of memory", no file named)."""
    project, images = _project(scene_dir, tmp_path / "col")
    with open(images[1], "r+b") as f:
        f.truncate(6 << 30)

    def cap() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))

    run = subprocess.run([sys.executable, "-m", "slamreloc.cli", "pseudo-label",
                          str(small_map.root), str(project), "--out", str(tmp_path / "new"),
                          "--report", str(tmp_path / "r.json")], capture_output=True, text=True,
                         timeout=300, preexec_fn=cap, env={**os.environ, "OMP_NUM_THREADS": "1"})
    last = run.stderr.strip().splitlines()[-1]
    assert run.returncode == 2, run.stderr
    assert last.startswith(f"error: {images[1]}: ") and "max_image_bytes" in last, last


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(1, 40), st.integers(1, 40), st.sampled_from([2, 3]), st.data())
def test_picture_digest_is_the_pixels_whatever_the_file(width, height, ndim, data):
    """The same pixels through PNG, lossless WebP and raw arrays are one picture; any one
    pixel changed, or the same bytes in another shape, is another."""
    shape = (height, width) if ndim == 2 else (height, width, 3)
    seed = data.draw(st.integers(0, 2**32 - 1))
    pixels = np.random.default_rng(seed).integers(0, 256, shape, dtype=np.uint8)
    rgb = pixels if ndim == 3 else np.repeat(pixels[..., None], 3, axis=2)
    ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    decoded = cv2.cvtColor(cv2.imdecode(png, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    assert ok and picture_digest(decoded) == picture_digest(rgb.copy())
    changed = rgb.copy()
    y, x, c = (data.draw(st.integers(0, n - 1)) for n in changed.shape)
    changed[y, x, c] ^= 1
    assert picture_digest(changed) != picture_digest(rgb)
    if width * height > 1 and width != height:
        assert picture_digest(rgb.reshape(width, height, 3)) != picture_digest(rgb)


def test_frame_pictures_are_checked_where_a_map_is_read(small_map, tmp_path):
    from slamreloc.map.meta import MapMeta

    doc = json.loads((small_map.root / "slamreloc_map.json").read_text())
    path = tmp_path / "slamreloc_map.json"
    n = len(doc["frame_pictures"])
    for bad, message in ((doc["frame_pictures"][:-1], "one picture digest per frame"),
                         (["ab"] * n, r"'frame_pictures'\[0\] 'ab' is not")):
        with pytest.raises(InputError, match=message):
            MapMeta.from_json({**doc, "frame_pictures": bad}, path)
    known_in_part = ["", *doc["frame_pictures"][1:]]  # "" where not known
    assert MapMeta.from_json({**doc, "frame_pictures": known_in_part}, path).frame_pictures[0] == ""


def test_a_relative_dataset_root_in_a_report_is_refused_by_the_viewer(viewer_case, tmp_path):
    """V4: the viewer read an evaluate report's `dataset.root` from the folder it ran in, and
    drew ground truth from whatever dataset had that name there."""
    from slamreloc.viewer import ViewerInputs, load_scene_data

    report = json.loads(viewer_case.report.read_text())
    report["dataset"]["root"] = "scene_rel"
    path = tmp_path / "report.json"
    path.write_text(json.dumps(report))
    with pytest.raises(InputError, match=r"report.json: 'dataset.root' must be an absolute path"):
        load_scene_data(ViewerInputs(viewer_case.map_dir, [viewer_case.trajectory], [path]))


def test_the_python_api_names_a_wrong_argument(small_map, scene_dir):
    """V5: a float or int16 image, a list, or no camera failed inside OpenCV or with an
    AttributeError; `refine_with_depth` without a pose too."""
    from slamreloc.datasets import load_dataset, read_frame_image
    from slamreloc.localize.localizer import make_localizer
    from slamreloc.map.surface import refine_with_depth

    frame = load_dataset(scene_dir).frames("test")[0]
    image = read_frame_image(frame)
    localizer = make_localizer(small_map, "regressor")
    for bad, message in ((image.astype(np.float64), "image: must be uint8 .* got float64"),
                         (image.astype(np.int16), "image: must be uint8 .* got int16"),
                         (image.tolist(), "image: must be a numpy array .* got list"),
                         (image[..., :2], r"image: must be H x W x 3 RGB.* got shape")):
        with pytest.raises(InputError, match=message):
            localizer.localize(bad, frame.camera)
    with pytest.raises(InputError, match="camera: must be a slamreloc Camera .* got NoneType"):
        localizer.localize(image, None)
    assert localizer.localize(np.dstack([image, image[..., :1]]), frame.camera).estimate.success
    depth = np.ones((frame.camera.height, frame.camera.width), np.float32)
    with pytest.raises(InputError, match="world_from_cam: must be a Rigid3, got NoneType"):
        refine_with_depth(small_map.surface, depth, frame.camera, None, None)
    with pytest.raises(InputError, match="depth: must be a numpy array"):
        refine_with_depth(small_map.surface, depth.tolist(), frame.camera, None,
                          frame.world_from_cam)


def test_an_older_maps_frames_stay_held_after_an_update(small_map, scene_dir, tmp_path):
    """W1: a map that recorded no pictures (0.1.0 and before), once updated, recorded ""
    for its old frames, and the updated map then took the old map's frames back in under
    other names: a picture not recorded is read from the map's datasets still at hand."""
    older = tmp_path / "older"
    shutil.copytree(small_map.root, older)
    meta_path = older / "slamreloc_map.json"
    meta = json.loads(meta_path.read_text())
    del meta["frame_pictures"]  # as the maps of 0.1.0 were written
    meta_path.write_text(json.dumps(meta))
    code, err = run_cli([str(a) for a in (
        "pseudo-label", older, scene_dir, "--out", tmp_path / "updated",
        "--report", tmp_path / "u.json", "--rounds", "1", "--epochs", "1")])
    assert code == 0, err
    updated = json.loads((tmp_path / "updated" / "slamreloc_map.json").read_text())
    n_old = len(meta["frame_names"])
    assert updated["frame_pictures"][:n_old] == [""] * n_old  # not known: not made up
    assert all(updated["frame_pictures"][n_old:])
    project, _ = _project(scene_dir, tmp_path / "col")
    code, err = run_cli([str(a) for a in ("pseudo-label", tmp_path / "updated", project, "--out",
                                          tmp_path / "new", "--report", tmp_path / "r.json")])
    assert code == 2 and REFUSED in err.strip().splitlines()[-1], err


@pytest.mark.parametrize("hang", ["save", "close"])
def test_a_session_save_or_close_the_server_never_answers_ends(hang, monkeypatch):
    """W2, W3: `ClientSession.save` and `close` waited without a bound; they wait the
    client's timeout_s plus the server's own bound on that work (here made 0)."""
    import threading
    import time
    from concurrent import futures

    import grpc

    from slamreloc import client as client_module
    from slamreloc.client import Client, RemoteError
    from slamreloc.proto import relocalizer_pb2 as pb
    from slamreloc.proto import relocalizer_pb2_grpc as pb_grpc

    release = threading.Event()

    class Stuck(pb_grpc.RelocalizerServicer):
        def Session(self, requests, context):
            next(requests)
            yield pb.SessionUpdate(opened=pb.SessionOpened())
            for request in requests:
                if request.HasField("save"):
                    release.wait(60)
            release.wait(60)  # the close

    monkeypatch.setattr(client_module, "SAVE_WAIT_S", 0.0)
    monkeypatch.setattr(client_module, "CLOSE_WAIT_S", 0.0)
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=2))
    pb_grpc.add_RelocalizerServicer_to_server(Stuck(), server)
    port = server.add_insecure_port("127.0.0.1:0")
    server.start()
    try:
        with Client(f"127.0.0.1:{port}", timeout_s=1.0) as client:
            session = client.session(learn=True)
            t0 = time.monotonic()
            with pytest.raises(RemoteError, match="no answer within 1 s") as err:
                session.save("m") if hang == "save" else session.close()
            assert time.monotonic() - t0 < 30
            assert err.value.code == grpc.StatusCode.DEADLINE_EXCEEDED
    finally:
        release.set()
        server.stop(None)
