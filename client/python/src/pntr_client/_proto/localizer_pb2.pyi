from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class FrameConvention(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    FRAME_CONVENTION_UNSPECIFIED: _ClassVar[FrameConvention]
    FRAME_CONVENTION_MAP: _ClassVar[FrameConvention]
    FRAME_CONVENTION_ROS: _ClassVar[FrameConvention]

class Mode(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    MODE_UNSPECIFIED: _ClassVar[Mode]
    GLOBAL: _ClassVar[Mode]
    PRIOR: _ClassVar[Mode]
    TRACKING: _ClassVar[Mode]

class ImageEncoding(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    IMAGE_ENCODING_UNSPECIFIED: _ClassVar[ImageEncoding]
    RAW_RGB8: _ClassVar[ImageEncoding]
    PNG: _ClassVar[ImageEncoding]
    JPEG: _ClassVar[ImageEncoding]

class DepthEncoding(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    DEPTH_ENCODING_UNSPECIFIED: _ClassVar[DepthEncoding]
    FLOAT32_METERS: _ClassVar[DepthEncoding]
    UINT16_MILLIMETERS: _ClassVar[DepthEncoding]
    PNG16_MILLIMETERS: _ClassVar[DepthEncoding]

class Status(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    STATUS_UNSPECIFIED: _ClassVar[Status]
    LOCALIZED: _ClassVar[Status]
    NOT_LOCALIZED: _ClassVar[Status]

class NotLocalizedCause(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    NOT_LOCALIZED_CAUSE_UNSPECIFIED: _ClassVar[NotLocalizedCause]
    NO_MATCH: _ClassVar[NotLocalizedCause]
    UNVERIFIED: _ClassVar[NotLocalizedCause]
    LOOK_ALIKE: _ClassVar[NotLocalizedCause]
    OUTSIDE_MAP: _ClassVar[NotLocalizedCause]
    BAD_INPUT: _ClassVar[NotLocalizedCause]

class TrackState(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    TRACK_STATE_UNSPECIFIED: _ClassVar[TrackState]
    TRACK_STATE_NONE: _ClassVar[TrackState]
    TRACK_STATE_RE_ACQUIRING: _ClassVar[TrackState]
    TRACK_STATE_ESTABLISHED: _ClassVar[TrackState]
    TRACK_STATE_CARRIED: _ClassVar[TrackState]
FRAME_CONVENTION_UNSPECIFIED: FrameConvention
FRAME_CONVENTION_MAP: FrameConvention
FRAME_CONVENTION_ROS: FrameConvention
MODE_UNSPECIFIED: Mode
GLOBAL: Mode
PRIOR: Mode
TRACKING: Mode
IMAGE_ENCODING_UNSPECIFIED: ImageEncoding
RAW_RGB8: ImageEncoding
PNG: ImageEncoding
JPEG: ImageEncoding
DEPTH_ENCODING_UNSPECIFIED: DepthEncoding
FLOAT32_METERS: DepthEncoding
UINT16_MILLIMETERS: DepthEncoding
PNG16_MILLIMETERS: DepthEncoding
STATUS_UNSPECIFIED: Status
LOCALIZED: Status
NOT_LOCALIZED: Status
NOT_LOCALIZED_CAUSE_UNSPECIFIED: NotLocalizedCause
NO_MATCH: NotLocalizedCause
UNVERIFIED: NotLocalizedCause
LOOK_ALIKE: NotLocalizedCause
OUTSIDE_MAP: NotLocalizedCause
BAD_INPUT: NotLocalizedCause
TRACK_STATE_UNSPECIFIED: TrackState
TRACK_STATE_NONE: TrackState
TRACK_STATE_RE_ACQUIRING: TrackState
TRACK_STATE_ESTABLISHED: TrackState
TRACK_STATE_CARRIED: TrackState

class LocalizeRequest(_message.Message):
    __slots__ = ("map_id", "rgb", "depth", "intrinsics", "request_id", "prior", "relocalize", "frame_convention", "stamp_s", "odometry", "continuation")
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    RGB_FIELD_NUMBER: _ClassVar[int]
    DEPTH_FIELD_NUMBER: _ClassVar[int]
    INTRINSICS_FIELD_NUMBER: _ClassVar[int]
    REQUEST_ID_FIELD_NUMBER: _ClassVar[int]
    PRIOR_FIELD_NUMBER: _ClassVar[int]
    RELOCALIZE_FIELD_NUMBER: _ClassVar[int]
    FRAME_CONVENTION_FIELD_NUMBER: _ClassVar[int]
    STAMP_S_FIELD_NUMBER: _ClassVar[int]
    ODOMETRY_FIELD_NUMBER: _ClassVar[int]
    CONTINUATION_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    rgb: Image
    depth: Depth
    intrinsics: Intrinsics
    request_id: str
    prior: Prior
    relocalize: bool
    frame_convention: FrameConvention
    stamp_s: float
    odometry: Pose
    continuation: TrackContinuation
    def __init__(self, map_id: _Optional[str] = ..., rgb: _Optional[_Union[Image, _Mapping]] = ..., depth: _Optional[_Union[Depth, _Mapping]] = ..., intrinsics: _Optional[_Union[Intrinsics, _Mapping]] = ..., request_id: _Optional[str] = ..., prior: _Optional[_Union[Prior, _Mapping]] = ..., relocalize: _Optional[bool] = ..., frame_convention: _Optional[_Union[FrameConvention, str]] = ..., stamp_s: _Optional[float] = ..., odometry: _Optional[_Union[Pose, _Mapping]] = ..., continuation: _Optional[_Union[TrackContinuation, _Mapping]] = ...) -> None: ...

class TrackContinuation(_message.Message):
    __slots__ = ("pose", "stamp_s", "sigma_m")
    POSE_FIELD_NUMBER: _ClassVar[int]
    STAMP_S_FIELD_NUMBER: _ClassVar[int]
    SIGMA_M_FIELD_NUMBER: _ClassVar[int]
    pose: Pose
    stamp_s: float
    sigma_m: float
    def __init__(self, pose: _Optional[_Union[Pose, _Mapping]] = ..., stamp_s: _Optional[float] = ..., sigma_m: _Optional[float] = ...) -> None: ...

class Prior(_message.Message):
    __slots__ = ("pose", "covariance", "radius_m")
    POSE_FIELD_NUMBER: _ClassVar[int]
    COVARIANCE_FIELD_NUMBER: _ClassVar[int]
    RADIUS_M_FIELD_NUMBER: _ClassVar[int]
    pose: Pose
    covariance: _containers.RepeatedScalarFieldContainer[float]
    radius_m: float
    def __init__(self, pose: _Optional[_Union[Pose, _Mapping]] = ..., covariance: _Optional[_Iterable[float]] = ..., radius_m: _Optional[float] = ...) -> None: ...

class Image(_message.Message):
    __slots__ = ("width", "height", "encoding", "data")
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    ENCODING_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    width: int
    height: int
    encoding: ImageEncoding
    data: bytes
    def __init__(self, width: _Optional[int] = ..., height: _Optional[int] = ..., encoding: _Optional[_Union[ImageEncoding, str]] = ..., data: _Optional[bytes] = ...) -> None: ...

class Depth(_message.Message):
    __slots__ = ("width", "height", "encoding", "data")
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    ENCODING_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    width: int
    height: int
    encoding: DepthEncoding
    data: bytes
    def __init__(self, width: _Optional[int] = ..., height: _Optional[int] = ..., encoding: _Optional[_Union[DepthEncoding, str]] = ..., data: _Optional[bytes] = ...) -> None: ...

class Intrinsics(_message.Message):
    __slots__ = ("fx", "fy", "cx", "cy", "distortion")
    FX_FIELD_NUMBER: _ClassVar[int]
    FY_FIELD_NUMBER: _ClassVar[int]
    CX_FIELD_NUMBER: _ClassVar[int]
    CY_FIELD_NUMBER: _ClassVar[int]
    DISTORTION_FIELD_NUMBER: _ClassVar[int]
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, fx: _Optional[float] = ..., fy: _Optional[float] = ..., cx: _Optional[float] = ..., cy: _Optional[float] = ..., distortion: _Optional[_Iterable[float]] = ...) -> None: ...

class Vector3(_message.Message):
    __slots__ = ("x", "y", "z")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    Z_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    z: float
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ..., z: _Optional[float] = ...) -> None: ...

class Quaternion(_message.Message):
    __slots__ = ("w", "x", "y", "z")
    W_FIELD_NUMBER: _ClassVar[int]
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    Z_FIELD_NUMBER: _ClassVar[int]
    w: float
    x: float
    y: float
    z: float
    def __init__(self, w: _Optional[float] = ..., x: _Optional[float] = ..., y: _Optional[float] = ..., z: _Optional[float] = ...) -> None: ...

class Pose(_message.Message):
    __slots__ = ("translation", "rotation")
    TRANSLATION_FIELD_NUMBER: _ClassVar[int]
    ROTATION_FIELD_NUMBER: _ClassVar[int]
    translation: Vector3
    rotation: Quaternion
    def __init__(self, translation: _Optional[_Union[Vector3, _Mapping]] = ..., rotation: _Optional[_Union[Quaternion, _Mapping]] = ...) -> None: ...

class StageTiming(_message.Message):
    __slots__ = ("stage", "seconds")
    STAGE_FIELD_NUMBER: _ClassVar[int]
    SECONDS_FIELD_NUMBER: _ClassVar[int]
    stage: str
    seconds: float
    def __init__(self, stage: _Optional[str] = ..., seconds: _Optional[float] = ...) -> None: ...

class LocalizeResponse(_message.Message):
    __slots__ = ("status", "pose", "confidence", "inliers", "matched_image_id", "timings", "map_id", "reason", "retrieved_image_ids", "matched_point", "request_id", "map_version", "covariance", "min_confidence", "mode", "frame_convention", "cause", "track_state")
    STATUS_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    CONFIDENCE_FIELD_NUMBER: _ClassVar[int]
    INLIERS_FIELD_NUMBER: _ClassVar[int]
    MATCHED_IMAGE_ID_FIELD_NUMBER: _ClassVar[int]
    TIMINGS_FIELD_NUMBER: _ClassVar[int]
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    RETRIEVED_IMAGE_IDS_FIELD_NUMBER: _ClassVar[int]
    MATCHED_POINT_FIELD_NUMBER: _ClassVar[int]
    REQUEST_ID_FIELD_NUMBER: _ClassVar[int]
    MAP_VERSION_FIELD_NUMBER: _ClassVar[int]
    COVARIANCE_FIELD_NUMBER: _ClassVar[int]
    MIN_CONFIDENCE_FIELD_NUMBER: _ClassVar[int]
    MODE_FIELD_NUMBER: _ClassVar[int]
    FRAME_CONVENTION_FIELD_NUMBER: _ClassVar[int]
    CAUSE_FIELD_NUMBER: _ClassVar[int]
    TRACK_STATE_FIELD_NUMBER: _ClassVar[int]
    status: Status
    pose: Pose
    confidence: float
    inliers: int
    matched_image_id: str
    timings: _containers.RepeatedCompositeFieldContainer[StageTiming]
    map_id: str
    reason: str
    retrieved_image_ids: _containers.RepeatedScalarFieldContainer[str]
    matched_point: int
    request_id: str
    map_version: str
    covariance: _containers.RepeatedScalarFieldContainer[float]
    min_confidence: float
    mode: Mode
    frame_convention: FrameConvention
    cause: NotLocalizedCause
    track_state: TrackState
    def __init__(self, status: _Optional[_Union[Status, str]] = ..., pose: _Optional[_Union[Pose, _Mapping]] = ..., confidence: _Optional[float] = ..., inliers: _Optional[int] = ..., matched_image_id: _Optional[str] = ..., timings: _Optional[_Iterable[_Union[StageTiming, _Mapping]]] = ..., map_id: _Optional[str] = ..., reason: _Optional[str] = ..., retrieved_image_ids: _Optional[_Iterable[str]] = ..., matched_point: _Optional[int] = ..., request_id: _Optional[str] = ..., map_version: _Optional[str] = ..., covariance: _Optional[_Iterable[float]] = ..., min_confidence: _Optional[float] = ..., mode: _Optional[_Union[Mode, str]] = ..., frame_convention: _Optional[_Union[FrameConvention, str]] = ..., cause: _Optional[_Union[NotLocalizedCause, str]] = ..., track_state: _Optional[_Union[TrackState, str]] = ...) -> None: ...

class GetMapInfoRequest(_message.Message):
    __slots__ = ("map_id",)
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    def __init__(self, map_id: _Optional[str] = ...) -> None: ...

class MapInfo(_message.Message):
    __slots__ = ("map_id", "images", "points", "scenes", "preset", "extractor", "matcher", "global_descriptor", "camera_axes", "intrinsics", "image_width", "image_height", "build_seconds", "loaded_map_ids", "built_preset", "extractor_engine", "up_axis", "version", "built_at", "ros_from_map", "frame_convention", "calibration")
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    IMAGES_FIELD_NUMBER: _ClassVar[int]
    POINTS_FIELD_NUMBER: _ClassVar[int]
    SCENES_FIELD_NUMBER: _ClassVar[int]
    PRESET_FIELD_NUMBER: _ClassVar[int]
    EXTRACTOR_FIELD_NUMBER: _ClassVar[int]
    MATCHER_FIELD_NUMBER: _ClassVar[int]
    GLOBAL_DESCRIPTOR_FIELD_NUMBER: _ClassVar[int]
    CAMERA_AXES_FIELD_NUMBER: _ClassVar[int]
    INTRINSICS_FIELD_NUMBER: _ClassVar[int]
    IMAGE_WIDTH_FIELD_NUMBER: _ClassVar[int]
    IMAGE_HEIGHT_FIELD_NUMBER: _ClassVar[int]
    BUILD_SECONDS_FIELD_NUMBER: _ClassVar[int]
    LOADED_MAP_IDS_FIELD_NUMBER: _ClassVar[int]
    BUILT_PRESET_FIELD_NUMBER: _ClassVar[int]
    EXTRACTOR_ENGINE_FIELD_NUMBER: _ClassVar[int]
    UP_AXIS_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    BUILT_AT_FIELD_NUMBER: _ClassVar[int]
    ROS_FROM_MAP_FIELD_NUMBER: _ClassVar[int]
    FRAME_CONVENTION_FIELD_NUMBER: _ClassVar[int]
    CALIBRATION_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    images: int
    points: int
    scenes: _containers.RepeatedScalarFieldContainer[str]
    preset: str
    extractor: str
    matcher: str
    global_descriptor: str
    camera_axes: str
    intrinsics: Intrinsics
    image_width: int
    image_height: int
    build_seconds: float
    loaded_map_ids: _containers.RepeatedScalarFieldContainer[str]
    built_preset: str
    extractor_engine: str
    up_axis: str
    version: str
    built_at: str
    ros_from_map: Pose
    frame_convention: FrameConvention
    calibration: CalibrationInfo
    def __init__(self, map_id: _Optional[str] = ..., images: _Optional[int] = ..., points: _Optional[int] = ..., scenes: _Optional[_Iterable[str]] = ..., preset: _Optional[str] = ..., extractor: _Optional[str] = ..., matcher: _Optional[str] = ..., global_descriptor: _Optional[str] = ..., camera_axes: _Optional[str] = ..., intrinsics: _Optional[_Union[Intrinsics, _Mapping]] = ..., image_width: _Optional[int] = ..., image_height: _Optional[int] = ..., build_seconds: _Optional[float] = ..., loaded_map_ids: _Optional[_Iterable[str]] = ..., built_preset: _Optional[str] = ..., extractor_engine: _Optional[str] = ..., up_axis: _Optional[str] = ..., version: _Optional[str] = ..., built_at: _Optional[str] = ..., ros_from_map: _Optional[_Union[Pose, _Mapping]] = ..., frame_convention: _Optional[_Union[FrameConvention, str]] = ..., calibration: _Optional[_Union[CalibrationInfo, _Mapping]] = ...) -> None: ...

class CalibrationInfo(_message.Message):
    __slots__ = ("source", "threshold", "fitted_on", "expected_precision", "negatives", "false_positives", "regions", "stale")
    SOURCE_FIELD_NUMBER: _ClassVar[int]
    THRESHOLD_FIELD_NUMBER: _ClassVar[int]
    FITTED_ON_FIELD_NUMBER: _ClassVar[int]
    EXPECTED_PRECISION_FIELD_NUMBER: _ClassVar[int]
    NEGATIVES_FIELD_NUMBER: _ClassVar[int]
    FALSE_POSITIVES_FIELD_NUMBER: _ClassVar[int]
    REGIONS_FIELD_NUMBER: _ClassVar[int]
    STALE_FIELD_NUMBER: _ClassVar[int]
    source: str
    threshold: float
    fitted_on: _containers.RepeatedScalarFieldContainer[str]
    expected_precision: float
    negatives: int
    false_positives: int
    regions: int
    stale: bool
    def __init__(self, source: _Optional[str] = ..., threshold: _Optional[float] = ..., fitted_on: _Optional[_Iterable[str]] = ..., expected_precision: _Optional[float] = ..., negatives: _Optional[int] = ..., false_positives: _Optional[int] = ..., regions: _Optional[int] = ..., stale: _Optional[bool] = ...) -> None: ...

class ExtendMapRequest(_message.Message):
    __slots__ = ("map_id", "sequence", "trajectory", "depth_scale", "rgb_topic", "depth_topic", "info_topic", "pose_topic", "map_frame", "camera_frame")
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    TRAJECTORY_FIELD_NUMBER: _ClassVar[int]
    DEPTH_SCALE_FIELD_NUMBER: _ClassVar[int]
    RGB_TOPIC_FIELD_NUMBER: _ClassVar[int]
    DEPTH_TOPIC_FIELD_NUMBER: _ClassVar[int]
    INFO_TOPIC_FIELD_NUMBER: _ClassVar[int]
    POSE_TOPIC_FIELD_NUMBER: _ClassVar[int]
    MAP_FRAME_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FRAME_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    sequence: _containers.RepeatedScalarFieldContainer[str]
    trajectory: _containers.RepeatedScalarFieldContainer[str]
    depth_scale: float
    rgb_topic: str
    depth_topic: str
    info_topic: str
    pose_topic: str
    map_frame: str
    camera_frame: str
    def __init__(self, map_id: _Optional[str] = ..., sequence: _Optional[_Iterable[str]] = ..., trajectory: _Optional[_Iterable[str]] = ..., depth_scale: _Optional[float] = ..., rgb_topic: _Optional[str] = ..., depth_topic: _Optional[str] = ..., info_topic: _Optional[str] = ..., pose_topic: _Optional[str] = ..., map_frame: _Optional[str] = ..., camera_frame: _Optional[str] = ...) -> None: ...

class ListMapsRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class LoadedMap(_message.Message):
    __slots__ = ("map_id", "version", "images", "file", "preset", "built_at", "heap_bytes", "calibration")
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    IMAGES_FIELD_NUMBER: _ClassVar[int]
    FILE_FIELD_NUMBER: _ClassVar[int]
    PRESET_FIELD_NUMBER: _ClassVar[int]
    BUILT_AT_FIELD_NUMBER: _ClassVar[int]
    HEAP_BYTES_FIELD_NUMBER: _ClassVar[int]
    CALIBRATION_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    version: str
    images: int
    file: str
    preset: str
    built_at: str
    heap_bytes: int
    calibration: CalibrationInfo
    def __init__(self, map_id: _Optional[str] = ..., version: _Optional[str] = ..., images: _Optional[int] = ..., file: _Optional[str] = ..., preset: _Optional[str] = ..., built_at: _Optional[str] = ..., heap_bytes: _Optional[int] = ..., calibration: _Optional[_Union[CalibrationInfo, _Mapping]] = ...) -> None: ...

class ListMapsResponse(_message.Message):
    __slots__ = ("maps",)
    MAPS_FIELD_NUMBER: _ClassVar[int]
    maps: _containers.RepeatedCompositeFieldContainer[LoadedMap]
    def __init__(self, maps: _Optional[_Iterable[_Union[LoadedMap, _Mapping]]] = ...) -> None: ...

class LoadMapRequest(_message.Message):
    __slots__ = ("file",)
    FILE_FIELD_NUMBER: _ClassVar[int]
    file: str
    def __init__(self, file: _Optional[str] = ...) -> None: ...

class ReplaceMapRequest(_message.Message):
    __slots__ = ("map_id", "file")
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    FILE_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    file: str
    def __init__(self, map_id: _Optional[str] = ..., file: _Optional[str] = ...) -> None: ...

class UnloadMapRequest(_message.Message):
    __slots__ = ("map_id",)
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    def __init__(self, map_id: _Optional[str] = ...) -> None: ...

class MapChange(_message.Message):
    __slots__ = ("map", "previous_version", "same_frame", "load_seconds", "images_added")
    MAP_FIELD_NUMBER: _ClassVar[int]
    PREVIOUS_VERSION_FIELD_NUMBER: _ClassVar[int]
    SAME_FRAME_FIELD_NUMBER: _ClassVar[int]
    LOAD_SECONDS_FIELD_NUMBER: _ClassVar[int]
    IMAGES_ADDED_FIELD_NUMBER: _ClassVar[int]
    map: LoadedMap
    previous_version: str
    same_frame: bool
    load_seconds: float
    images_added: int
    def __init__(self, map: _Optional[_Union[LoadedMap, _Mapping]] = ..., previous_version: _Optional[str] = ..., same_frame: _Optional[bool] = ..., load_seconds: _Optional[float] = ..., images_added: _Optional[int] = ...) -> None: ...

class ReloadMapsRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ReloadMapsResponse(_message.Message):
    __slots__ = ("reloaded", "unchanged_map_ids", "failed")
    RELOADED_FIELD_NUMBER: _ClassVar[int]
    UNCHANGED_MAP_IDS_FIELD_NUMBER: _ClassVar[int]
    FAILED_FIELD_NUMBER: _ClassVar[int]
    reloaded: _containers.RepeatedCompositeFieldContainer[MapChange]
    unchanged_map_ids: _containers.RepeatedScalarFieldContainer[str]
    failed: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, reloaded: _Optional[_Iterable[_Union[MapChange, _Mapping]]] = ..., unchanged_map_ids: _Optional[_Iterable[str]] = ..., failed: _Optional[_Iterable[str]] = ...) -> None: ...
