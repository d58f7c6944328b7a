"""A map learned while the SLAM backend runs: the keyframes' labelled rows (keyframes.py), the
regressor trained on them in the background (learner.py), relocalization against both, and
writing it as a map every command takes.

Relocalization of a frame (`localize_features`), against the map as it stands:
1. the regressor, once a round has published one: regressed points -> PnP-RANSAC on the
   confident half, then guided matching to the database rows near that pose and the final
   refinement on their points (as `RegressorLocalizer`);
2. the database, where there is no regressor yet or it finds too few inliers (a place mapped
   since its last round): each descriptor's nearest database row (ratio test) -> PnP-RANSAC.
   A regressor pose with enough inliers but no old rows near it (a loop query in a place only
   mapped recently) is returned without a reference: it confirms the track, closes nothing.
Either way the result names the keyframe that holds most of its inliers and the pose relative
to it (`Reference`): the backend turns a relocalization against an old keyframe into a loop
closure between keyframes, so it holds wherever the graph later moves them.

Frames: the map frame is the session's (its first keyframe's camera frame, or the prior map's
frame in multi-session); poses are world_from_cam, points in metres.
"""

from __future__ import annotations

import copy
import time
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from slamreloc.features import make_extractor
from slamreloc.features.matcher import LOCALIZER_DB_CHUNK, match_descriptors
from slamreloc.geometry import Rigid3, project, reprojection_px
from slamreloc.localize.guided import GuidedConfig, GuidedMatcher
from slamreloc.localize.localizer import REGRESSOR_PNP, Localization
from slamreloc.localize.pnp import PnPConfig, PoseEstimate, estimate_pose, refine_from
from slamreloc.io.images import picture_digest
from slamreloc.map.format import SURFACE
from slamreloc.map.joining import Held, held_by
from slamreloc.map.meta import (
    CameraMeta,
    DatasetMeta,
    ExtensionMeta,
    FeatureMeta,
    MapMeta,
    RegressorMeta,
)
from slamreloc.map.scene_map import SceneMap
from slamreloc.map.write import save_map
from slamreloc.regressor.model import RegressorConfig
from slamreloc.rgbd import keypoint_points_from
from slamreloc.slam.events import FrameData
from slamreloc.slam.keyframes import KeyframeRows, KeyframeStore, LiveDatabase
from slamreloc.slam.learner import BackgroundLearner, LearnerConfig
from slamreloc.types import Camera, Features


