"""Python client of pntr-server: send an RGB-D frame, get the camera's pose in a prebuilt map.

    import pntr_client

    with pntr_client.Client("127.0.0.1:50051", token=None, tls_ca=None) as c:
        # rgb: HxWx3 uint8; depth: HxW float32 metres, or uint16 millimetres (0 = missing)
        a = c.localize(rgb, depth, intrinsics=(fx, fy, cx, cy))
        if a.localized:
            world_from_camera = a.pose  # 4x4 float64, metres

`Client(addr, frame_convention="ros")` answers in ROS conventions (z-up map frame, optical camera
axes: the pose is map_from_camera_optical); `map_to_ros` / `ros_to_map` convert a pose yourself.
`Client.localize_stream(frames)` sends a stream of frames over one call (a `Frame` with
`relocalize=True` is searched over the whole map, ignoring the stream's track; `continuation=` with
`answer.as_continuation(stamp_s)` of an earlier stream's last answer continues its track), `Client.map_info()`
describes the map. A `Prior` (or `answer.as_prior(radius_m)`) restricts the search to where the
camera roughly is. gRPC failures raise `PntrError` subclasses (see `pntr_client.errors`); malformed
inputs raise ValueError before anything is sent. `pntr_client.hpointloc` reads HPointLoc files (needs
the `hpointloc` extra) and `pntr-client` / `python -m pntr_client` is the command-line script.
"""

from importlib import metadata as _metadata

from pntr_client._geometry import map_to_ros, ros_from_map_world, ros_to_map, rotate_covariance
from pntr_client._messages import make_request
from pntr_client._values import Answer, Continuation, Frame, MapInfo, Prior
from pntr_client.client import Client
from pntr_client.errors import (
    CancelledError,
    DeadlineExceededError,
    InvalidArgumentError,
    NotFoundError,
    OutOfRangeError,
    PntrError,
    ResourceExhaustedError,
    UnauthenticatedError,
    UnavailableError,
)

try:
    __version__ = _metadata.version("pntr-client")
except _metadata.PackageNotFoundError:  # imported from a source tree that was not installed
    __version__ = "0+unknown"

__all__ = [
    "Answer",
    "CancelledError",
    "Client",
    "Continuation",
    "DeadlineExceededError",
    "Frame",
    "InvalidArgumentError",
    "MapInfo",
    "NotFoundError",
    "OutOfRangeError",
    "PntrError",
    "Prior",
    "ResourceExhaustedError",
    "UnauthenticatedError",
    "UnavailableError",
    "__version__",
    "make_request",
    "map_to_ros",
    "ros_from_map_world",
    "ros_to_map",
    "rotate_covariance",
]
