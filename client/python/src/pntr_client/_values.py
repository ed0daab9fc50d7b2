"""The client's value types: what goes in (`Frame`, `Prior`) and what comes back (`Answer`, `MapInfo`).

Conventions: poses are 4x4 float64 `world_from_camera` matrices (they map points from the camera's
frame into the map's world frame), metres, in the frame convention of the call: "map" (the map's
world frame with the camera axes of the map's dataset, e.g. Habitat axes x right, y up, z backwards
for HPointLoc maps) or "ros" (the map frame turned z-up, optical camera axes x right, y down, z
forward: map_from_camera_optical); covariances are 6x6 row-major in ROS order (x, y, z, rotation
about x, y, z), metres² and radians², in the same world frame; times are milliseconds.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from pntr_client._geometry import Quaternion, check_pose, matrix_to_quaternion

LOCALIZED = "LOCALIZED"
NOT_LOCALIZED = "NOT_LOCALIZED"


def _frozen(a: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    a = np.array(a, dtype=np.float64, copy=True)
    a.setflags(write=False)
    return a


def check_covariance(covariance: npt.ArrayLike, what: str) -> npt.NDArray[np.float64]:
    """A read-only 6x6 float64 covariance from 36 values (6x6 or flat row-major); ValueError otherwise."""
    try:
        c = np.asarray(covariance, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{what} must be a 6x6 array (metres², radians²): {e}") from None
    if c.shape == (36,):
        c = c.reshape(6, 6)
    if c.shape != (6, 6):
        raise ValueError(f"{what} has shape {c.shape}: expected 6x6 (x, y, z, rotation about x, y, z)")
    if not np.all(np.isfinite(c)):
        raise ValueError(f"{what} holds a value that is not finite")
    if np.any(np.diag(c) < 0.0):
        raise ValueError(f"{what} has a negative variance on its diagonal: {np.diag(c).tolist()}")
    return _frozen(c)


@dataclass(frozen=True, eq=False)
class Prior:
    """Where the camera roughly is (odometry, the last fix): the server then searches the map images
    inside a sphere around `pose`'s position first, and falls back to the whole map when none of them
    verifies (`Answer.mode` says which path answered). A prior never makes a pose LOCALIZED by itself.

    Attributes:
        pose: 4x4 float64 world_from_camera (metres), in the request's frame convention (the map's
            own frame, or the ROS z-up frame under frame_convention="ros"; an answer's pose is
            already in the convention it was asked in). A (3,) position is accepted and stored with
            the identity rotation (only the position is used to choose map images).
        covariance: optional 6x6 pose covariance (metres², radians²; 36 flat values are accepted).
            Without `radius_m` the region's radius is three standard deviations of the position.
        radius_m: optional radius of the region, metres, > 0; takes precedence over `covariance`.

    At least one of `radius_m` and `covariance` is needed; invalid values raise ValueError.
    """

    pose: npt.NDArray[np.float64]
    covariance: npt.NDArray[np.float64] | None = None
    radius_m: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "pose", _frozen(check_pose(self.pose, "prior.pose")))
        if self.covariance is not None:
            object.__setattr__(self, "covariance", check_covariance(self.covariance, "prior.covariance"))
        if self.radius_m is not None:
            r = float(self.radius_m)
            if not (math.isfinite(r) and r > 0.0):
                raise ValueError(f"prior.radius_m must be a finite number > 0 (metres), got {self.radius_m}")
            object.__setattr__(self, "radius_m", r)
        if self.radius_m is None:
            if self.covariance is None:
                raise ValueError(
                    "a prior needs radius_m > 0 or a 6x6 covariance (metres², radians²) to size its search region"
                )
            if float(np.max(np.diag(self.covariance)[:3])) <= 0.0:
                raise ValueError(
                    "prior.covariance has no position variance (x, y, z all 0), so the region would "
                    "have no size: give radius_m"
                )

    @property
    def position(self) -> npt.NDArray[np.float64]:
        """The prior's position (3,), metres: the centre of the search region."""
        return self.pose[:3, 3]


