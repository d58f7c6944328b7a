"""SLAM that learns its own map (`slam --out`): a session with no prior map recovers its
kidnaps in the map it is building and saves a map every command takes; loop closures between
keyframes move the keyframes' labels with them; a second session anchors in the first's map
and extends it; a learned map is written crash-safely."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slamreloc.geometry import Rigid3, axis_angle_to_matrix, pose_error
from slamreloc.slam.backend import BackendConfig, SlamBackend
from slamreloc.slam.keyframes import KeyframeRows
from slamreloc.slam.live_map import LiveMap, LiveMapConfig
from slamreloc.types import Camera

LIVE = ["--split", "kidnap", "--kidnap-every", "30", "--kidnap-skip", "10"]


def cli(*args):
    return subprocess.run([sys.executable, "-m", "slamreloc.cli", *map(str, args)],
                          capture_output=True, text=True)


@pytest.fixture(scope="module")
def live_session(kidnap_scene, tmp_path_factory):
    """`slam --out` with no map on the kidnap sequence: (report, map folder, workdir). Its
    rounds run on the tracker's thread every 10 keyframes (`--learn-every`), so what the map
    knows at each kidnap does not depend on how busy the machine is."""
    out = tmp_path_factory.mktemp("live")
    res = cli("slam", kidnap_scene, *LIVE, "--out", out / "map", "--report", out / "r.json",
              "--trajectory", out / "t.txt", "--learn-every", "10")
    assert res.returncode == 0, res.stderr
    return json.loads((out / "r.json").read_text()), out / "map", out


def test_live_session_recovers_kidnaps_in_its_own_map(live_session):
    r, _, _ = live_session
    assert r["truth_aligned_on_keyframes"]
    assert r["n_kidnaps"] == 2 and r["n_recovered"] == 2, r
    assert r["median_frames_to_recover"] <= 3
    assert r["recovered_median_error_m"] <= 0.05 and r["recovered_median_error_deg"] <= 2
    assert r["n_false_anchors"] == 0
    assert r["ate_rmse_aligned_m"] <= 0.4 * r["ate_rmse_odometry_only_aligned_m"]
    live = r["live_map"]
    assert live["n_keyframes"] > 10 and live["n_prior_frames"] == 0
    assert live["n_feature_links"] >= live["n_keyframes"]
    assert live["rounds"] and live["rounds"][0]["scratch"]
    assert live["n_writes"] >= 1


def test_a_full_disk_at_the_report_keeps_the_map_it_had(live_session, kidnap_scene,
                                                         tmp_path, monkeypatch):
    """The session's final map, trajectory and report are put in place together: a full
    disk at the report leaves the map (and the rest) a session before wrote, and no
    temporary (attack round 12, H3: the map was swapped in before the report failed)."""
    import errno
    import shutil

    from slamreloc.cli import jobs
    from tests.fuzzing import run_cli
    from tests.test_round12 import _tree

    _, map_dir, work = live_session
    shutil.copytree(map_dir, tmp_path / "map")
    for name in ("r.json", "t.txt", "t.names.txt"):
        shutil.copy(work / name, tmp_path / name)
    before = _tree(tmp_path)

    def no_space(path, data):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(jobs, "write_json", no_space)
    code, err = run_cli(["slam", str(kidnap_scene), *LIVE, "--out", str(tmp_path / "map"),
                         "--save-every", "0", "--report", str(tmp_path / "r.json"),
                         "--trajectory", str(tmp_path / "t.txt")], hang_s=600)
    assert code == 2 and "No space left" in err and "r.json" in err, err
    assert _tree(tmp_path) == before


def test_learned_map_is_a_map_every_command_takes(live_session, kidnap_scene):
    """evaluate and export read the saved map; its frame is the session's, so evaluate scores
    against the dataset's poses after a similarity fitted on its keyframes (without it every
    error would be the offset between the two frames). How accurate a learned map is, against
    one mapped offline, is measured on RedKitchen (benchmarks/live_map_benchmark.py)."""
    from slamreloc.map.scene_map import SceneMap

    r, map_dir, work = live_session
    m = SceneMap.load(map_dir)
    assert m.info.train["learned_live"] and len(m.database.frame_names) == \
        r["live_map"]["n_keyframes"]
    res = cli("evaluate", map_dir, kidnap_scene, "--split", "seq-01,seq-02,seq-04",
              "--report", work / "eval.json")
    assert res.returncode == 0, res.stderr
    ev = json.loads((work / "eval.json").read_text())
    assert ev["alignment"]["n_frames"] == r["live_map"]["n_keyframes"]
    assert ev["alignment"]["median_residual_m"] < 0.02, ev["alignment"]
    assert ev["recall"]["5cm5deg"] > 0, ev["per_query"]
    res = cli("export", map_dir, "--tum", work / "keyframes.txt")
    assert res.returncode == 0, res.stderr
    assert len((work / "keyframes.txt").read_text().split("\n")) > r["live_map"]["n_keyframes"]


@settings(max_examples=6, deadline=None)
@given(drift_deg=st.floats(0.5, 3.0), drift_m=st.floats(0.03, 0.10))
def test_loop_closure_moves_labels_with_keyframes(drift_deg, drift_m):
    """A 40-keyframe track whose odometry drifts: the last keyframe's rows sit where the
    drifted pose puts them until loop closures against the first keyframe (three agreeing
    relocalizations, as the gate asks) move the keyframe, and its rows with it, towards
    where they are."""
    camera = Camera(640, 480, 500.0, 500.0, 320.0, 240.0)
    backend = SlamBackend(None, [], BackendConfig(keyframe_every=1))
    live = LiveMap(LiveMapConfig())
    live.attach(backend)
    rng = np.random.default_rng(0)
    n = 40
    truth = [Rigid3(axis_angle_to_matrix(np.array([0, 0.01 * i, 0])),
                    np.array([0.035 * i, 0, 0])) for i in range(n)]
    world_points = rng.uniform(-1, 1, (50, 3)) + [0.7, 0, 3]
    for i, t in enumerate(truth):
        drift = Rigid3(axis_angle_to_matrix(np.radians([0, 0, drift_deg * i / (n - 1)])),
                       np.array([drift_m * i / (n - 1), 0, 0]))  # grows along the track
        backend.process(None, None, camera, drift @ t, float(i))
        if i == 0:
            backend.anchor(0, t)
        rec = backend.frames[-1]
        assert rec.key is not None
        live.store.add(KeyframeRows(rec.key, i, f"f{i}", np.zeros((50, 2), np.float32),
                                    np.zeros((50, 128), np.float16),
                                    t.inverse().transform(world_points).astype(np.float32)))
    last = backend.frames[-1]
    error = (lambda pts: float(np.median(np.linalg.norm(pts - world_points, axis=1))))  # noqa
    before = live.database().database.points[-50:]
    before_m, _ = pose_error(backend.keyframe_pose(last.key), truth[-1])
    for _ in range(3):
        backend.add_keyframe_loop(n - 1, backend.frames[0].key,
                                  truth[0].inverse() @ truth[-1])
    backend.finish()
    after = live.database().database.points[-50:]
    placed = backend.keyframe_pose(last.key)
    # the rows are where the corrected pose puts them ...
    np.testing.assert_allclose(after, placed.transform(
        truth[-1].inverse().transform(world_points)), atol=1e-4)
    # ... which is nearer the truth than the drifted one
    after_m, _ = pose_error(placed, truth[-1])
    assert after_m <= 0.7 * before_m
    assert error(after) <= 0.8 * error(before)


def test_second_session_anchors_in_the_first_map_and_extends_it(live_session, kidnap_scene):
    """The first session's frames again: it anchors in MAP1 and extends it by the frames MAP1
    does not hold (its keyframes are not added twice); MAP1 is left as it was."""
    r1, map1, work = live_session
    map2 = work / "map2"
    before = {p.name: p.read_bytes() for p in map1.iterdir() if p.is_file()}
    res = cli("slam", kidnap_scene, "--split", "kidnap", "--map", map1, "--out", map2,
              "--report", work / "r2.json")
    assert res.returncode == 0, res.stderr
    r = json.loads((work / "r2.json").read_text())
    anchors = [e["frame"] for e in r["events"] if e["type"] == "tracking_recovered"]
    assert anchors and anchors[0] <= 3, r["events"][:5]
    assert r["n_false_anchors"] == 0
    assert r["live_map"]["n_prior_frames"] == r1["live_map"]["n_keyframes"]
    assert r["live_map"]["n_keyframes"] > 0
    assert {p.name: p.read_bytes() for p in map1.iterdir() if p.is_file()} == before


def test_a_session_of_another_dataset_records_where_the_map_s_frames_are(
        live_session, kidnap_scene, scene_dir, tmp_path):
    """Attack round 28, H1: `slam OTHER --map MAP1 --out MAP3` recorded OTHER alone, while its
    first frames are MAP1's, from MAP1's dataset: export coloured them grey and said "colours
    from the images", and MAP1's dataset was no input of commands on MAP3. MAP3 now records
    the datasets of the frames it took over (`extended`)."""
    r1, map1, work = live_session
    map3 = work / "map3"
    # the kidnap path again, renamed: no frame is named as MAP1's (seq-03/...)
    other = _renamed_copy(kidnap_scene, tmp_path / "other")
    res = cli("slam", other, "--split", "seq-05", "--map", map1, "--out", map3,
              "--report", work / "r3x.json", "--save-every", "0")
    assert res.returncode == 0, res.stderr
    meta = json.loads((map3 / "slamreloc_map.json").read_text())
    assert meta["dataset"]["root"] == str(other.resolve())
    assert meta["extended"] == {"source_map": str(map1.resolve()),
                                "dataset_roots": [str(kidnap_scene.resolve())],
                                "n_prior_frames": r1["live_map"]["n_keyframes"]}
    res = cli("export", map3, "--ply", work / "m3.ply")
    assert res.returncode == 0 and "colours from the images)" in " ".join(res.stderr.split())
    res = cli("export", map3, "--colmap", kidnap_scene / "col")
    assert res.returncode == 2 and "a dataset of the map's earlier sessions" in res.stderr
    assert not (kidnap_scene / "col").exists()
    # a session whose frames are named as MAP1's but come from elsewhere: refused, naming
    # the dataset they do come from
    res = cli("slam", scene_dir, "--split", "kidnap", "--map", map1, "--out", work / "map4",
              "--report", work / "r4x.json")
    assert res.returncode == 2 and not (work / "map4").exists()
    assert f"which come from the map's dataset ({kidnap_scene.resolve()})" in res.stderr


def _with_sequence(root: Path, name: str, frames_of: Path) -> None:
    """Give the synthetic dataset `root` a sequence `name` holding the frames of the sequence
    folder `frames_of` (as an unlabelled one)."""
    shutil.copytree(frames_of, root / name)
    scene = json.loads((root / "scene.json").read_text())
    scene["sequences"][name] = "unlabelled"
    (root / "scene.json").write_text(json.dumps(scene, indent=2))


def _renamed_copy(scene: Path, b: Path) -> Path:
    """A copy of the kidnap scene `scene` at `b` whose kidnap sequence is named seq-05, not
    seq-03: the same pictures, none named as a frame of a map learned from `scene`."""
    b.mkdir()
    for entry in scene.iterdir():
        if entry.name != "seq-03":
            (shutil.copytree if entry.is_dir() else shutil.copy)(entry, b / entry.name)
    scene_json = json.loads((b / "scene.json").read_text())
    del scene_json["sequences"]["seq-03"]
    (b / "scene.json").write_text(json.dumps(scene_json, indent=2))
    _with_sequence(b, "seq-05", scene / "seq-03")
    return b


def test_a_name_two_of_the_map_s_datasets_hold_is_refused(live_session, kidnap_scene,
                                                          tmp_path):
    """Attack round 29, L1: MAP2 = the kidnap sequence of dataset B (named seq-05) extending
    MAP1 (the kidnap scene's seq-03). Once B also holds a seq-03 of its own, a session of B
    on MAP2 was taken: B is one of MAP2's datasets, but MAP2's seq-03 frames are the kidnap
    scene's, and the extended map held each such name for two pictures."""
    _, map1, work = live_session
    b = _renamed_copy(kidnap_scene, tmp_path / "B")
    map2 = tmp_path / "map2"
    res = cli("slam", b, "--split", "seq-05", "--map", map1, "--out", map2, "--report",
              tmp_path / "r2.json", "--learn-every", "10", "--save-every", "0")
    assert res.returncode == 0, res.stderr
    assert json.loads((map2 / "slamreloc_map.json").read_text())["extended"][
        "dataset_roots"] == [str(kidnap_scene.resolve())]
    _with_sequence(b, "seq-03", kidnap_scene / "seq-03")
    res = cli("slam", b, "--split", "seq-05", "--map", map2, "--out", tmp_path / "map3",
              "--report", tmp_path / "r3.json")
    assert res.returncode == 2 and not (tmp_path / "map3").exists()
    assert res.stderr.strip().splitlines()[-1] == (
        f"error: {b}: holds frames named as the map {map2}'s own (such as "
        f"'seq-03/frame-000000'), and so does {kidnap_scene.resolve()}, another dataset of "
        "the map's: which one's picture is the map's frame cannot be told; extend it with "
        "frames named apart")


def test_slam_in_a_learned_map_scores_in_its_frame(live_session, kidnap_scene):
    """`slam --map` of a learned map (no --out): the ground truth is fitted onto the map's
    keyframes, as `evaluate` does, so the ATE and the anchors are judged in the map's frame,
    not against truth in another frame (metres off)."""
    r1, map1, work = live_session
    res = cli("slam", kidnap_scene, *LIVE, "--map", map1, "--report", work / "r3.json")
    assert res.returncode == 0, res.stderr
    r = json.loads((work / "r3.json").read_text())
    assert r["truth_aligned_on_keyframes"]
    assert r["n_kidnaps"] == r["n_recovered"] and r["n_false_anchors"] == 0
    assert r["ate_rmse_m"] < 0.05, r["ate_rmse_m"]


def test_slam_needs_a_map_or_an_out(kidnap_scene, tmp_path):
    res = cli("slam", kidnap_scene, "--report", tmp_path / "r.json")
    assert res.returncode == 2
    assert res.stderr.strip().count("\n") == 0 and "--map or --out" in res.stderr


@pytest.mark.parametrize("args, says", [
    (["--learn-every", "5"], "--learn-every applies only with --out"),
    (["--out", "m", "--learn-every", "0"], "--learn-every must be in 1..10000000"),
])
def test_learn_every_needs_out_and_a_count(kidnap_scene, tmp_path, args, says):
    args = [tmp_path / a if a == "m" else a for a in args]
    res = cli("slam", kidnap_scene, "--map", tmp_path / "none", *args,
              "--report", tmp_path / "r.json")
    assert res.returncode == 2 and res.stderr.count("\n") == 1 and says in res.stderr, res.stderr
    assert not (tmp_path / "m").exists()


def test_out_refuses_a_foreign_folder(kidnap_scene, tmp_path):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep me")
    res = cli("slam", kidnap_scene, "--out", tmp_path / "mine", "--report", tmp_path / "r.json")
    assert res.returncode == 2 and "--out" in res.stderr
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep me"


def test_learner_rounds_scratch_then_bounded_warm_windows():
    """The first round starts from scratch; later ones warm-start on the new rows plus replayed
    old ones, at most `round_rows`; rows doubling forces a scratch round; the final round
    trains every row; a published model is never trained further."""
    from slamreloc.regressor.model import RegressorConfig
    from slamreloc.regressor.train import TrainConfig
    from slamreloc.slam.learner import BackgroundLearner, LearnerConfig

    rng = np.random.default_rng(0)
    desc = rng.standard_normal((5000, 32)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    pts = rng.uniform(-1, 1, (5000, 3)).astype(np.float32)
    config = LearnerConfig(warm_epochs=1, scratch_epochs=1, final_epochs=1, round_rows=1000,
                           min_rows=500, train=TrainConfig(batch_size=256))
    learner = BackgroundLearner(RegressorConfig(in_dim=32, hidden=(64, 32)), config)
    learner.submit(desc[:400], pts[:400])  # below min_rows: no round
    learner.wait()
    assert learner.model is None and not learner.rounds
    learner.submit(desc[:2000], pts[:2000])
    learner.wait()
    first = learner.model
    assert learner.rounds[-1].scratch and learner.rounds[-1].n_rows == 2000
    assert not any(p.requires_grad for p in first.parameters())
    weights = [p.clone() for p in first.parameters()]
    learner.submit(desc[:2500], pts[:2500])
    learner.wait()
    assert not learner.rounds[-1].scratch and learner.rounds[-1].n_rows == 1000
    assert learner.model is not first and learner.version == 2
    assert all(torch_equal(a, b) for a, b in zip(weights, first.parameters()))
    learner.submit(desc[:4000], pts[:4000])  # doubled since the last scratch round
    learner.wait()
    assert learner.rounds[-1].scratch and learner.rounds[-1].n_rows == 4000
    learner.submit(desc, pts, final=True)
    learner.wait()
    assert not learner.rounds[-1].scratch and learner.rounds[-1].n_rows == 5000


def test_more_new_rows_than_a_warm_window_makes_a_scratch_round():
    """Rows grown by less than `regrow`, but more new rows than `round_rows`: a warm window
    would leave some of them out, so the round trains every row from scratch; fewer new rows
    than the window: warm."""
    from slamreloc.regressor.model import RegressorConfig
    from slamreloc.regressor.train import TrainConfig
    from slamreloc.slam.learner import BackgroundLearner, LearnerConfig

    rng = np.random.default_rng(3)
    desc = rng.standard_normal((4000, 32)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    pts = rng.uniform(-1, 1, (4000, 3)).astype(np.float32)
    config = LearnerConfig(warm_epochs=1, scratch_epochs=1, round_rows=1000, min_rows=500,
                           train=TrainConfig(batch_size=256), background=False)
    learner = BackgroundLearner(RegressorConfig(in_dim=32, hidden=(64, 32)), config)
    for n in (2000, 3000, 3900):  # 1000 new: warm; then 900 new after a warm round: warm
        learner.submit(desc[:n], pts[:n])
    assert [r.scratch for r in learner.rounds] == [True, False, False]
    learner = BackgroundLearner(RegressorConfig(in_dim=32, hidden=(64, 32)), config)
    for n in (2000, 3001):  # 1001 new, 1.5x the rows
        learner.submit(desc[:n], pts[:n])
    assert [r.scratch for r in learner.rounds] == [True, True]
    assert learner.rounds[-1].n_rows == 3001


def test_learner_on_the_submitting_thread_is_reproducible():
    """`background=False` (`slam --learn-every`): each submission's round has ended when
    `submit` returns, no thread is started, and the same submissions give the same model."""
    import threading

    from slamreloc.regressor.model import RegressorConfig
    from slamreloc.regressor.train import TrainConfig
    from slamreloc.slam.learner import BackgroundLearner, LearnerConfig

    rng = np.random.default_rng(1)
    desc = rng.standard_normal((3000, 32)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    pts = rng.uniform(-1, 1, (3000, 3)).astype(np.float32)
    config = LearnerConfig(warm_epochs=1, scratch_epochs=1, round_rows=1000, min_rows=500,
                           train=TrainConfig(batch_size=256), background=False)
    models = []
    for _ in range(2):
        threads = threading.active_count()
        learner = BackgroundLearner(RegressorConfig(in_dim=32, hidden=(64, 32)), config)
        for n in (1000, 2000, 3000):
            learner.submit(desc[:n], pts[:n])
            assert learner.rounds[-1].n_rows == min(n, 1000) or learner.rounds[-1].scratch
        assert len(learner.rounds) == 3 and not learner.running
        assert threading.active_count() == threads
        models.append(learner.model)
    assert all(torch_equal(a, b) for a, b in zip(*(m.parameters() for m in models)))


def test_a_warm_round_that_fits_badly_makes_the_next_one_scratch():
    """Rows grown by less than `regrow`, but in a place far outside the first one's regions:
    the warm round ends far above the scratch round's training distance, so the next round,
    the final one included, starts from scratch and fits again."""
    from slamreloc.regressor.model import RegressorConfig
    from slamreloc.regressor.train import TrainConfig
    from slamreloc.slam.learner import BackgroundLearner, LearnerConfig

    rng = np.random.default_rng(2)
    desc = rng.standard_normal((1800, 32)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    pts = rng.uniform(-1, 1, (1800, 3)).astype(np.float32)
    pts[1000:] += np.float32([40.0, 0.0, 0.0])  # a new room, 40 m away
    config = LearnerConfig(warm_epochs=1, scratch_epochs=6, final_epochs=6, round_rows=4000,
                           min_rows=500, scratch_steps=10_000, background=False,
                           train=TrainConfig(batch_size=128))
    learner = BackgroundLearner(RegressorConfig(in_dim=32, hidden=(128, 64), head="clusters",
                                                n_clusters=16), config)
    learner.submit(desc[:1000], pts[:1000])
    learner.submit(desc, pts)  # 1.8x the rows: warm by the growth rule
    learner.submit(desc, pts, final=True)
    first, warm, final = learner.rounds
    assert first.scratch and not warm.scratch and final.scratch
    assert warm.final_loss_m > 3 * first.final_loss_m
    assert final.final_loss_m < warm.final_loss_m / 3


def test_learner_failure_reaches_the_tracker():
    from slamreloc.regressor.model import RegressorConfig
    from slamreloc.slam.learner import BackgroundLearner, LearnerConfig

    learner = BackgroundLearner(RegressorConfig(in_dim=32, hidden=(16,)),
                                LearnerConfig(min_rows=10))
    learner.submit(np.zeros((100, 8), np.float32), np.zeros((100, 3), np.float32))
    with pytest.raises(RuntimeError):
        learner.wait()


def torch_equal(a, b) -> bool:
    import torch

    return bool(torch.equal(a, b))


@pytest.mark.parametrize("search_frames, expect_home", [(1, True), (2, False)])
def test_loop_query_searches_only_keyframes_near_the_tracked_pose(search_frames, expect_home):
    """A camera that went out 1.2 m and came back home: its loop query at home matches the
    home keyframe's rows, not a far keyframe whose rows hold the very same descriptors (a
    repeated texture elsewhere) at points that place the camera there; searching the whole
    map (2 keyframes here) takes the far copy, whose descriptors are the nearer ones."""
    from slamreloc.types import Features

    camera = Camera(640, 480, 500.0, 500.0, 320.0, 240.0)
    backend = SlamBackend(None, [], BackendConfig(keyframe_every=1))
    live = LiveMap(LiveMapConfig(loop_search_frames=search_frames))
    live.attach(backend)
    rng = np.random.default_rng(1)
    home_points = rng.uniform(-1, 1, (200, 3)) + [0, 0, 3]
    desc = rng.standard_normal((200, 128)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    noisy = desc + 0.05 * rng.standard_normal(desc.shape).astype(np.float32)
    noisy /= np.linalg.norm(noisy, axis=1, keepdims=True)
    n = 81
    at = [Rigid3(np.eye(3), np.array([0.03 * min(i, n - 1 - i), 0, 0])) for i in range(n)]
    for i, world_from_cam in enumerate(at):
        backend.process(None, None, camera, world_from_cam, float(i))
        if i == 0:
            backend.anchor(0, world_from_cam)
        key = backend.frames[-1].key
        if i == 0:  # home: the true rows, descriptors a little off the query's
            rows = (noisy, home_points)
        elif i == 40:  # 1.2 m away: the query's exact descriptors, points seen from there
            rows = (desc, home_points + at[40].translation)
        else:
            continue
        live.store.add(KeyframeRows(key, i, f"f{i}", np.zeros((200, 2), np.float32),
                                    rows[0].astype(np.float16), world_from_cam.inverse()
                                    .transform(rows[1]).astype(np.float32)))
    uv = home_points[:, :2] / home_points[:, 2:] * 500.0 + [320.0, 240.0]
    feats = Features(uv.astype(np.float32), desc, np.ones(200, np.float32))
    result = live.localize_query(feats, camera, n - 1, loop_only=True)
    assert result.source == "database" and result.estimate.success
    found = result.estimate.world_from_cam.translation
    if expect_home:
        np.testing.assert_allclose(found, at[0].translation, atol=0.01)
        assert result.reference.frame == 0
    else:
        np.testing.assert_allclose(found, at[40].translation, atol=0.01)


def _slam_process(kidnap_scene, work):
    import os

    return subprocess.Popen(
        [sys.executable, "-m", "slamreloc.cli", "slam", str(kidnap_scene), *LIVE, "--out",
         str(work / "map"), "--save-every", "1", "--report", str(work / "r.json")],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"})


def test_sigterm_while_learning_writes_the_map_and_ends_in_one_line(kidnap_scene, tmp_path):
    """SIGTERM once a round has published (the map is on disk): the session ends as on
    Ctrl-C, exit 130, one `interrupted:` line, the map written and loadable; the learner's
    thread is stopped first (a process leaving it inside torch aborts: SIGABRT, exit 134)."""
    import signal
    import time

    from slamreloc.map.scene_map import SceneMap

    proc = _slam_process(kidnap_scene, tmp_path)
    deadline = time.monotonic() + 240
    while not (tmp_path / "map" / "slamreloc_map.json").exists():
        assert proc.poll() is None, proc.stderr.read()
        assert time.monotonic() < deadline
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("interrupted:"), err
    SceneMap.load(tmp_path / "map")


def test_sigterm_at_start_up_is_one_line(kidnap_scene, tmp_path):
    """SIGTERM while the command is still importing its libraries: one line, exit 130."""
    import signal
    import time

    proc = _slam_process(kidnap_scene, tmp_path)
    time.sleep(1.5)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    lines = [line for line in err.splitlines() if line.strip()]
    assert proc.returncode in (130, -signal.SIGTERM), err  # -15: before our handler is set
    if proc.returncode == 130:  # wherever it landed (an import, a dataclass): one line
        assert len(lines) == 1 and lines[0].startswith("interrupted"), err
    else:
        assert not lines, err


def test_feature_links_hold_keyframes_where_odometry_drifts(kidnap_scene):
    """Odometry that drifts (2 deg and 8 cm over 24 frames): keyframes linked by their
    keypoints on recent keyframes' depth points stay near their true relative poses; without
    links the drift stays in the graph."""
    from plugins.live_mapping import LiveMappingPlugin
    from slamreloc.datasets import load_dataset
    from slamreloc.slam.feed import read_frames

    dataset = load_dataset(kidnap_scene)
    frames = dataset.frames("seq-03")[:24]
    inputs = list(read_frames(dataset, frames))
    n = len(frames)

    def track(link_keyframes: int) -> tuple[float, float, int]:
        live = LiveMap(LiveMapConfig(train_every=10 ** 9, link_keyframes=link_keyframes))
        backend = SlamBackend(None, [LiveMappingPlugin(live)], BackendConfig(keyframe_every=2))
        for i, (frame, inp) in enumerate(zip(frames, inputs)):
            drift = Rigid3(axis_angle_to_matrix(np.radians([0, 2.0 * i / (n - 1), 0])),
                           np.array([0.08 * i / (n - 1), 0, 0]))
            backend.process(inp.image, inp.depth, inp.camera, drift @ frame.world_from_cam,
                            float(i))
        keys = [r for r in backend.frames if r.key is not None]
        first, last = keys[0], keys[-1]
        estimate = backend.keyframe_pose(first.key).inverse() @ backend.keyframe_pose(last.key)
        truth = frames[first.index].world_from_cam.inverse() @ frames[last.index].world_from_cam
        return (*pose_error(estimate, truth), backend.graph.n_links)

    linked_m, linked_deg, n_links = track(3)
    drifted_m, drifted_deg, no_links = track(0)
    assert no_links == 0 and n_links >= 20
    assert drifted_m > 0.05  # the drift is there without links ...
    assert linked_m <= 0.3 * drifted_m and linked_deg <= 0.3 * drifted_deg  # ... not with them


def test_a_bounded_map_stops_growing_and_tracks_on(kidnap_scene):
    """`max_keyframes` (the service's bound on a learning session's map): keyframes past it
    add no rows, and the session goes on tracking."""
    from plugins.live_mapping import LiveMappingPlugin
    from slamreloc.datasets import load_dataset
    from slamreloc.slam.feed import read_frames

    dataset = load_dataset(kidnap_scene)
    frames = dataset.frames("seq-03")[:16]
    live = LiveMap(LiveMapConfig(train_every=10 ** 9, max_keyframes=3, link_keyframes=0))
    backend = SlamBackend(None, [LiveMappingPlugin(live)], BackendConfig(keyframe_every=2))
    for i, (frame, inp) in enumerate(zip(frames, read_frames(dataset, frames))):
        result = backend.process(inp.image, inp.depth, inp.camera, frame.world_from_cam, float(i))
        assert result.world_from_cam is not None
    assert live.full and live.store.n_keyframes == 3
    assert sum(r.key is not None for r in backend.frames) > 3  # the graph went on
