"""One `Localize` request: checked inputs -> the map's localizer -> optional depth refinement
and prior check -> the response. The same computation as `slamreloc localize` (one
`Localizer.localize` call), so the poses are bit-identical to it for the same image bytes."""

from __future__ import annotations

import time

from slamreloc.geometry import pose_error
from slamreloc.proto import relocalizer_pb2 as pb
from slamreloc.proto.messages import (
    ServiceError,
    camera_from_msg,
    check_depth_camera,
    depth_camera_from_msg,
    depth_from_msg,
    image_from_msg,
    rigid_from_msg,
    transform_msg,
)
from slamreloc.service.maps import ServedMap
from slamreloc.map.surface import IcpConfig, refine_with_depth

PRIOR_MAX_M, PRIOR_MAX_DEG = 0.5, 20.0  # defaults of LocalizeRequest.prior_max_*
ICP = IcpConfig()  # the depth refinement, as `slamreloc evaluate --depth`
MIN_KEYPOINTS = 4  # PnP needs four correspondences


def prior_limits(request: pb.LocalizeRequest) -> tuple[float, float]:
    """(prior_max_m metres, prior_max_deg degrees): each checked whenever it is set, with or
    without a prior (0: the default); BAD_POSE naming the field otherwise."""
    out = []
    for name, default in (("prior_max_m", PRIOR_MAX_M), ("prior_max_deg", PRIOR_MAX_DEG)):
        value = getattr(request, name)
        if value != 0 and not 0 < value < float("inf"):  # NaN fails
            raise ServiceError(pb.BAD_POSE, f"{name} {value!r}: a positive finite number "
                               "(0: the default)")
        out.append(value or default)
    return out[0], out[1]


def localize(served: ServedMap, request: pb.LocalizeRequest) -> pb.LocalizeResponse:
    """Answer one request from `served`; ServiceError for a defective request."""
    t0 = time.perf_counter()
    scene_map = served.scene_map
    with served.localizer() as loc:
        image = image_from_msg(request.image, loc.extractor.check_size)
        h, w = image.shape[:2]
        camera = camera_from_msg(request.camera if request.HasField("camera") else None, w, h,
                                 scene_map.camera)
        prior = (rigid_from_msg(request.world_from_cam_prior, "world_from_cam_prior")
                 if request.HasField("world_from_cam_prior") else None)
        limits = prior_limits(request)
        depth = depth_camera = None  # depth_camera None: depth registered to the image
        if request.HasField("depth"):
            if request.depth.HasField("depth_camera"):
                depth_camera = depth_camera_from_msg(request.depth.depth_camera,
                                                     "depth.depth_camera")
            depth = depth_from_msg(request.depth, (w, h) if depth_camera is None else None)
            if depth_camera is not None:
                check_depth_camera(request.depth.depth_camera, depth, "depth.depth_camera")
        t1 = time.perf_counter()
        result = loc.localize(image, camera)
    est = result.estimate
    world_from_cam, refined = est.world_from_cam, False
    t2 = time.perf_counter()
    if world_from_cam is not None and depth is not None and scene_map.surface is not None:
        # a depth map without a valid pixel leaves the pose as PnP found it
        fit = refine_with_depth(scene_map.surface, depth, camera, depth_camera, world_from_cam,
                                ICP)
        world_from_cam, refined = fit.chosen(), bool(fit.accepted)
    t3 = time.perf_counter()
    out = pb.LocalizeResponse(
        num_inliers=est.num_inliers, num_correspondences=est.num_correspondences,
        confidence=est.confidence, refined=refined, num_keypoints=result.n_keypoints,
        map_version=served.version)
    ms = result.timings_ms
    out.timings.CopyFrom(pb.Timings(
        decode_ms=1000 * (t1 - t0), features_ms=ms["features"], regressor_ms=ms["regressor"],
        pnp_ms=ms["pnp"], refine_ms=1000 * (t3 - t2), total_ms=1000 * (time.perf_counter() - t0)))
    if world_from_cam is None:
        few = result.n_keypoints < MIN_KEYPOINTS
        out.reason = pb.TOO_FEW_KEYPOINTS if few else pb.TOO_FEW_INLIERS
        out.detail = (f"{result.n_keypoints} keypoints" if few else
                      f"{est.num_inliers} inliers of {est.num_correspondences} correspondences")
        return out
    out.world_from_cam.CopyFrom(transform_msg(world_from_cam))
    if prior is not None:
        dist_m, angle_deg = pose_error(world_from_cam, prior)
        if dist_m > limits[0] or angle_deg > limits[1]:
            out.reason = pb.FAR_FROM_PRIOR
            out.detail = f"{dist_m:.3f} m / {angle_deg:.1f} deg from the prior"
            return out
    out.localized = True
    return out
