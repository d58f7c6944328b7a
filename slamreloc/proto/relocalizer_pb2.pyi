from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class ErrorKind(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    ERROR_KIND_UNSPECIFIED: _ClassVar[ErrorKind]
    BAD_IMAGE: _ClassVar[ErrorKind]
    BAD_CAMERA: _ClassVar[ErrorKind]
    BAD_DEPTH: _ClassVar[ErrorKind]
    BAD_POSE: _ClassVar[ErrorKind]
    UNKNOWN_MAP: _ClassVar[ErrorKind]
    BAD_REQUEST: _ClassVar[ErrorKind]
    TOO_LARGE: _ClassVar[ErrorKind]
    UNAUTHENTICATED: _ClassVar[ErrorKind]
    OVERLOADED: _ClassVar[ErrorKind]
    INTERNAL: _ClassVar[ErrorKind]
    FAILED_PRECONDITION: _ClassVar[ErrorKind]

class NotLocalized(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    LOCALIZED: _ClassVar[NotLocalized]
    TOO_FEW_KEYPOINTS: _ClassVar[NotLocalized]
    TOO_FEW_INLIERS: _ClassVar[NotLocalized]
    FAR_FROM_PRIOR: _ClassVar[NotLocalized]

class TrackState(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    INITIALIZING: _ClassVar[TrackState]
    TRACKING: _ClassVar[TrackState]
    LOST: _ClassVar[TrackState]
ERROR_KIND_UNSPECIFIED: ErrorKind
BAD_IMAGE: ErrorKind
BAD_CAMERA: ErrorKind
BAD_DEPTH: ErrorKind
BAD_POSE: ErrorKind
UNKNOWN_MAP: ErrorKind
BAD_REQUEST: ErrorKind
TOO_LARGE: ErrorKind
UNAUTHENTICATED: ErrorKind
OVERLOADED: ErrorKind
INTERNAL: ErrorKind
FAILED_PRECONDITION: ErrorKind
LOCALIZED: NotLocalized
TOO_FEW_KEYPOINTS: NotLocalized
TOO_FEW_INLIERS: NotLocalized
FAR_FROM_PRIOR: NotLocalized
INITIALIZING: TrackState
TRACKING: TrackState
LOST: TrackState

class Transform(_message.Message):
    __slots__ = ("tx", "ty", "tz", "qx", "qy", "qz", "qw")
    TX_FIELD_NUMBER: _ClassVar[int]
    TY_FIELD_NUMBER: _ClassVar[int]
    TZ_FIELD_NUMBER: _ClassVar[int]
    QX_FIELD_NUMBER: _ClassVar[int]
    QY_FIELD_NUMBER: _ClassVar[int]
    QZ_FIELD_NUMBER: _ClassVar[int]
    QW_FIELD_NUMBER: _ClassVar[int]
    tx: float
    ty: float
    tz: float
    qx: float
    qy: float
    qz: float
    qw: float
    def __init__(self, tx: _Optional[float] = ..., ty: _Optional[float] = ..., tz: _Optional[float] = ..., qx: _Optional[float] = ..., qy: _Optional[float] = ..., qz: _Optional[float] = ..., qw: _Optional[float] = ...) -> None: ...

class Image(_message.Message):
    __slots__ = ("encoded", "raw")
    ENCODED_FIELD_NUMBER: _ClassVar[int]
    RAW_FIELD_NUMBER: _ClassVar[int]
    encoded: bytes
    raw: RawImage
    def __init__(self, encoded: _Optional[bytes] = ..., raw: _Optional[_Union[RawImage, _Mapping]] = ...) -> None: ...

class RawImage(_message.Message):
    __slots__ = ("width", "height", "channels", "data")
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    CHANNELS_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    width: int
    height: int
    channels: int
    data: bytes
    def __init__(self, width: _Optional[int] = ..., height: _Optional[int] = ..., channels: _Optional[int] = ..., data: _Optional[bytes] = ...) -> None: ...

class PinholeCamera(_message.Message):
    __slots__ = ("width", "height", "fx", "fy", "cx", "cy")
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    FX_FIELD_NUMBER: _ClassVar[int]
    FY_FIELD_NUMBER: _ClassVar[int]
    CX_FIELD_NUMBER: _ClassVar[int]
    CY_FIELD_NUMBER: _ClassVar[int]
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    def __init__(self, width: _Optional[int] = ..., height: _Optional[int] = ..., fx: _Optional[float] = ..., fy: _Optional[float] = ..., cx: _Optional[float] = ..., cy: _Optional[float] = ...) -> None: ...

class Camera(_message.Message):
    __slots__ = ("pinhole", "colmap")
    PINHOLE_FIELD_NUMBER: _ClassVar[int]
    COLMAP_FIELD_NUMBER: _ClassVar[int]
    pinhole: PinholeCamera
    colmap: str
    def __init__(self, pinhole: _Optional[_Union[PinholeCamera, _Mapping]] = ..., colmap: _Optional[str] = ...) -> None: ...

class Depth(_message.Message):
    __slots__ = ("encoding", "width", "height", "data", "units_per_metre", "depth_camera")
    class Encoding(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        FLOAT32_METRES: _ClassVar[Depth.Encoding]
        UINT16: _ClassVar[Depth.Encoding]
        PNG16: _ClassVar[Depth.Encoding]
    FLOAT32_METRES: Depth.Encoding
    UINT16: Depth.Encoding
    PNG16: Depth.Encoding
    ENCODING_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    UNITS_PER_METRE_FIELD_NUMBER: _ClassVar[int]
    DEPTH_CAMERA_FIELD_NUMBER: _ClassVar[int]
    encoding: Depth.Encoding
    width: int
    height: int
    data: bytes
    units_per_metre: float
    depth_camera: PinholeCamera
    def __init__(self, encoding: _Optional[_Union[Depth.Encoding, str]] = ..., width: _Optional[int] = ..., height: _Optional[int] = ..., data: _Optional[bytes] = ..., units_per_metre: _Optional[float] = ..., depth_camera: _Optional[_Union[PinholeCamera, _Mapping]] = ...) -> None: ...

class LocalizeRequest(_message.Message):
    __slots__ = ("map", "image", "camera", "depth", "world_from_cam_prior", "prior_max_m", "prior_max_deg")
    MAP_FIELD_NUMBER: _ClassVar[int]
    IMAGE_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    DEPTH_FIELD_NUMBER: _ClassVar[int]
    WORLD_FROM_CAM_PRIOR_FIELD_NUMBER: _ClassVar[int]
    PRIOR_MAX_M_FIELD_NUMBER: _ClassVar[int]
    PRIOR_MAX_DEG_FIELD_NUMBER: _ClassVar[int]
    map: str
    image: Image
    camera: Camera
    depth: Depth
    world_from_cam_prior: Transform
    prior_max_m: float
    prior_max_deg: float
    def __init__(self, map: _Optional[str] = ..., image: _Optional[_Union[Image, _Mapping]] = ..., camera: _Optional[_Union[Camera, _Mapping]] = ..., depth: _Optional[_Union[Depth, _Mapping]] = ..., world_from_cam_prior: _Optional[_Union[Transform, _Mapping]] = ..., prior_max_m: _Optional[float] = ..., prior_max_deg: _Optional[float] = ...) -> None: ...

class Timings(_message.Message):
    __slots__ = ("decode_ms", "features_ms", "regressor_ms", "pnp_ms", "refine_ms", "total_ms")
    DECODE_MS_FIELD_NUMBER: _ClassVar[int]
    FEATURES_MS_FIELD_NUMBER: _ClassVar[int]
    REGRESSOR_MS_FIELD_NUMBER: _ClassVar[int]
    PNP_MS_FIELD_NUMBER: _ClassVar[int]
    REFINE_MS_FIELD_NUMBER: _ClassVar[int]
    TOTAL_MS_FIELD_NUMBER: _ClassVar[int]
    decode_ms: float
    features_ms: float
    regressor_ms: float
    pnp_ms: float
    refine_ms: float
    total_ms: float
    def __init__(self, decode_ms: _Optional[float] = ..., features_ms: _Optional[float] = ..., regressor_ms: _Optional[float] = ..., pnp_ms: _Optional[float] = ..., refine_ms: _Optional[float] = ..., total_ms: _Optional[float] = ...) -> None: ...

class LocalizeResponse(_message.Message):
    __slots__ = ("localized", "reason", "detail", "world_from_cam", "num_inliers", "num_correspondences", "confidence", "refined", "num_keypoints", "timings", "map_version")
    LOCALIZED_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    DETAIL_FIELD_NUMBER: _ClassVar[int]
    WORLD_FROM_CAM_FIELD_NUMBER: _ClassVar[int]
    NUM_INLIERS_FIELD_NUMBER: _ClassVar[int]
    NUM_CORRESPONDENCES_FIELD_NUMBER: _ClassVar[int]
    CONFIDENCE_FIELD_NUMBER: _ClassVar[int]
    REFINED_FIELD_NUMBER: _ClassVar[int]
    NUM_KEYPOINTS_FIELD_NUMBER: _ClassVar[int]
    TIMINGS_FIELD_NUMBER: _ClassVar[int]
    MAP_VERSION_FIELD_NUMBER: _ClassVar[int]
    localized: bool
    reason: NotLocalized
    detail: str
    world_from_cam: Transform
    num_inliers: int
    num_correspondences: int
    confidence: float
    refined: bool
    num_keypoints: int
    timings: Timings
    map_version: str
    def __init__(self, localized: _Optional[bool] = ..., reason: _Optional[_Union[NotLocalized, str]] = ..., detail: _Optional[str] = ..., world_from_cam: _Optional[_Union[Transform, _Mapping]] = ..., num_inliers: _Optional[int] = ..., num_correspondences: _Optional[int] = ..., confidence: _Optional[float] = ..., refined: _Optional[bool] = ..., num_keypoints: _Optional[int] = ..., timings: _Optional[_Union[Timings, _Mapping]] = ..., map_version: _Optional[str] = ...) -> None: ...

class SessionOpen(_message.Message):
    __slots__ = ("map", "odometry", "depth_camera", "depth_units_per_metre", "learn")
    MAP_FIELD_NUMBER: _ClassVar[int]
    ODOMETRY_FIELD_NUMBER: _ClassVar[int]
    DEPTH_CAMERA_FIELD_NUMBER: _ClassVar[int]
    DEPTH_UNITS_PER_METRE_FIELD_NUMBER: _ClassVar[int]
    LEARN_FIELD_NUMBER: _ClassVar[int]
    map: str
    odometry: str
    depth_camera: PinholeCamera
    depth_units_per_metre: float
    learn: bool
    def __init__(self, map: _Optional[str] = ..., odometry: _Optional[str] = ..., depth_camera: _Optional[_Union[PinholeCamera, _Mapping]] = ..., depth_units_per_metre: _Optional[float] = ..., learn: _Optional[bool] = ...) -> None: ...

class SessionFrame(_message.Message):
    __slots__ = ("image", "camera", "depth", "odometry_world_from_cam", "timestamp")
    IMAGE_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    DEPTH_FIELD_NUMBER: _ClassVar[int]
    ODOMETRY_WORLD_FROM_CAM_FIELD_NUMBER: _ClassVar[int]
    TIMESTAMP_FIELD_NUMBER: _ClassVar[int]
    image: Image
    camera: Camera
    depth: Depth
    odometry_world_from_cam: Transform
    timestamp: float
    def __init__(self, image: _Optional[_Union[Image, _Mapping]] = ..., camera: _Optional[_Union[Camera, _Mapping]] = ..., depth: _Optional[_Union[Depth, _Mapping]] = ..., odometry_world_from_cam: _Optional[_Union[Transform, _Mapping]] = ..., timestamp: _Optional[float] = ...) -> None: ...

class SessionRequest(_message.Message):
    __slots__ = ("open", "frame", "save")
    OPEN_FIELD_NUMBER: _ClassVar[int]
    FRAME_FIELD_NUMBER: _ClassVar[int]
    SAVE_FIELD_NUMBER: _ClassVar[int]
    open: SessionOpen
    frame: SessionFrame
    save: SessionSave
    def __init__(self, open: _Optional[_Union[SessionOpen, _Mapping]] = ..., frame: _Optional[_Union[SessionFrame, _Mapping]] = ..., save: _Optional[_Union[SessionSave, _Mapping]] = ...) -> None: ...

class SessionSave(_message.Message):
    __slots__ = ("name",)
    NAME_FIELD_NUMBER: _ClassVar[int]
    name: str
    def __init__(self, name: _Optional[str] = ...) -> None: ...

class SessionEvent(_message.Message):
    __slots__ = ("kind", "frame", "world_from_cam", "has_pose", "reason", "num_inliers", "confidence", "reanchor", "position")
    class Kind(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        KIND_UNSPECIFIED: _ClassVar[SessionEvent.Kind]
        TRACKING_LOST: _ClassVar[SessionEvent.Kind]
        TRACKING_RECOVERED: _ClassVar[SessionEvent.Kind]
        LOOP_CLOSURE: _ClassVar[SessionEvent.Kind]
        RELOCALIZATION_ACCEPTED: _ClassVar[SessionEvent.Kind]
        RELOCALIZATION_REJECTED: _ClassVar[SessionEvent.Kind]
        NEW_KEYFRAME: _ClassVar[SessionEvent.Kind]
    KIND_UNSPECIFIED: SessionEvent.Kind
    TRACKING_LOST: SessionEvent.Kind
    TRACKING_RECOVERED: SessionEvent.Kind
    LOOP_CLOSURE: SessionEvent.Kind
    RELOCALIZATION_ACCEPTED: SessionEvent.Kind
    RELOCALIZATION_REJECTED: SessionEvent.Kind
    NEW_KEYFRAME: SessionEvent.Kind
    KIND_FIELD_NUMBER: _ClassVar[int]
    FRAME_FIELD_NUMBER: _ClassVar[int]
    WORLD_FROM_CAM_FIELD_NUMBER: _ClassVar[int]
    HAS_POSE_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    NUM_INLIERS_FIELD_NUMBER: _ClassVar[int]
    CONFIDENCE_FIELD_NUMBER: _ClassVar[int]
    REANCHOR_FIELD_NUMBER: _ClassVar[int]
    POSITION_FIELD_NUMBER: _ClassVar[int]
    kind: SessionEvent.Kind
    frame: int
    world_from_cam: Transform
    has_pose: bool
    reason: str
    num_inliers: int
    confidence: float
    reanchor: bool
    position: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, kind: _Optional[_Union[SessionEvent.Kind, str]] = ..., frame: _Optional[int] = ..., world_from_cam: _Optional[_Union[Transform, _Mapping]] = ..., has_pose: _Optional[bool] = ..., reason: _Optional[str] = ..., num_inliers: _Optional[int] = ..., confidence: _Optional[float] = ..., reanchor: _Optional[bool] = ..., position: _Optional[_Iterable[float]] = ...) -> None: ...

class SessionOpened(_message.Message):
    __slots__ = ("session_id", "map_version", "odometry")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    MAP_VERSION_FIELD_NUMBER: _ClassVar[int]
    ODOMETRY_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    map_version: str
    odometry: str
    def __init__(self, session_id: _Optional[str] = ..., map_version: _Optional[str] = ..., odometry: _Optional[str] = ...) -> None: ...

class FrameResult(_message.Message):
    __slots__ = ("index", "state", "has_pose", "world_from_cam", "events", "backend_ms")
    INDEX_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    HAS_POSE_FIELD_NUMBER: _ClassVar[int]
    WORLD_FROM_CAM_FIELD_NUMBER: _ClassVar[int]
    EVENTS_FIELD_NUMBER: _ClassVar[int]
    BACKEND_MS_FIELD_NUMBER: _ClassVar[int]
    index: int
    state: TrackState
    has_pose: bool
    world_from_cam: Transform
    events: _containers.RepeatedCompositeFieldContainer[SessionEvent]
    backend_ms: float
    def __init__(self, index: _Optional[int] = ..., state: _Optional[_Union[TrackState, str]] = ..., has_pose: _Optional[bool] = ..., world_from_cam: _Optional[_Union[Transform, _Mapping]] = ..., events: _Optional[_Iterable[_Union[SessionEvent, _Mapping]]] = ..., backend_ms: _Optional[float] = ...) -> None: ...

class SessionError(_message.Message):
    __slots__ = ("kind", "message", "frame")
    KIND_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    FRAME_FIELD_NUMBER: _ClassVar[int]
    kind: ErrorKind
    message: str
    frame: int
    def __init__(self, kind: _Optional[_Union[ErrorKind, str]] = ..., message: _Optional[str] = ..., frame: _Optional[int] = ...) -> None: ...

class SessionClosed(_message.Message):
    __slots__ = ("world_from_cam", "has_pose", "stats_json")
    WORLD_FROM_CAM_FIELD_NUMBER: _ClassVar[int]
    HAS_POSE_FIELD_NUMBER: _ClassVar[int]
    STATS_JSON_FIELD_NUMBER: _ClassVar[int]
    world_from_cam: _containers.RepeatedCompositeFieldContainer[Transform]
    has_pose: _containers.RepeatedScalarFieldContainer[bool]
    stats_json: str
    def __init__(self, world_from_cam: _Optional[_Iterable[_Union[Transform, _Mapping]]] = ..., has_pose: _Optional[_Iterable[bool]] = ..., stats_json: _Optional[str] = ...) -> None: ...

class MapSaved(_message.Message):
    __slots__ = ("name", "map_version", "num_points", "num_keyframes")
    NAME_FIELD_NUMBER: _ClassVar[int]
    MAP_VERSION_FIELD_NUMBER: _ClassVar[int]
    NUM_POINTS_FIELD_NUMBER: _ClassVar[int]
    NUM_KEYFRAMES_FIELD_NUMBER: _ClassVar[int]
    name: str
    map_version: str
    num_points: int
    num_keyframes: int
    def __init__(self, name: _Optional[str] = ..., map_version: _Optional[str] = ..., num_points: _Optional[int] = ..., num_keyframes: _Optional[int] = ...) -> None: ...

class SessionUpdate(_message.Message):
    __slots__ = ("opened", "frame", "error", "closed", "saved")
    OPENED_FIELD_NUMBER: _ClassVar[int]
    FRAME_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    CLOSED_FIELD_NUMBER: _ClassVar[int]
    SAVED_FIELD_NUMBER: _ClassVar[int]
    opened: SessionOpened
    frame: FrameResult
    error: SessionError
    closed: SessionClosed
    saved: MapSaved
    def __init__(self, opened: _Optional[_Union[SessionOpened, _Mapping]] = ..., frame: _Optional[_Union[FrameResult, _Mapping]] = ..., error: _Optional[_Union[SessionError, _Mapping]] = ..., closed: _Optional[_Union[SessionClosed, _Mapping]] = ..., saved: _Optional[_Union[MapSaved, _Mapping]] = ...) -> None: ...

class HealthRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class HealthResponse(_message.Message):
    __slots__ = ("serving", "protocol", "version", "num_maps", "num_sessions", "uptime_s", "num_requests")
    SERVING_FIELD_NUMBER: _ClassVar[int]
    PROTOCOL_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    NUM_MAPS_FIELD_NUMBER: _ClassVar[int]
    NUM_SESSIONS_FIELD_NUMBER: _ClassVar[int]
    UPTIME_S_FIELD_NUMBER: _ClassVar[int]
    NUM_REQUESTS_FIELD_NUMBER: _ClassVar[int]
    serving: bool
    protocol: str
    version: str
    num_maps: int
    num_sessions: int
    uptime_s: float
    num_requests: int
    def __init__(self, serving: _Optional[bool] = ..., protocol: _Optional[str] = ..., version: _Optional[str] = ..., num_maps: _Optional[int] = ..., num_sessions: _Optional[int] = ..., uptime_s: _Optional[float] = ..., num_requests: _Optional[int] = ...) -> None: ...

class ListMapsRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class MapInfo(_message.Message):
    __slots__ = ("name", "path", "version", "feature", "camera", "metric", "num_points", "size_bytes", "loaded_at", "has_surface")
    NAME_FIELD_NUMBER: _ClassVar[int]
    PATH_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    FEATURE_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    METRIC_FIELD_NUMBER: _ClassVar[int]
    NUM_POINTS_FIELD_NUMBER: _ClassVar[int]
    SIZE_BYTES_FIELD_NUMBER: _ClassVar[int]
    LOADED_AT_FIELD_NUMBER: _ClassVar[int]
    HAS_SURFACE_FIELD_NUMBER: _ClassVar[int]
    name: str
    path: str
    version: str
    feature: str
    camera: str
    metric: bool
    num_points: int
    size_bytes: int
    loaded_at: float
    has_surface: bool
    def __init__(self, name: _Optional[str] = ..., path: _Optional[str] = ..., version: _Optional[str] = ..., feature: _Optional[str] = ..., camera: _Optional[str] = ..., metric: _Optional[bool] = ..., num_points: _Optional[int] = ..., size_bytes: _Optional[int] = ..., loaded_at: _Optional[float] = ..., has_surface: _Optional[bool] = ...) -> None: ...

class ListMapsResponse(_message.Message):
    __slots__ = ("maps",)
    MAPS_FIELD_NUMBER: _ClassVar[int]
    maps: _containers.RepeatedCompositeFieldContainer[MapInfo]
    def __init__(self, maps: _Optional[_Iterable[_Union[MapInfo, _Mapping]]] = ...) -> None: ...

class ReloadMapRequest(_message.Message):
    __slots__ = ("map",)
    MAP_FIELD_NUMBER: _ClassVar[int]
    map: str
    def __init__(self, map: _Optional[str] = ...) -> None: ...

class ReloadMapResponse(_message.Message):
    __slots__ = ("map", "changed")
    MAP_FIELD_NUMBER: _ClassVar[int]
    CHANGED_FIELD_NUMBER: _ClassVar[int]
    map: MapInfo
    changed: bool
    def __init__(self, map: _Optional[_Union[MapInfo, _Mapping]] = ..., changed: _Optional[bool] = ...) -> None: ...