@dataclass(frozen=True, eq=False)
class Continuation:
    """Where an earlier stream left the camera, for a new `Client.localize_stream` that continues
    its track (after a server restart, a dropped connection, a bad frame that ended the stream):
    the new stream's first frame is then held to the camera's motion since, as the earlier
    stream's next frame would have been, instead of being judged alone.

    Attributes:
        pose: 4x4 float64 world_from_camera (metres) of the earlier stream's last LOCALIZED answer,
            in the new stream's frame convention (an answer's pose already is).
        stamp_s: that frame's capture stamp (its `Frame.stamp_s`, the same clock as the new
            stream's stamps); None = the pose is taken as of the new stream's first frame.
        sigma_m: its position uncertainty, metres, one standard deviation; 0 = a map fix's (5 cm).

    Invalid values raise ValueError.
    """

    pose: npt.NDArray[np.float64]
    stamp_s: float | None = None
    sigma_m: float = 0.0

    def __post_init__(self) -> None:
        # Imported here: the message helpers import these value types.
        from pntr_client._messages import check_stamp

        if np.shape(self.pose) != (4, 4):
            raise ValueError(
                f"continuation.pose must be a 4x4 world_from_camera matrix, got shape {np.shape(self.pose)} "
                "(the last LOCALIZED answer's pose: answer.as_continuation(stamp_s))"
            )
        object.__setattr__(self, "pose", _frozen(check_pose(self.pose, "continuation.pose")))
        s = float(self.sigma_m)
        if not (math.isfinite(s) and s >= 0.0):
            raise ValueError(f"continuation.sigma_m must be a finite number >= 0 (metres), got {self.sigma_m}")
        object.__setattr__(self, "sigma_m", s)
        object.__setattr__(self, "stamp_s", check_stamp(self.stamp_s, "continuation."))


@dataclass(frozen=True, eq=False)
class Frame:
    """One RGB-D frame for `Client.localize_stream` (a dict with the same keys works too).

    Attributes:
        rgb: HxWx3 uint8 colour image, R G B order.
        depth: HxW planar depth (along the optical axis), pixel-aligned with `rgb` and of its size:
            float metres (any float dtype, sent as float32; 0, negative, NaN or infinite pixels are
            missing depth) or uint16 millimetres (a RealSense / ROS 16UC1 image, sent as is; 0 is
            missing depth).
        intrinsics: (fx, fy, cx, cy) in pixels, optionally followed by 4 or 5 distortion
            coefficients (k1, k2, p1, p2[, k3]); None means the HPointLoc camera (256x256 frames only).
        prior: optional `Prior` for this frame.
        request_id: optional id echoed in the answer (the server makes one when empty).
        relocalize: search the whole map for this frame, ignoring the stream's tracking state (the
            robot was carried elsewhere, or a benchmark of global localization); the frame's own
            `prior` is still used, and a LOCALIZED answer becomes the stream's new state. Only a
            stream has such a state: a unary `Client.localize` call is always global.
        stamp_s: when the frame was captured, seconds on the camera's clock (any epoch: a ROS
            header.stamp as sec + nanosec * 1e-9, a recording's timestamps); None = not given. The
            stream judges how far the camera can have moved between two frames by their stamps
            when both carry one, else by when they reached the server: send stamps whenever the
            frames do not reach the server at the pace they were taken (a recording sent faster,
            frames buffered on the way). A stamp earlier than the previous frame's starts the
            stream's tracking afresh.
        odometry: optional 4x4 odom_from_camera: the camera's pose in the robot's own odometry frame
            when the frame was captured (wheel or visual-inertial odometry composed with the camera's
            mounting; camera axes of the stream's frame convention, optical under "ros"). Where the
            map gives the stream no fix, it carries its pose by the motion between two frames'
            odometry, and a later fix must agree with it. Send it on every frame or on none.
    """

    rgb: npt.NDArray[np.uint8]
    depth: npt.NDArray[np.floating[Any]] | npt.NDArray[np.uint16]
    intrinsics: Sequence[float] | None = None
    prior: Prior | None = None
    request_id: str = ""
    relocalize: bool = False
    stamp_s: float | None = None
    odometry: npt.NDArray[np.float64] | None = None


