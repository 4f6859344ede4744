from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Header(_message.Message):
    __slots__ = ("stamp_ns", "frame_id", "seq")
    STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    stamp_ns: int
    frame_id: str
    seq: int
    def __init__(self, stamp_ns: _Optional[int] = ..., frame_id: _Optional[str] = ..., seq: _Optional[int] = ...) -> None: ...

class Vector3(_message.Message):
    __slots__ = ("x", "y", "z")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    Z_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    z: float
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ..., z: _Optional[float] = ...) -> None: ...

class Pose(_message.Message):
    __slots__ = ("position", "qw", "qx", "qy", "qz")
    POSITION_FIELD_NUMBER: _ClassVar[int]
    QW_FIELD_NUMBER: _ClassVar[int]
    QX_FIELD_NUMBER: _ClassVar[int]
    QY_FIELD_NUMBER: _ClassVar[int]
    QZ_FIELD_NUMBER: _ClassVar[int]
    position: Vector3
    qw: float
    qx: float
    qy: float
    qz: float
    def __init__(self, position: _Optional[_Union[Vector3, _Mapping]] = ..., qw: _Optional[float] = ..., qx: _Optional[float] = ..., qy: _Optional[float] = ..., qz: _Optional[float] = ...) -> None: ...

class CameraInfo(_message.Message):
    __slots__ = ("width", "height", "fx", "fy", "cx", "cy", "baseline_m", "T_body_cam")
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    FX_FIELD_NUMBER: _ClassVar[int]
    FY_FIELD_NUMBER: _ClassVar[int]
    CX_FIELD_NUMBER: _ClassVar[int]
    CY_FIELD_NUMBER: _ClassVar[int]
    BASELINE_M_FIELD_NUMBER: _ClassVar[int]
    T_BODY_CAM_FIELD_NUMBER: _ClassVar[int]
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    baseline_m: float
    T_body_cam: Pose
    def __init__(self, width: _Optional[int] = ..., height: _Optional[int] = ..., fx: _Optional[float] = ..., fy: _Optional[float] = ..., cx: _Optional[float] = ..., cy: _Optional[float] = ..., baseline_m: _Optional[float] = ..., T_body_cam: _Optional[_Union[Pose, _Mapping]] = ...) -> None: ...

class Image(_message.Message):
    __slots__ = ("width", "height", "encoding", "data")
    class Encoding(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        ENCODING_UNSPECIFIED: _ClassVar[Image.Encoding]
        PNG: _ClassVar[Image.Encoding]
        JPEG: _ClassVar[Image.Encoding]
        RAW_MONO8: _ClassVar[Image.Encoding]
        RAW_BGR8: _ClassVar[Image.Encoding]
        RAW_DEPTH_F32: _ClassVar[Image.Encoding]
    ENCODING_UNSPECIFIED: Image.Encoding
    PNG: Image.Encoding
    JPEG: Image.Encoding
    RAW_MONO8: Image.Encoding
    RAW_BGR8: Image.Encoding
    RAW_DEPTH_F32: Image.Encoding
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    ENCODING_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    width: int
    height: int
    encoding: Image.Encoding
    data: bytes
    def __init__(self, width: _Optional[int] = ..., height: _Optional[int] = ..., encoding: _Optional[_Union[Image.Encoding, str]] = ..., data: _Optional[bytes] = ...) -> None: ...

class StereoFrame(_message.Message):
    __slots__ = ("header", "camera_id", "left", "right", "info", "depth")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    CAMERA_ID_FIELD_NUMBER: _ClassVar[int]
    LEFT_FIELD_NUMBER: _ClassVar[int]
    RIGHT_FIELD_NUMBER: _ClassVar[int]
    INFO_FIELD_NUMBER: _ClassVar[int]
    DEPTH_FIELD_NUMBER: _ClassVar[int]
    header: Header
    camera_id: str
    left: Image
    right: Image
    info: CameraInfo
    depth: Image
    def __init__(self, header: _Optional[_Union[Header, _Mapping]] = ..., camera_id: _Optional[str] = ..., left: _Optional[_Union[Image, _Mapping]] = ..., right: _Optional[_Union[Image, _Mapping]] = ..., info: _Optional[_Union[CameraInfo, _Mapping]] = ..., depth: _Optional[_Union[Image, _Mapping]] = ...) -> None: ...

class Imu(_message.Message):
    __slots__ = ("header", "accel_mps2", "gyro_radps")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    ACCEL_MPS2_FIELD_NUMBER: _ClassVar[int]
    GYRO_RADPS_FIELD_NUMBER: _ClassVar[int]
    header: Header
    accel_mps2: Vector3
    gyro_radps: Vector3
    def __init__(self, header: _Optional[_Union[Header, _Mapping]] = ..., accel_mps2: _Optional[_Union[Vector3, _Mapping]] = ..., gyro_radps: _Optional[_Union[Vector3, _Mapping]] = ...) -> None: ...

class Odometry(_message.Message):
    __slots__ = ("header", "T_map_body", "covariance")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    T_MAP_BODY_FIELD_NUMBER: _ClassVar[int]
    COVARIANCE_FIELD_NUMBER: _ClassVar[int]
    header: Header
    T_map_body: Pose
    covariance: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, header: _Optional[_Union[Header, _Mapping]] = ..., T_map_body: _Optional[_Union[Pose, _Mapping]] = ..., covariance: _Optional[_Iterable[float]] = ...) -> None: ...