@contextmanager
def _tracker_thread():
    """The tracker's torch work in one thread while the learner trains in its own: OpenMP's
    team size is per thread, and a team of two here waits, operation by operation, for the
    core the learner holds (RedKitchen stream, 2 cores: a feature link's matching took 22 ms
    a pair, 5 ms alone)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


@dataclass(frozen=True)
class LiveMapConfig:
    """features / feature_options / arch: as `slamreloc map`'s (a prior map's are used where
    the session extends one); max_rows_per_keyframe: the strongest keypoints with depth kept
    per keyframe; train_every: keyframes between submissions to the learner; regressor_inliers:
    a regressor pose with fewer PnP inliers falls back to the database; keep_fraction: share
    of the most confident predictions RANSAC uses; ratio: the database matching's ratio test;
    loop_min_frames: what a loop query leaves out and loop_search_*: where it looks
    (`localize_query`)."""

    features: str = "sift"
    feature_options: dict = field(default_factory=dict)
    arch: str = "wide"
    learner: LearnerConfig = field(default_factory=LearnerConfig)
    max_rows_per_keyframe: int = 1000
    train_every: int = 1
    regressor_inliers: int = 40
    # a loop query (`localize_query` while tracking) matches only keyframes at least this many
    # frames older than the query or of another track segment, and prior maps' frames
    loop_min_frames: int = 30
    # a loop query's database search (a tracked frame: its pose is known to within the drift)
    # takes only the rows of the `loop_search_frames` keyframes nearest to the tracked pose
    # that look within `loop_search_angle_deg` of its direction, not the whole map
    loop_search_frames: int = 20
    loop_search_angle_deg: float = 60.0
    # a loop query runs the regressor's RANSAC only where at least `regressor_inliers` of its
    # confident points reproject within this many pixels of the tracked pose (a place it has
    # not learned yet fails RANSAC only after all of its trials, ~0.1 s)
    loop_gate_px: float = 40.0
    keep_fraction: float = 0.5
    ratio: float = 0.9
    guided: GuidedConfig = field(default_factory=GuidedConfig)
    # feature links (`link`): each keyframe's keypoints registered by PnP on the depth points
    # of the last `link_keyframes` keyframes of its segment (0: none); a link needs
    # `link_min_inliers` within `link_max_error_px`
    link_keyframes: int = 3
    link_min_inliers: int = 40
    link_max_error_px: float = 3.0
    # the most keyframes the map takes (None: no bound); past it the map stops growing and
    # tracking goes on in it (the service bounds its learning sessions' memory so)
    max_keyframes: int | None = None


@dataclass(frozen=True)
class Reference:
    """The keyframe a relocalization's inliers mostly came from: its graph `key` (None: a
    prior map's fixed frame), its index among the session's frames (-1: a prior map's), and
    the query seen from it (cam_key_from_cam, metres)."""

    key: int | None
    frame: int
    key_from_cam: Rigid3
    n_inliers: int


@dataclass
class LiveLocalization(Localization):
    """`Localization` with the source of its correspondences (`regressor` | `database`) and
    the keyframe they mostly came from."""

    source: str = ""
    reference: Reference | None = None


def _not_localized(n: int, source: str = "") -> LiveLocalization:
    """The result for a frame of `n` keypoints that was not localized."""
    return LiveLocalization(PoseEstimate(None, 0, n, np.zeros(n, bool)), {}, n, source=source)


class LiveMap:
    """The map a session builds (see the module's docstring). `prior`: a map to extend
    (multi-session): its rows become fixed frames and its regressor the learner's start;
    `held`: what the prior holds (`map.joining.check_joining`, or by default `held_by`): its
    frames, by name or by picture, never become keyframes."""

    def __init__(self, config: LiveMapConfig = LiveMapConfig(), prior: SceneMap | None = None,
                 held: Held | None = None):
        if prior is not None:
            config = replace(config, features=prior.info.feature_name,
                             feature_options=prior.info.feature_options,
                             arch=prior.info.regressor.arch)
        self.config, self.prior = config, prior
        self.extractor = make_extractor(config.features, **config.feature_options)
        if prior is not None:
            model_config = prior.info.regressor.to_config()
            self.store = KeyframeStore.from_database(prior.database)
            self.camera: Camera | None = prior.camera
            # frames the prior holds (by name or by picture) are never added again
            self._held = held or held_by(prior)
        else:
            model_config = RegressorConfig.preset(config.arch, self.extractor.dim)
            self.store = KeyframeStore()
            self.camera = None
            self._held = Held()
        self.learner = BackgroundLearner(
            model_config, config.learner,
            # a copy: the caller's map (trained again later, say) is left as it was
            initial=None if prior is None else
            copy.deepcopy(prior.regressor).eval().requires_grad_(False),
            initial_rows=self.store.n_rows)
        self.surface = None  # no fused surface: the relocalization plugin's ICP does not run
        self.backend = None
        self._db: LiveDatabase | None = None
        self._guided: GuidedMatcher | None = None  # for `_db`, made when a search needs it
        self._feats: tuple[int, Features] | None = None
        self._since_submit = 0
        self.t_keyframes_s = 0.0  # seconds spent extracting and lifting keyframe rows

    # the relocalization plugin reads `localizer.map.surface` and `localizer.extractor`
    @property
    def map(self) -> LiveMap:
        return self

    def attach(self, backend) -> None:
        """The backend whose pose graph places the keyframes."""
        self.backend = backend

    # ---- growing -------------------------------------------------------------------------
    def features(self, frame: FrameData) -> Features:
        """The frame's features (extracted once per frame: a keyframe that is also relocalized
        is not extracted twice)."""
        if self._feats is None or self._feats[0] != frame.index:
            self._feats = (frame.index, self.extractor.extract(frame.image, frame.camera))
        return self._feats[1]

    def add_keyframe(self, frame: FrameData, key: int) -> int:
        """The keyframe's rows (keypoints with valid depth, the strongest first); returns how
        many. Frames without image or depth add none, and so do frames the prior map holds
        already (by name or by picture: a map holds each frame once, `map.joining`)."""
        if frame.image is None or frame.depth is None or self.full:
            return 0
        t0 = time.perf_counter()
        picture = picture_digest(frame.image)
        if self._held.holds(frame.name, picture):  # a map holds each frame once
            return 0
        self.camera = self.camera or frame.camera
        feats = self.features(frame)
        points = keypoint_points_from(feats.keypoints, frame.depth, frame.camera,
                                      frame.depth_camera, frame.rgb_from_depth)
        ok = np.flatnonzero(np.isfinite(points[:, 0]))
        if len(feats.scores) == len(feats):
            ok = ok[np.argsort(-feats.scores[ok], kind="stable")]
        ok = np.sort(ok[:self.config.max_rows_per_keyframe])
        rows = KeyframeRows(key, frame.index, frame.name or f"frame{frame.index:06d}",
                            feats.keypoints[ok].astype(np.float32),
                            feats.descriptors[ok].astype(np.float16), points[ok].astype(np.float32),
                            picture=picture)
        self.store.add(rows)
        self.link(rows, frame.camera)
        self.t_keyframes_s += time.perf_counter() - t0
        self._since_submit += 1
        if self._since_submit >= self.config.train_every:
            self.train()
        return len(ok)

    @property
    def full(self) -> bool:
        """Whether the map holds `max_keyframes` keyframes of this session (it grows no more)."""
        most = self.config.max_keyframes
        return most is not None and self.store.n_session_keyframes >= most

    def link(self, new: KeyframeRows, camera: Camera) -> int:
        """Feature links of keyframe `new` (just added): its rows' keypoints matched to the
        rows of the last `link_keyframes` keyframes of its track segment and registered by PnP
        on their depth points give cam_old_from_cam_new, a between-factor tighter than the
        odometry's (`GraphConfig.link_sigma_*`); returns how many were added. Depth makes the
        links metric, and they hold where depth odometry slides (flat walls, glass). Only the
        keyframe's rows (its strongest keypoints with depth, `max_rows_per_keyframe`) are
        matched, not all its keypoints: fewer products for links as good (RedKitchen: 24.5 ->
        21.2 ms a keyframe, recovered pose and ATE within the runs' spread)."""
        c = self.config
        if (self.backend is None or c.link_keyframes <= 0
                or len(new.keypoints) < c.link_min_inliers):
            return 0
        frames = self.backend.frames
        segment = frames[new.frame].segment
        recent = [k for k in reversed(self.store.keyframes[:-1])
                  if k.key is not None and frames[k.frame].segment == segment
                  and len(k.keypoints) >= c.link_min_inliers][:c.link_keyframes]
        query = new.descriptors.astype(np.float32)
        keypoints = new.keypoints.astype(np.float64)
        pnp = PnPConfig(max_error_px=c.link_max_error_px, min_inliers=c.link_min_inliers)
        links = []
        with _tracker_thread():
            for old in recent:
                m = match_descriptors(query, old.descriptors.astype(np.float32), c.ratio)
                est = estimate_pose(keypoints[m[:, 0]], old.points_cam[m[:, 1]].astype(np.float64),
                                    camera.pinhole, pnp)
                if est.success:
                    links.append((old.key, new.key, est.cam_from_world.inverse()))
        self.backend.graph.add_links(links)
        return len(links)

    def train(self, final: bool = False) -> None:
        """Hand the learner the database as the graph places it now (a round starts at once
        when none runs); `final`: the session's last round (`LearnerConfig.final_epochs`)."""
        self._since_submit = 0
        db = self.database().database
        self.learner.submit(db.descriptors, db.points, final)

    def _version(self) -> tuple:
        g = self.backend.graph if self.backend is not None else None
        return (self.store.n_keyframes,) + ((g.n_priors, g.n_loops) if g is not None else ())

    def poses(self) -> dict[int, Rigid3]:
        """Graph keyframes' current world_from_cam, by key."""
        return self.backend.graph.poses() if self.backend is not None else {}

    def database(self) -> LiveDatabase:
        """Every row placed with the keyframes' current poses (recomputed when keyframes were
        added or the graph took a relocalization or loop closure since the last call)."""
        version = self._version()
        if self._db is None or self._db.version != version:
            self._db = self.store.database(self.poses(), version)
            self._guided = None
        return self._db

    def _guided_matcher(self) -> GuidedMatcher | None:
        """The guided matcher over the current database (None while it is empty); made at the
        first search of each database version, not at every keyframe."""
        if self._guided is None and len(self.database().database.points):
            self._guided = GuidedMatcher(self._db.database, self.config.guided,
                                         self.store.descriptors_f32())
        return self._guided

    def _descriptors(self, rows: np.ndarray | None) -> torch.Tensor:
        """The database's descriptors as float32 (all of them, or only `rows`)."""
        descriptors = self.store.descriptors_f32()
        return torch.from_numpy(descriptors if rows is None else descriptors[rows])

    # ---- relocalizing --------------------------------------------------------------------
    def localize_features(self, feats: Features, camera: Camera) -> LiveLocalization:
        """The pose of a frame from its features (`extractor`'s), against the map as it
        stands: the regressor, else the database (the module's docstring)."""
        return self._localize(feats, camera, None)

    def localize_query(self, feats: Features, camera: Camera, frame: int,
                       loop_only: bool) -> LiveLocalization:
        """`localize_features` for processed frame `frame`; `loop_only` (a tracked frame):
        its correspondences come only from frames a loop can close on (prior maps' frames,
        keyframes `loop_min_frames` older or of another track segment), since the track's
        own recent keyframes always match and close no loop."""
        if not loop_only:
            return self._localize(feats, camera, None)
        world_from_cam = self.backend.pose_of(frame) if self.backend is not None else None
        return self._localize(feats, camera, self._loop_frames(frame),
                              None if world_from_cam is None else world_from_cam.inverse())

    def _loop_frames(self, frame: int) -> np.ndarray:
        """Mask over the database's frames: those a loop query of `frame` may use."""
        live = self.database()
        frames = self.backend.frames
        segment = frames[frame].segment
        return np.array([f < 0 or frame - f >= self.config.loop_min_frames
                         or frames[f].segment != segment for f in live.frames], bool)

    def _localize(self, feats: Features, camera: Camera, allowed: np.ndarray | None,
                  near: Rigid3 | None = None) -> LiveLocalization:
        """`allowed`: mask over the database's frames; `near`: the tracked cam_from_world
        (map frame), which narrows the database search (`loop_search_*`)."""
        with _tracker_thread():
            return self._localize_here(feats, camera, allowed, near)

    def _localize_here(self, feats, camera, allowed, near) -> LiveLocalization:
        t0 = time.perf_counter()
        live = self.database()
        n = len(feats)
        result = _not_localized(n)
        if (len(live.database.points) < 4 or n < 4
                or (allowed is not None and not allowed.any())):
            return result
        model = self.learner.model
        if model is not None:
            result = self._by_regressor(model, feats, camera, live, allowed, near)
        if (not result.estimate.success
                or result.estimate.num_inliers < self.config.regressor_inliers):
            # the regressor does not know the place (yet): the rows, which know it at once
            result = self._by_database(feats, camera, live, allowed, near)
        result.timings_ms = {"total": 1000 * (time.perf_counter() - t0)}
        return result

    def _by_regressor(self, model, feats, camera, live, allowed, near) -> LiveLocalization:
        with torch.inference_mode():
            points, confidence = model.predict(torch.as_tensor(feats.descriptors,
                                                               dtype=torch.float32))
        points = points.numpy().astype(np.float64)
        conf = None if confidence is None else confidence.numpy()
        keep = np.arange(len(points))
        if conf is not None:
            n_keep = max(round(self.config.keep_fraction * len(conf)), min(len(conf), 50))
            keep = np.argsort(-conf, kind="stable")[:n_keep]
        if near is not None and np.sum(reprojection_px(
                near, feats.keypoints[keep], points[keep], camera.pinhole.params(),
                min_depth_m=1e-3) <= self.config.loop_gate_px) < self.config.regressor_inliers:
            return _not_localized(len(feats), "regressor")
        est = estimate_pose(feats.keypoints[keep], points[keep], camera.pinhole, REGRESSOR_PNP)
        result = LiveLocalization(est, {}, len(feats), source="regressor")
        if not est.success:
            return result
        if conf is not None:
            result.inlier_confidence = float(np.median(conf[keep][est.inlier_mask]))
        p2d, rows = self._guided_matcher().matches(est.cam_from_world, feats, camera, allowed)
        refined = refine_from(est.cam_from_world, p2d, live.database.points[rows]
                              .astype(np.float64), camera.pinhole, REGRESSOR_PNP,
                              max_error_px=self.config.guided.radius_px)
        if refined is not None:
            result.estimate = replace(est, cam_from_world=refined)
            result.n_guided = len(rows)
            result.reference = self._reference(live, rows, refined, p2d, camera)
        return result

    def _by_database(self, feats, camera, live, allowed, near) -> LiveLocalization:
        db = live.database
        index = None
        guided = self._guided_matcher() if near is not None else None
        if guided is not None:
            index = np.sort(guided.nearby_rows(
                near, allowed, self.config.loop_search_frames, self.config.loop_search_angle_deg))
        elif allowed is not None:
            index = np.flatnonzero(allowed[db.frame_index])
        if index is not None and len(index) < 4:
            return _not_localized(len(feats), "database")
        desc = self._descriptors(index)
        m = match_descriptors(feats.descriptors, desc, self.config.ratio, mutual=False,
                              db_points=db.points if index is None else db.points[index],
                              same_point_m=0.05, db_chunk=LOCALIZER_DB_CHUNK)
        if index is not None:
            m[:, 1] = index[m[:, 1]]
        est = estimate_pose(feats.keypoints[m[:, 0]], db.points[m[:, 1]].astype(np.float64),
                            camera.pinhole, PnPConfig())
        result = LiveLocalization(est, {}, len(feats), source="database")
        if est.success:
            rows = m[est.inlier_mask, 1]
            result.reference = self._reference(live, rows, est.cam_from_world)
        return result

    def _reference(self, live: LiveDatabase, rows: np.ndarray, cam_from_world: Rigid3,
                   p2d: np.ndarray | None = None, camera: Camera | None = None
                   ) -> Reference | None:
        """The keyframe holding most of the rows; with p2d, only rows reprojecting within the
        guided radius of their keypoints count."""
        if p2d is not None:
            uv = project(cam_from_world.transform(live.database.points[rows].astype(np.float64)),
                         *camera.pinhole.params())
            rows = rows[np.linalg.norm(uv - p2d, axis=1) <= self.config.guided.radius_px]
        if len(rows) == 0:
            return None
        counts = np.bincount(live.database.frame_index[rows])
        f = int(np.argmax(counts))
        world_from_key = Rigid3.from_matrix(live.database.world_from_cam[f], source="keyframe")
        return Reference(live.keys[f], live.frames[f],
                         world_from_key.inverse() @ cam_from_world.inverse(), int(counts[f]))

    # ---- writing -------------------------------------------------------------------------
    def finish(self, final_round: bool = True, timeout_s: float | None = None) -> None:
        """End of the session: the last round on the keyframes' final placement, waited for
        (none where the session added nothing to its prior map: there is nothing to save)."""
        if final_round and not self.adds_nothing:
            self.learner.wait(timeout_s)
            self.train(final=True)
        self.learner.wait(timeout_s)

    @property
    def adds_nothing(self) -> bool:
        """A session extending a prior map that has added no keyframe to it yet."""
        return self.prior is not None and self.store.n_session_keyframes == 0

    def save(self, out: str | Path, dataset: DatasetMeta | None = None) -> Path | None:
        """Write the map (atomically, `save_map`): the published regressor and every row placed
        with the keyframes' current poses; None (nothing written) before the first round."""
        model = self.learner.model
        if model is None or self.camera is None:
            return None
        live = self.database()
        db = live.database
        learner = self.learner
        n_new = sum(1 for k in live.keys if k is not None)
        surface = None if self.prior is None else self.prior.surface
        meta = MapMeta(
            features=FeatureMeta(self.config.features, self.extractor.config_dict()),
            regressor=RegressorMeta(self.config.arch, model.config.to_dict(),
                                    model.num_parameters()),
            train={**self.config.learner.train.to_dict(), "learned_live": True,
                   "rounds": len(learner.rounds), "trained_rows": learner.trained_rows,
                   "final_loss_m": learner.rounds[-1].final_loss_m if learner.rounds else None,
                   "learner_busy_s": round(learner.busy_s, 3)},
            labels={"n_labelled": int(len(db.points)), "n_keyframes": n_new,
                    "n_prior_frames": len(live.keys) - n_new, "source": "keyframe depth",
                    "median_reproj_error_px": None},
            camera=CameraMeta.from_camera(self.camera),
            dataset=dataset,
            timings_s={"keyframes_s": round(self.t_keyframes_s, 3)},
            # the prior map's frames come first, their images in the datasets it records
            extended=None if self.prior is None else ExtensionMeta(
                source_map=str(self.prior.root.resolve()),
                dataset_roots=tuple(self.prior.info.dataset_roots()),
                pose_files=tuple(self.prior.info.pose_files()) or None,
                n_prior_frames=len(live.keys) - n_new),
            surface=None if surface is None else self.prior.info.surface)
        # a prior map's fused depth surface is kept (`evaluate --depth` refines on it where
        # the session's queries see its places); the session's own keyframes add none
        return save_map(out, meta, model, db,
                        extra=None if surface is None else {SURFACE: surface.to_arrays()})