@dataclass(frozen=True, eq=False)
class Answer:
    """The server's answer for one frame.

    Attributes:
        status: "LOCALIZED" or "NOT_LOCALIZED".
        pose: 4x4 float64 world_from_camera (metres) when LOCALIZED, else None, in the convention
            `frame_convention` names: the map's own world frame and camera axes (`MapInfo.up_axis`,
            `MapInfo.camera_axes`), or under "ros" the z-up map frame and optical camera axes
            (map_from_camera_optical).
        confidence: calibrated probability in [0, 1] that the best pose found is within 1 m and 10
            degrees of the truth (reported for NOT_LOCALIZED answers too; 0 when no pose was found).
        covariance: 6x6 float64 covariance of `pose` (metres², radians², ROS order, in the world
            frame of `pose`) when the server sends it (LOCALIZED answers), else None.
        inliers: registration inliers of the matched map image.
        stage_ms: server time per stage, milliseconds, in the server's order (e.g. "queue",
            "resampling", "extraction", "retrieval", "matching", "registration", "verification", "total").
        reason: why the frame is NOT_LOCALIZED; empty when LOCALIZED.
        matched_image_id: the map image the pose was registered against (LOCALIZED only).
        map_id: the map that answered.
        map_version: the version of the map that answered (`MapInfo.version`, e.g.
            "20261203T041500Z-3f2a9c1e0b7d4a55"): after the map is replaced on the server, answers
            to frames already being localized carry the old version, later ones the new; empty from
            a server that does not report it.
        request_id: the request's id (the caller's, or one the server made).
        min_confidence: the server's LOCALIZED threshold on `confidence`.
        mode: which path answered: "GLOBAL", "PRIOR", "TRACKING" ("MODE_UNSPECIFIED" from a server
            that does not report it).
        matched_point: HPointLoc Point index of `matched_image_id` (LOCALIZED only).
        retrieved_image_ids: retrieval candidates, best first.
        frame_convention: "map" (pose and covariance in the map's own frame and camera axes) or
            "ros" (z-up map frame, optical camera axes: map_from_camera_optical), as the server says.
        cause: why the frame is NOT_LOCALIZED, one of "NO_MATCH", "UNVERIFIED", "LOOK_ALIKE",
            "OUTSIDE_MAP" (the camera is where the map does not reach; `reason` then begins with
            "outside the mapped area:") and "BAD_INPUT"; empty when LOCALIZED or from a server that
            does not report it.
        track_state: LocalizeStream only: what the stream knows of where the camera is after this
            frame: "TRACK_STATE_ESTABLISHED", "TRACK_STATE_CARRIED" (no map fix this frame: the pose
            carried by the camera's motion), "TRACK_STATE_RE_ACQUIRING", "TRACK_STATE_NONE"; empty in
            unary answers or from a server that does not report it.
    """

    status: str
    pose: npt.NDArray[np.float64] | None
    confidence: float
    covariance: npt.NDArray[np.float64] | None
    inliers: int
    stage_ms: dict[str, float]
    reason: str
    matched_image_id: str = ""
    map_id: str = ""
    request_id: str = ""
    min_confidence: float = 0.0
    mode: str = "MODE_UNSPECIFIED"
    matched_point: int = 0
    retrieved_image_ids: tuple[str, ...] = field(default_factory=tuple)
    frame_convention: str = "map"
    cause: str = ""
    map_version: str = ""
    track_state: str = ""

    def __post_init__(self) -> None:
        if self.pose is not None:
            object.__setattr__(self, "pose", _frozen(self.pose))
        if self.covariance is not None:
            object.__setattr__(self, "covariance", _frozen(self.covariance))

    @property
    def localized(self) -> bool:
        """True when the status is LOCALIZED (and so `pose` is set)."""
        return self.status == LOCALIZED and self.pose is not None

    @property
    def translation(self) -> npt.NDArray[np.float64] | None:
        """The camera's position in the map (3,), metres, or None when not LOCALIZED."""
        return None if self.pose is None else self.pose[:3, 3]

    @property
    def rotation_wxyz(self) -> Quaternion | None:
        """The pose's rotation as a unit quaternion (w, x, y, z) with w >= 0, or None."""
        return None if self.pose is None else matrix_to_quaternion(self.pose[:3, :3])

    def as_prior(self, radius_m: float | None = None) -> Prior:
        """This answer's pose (and covariance) as the `Prior` of the next frame.

        `radius_m` sizes the search region; without it the region comes from the answer's covariance
        (three standard deviations of the position), which is small: pass a radius covering how far
        the camera may have moved since. Raises ValueError when the answer has no pose, or neither a
        radius nor a covariance.
        """
        if self.pose is None:
            raise ValueError(f"as_prior: this answer is {self.status} and has no pose to use as a prior")
        return Prior(self.pose, covariance=self.covariance, radius_m=radius_m)

    def as_continuation(self, stamp_s: float | None = None) -> Continuation:
        """This LOCALIZED answer as the `Continuation` of a new stream: its pose, the capture stamp
        of its frame (`stamp_s`, the frame's `Frame.stamp_s`), and the position uncertainty of its
        covariance (the root of the largest position variance; 0 without one). Raises ValueError
        when the answer has no pose.
        """
        if self.pose is None:
            raise ValueError(f"as_continuation: this answer is {self.status} and has no pose to continue from")
        sigma_m = 0.0
        if self.covariance is not None:
            sigma_m = math.sqrt(max(0.0, float(np.max(np.diag(self.covariance)[:3]))))
        return Continuation(self.pose, stamp_s=stamp_s, sigma_m=sigma_m)