class ObservedFeature(_message.Message):
    __slots__ = ("type", "score", "corners", "box_xyxy", "id", "centroid", "source_id")
    TYPE_FIELD_NUMBER: _ClassVar[int]
    SCORE_FIELD_NUMBER: _ClassVar[int]
    CORNERS_FIELD_NUMBER: _ClassVar[int]
    BOX_XYXY_FIELD_NUMBER: _ClassVar[int]
    ID_FIELD_NUMBER: _ClassVar[int]
    CENTROID_FIELD_NUMBER: _ClassVar[int]
    SOURCE_ID_FIELD_NUMBER: _ClassVar[int]
    type: str
    score: float
    corners: _containers.RepeatedCompositeFieldContainer[Vector3]
    box_xyxy: _containers.RepeatedScalarFieldContainer[float]
    id: str
    centroid: Vector3
    source_id: str
    def __init__(self, type: _Optional[str] = ..., score: _Optional[float] = ..., corners: _Optional[_Iterable[_Union[Vector3, _Mapping]]] = ..., box_xyxy: _Optional[_Iterable[float]] = ..., id: _Optional[str] = ..., centroid: _Optional[_Union[Vector3, _Mapping]] = ..., source_id: _Optional[str] = ...) -> None: ...

class ObservedFeatures(_message.Message):
    __slots__ = ("header", "features")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    FEATURES_FIELD_NUMBER: _ClassVar[int]
    header: Header
    features: _containers.RepeatedCompositeFieldContainer[ObservedFeature]
    def __init__(self, header: _Optional[_Union[Header, _Mapping]] = ..., features: _Optional[_Iterable[_Union[ObservedFeature, _Mapping]]] = ...) -> None: ...

class GeoPoint(_message.Message):
    __slots__ = ("latitude_deg", "longitude_deg", "altitude_m")
    LATITUDE_DEG_FIELD_NUMBER: _ClassVar[int]
    LONGITUDE_DEG_FIELD_NUMBER: _ClassVar[int]
    ALTITUDE_M_FIELD_NUMBER: _ClassVar[int]
    latitude_deg: float
    longitude_deg: float
    altitude_m: float
    def __init__(self, latitude_deg: _Optional[float] = ..., longitude_deg: _Optional[float] = ..., altitude_m: _Optional[float] = ...) -> None: ...

