"""Keyframe pose graph on gtsam ISAM2: nodes are map-frame `world_from_cam` poses of keyframes,
odometry between-factors link consecutive keyframes of one track segment, feature links (a
keyframe's keypoints registered on a recent keyframe's depth points) add tighter robust
between-factors to the last few keyframes of the segment, relocalizations are
robust (Cauchy) prior factors tying a keyframe to the map frame, and loop closures found in a
map the session is building are robust between-factors from the keyframe the query was
relocalized against to the query's keyframe (a constraint between keyframes, so the loop holds
wherever the graph moves them)."""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from slamreloc.geometry import Rigid3


@dataclass(frozen=True)
class GraphConfig:
    """Sigmas: rotation in radians, translation in metres. Odometry noise grows with the
    distance and angle travelled between the two keyframes (per metre / per radian)."""

    odom_sigma_rad: float = 0.003
    odom_sigma_m: float = 0.005
    odom_sigma_per_m: float = 0.04
    odom_sigma_per_rad: float = 0.04
    reloc_sigma_rad: float = 0.03
    reloc_sigma_m: float = 0.04
    # a feature link's sigmas: consecutive keyframes of RedKitchen seq-01 (every 3rd frame)
    # registered by PnP on depth points were a median 0.54 cm / 0.18 deg from the dSLAM
    # reference's motion and 0.17 cm / 0.04 deg from SfM's (kiss-icp: 0.90 cm / 0.39 deg)
    link_sigma_rad: float = 0.003
    link_sigma_m: float = 0.004
    cauchy_k: float = 1.0  # robust kernel scale, in standard deviations
    relinearize_threshold: float = 0.01


def _pose3(p: Rigid3) -> gtsam.Pose3:
    return gtsam.Pose3(p.matrix())


def _rigid(p: gtsam.Pose3) -> Rigid3:
    m = p.matrix()
    return Rigid3(m[:3, :3].copy(), m[:3, 3].copy())


class PoseGraph:
    """Incremental keyframe graph. Keys are integers (keyframe ids); poses are world_from_cam."""

    def __init__(self, config: GraphConfig = GraphConfig()):
        self.config = config
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(config.relinearize_threshold)
        params.relinearizeSkip = 1  # robust kernels re-weight with every relinearization
        self._isam = gtsam.ISAM2(params)
        self._batch: gtsam.Values | None = None  # the last optimize_batch, until the next update
        self.n_odometry, self.n_priors, self.n_loops, self.n_links = 0, 0, 0, 0

    def _sigmas(self, rad: float, m: float) -> np.ndarray:
        return np.array([rad] * 3 + [m] * 3)

    def add_node(self, key: int, initial: Rigid3, prev_key: int | None = None,
                 prev_from_cur: Rigid3 | None = None, prior: Rigid3 | None = None) -> None:
        """A new keyframe: linked to `prev_key` by odometry, and/or anchored by `prior`."""
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        values.insert(key, _pose3(initial))
        if prev_key is not None:
            c = self.config
            dist = float(np.linalg.norm(prev_from_cur.translation))
            ang = float(np.radians(_angle_deg(prev_from_cur)))
            grow = c.odom_sigma_per_m * dist + c.odom_sigma_per_rad * ang
            noise = gtsam.noiseModel.Diagonal.Sigmas(
                self._sigmas(c.odom_sigma_rad + grow, c.odom_sigma_m + grow))
            graph.add(gtsam.BetweenFactorPose3(prev_key, key, _pose3(prev_from_cur), noise))
            self.n_odometry += 1
        if prior is not None:
            graph.add(self._prior(key, prior))
        self._update(graph, values)

    def add_prior(self, key: int, world_from_cam: Rigid3, sigma_scale: float = 1.0) -> None:
        """A relocalization of keyframe `key` in the map frame (robust); `sigma_scale`
        widens its sigmas (a less certain source)."""
        graph = gtsam.NonlinearFactorGraph()
        graph.add(self._prior(key, world_from_cam, sigma_scale))
        self._update(graph, gtsam.Values())

    def add_between(self, key_a: int, key_b: int, a_from_b: Rigid3,
                    sigma_scale: float = 1.0) -> None:
        """A loop closure: keyframe b seen from keyframe a (cam_a_from_cam_b, metres), robust,
        with the relocalization sigmas times `sigma_scale`."""
        c = self.config
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.BetweenFactorPose3(key_a, key_b, _pose3(a_from_b), self._robust(
            sigma_scale * c.reloc_sigma_rad, sigma_scale * c.reloc_sigma_m)))
        self.n_loops += 1
        self._update(graph, gtsam.Values())

    def add_links(self, links: list[tuple[int, int, Rigid3]]) -> None:
        """Feature links: (key_a, key_b, cam_a_from_cam_b) of keyframes of one segment, robust,
        with the link sigmas; one update for all."""
        c = self.config
        graph = gtsam.NonlinearFactorGraph()
        for key_a, key_b, a_from_b in links:
            graph.add(gtsam.BetweenFactorPose3(key_a, key_b, _pose3(a_from_b),
                                               self._robust(c.link_sigma_rad, c.link_sigma_m)))
        self.n_links += len(links)
        if links:
            self._update(graph, gtsam.Values())

    def _robust(self, rad: float, m: float):
        """A Cauchy-robust noise model of these sigmas (radians, metres)."""
        return gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Cauchy.Create(self.config.cauchy_k),
            gtsam.noiseModel.Diagonal.Sigmas(self._sigmas(rad, m)))

    def _prior(self, key: int, world_from_cam: Rigid3, sigma_scale: float = 1.0):
        c = self.config
        self.n_priors += 1
        return gtsam.PriorFactorPose3(key, _pose3(world_from_cam), self._robust(
            sigma_scale * c.reloc_sigma_rad, sigma_scale * c.reloc_sigma_m))

    def _update(self, graph, values) -> None:
        # no full calculateEstimate() here: it copies every node, so a run's graph time would
        # grow with its length; poses are read one at a time (pose) or all at the end (poses)
        self._isam.update(graph, values)
        self._batch = None

    def optimize_batch(self) -> None:
        """Polish the whole graph with Levenberg-Marquardt from the ISAM2 estimate (end of a
        run: ISAM2 relinearizes only part of the graph at each update)."""
        graph = self._isam.getFactorsUnsafe()
        self._batch = gtsam.LevenbergMarquardtOptimizer(graph, self._values()).optimize()

    def _values(self) -> gtsam.Values:
        return self._batch if self._batch is not None else self._isam.calculateEstimate()

    def pose(self, key: int) -> Rigid3:
        if self._batch is not None:
            return _rigid(self._batch.atPose3(key))
        return _rigid(self._isam.calculateEstimatePose3(key))

    def poses(self) -> dict[int, Rigid3]:
        values = self._values()
        return {k: _rigid(values.atPose3(k)) for k in values.keys()}


def _angle_deg(p: Rigid3) -> float:
    from slamreloc.geometry import rotation_angle_deg

    return rotation_angle_deg(p.rotation)