@dataclass(frozen=True)
class MapInfo:
    """A map the server holds (`Client.map_info`).

    Attributes:
        map_id: the map's id.
        images: database images in the map.
        points: distinct (scene, Point) pairs the images come from.
        scenes: scene names the map covers.
        preset: the preset the server runs for the map (e.g. "fast"): the one it was built with
            unless `pntr-server --preset` names a compatible one.
        extractor, matcher: local feature extractor and matcher of that preset.
        global_descriptor: retrieval descriptor (vlad, bow, onnx).
        camera_axes: camera axes of the map's poses, and of `Answer.pose` under the "map"
            convention: "habitat" (HPointLoc, `pntr synth`) or "opencv" (maps built from recordings).
        intrinsics: the database images' camera (fx, fy, cx, cy, *distortion), pixels, or None.
        image_width, image_height: the database images' size, pixels.
        build_seconds: how long building the map took, seconds.
        loaded_map_ids: every map id the server holds.
        up_axis: the map world's up axis, "y" (HPointLoc, `pntr synth`) or "z".
        version: the map's version (build time and content checksum).
        frame_convention: the server's default answer convention, "map" or "ros".
        ros_from_map: 3x3 rotation from the map's world frame to the ROS z-up frame.
        calibration_source: the calibration answers use: "map" (the map's own, fitted on its
            regions held out), "file" (`pntr-server --calibration`) or "shipped".
        min_confidence: the LOCALIZED threshold answers are held to.
        calibration_stale: the map changed since its own calibration was fitted.
    """

    map_id: str
    images: int
    points: int
    scenes: tuple[str, ...]
    preset: str
    extractor: str
    matcher: str
    global_descriptor: str
    camera_axes: str
    intrinsics: tuple[float, ...] | None
    image_width: int
    image_height: int
    build_seconds: float
    loaded_map_ids: tuple[str, ...]
    up_axis: str = "y"
    version: str = ""
    frame_convention: str = "map"
    ros_from_map: npt.NDArray[np.float64] | None = None
    calibration_source: str = ""
    min_confidence: float = float("nan")
    calibration_stale: bool = False