class PoseEstimate(_message.Message):
    __slots__ = ("header", "T_cad_body", "covariance", "status", "storey", "T_cad_map", "inliers", "T_enu_body", "wgs84")
    class Status(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        STATUS_UNSPECIFIED: _ClassVar[PoseEstimate.Status]
        EXPLORING: _ClassVar[PoseEstimate.Status]
        LOCALIZED: _ClassVar[PoseEstimate.Status]
        AMBIGUOUS: _ClassVar[PoseEstimate.Status]
        DEGRADED: _ClassVar[PoseEstimate.Status]
        LOST: _ClassVar[PoseEstimate.Status]
    STATUS_UNSPECIFIED: PoseEstimate.Status
    EXPLORING: PoseEstimate.Status
    LOCALIZED: PoseEstimate.Status
    AMBIGUOUS: PoseEstimate.Status
    DEGRADED: PoseEstimate.Status
    LOST: PoseEstimate.Status
    HEADER_FIELD_NUMBER: _ClassVar[int]
    T_CAD_BODY_FIELD_NUMBER: _ClassVar[int]
    COVARIANCE_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    STOREY_FIELD_NUMBER: _ClassVar[int]
    T_CAD_MAP_FIELD_NUMBER: _ClassVar[int]
    INLIERS_FIELD_NUMBER: _ClassVar[int]
    T_ENU_BODY_FIELD_NUMBER: _ClassVar[int]
    WGS84_FIELD_NUMBER: _ClassVar[int]
    header: Header
    T_cad_body: Pose
    covariance: _containers.RepeatedScalarFieldContainer[float]
    status: PoseEstimate.Status
    storey: str
    T_cad_map: Pose
    inliers: int
    T_enu_body: Pose
    wgs84: GeoPoint
    def __init__(self, header: _Optional[_Union[Header, _Mapping]] = ..., T_cad_body: _Optional[_Union[Pose, _Mapping]] = ..., covariance: _Optional[_Iterable[float]] = ..., status: _Optional[_Union[PoseEstimate.Status, str]] = ..., storey: _Optional[str] = ..., T_cad_map: _Optional[_Union[Pose, _Mapping]] = ..., inliers: _Optional[int] = ..., T_enu_body: _Optional[_Union[Pose, _Mapping]] = ..., wgs84: _Optional[_Union[GeoPoint, _Mapping]] = ...) -> None: ...

class Goal(_message.Message):
    __slots__ = ("header", "position_cad", "feature_id", "space_name", "start_cad", "has_start")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    POSITION_CAD_FIELD_NUMBER: _ClassVar[int]
    FEATURE_ID_FIELD_NUMBER: _ClassVar[int]
    SPACE_NAME_FIELD_NUMBER: _ClassVar[int]
    START_CAD_FIELD_NUMBER: _ClassVar[int]
    HAS_START_FIELD_NUMBER: _ClassVar[int]
    header: Header
    position_cad: Vector3
    feature_id: str
    space_name: str
    start_cad: Vector3
    has_start: bool
    def __init__(self, header: _Optional[_Union[Header, _Mapping]] = ..., position_cad: _Optional[_Union[Vector3, _Mapping]] = ..., feature_id: _Optional[str] = ..., space_name: _Optional[str] = ..., start_cad: _Optional[_Union[Vector3, _Mapping]] = ..., has_start: _Optional[bool] = ...) -> None: ...

class Waypoints(_message.Message):
    __slots__ = ("header", "points_cad", "path_length_m", "goal_description", "error", "yaw_rad")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    POINTS_CAD_FIELD_NUMBER: _ClassVar[int]
    PATH_LENGTH_M_FIELD_NUMBER: _ClassVar[int]
    GOAL_DESCRIPTION_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    YAW_RAD_FIELD_NUMBER: _ClassVar[int]
    header: Header
    points_cad: _containers.RepeatedCompositeFieldContainer[Vector3]
    path_length_m: float
    goal_description: str
    error: str
    yaw_rad: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, header: _Optional[_Union[Header, _Mapping]] = ..., points_cad: _Optional[_Iterable[_Union[Vector3, _Mapping]]] = ..., path_length_m: _Optional[float] = ..., goal_description: _Optional[str] = ..., error: _Optional[str] = ..., yaw_rad: _Optional[_Iterable[float]] = ...) -> None: ...

class Diagnostics(_message.Message):
    __slots__ = ("header", "rates_hz", "latencies_ms", "dropped", "state", "counts")
    class RatesHzEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: float
        def __init__(self, key: _Optional[str] = ..., value: _Optional[float] = ...) -> None: ...
    class LatenciesMsEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: float
        def __init__(self, key: _Optional[str] = ..., value: _Optional[float] = ...) -> None: ...
    class DroppedEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: int
        def __init__(self, key: _Optional[str] = ..., value: _Optional[int] = ...) -> None: ...
    class CountsEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: int
        def __init__(self, key: _Optional[str] = ..., value: _Optional[int] = ...) -> None: ...
    HEADER_FIELD_NUMBER: _ClassVar[int]
    RATES_HZ_FIELD_NUMBER: _ClassVar[int]
    LATENCIES_MS_FIELD_NUMBER: _ClassVar[int]
    DROPPED_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    COUNTS_FIELD_NUMBER: _ClassVar[int]
    header: Header
    rates_hz: _containers.ScalarMap[str, float]
    latencies_ms: _containers.ScalarMap[str, float]
    dropped: _containers.ScalarMap[str, int]
    state: str
    counts: _containers.ScalarMap[str, int]
    def __init__(self, header: _Optional[_Union[Header, _Mapping]] = ..., rates_hz: _Optional[_Mapping[str, float]] = ..., latencies_ms: _Optional[_Mapping[str, float]] = ..., dropped: _Optional[_Mapping[str, int]] = ..., state: _Optional[str] = ..., counts: _Optional[_Mapping[str, int]] = ...) -> None: ...

class ServiceStatus(_message.Message):
    __slots__ = ("header", "version", "vehicle", "status", "building", "keyframes", "landmarks")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    VEHICLE_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    BUILDING_FIELD_NUMBER: _ClassVar[int]
    KEYFRAMES_FIELD_NUMBER: _ClassVar[int]
    LANDMARKS_FIELD_NUMBER: _ClassVar[int]
    header: Header
    version: str
    vehicle: str
    status: PoseEstimate.Status
    building: str
    keyframes: int
    landmarks: int
    def __init__(self, header: _Optional[_Union[Header, _Mapping]] = ..., version: _Optional[str] = ..., vehicle: _Optional[str] = ..., status: _Optional[_Union[PoseEstimate.Status, str]] = ..., building: _Optional[str] = ..., keyframes: _Optional[int] = ..., landmarks: _Optional[int] = ...) -> None: ...

