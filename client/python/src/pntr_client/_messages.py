"""Between numpy and the wire: input checks, LocalizeRequest building, response conversion."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from pntr_client._geometry import check_pose, matrix_to_quaternion, pose_matrix, quaternion_to_matrix, ros_from_map_world
from pntr_client._proto import localizer_pb2 as pb2
from pntr_client._values import Answer, Continuation, Frame, MapInfo, Prior

# The camera the server assumes when a request has no intrinsics (HPointLoc), and the only size it
# accepts then.
HPOINTLOC_SIZE = (256, 256)
_FRAME_KEYS = ("rgb", "depth", "intrinsics", "prior", "request_id", "relocalize", "stamp_s", "odometry")
# Stamps at or above this many seconds are another unit (the server refuses them the same way): 1e11 s
# is the year 5138; Unix time in milliseconds or nanoseconds lies above it.
MAX_STAMP_S = 1e11
# The plausible median of a frame's valid depth, metres: the server refuses a frame whose median lies
# outside (the proto's DepthEncoding), naming the unit the values look like; the client does the same
# before sending, on the same sample (every `stride`-th pixel, `stride` = pixels // 8192, at least 1).
MIN_MEDIAN_DEPTH_M = 0.05
MAX_MEDIAN_DEPTH_M = 50.0
_DEPTH_SAMPLE = 8192


def check_rgb(rgb: Any, where: str = "") -> npt.NDArray[np.uint8]:
    """`rgb` as a C-contiguous HxWx3 uint8 array; ValueError naming the mistake otherwise."""
    a = np.asarray(rgb)
    s = tuple(a.shape)
    if a.ndim == 2:
        raise ValueError(
            f"{where}rgb has shape {s}: expected HxWx3 (a colour image); for a grey image use "
            f"np.stack([grey] * 3, axis=-1)"
        )
    if a.ndim == 3 and s[2] == 4:
        raise ValueError(f"{where}rgb has shape {s} (RGBA?): expected HxWx3; drop the alpha channel: rgb[..., :3]")
    if a.ndim == 3 and s[0] == 3 and s[2] != 3:
        raise ValueError(f"{where}rgb has shape {s} (channels first?): expected HxWx3; use rgb.transpose(1, 2, 0)")
    if a.ndim != 3 or s[2] != 3:
        raise ValueError(f"{where}rgb has shape {s}: expected HxWx3 (height, width, R G B)")
    if a.dtype != np.uint8:
        hint = (
            "; for values in 0..1 use (rgb * 255).round().astype(np.uint8)"
            if np.issubdtype(a.dtype, np.floating)
            else ""
        )
        raise ValueError(f"{where}rgb has dtype {a.dtype}: expected uint8 (0..255){hint}")
    if a.size == 0:
        raise ValueError(f"{where}rgb is empty (shape {s})")
    return np.ascontiguousarray(a)


def _sampled_median(valid_of_sample: npt.NDArray[Any]) -> float:
    """The median of the valid values of a strided sample (the upper one of an even count, as the
    server takes it)."""
    mid = valid_of_sample.size // 2
    return float(np.partition(valid_of_sample, mid)[mid])


def check_depth(
    depth: Any, rgb_shape: tuple[int, ...], where: str = ""
) -> npt.NDArray[np.float32] | npt.NDArray[np.uint16]:
    """`depth` as a C-contiguous HxW little-endian array, the size of the rgb image, in one of the two
    raw encodings the server reads: float32 metres (FLOAT32_METERS) or uint16 millimetres
    (UINT16_MILLIMETERS).

    Any floating dtype is taken as metres and converted to float32; uint16 (either byte order) is
    taken as millimetres and kept as uint16 (a RealSense or ROS 16UC1 image, 0 = missing); an HxWx1
    array is squeezed. ValueError for any other dtype (other integers name the conversion), a wrong
    shape, a size differing from rgb's, no valid pixel at all (every value 0, negative or not
    finite), or values whose median is implausible for their unit (outside 0.05 .. 50 m, the
    server's own rule): float millimetres, metres stored in uint16, normalised depth.
    """
    a = np.asarray(depth)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    s = tuple(a.shape)
    if a.ndim != 2:
        raise ValueError(
            f"{where}depth has shape {s}: expected HxW (one value per pixel: float metres or uint16 millimetres)"
        )
    millimetres = a.dtype.kind == "u" and a.dtype.itemsize == 2
    if not millimetres and a.dtype.kind != "f":
        if a.dtype.kind in "iu":
            hint = (
                "; integer depth must be uint16 millimetres: for millimetres in another integer type use "
                "np.clip(depth, 0, 65535).astype(np.uint16), for metres depth.astype(np.float32)"
            )
        else:
            hint = ""
        raise ValueError(
            f"{where}depth has dtype {a.dtype}: expected float metres (float32) or uint16 millimetres{hint}"
        )
    h, w = rgb_shape[:2]
    if s != (h, w):
        raise ValueError(
            f"{where}depth is {s[0]}x{s[1]} (HxW) but rgb is {h}x{w}: depth must be pixel-aligned "
            f"with rgb and of the same size (register it to the colour camera)"
        )
    stride = max(a.size // _DEPTH_SAMPLE, 1)
    if millimetres:
        mm = np.ascontiguousarray(a, dtype="<u2")
        if not np.any(mm):
            raise ValueError(f"{where}depth (uint16 millimetres) has no valid pixel (every value is 0)")
        sample = mm.ravel()[::stride]
        sample = sample[sample > 0]
        if sample.size:
            median_m = _sampled_median(sample) / 1000.0
            if median_m < MIN_MEDIAN_DEPTH_M:
                raise ValueError(
                    f"{where}depth (uint16 millimetres) has a median valid depth of {median_m * 1000:.0f} mm, "
                    f"below the plausible {MIN_MEDIAN_DEPTH_M * 1000:.0f} mm: these look like metres stored "
                    f"in a millimetre image: send float metres (depth.astype(np.float32)) or millimetres"
                )
            if median_m > MAX_MEDIAN_DEPTH_M:
                raise ValueError(
                    f"{where}depth (uint16 millimetres) has a median valid depth of {median_m:.1f} m, beyond "
                    f"the plausible {MAX_MEDIAN_DEPTH_M:g} m: these look like a unit finer than millimetres "
                    f"(e.g. 0.1 mm): convert to millimetres"
                )
        return mm
    d = np.ascontiguousarray(a, dtype="<f4")
    with np.errstate(invalid="ignore"):
        if not np.any(np.isfinite(d) & (d > 0.0)):
            raise ValueError(f"{where}depth has no valid pixel (every value is 0, negative or not finite)")
        sample = d.ravel()[::stride]
        sample = sample[np.isfinite(sample) & (sample > 0.0)]
    if sample.size:
        median_m = _sampled_median(sample)
        if median_m > MAX_MEDIAN_DEPTH_M:
            raise ValueError(
                f"{where}depth (float, metres) has a median valid depth of {median_m:.1f} m, beyond the "
                f"plausible {MAX_MEDIAN_DEPTH_M:g} m: these look like millimetres: divide by 1000, or send "
                f"uint16 millimetres (np.round(depth).astype(np.uint16))"
            )
        if median_m < MIN_MEDIAN_DEPTH_M:
            raise ValueError(
                f"{where}depth (float, metres) has a median valid depth of {median_m:.4f} m, below the "
                f"plausible {MIN_MEDIAN_DEPTH_M:g} m: these look like a unit larger than metres, or "
                f"normalised or inverse depth: send metres"
            )
    return d


def check_intrinsics(
    intrinsics: Sequence[float] | None, rgb_shape: tuple[int, ...], where: str = ""
) -> pb2.Intrinsics | None:
    """The Intrinsics message for (fx, fy, cx, cy[, k1, k2, p1, p2[, k3]]), or None for the HPointLoc
    camera (allowed only for 256x256 frames); ValueError naming the mistake."""
    h, w = rgb_shape[:2]
    if intrinsics is None:
        if (h, w) != HPOINTLOC_SIZE:
            raise ValueError(
                f"{where}intrinsics=None means the HPointLoc camera, which the server accepts only for "
                f"256x256 frames; pass intrinsics=(fx, fy, cx, cy) for this {h}x{w} (HxW) frame"
            )
        return None
    if np.ndim(intrinsics) != 1:
        raise ValueError(
            f"{where}intrinsics must be a flat sequence (fx, fy, cx, cy[, k1, k2, p1, p2[, k3]]), got "
            f"shape {np.shape(intrinsics)}; from a 3x3 camera matrix K use (K[0, 0], K[1, 1], K[0, 2], K[1, 2])"
        )
    try:
        v = [float(x) for x in intrinsics]
    except (TypeError, ValueError):
        raise ValueError(f"{where}intrinsics must be numbers, got {intrinsics!r}") from None
    if len(v) not in (4, 8, 9):
        raise ValueError(
            f"{where}intrinsics has {len(v)} values: expected (fx, fy, cx, cy) in pixels, optionally "
            f"followed by 4 or 5 distortion coefficients (k1, k2, p1, p2[, k3])"
        )
    if not all(math.isfinite(x) for x in v):
        raise ValueError(f"{where}intrinsics hold a value that is not finite: {v}")
    if v[0] <= 0.0 or v[1] <= 0.0:
        raise ValueError(f"{where}intrinsics: fx and fy must be positive (pixels), got fx={v[0]}, fy={v[1]}")
    return pb2.Intrinsics(fx=v[0], fy=v[1], cx=v[2], cy=v[3], distortion=v[4:])


def pose_message(pose: npt.NDArray[np.float64]) -> pb2.Pose:
    """The Pose message of a checked 4x4 rigid transform."""
    w, x, y, z = matrix_to_quaternion(pose[:3, :3])
    return pb2.Pose(
        translation=pb2.Vector3(x=float(pose[0, 3]), y=float(pose[1, 3]), z=float(pose[2, 3])),
        rotation=pb2.Quaternion(w=w, x=x, y=y, z=z),
    )


def continuation_message(c: Continuation) -> pb2.TrackContinuation:
    """The TrackContinuation message of a `Continuation` (already validated by its constructor)."""
    msg = pb2.TrackContinuation(pose=pose_message(c.pose), sigma_m=c.sigma_m)
    if c.stamp_s is not None:
        msg.stamp_s = c.stamp_s
    return msg


def prior_message(prior: Prior) -> pb2.Prior:
    """The Prior message of a `Prior` (already validated by its constructor)."""
    msg = pb2.Prior(pose=pose_message(prior.pose), radius_m=prior.radius_m or 0.0)
    if prior.covariance is not None:
        msg.covariance.extend(float(c) for c in prior.covariance.ravel())
    return msg


def make_request(
    rgb: npt.NDArray[np.uint8],
    depth: npt.NDArray[np.floating[Any]] | npt.NDArray[np.uint16],
    intrinsics: Sequence[float] | None = None,
    map_id: str = "",
    prior: Prior | None = None,
    request_id: str = "",
    *,
    frame_convention: str | None = None,
    relocalize: bool = False,
    stamp_s: float | None = None,
    odometry: npt.ArrayLike | None = None,
    where: str = "",
) -> pb2.LocalizeRequest:
    """A LocalizeRequest (RAW_RGB8 colour; FLOAT32_METERS or UINT16_MILLIMETERS depth) after checking
    every input.

    Args:
        rgb: HxWx3 uint8, R G B.
        depth: HxW, pixel-aligned with rgb: float metres, sent as FLOAT32_METERS (0 / negative / NaN
            / inf = missing), or uint16 millimetres, sent as UINT16_MILLIMETERS (0 = missing).
        intrinsics: (fx, fy, cx, cy) pixels, optionally + (k1, k2, p1, p2[, k3]); None = HPointLoc camera.
        map_id: the map to localize in; "" = the server's only map.
        prior: optional `Prior`.
        request_id: optional id echoed in the answer.
        frame_convention: "map" or "ros" for the answer's pose, covariance and the prior; None = the
            server's default.
        relocalize: LocalizeStream only: search the whole map for this frame, ignoring the stream's
            tracking state (the server ignores it in a unary Localize call, which is always global).
        stamp_s: when the frame was captured, seconds on the sensor's clock (any epoch; a ROS
            header.stamp is sec + nanosec * 1e-9); None = not given. A stream judges the camera's
            motion by these stamps when its frames carry them, else by when they arrive.
        odometry: LocalizeStream only: 4x4 odom_from_camera, the camera's pose in the robot's own
            odometry frame at capture (camera axes of the frame convention: optical under "ros");
            the stream carries its pose by the motion between frames' odometry where the map gives
            no fix. None = not given.
        where: prefix of error messages (e.g. "frame 3: ").

    Raises ValueError naming the first mistake found.
    """
    rgb_a = check_rgb(rgb, where)
    depth_a = check_depth(depth, rgb_a.shape, where)
    k = check_intrinsics(intrinsics, rgb_a.shape, where)
    if prior is not None and not isinstance(prior, Prior):
        raise ValueError(
            f"{where}prior must be a pntr_client.Prior(pose, covariance=None, radius_m=None), got "
            f"{type(prior).__name__} (an Answer becomes one with answer.as_prior(radius_m))"
        )
    if not isinstance(map_id, str) or not isinstance(request_id, str):
        raise ValueError(f"{where}map_id and request_id must be strings")
    if not isinstance(relocalize, (bool, np.bool_)):
        raise ValueError(f"{where}relocalize must be True or False, got {relocalize!r}")
    stamp = check_stamp(stamp_s, where)
    odom = None
    if odometry is not None:
        shape = np.shape(odometry)
        if shape != (4, 4):
            raise ValueError(f"{where}odometry must be a 4x4 odom_from_camera matrix, got shape {shape}")
        odom = check_pose(odometry, f"{where}odometry")
    h, w = rgb_a.shape[:2]
    depth_encoding = pb2.UINT16_MILLIMETERS if depth_a.dtype == np.dtype("<u2") else pb2.FLOAT32_METERS
    req = pb2.LocalizeRequest(
        map_id=map_id,
        request_id=request_id,
        rgb=pb2.Image(width=w, height=h, encoding=pb2.RAW_RGB8, data=rgb_a.tobytes()),
        depth=pb2.Depth(width=w, height=h, encoding=depth_encoding, data=depth_a.tobytes()),
        relocalize=bool(relocalize),
    )
    if stamp is not None:
        req.stamp_s = stamp
    if frame_convention is not None:
        req.frame_convention = frame_convention_value(frame_convention, where)
    if k is not None:
        req.intrinsics.CopyFrom(k)
    if prior is not None:
        req.prior.CopyFrom(prior_message(prior))
    if odom is not None:
        req.odometry.CopyFrom(pose_message(odom))
    return req


def check_stamp(stamp_s: Any, where: str = "") -> float | None:
    """`stamp_s` as float seconds (None stays None); ValueError naming a wrong unit or value."""
    if stamp_s is None:
        return None
    if isinstance(stamp_s, (bool, np.bool_)) or not isinstance(stamp_s, (int, float, np.integer, np.floating)):
        raise ValueError(f"{where}stamp_s must be seconds as a number, got {stamp_s!r}")
    try:
        s = float(stamp_s)
    except OverflowError:
        s = math.inf
    if not math.isfinite(s) or s < 0:
        raise ValueError(f"{where}stamp_s must be a finite number of seconds >= 0, got {stamp_s!r}")
    if s >= MAX_STAMP_S:
        unit = "nanoseconds" if s >= 1e17 else "microseconds" if s >= 1e14 else "milliseconds"
        raise ValueError(
            f"{where}stamp_s = {stamp_s!r} looks like {unit}: give seconds (a ROS header.stamp is sec + nanosec * 1e-9)"
        )
    return s


def frame_convention_value(name: str, where: str = "") -> int:
    """The FrameConvention enum value of "map" or "ros" (any case); ValueError otherwise."""
    values = {"map": pb2.FRAME_CONVENTION_MAP, "ros": pb2.FRAME_CONVENTION_ROS}
    if not isinstance(name, str) or name.lower() not in values:
        raise ValueError(
            f"{where}frame_convention must be 'map' (the map's own axes) or 'ros' (z-up, optical camera), got {name!r}"
        )
    return int(values[name.lower()])


def frame_convention_name(value: int) -> str:
    """'map', 'ros' or 'unspecified' for a FrameConvention value."""
    return {int(pb2.FRAME_CONVENTION_MAP): "map", int(pb2.FRAME_CONVENTION_ROS): "ros"}.get(value, "unspecified")


def as_frame(frame: Any, index: int) -> Frame:
    """A `Frame` from a `Frame` or a dict with its keys; ValueError for anything else."""
    if isinstance(frame, Frame):
        return frame
    if isinstance(frame, Mapping):
        unknown = [k for k in frame if k not in _FRAME_KEYS]
        if unknown:
            raise ValueError(f"frame {index}: unknown key(s) {unknown} (expected some of {list(_FRAME_KEYS)})")
        missing = [k for k in ("rgb", "depth") if k not in frame]
        if missing:
            raise ValueError(f"frame {index}: missing {missing}")
        return Frame(**frame)
    raise ValueError(f"frame {index} is a {type(frame).__name__}: expected a pntr_client.Frame or a dict")


def _enum_name(enum: Any, value: int) -> str:
    try:
        return str(enum.Name(value))
    except ValueError:  # a value newer than these stubs
        return str(value)


def answer_from_response(resp: pb2.LocalizeResponse) -> Answer:
    """The `Answer` of a LocalizeResponse."""
    status = _enum_name(pb2.Status, resp.status)
    pose = None
    if status == "LOCALIZED" and resp.HasField("pose"):
        t, q = resp.pose.translation, resp.pose.rotation
        pose = pose_matrix((t.x, t.y, t.z), (q.w, q.x, q.y, q.z))
    cov = None
    if len(resp.covariance) == 36:
        cov = np.asarray(resp.covariance, dtype=np.float64).reshape(6, 6)
    return Answer(
        status=status,
        pose=pose,
        confidence=resp.confidence,
        covariance=cov,
        inliers=resp.inliers,
        stage_ms={t.stage: t.seconds * 1e3 for t in resp.timings},
        reason=resp.reason,
        matched_image_id=resp.matched_image_id,
        map_id=resp.map_id,
        map_version=resp.map_version,
        request_id=resp.request_id,
        min_confidence=resp.min_confidence,
        mode=_enum_name(pb2.Mode, resp.mode),
        matched_point=resp.matched_point,
        retrieved_image_ids=tuple(resp.retrieved_image_ids),
        frame_convention=frame_convention_name(resp.frame_convention),
        cause="" if resp.cause == 0 else _enum_name(pb2.NotLocalizedCause, resp.cause),
        track_state="" if resp.track_state == 0 else _enum_name(pb2.TrackState, resp.track_state),
    )


def map_info_from_message(m: pb2.MapInfo) -> MapInfo:
    """The `MapInfo` of a MapInfo message."""
    k = None
    if m.HasField("intrinsics"):
        i = m.intrinsics
        k = (i.fx, i.fy, i.cx, i.cy, *i.distortion)
    return MapInfo(
        map_id=m.map_id,
        images=m.images,
        points=m.points,
        scenes=tuple(m.scenes),
        preset=m.preset,
        extractor=m.extractor,
        matcher=m.matcher,
        global_descriptor=m.global_descriptor,
        camera_axes=m.camera_axes,
        intrinsics=k,
        image_width=m.image_width,
        image_height=m.image_height,
        build_seconds=m.build_seconds,
        loaded_map_ids=tuple(m.loaded_map_ids),
        up_axis=m.up_axis or "y",
        version=m.version,
        frame_convention=frame_convention_name(m.frame_convention),
        ros_from_map=quaternion_to_matrix(
            m.ros_from_map.rotation.w, m.ros_from_map.rotation.x, m.ros_from_map.rotation.y, m.ros_from_map.rotation.z
        )
        if m.HasField("ros_from_map")
        else ros_from_map_world(m.up_axis or "y"),
        calibration_source=m.calibration.source if m.HasField("calibration") else "",
        min_confidence=m.calibration.threshold if m.HasField("calibration") else float("nan"),
        calibration_stale=m.calibration.stale if m.HasField("calibration") else False,
    )