class MapSnapshot(_message.Message):
    __slots__ = ("header", "building", "building_sha256", "status", "T_cad_map", "storey", "landmarks_map", "T_map_body", "keyframes", "views", "view_poses", "view_log")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    BUILDING_FIELD_NUMBER: _ClassVar[int]
    BUILDING_SHA256_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    T_CAD_MAP_FIELD_NUMBER: _ClassVar[int]
    STOREY_FIELD_NUMBER: _ClassVar[int]
    LANDMARKS_MAP_FIELD_NUMBER: _ClassVar[int]
    T_MAP_BODY_FIELD_NUMBER: _ClassVar[int]
    KEYFRAMES_FIELD_NUMBER: _ClassVar[int]
    VIEWS_FIELD_NUMBER: _ClassVar[int]
    VIEW_POSES_FIELD_NUMBER: _ClassVar[int]
    VIEW_LOG_FIELD_NUMBER: _ClassVar[int]
    header: Header
    building: str
    building_sha256: str
    status: PoseEstimate.Status
    T_cad_map: Pose
    storey: str
    landmarks_map: _containers.RepeatedCompositeFieldContainer[ObservedFeature]
    T_map_body: Pose
    keyframes: int
    views: _containers.RepeatedCompositeFieldContainer[KeyframeView]
    view_poses: _containers.RepeatedCompositeFieldContainer[ViewPose]
    view_log: str
    def __init__(self, header: _Optional[_Union[Header, _Mapping]] = ..., building: _Optional[str] = ..., building_sha256: _Optional[str] = ..., status: _Optional[_Union[PoseEstimate.Status, str]] = ..., T_cad_map: _Optional[_Union[Pose, _Mapping]] = ..., storey: _Optional[str] = ..., landmarks_map: _Optional[_Iterable[_Union[ObservedFeature, _Mapping]]] = ..., T_map_body: _Optional[_Union[Pose, _Mapping]] = ..., keyframes: _Optional[int] = ..., views: _Optional[_Iterable[_Union[KeyframeView, _Mapping]]] = ..., view_poses: _Optional[_Iterable[_Union[ViewPose, _Mapping]]] = ..., view_log: _Optional[str] = ...) -> None: ...

class ViewPose(_message.Message):
    __slots__ = ("record", "T_map_body")
    RECORD_FIELD_NUMBER: _ClassVar[int]
    T_MAP_BODY_FIELD_NUMBER: _ClassVar[int]
    record: int
    T_map_body: Pose
    def __init__(self, record: _Optional[int] = ..., T_map_body: _Optional[_Union[Pose, _Mapping]] = ...) -> None: ...

class KeyframeView(_message.Message):
    __slots__ = ("T_map_body", "points_body", "descriptors")
    T_MAP_BODY_FIELD_NUMBER: _ClassVar[int]
    POINTS_BODY_FIELD_NUMBER: _ClassVar[int]
    DESCRIPTORS_FIELD_NUMBER: _ClassVar[int]
    T_map_body: Pose
    points_body: bytes
    descriptors: bytes
    def __init__(self, T_map_body: _Optional[_Union[Pose, _Mapping]] = ..., points_body: _Optional[bytes] = ..., descriptors: _Optional[bytes] = ...) -> None: ...

class GroundTruth(_message.Message):
    __slots__ = ("header", "T_cad_body", "T_body_cam", "features_cam", "corner_visible", "depth")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    T_CAD_BODY_FIELD_NUMBER: _ClassVar[int]
    T_BODY_CAM_FIELD_NUMBER: _ClassVar[int]
    FEATURES_CAM_FIELD_NUMBER: _ClassVar[int]
    CORNER_VISIBLE_FIELD_NUMBER: _ClassVar[int]
    DEPTH_FIELD_NUMBER: _ClassVar[int]
    header: Header
    T_cad_body: Pose
    T_body_cam: Pose
    features_cam: _containers.RepeatedCompositeFieldContainer[ObservedFeature]
    corner_visible: _containers.RepeatedScalarFieldContainer[bool]
    depth: Image
    def __init__(self, header: _Optional[_Union[Header, _Mapping]] = ..., T_cad_body: _Optional[_Union[Pose, _Mapping]] = ..., T_body_cam: _Optional[_Union[Pose, _Mapping]] = ..., features_cam: _Optional[_Iterable[_Union[ObservedFeature, _Mapping]]] = ..., corner_visible: _Optional[_Iterable[bool]] = ..., depth: _Optional[_Union[Image, _Mapping]] = ...) -> None: ...
