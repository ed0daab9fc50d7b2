#!/usr/bin/env python3
"""A robot on a ROS 2 graph, for the pntr-ros test, spoken through Eclipse Cyclone DDS (the PyPI
`cyclonedds` package: the DDS that ROS 2 ships as rmw_cyclonedds), so pntr-ros is checked against
another DDS stack and the ROS 2 wire conventions, never against itself.

It replays a TUM RGB-D folder in real time as a RealSense driver with image_transport and a robot
base would publish it, every message stamped with the wall clock:
  /camera/color/image_raw (sensor_msgs/Image rgb8) and its /compressed sibling (JPEG),
  /camera/aligned_depth_to_color/image_raw (16UC1 millimetres) and its /compressedDepth sibling
  (12-byte ConfigHeader + 16-bit PNG), /camera/color/camera_info (plumb_bob, d = 0), all with the
  frame's stamp and frame_id camera_color_optical_frame, best effort;
  /tf_static once (reliable, transient local): base_link -> camera_link -> camera_color_optical_frame;
  /tf at 50 Hz: odom -> base_link, odometry that is the true base pose seen from an odom frame
  offset from the map by a known transform (MAP_FROM_ODOM).
The truth of each frame is the base frame's pose in the ROS map frame: ros_from_map (the map's
MapInfo.ros_from_map, given) * world_from_camera (the folder's groundtruth, optical axes) *
camera_from_base.

It listens to what the node publishes (pntr/pose, /tf's map -> odom, /diagnostics) and to
ros_discovery_info (the ROS graph), calls the std_srvs/Trigger service pntr/relocalize as an
rmw_cyclonedds client does (16-byte request header echoed in the reply), and writes everything it
saw, with its truth, as JSON for the test to judge.

Usage: robot.py --tum DIR --ros-from-map QW QX QY QZ --seconds S --out REPORT.json
                [--relocalize-at S ...] [--silent-at S --silent-for S]
It prints `ready` once its writers exist; times in the report are seconds after that.

With `--direct HOST:PORT --rate-hz R` it is instead a robot that calls pntr-server itself with the
Python client (`pntr_client`, client/python: one LocalizeStream, frames of the same drive handed over
at R Hz as the camera takes them) and reports each answer's latency from capture: the baseline the
node's own latency is compared with (scripts/bench_ros.sh).
"""
import argparse, bisect, io, json, math, struct, sys, threading, time, zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image as PILImage
import cyclonedds.idl as idl
import cyclonedds.idl.types as t
from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration


# ---- ROS 2 types as rosidl names them on DDS (final, XCDR1: what rmw_cyclonedds writes) ----
@dataclass
class Time(idl.IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: t.int32
    nanosec: t.uint32

@dataclass
class Header(idl.IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time
    frame_id: str

@dataclass
class Image(idl.IdlStruct, typename="sensor_msgs::msg::dds_::Image_"):
    header: Header
    height: t.uint32
    width: t.uint32
    encoding: str
    is_bigendian: t.uint8
    step: t.uint32
    data: t.sequence[t.uint8]

@dataclass
class CompressedImage(idl.IdlStruct, typename="sensor_msgs::msg::dds_::CompressedImage_"):
    header: Header
    format: str
    data: t.sequence[t.uint8]

@dataclass
class RegionOfInterest(idl.IdlStruct, typename="sensor_msgs::msg::dds_::RegionOfInterest_"):
    x_offset: t.uint32
    y_offset: t.uint32
    height: t.uint32
    width: t.uint32
    do_rectify: bool

@dataclass
class CameraInfo(idl.IdlStruct, typename="sensor_msgs::msg::dds_::CameraInfo_"):
    header: Header
    height: t.uint32
    width: t.uint32
    distortion_model: str
    d: t.sequence[t.float64]
    k: t.array[t.float64, 9]
    r: t.array[t.float64, 9]
    p: t.array[t.float64, 12]
    binning_x: t.uint32
    binning_y: t.uint32
    roi: RegionOfInterest

@dataclass
class Vector3(idl.IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: t.float64
    y: t.float64
    z: t.float64

@dataclass
class Point(idl.IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    x: t.float64
    y: t.float64
    z: t.float64

@dataclass
class Quaternion(idl.IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: t.float64
    y: t.float64
    z: t.float64
    w: t.float64

@dataclass
class Transform(idl.IdlStruct, typename="geometry_msgs::msg::dds_::Transform_"):
    translation: Vector3
    rotation: Quaternion

@dataclass
class TransformStamped(idl.IdlStruct, typename="geometry_msgs::msg::dds_::TransformStamped_"):
    header: Header
    child_frame_id: str
    transform: Transform

@dataclass
class TFMessage(idl.IdlStruct, typename="tf2_msgs::msg::dds_::TFMessage_"):
    transforms: t.sequence[TransformStamped]

@dataclass
class Pose(idl.IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    position: Point
    orientation: Quaternion

@dataclass
class PoseWithCovariance(idl.IdlStruct, typename="geometry_msgs::msg::dds_::PoseWithCovariance_"):
    pose: Pose
    covariance: t.array[t.float64, 36]

@dataclass
class PoseWithCovarianceStamped(idl.IdlStruct, typename="geometry_msgs::msg::dds_::PoseWithCovarianceStamped_"):
    header: Header
    pose: PoseWithCovariance

@dataclass
class KeyValue(idl.IdlStruct, typename="diagnostic_msgs::msg::dds_::KeyValue_"):
    key: str
    value: str

@dataclass
class DiagnosticStatus(idl.IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticStatus_"):
    level: t.uint8
    name: str
    message: str
    hardware_id: str
    values: t.sequence[KeyValue]

@dataclass
class DiagnosticArray(idl.IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticArray_"):
    header: Header
    status: t.sequence[DiagnosticStatus]

@dataclass
class Gid(idl.IdlStruct, typename="rmw_dds_common::msg::dds_::Gid_"):
    data: t.array[t.uint8, 16]

@dataclass
class NodeEntitiesInfo(idl.IdlStruct, typename="rmw_dds_common::msg::dds_::NodeEntitiesInfo_"):
    node_namespace: str
    node_name: str
    reader_gid_seq: t.sequence[Gid]
    writer_gid_seq: t.sequence[Gid]

@dataclass
class ParticipantEntitiesInfo(idl.IdlStruct, typename="rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_"):
    gid: Gid
    node_entities_info_seq: t.sequence[NodeEntitiesInfo]

# rmw_cyclonedds puts a request header (the client's writer instance handle, a sequence number)
# before the fields of a request and expects it echoed before those of the reply.
@dataclass
class TriggerRequest(idl.IdlStruct, typename="std_srvs::srv::dds_::Trigger_Request_"):
    client: t.uint64
    seq: t.int64
    structure_needs_at_least_one_member: t.uint8

@dataclass
class TriggerResponse(idl.IdlStruct, typename="std_srvs::srv::dds_::Trigger_Response_"):
    client: t.uint64
    seq: t.int64
    success: bool
    message: str


# ---- rigid transforms: (translation[3], quaternion x,y,z,w), parent_from_child ----
def qmul(a, b):
    ax, ay, az, aw = a; bx, by, bz, bw = b
    return np.array([aw*bx + ax*bw + ay*bz - az*by, aw*by - ax*bz + ay*bw + az*bx,
                     aw*bz + ax*by - ay*bx + az*bw, aw*bw - ax*bx - ay*by - az*bz])

def qconj(q):
    return np.array([-q[0], -q[1], -q[2], q[3]])

def qrot(q, v):
    return qmul(qmul(q, np.array([*v, 0.0])), qconj(q))[:3]

def compose(a, b):
    q = qmul(a[1], b[1])
    return a[0] + qrot(a[1], b[0]), q / np.linalg.norm(q)

def inverse(a):
    return -qrot(qconj(a[1]), a[0]), qconj(a[1])

def slerp(q0, q1, s):
    d = float(q0 @ q1)
    if d < 0:
        q1, d = -q1, -d
    if d > 1 - 1e-12:
        q = q0 + s * (q1 - q0)
    else:
        th = math.acos(min(d, 1.0))
        q = (math.sin((1 - s) * th) * q0 + math.sin(s * th) * q1) / math.sin(th)
    return q / np.linalg.norm(q)

def angle_deg(qa, qb):
    return math.degrees(2 * math.acos(min(1.0, abs(float(qa @ qb)))))

OPTICAL = "camera_color_optical_frame"
STATIC = [("base_link", "camera_link", (0.10, 0.0, 0.30), (0.0, 0.0, 0.0, 1.0)),
          ("camera_link", OPTICAL, (0.0, 0.0, 0.0), (-0.5, 0.5, -0.5, 0.5))]
BASE_FROM_OPTICAL = compose(*[(np.array(tr), np.array(q)) for _, _, tr, q in STATIC])
MAP_FROM_ODOM = (np.array([0.5, -0.2, 0.0]), np.array([0.0, 0.0, math.sin(math.radians(5)), math.cos(math.radians(5))]))


def read_lines(path):
    rows = [ln.split() for ln in Path(path).read_text().splitlines()]
    return [r for r in rows if r and not r[0].startswith("#")]


def load(folder, intrinsics=None):
    d = Path(folder)
    rgb = sorted((float(r[0]), d / r[1]) for r in read_lines(d / "rgb.txt"))
    depth = dict((round(float(r[0]), 6), d / r[1]) for r in read_lines(d / "depth.txt"))
    gt = dict((round(float(r[0]), 6), (np.array(r[1:4], float), np.array(r[4:8], float))) for r in read_lines(d / "groundtruth.txt"))
    fx, fy, cx, cy = intrinsics or map(float, read_lines(d / "calibration.txt")[0][:4])
    frames = [(s, p, depth[round(s, 6)], gt[round(s, 6)]) for s, p in rgb if round(s, 6) in depth and round(s, 6) in gt]
    return frames, (fx, fy, cx, cy)


def png16(a):
    h, w = a.shape
    rows = np.frombuffer(a.astype(">u2").tobytes(), np.uint8).reshape(h, -1)
    raw = np.hstack([np.zeros((h, 1), np.uint8), rows]).tobytes()
    chunk = lambda tag, data: struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 16, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))


def stamp_of(ns):
    return Time(sec=ns // 10**9, nanosec=ns % 10**9)


def direct(a, frames, intrinsics):
    """The same drive sent by the Python client straight to the server, at `--rate-hz`."""
    import pntr_client

    period_ns = int(1e9 / a.rate_hz)
    captured = {}

    def camera():
        t0_ns = time.time_ns()
        k = 0
        while (k * period_ns) * 1e-9 <= a.seconds:
            due = t0_ns + k * period_ns
            sleep = (due - time.time_ns()) * 1e-9
            if sleep > 0:
                time.sleep(sleep)
            _, rgb_path, depth_path, _ = frames[int((due - t0_ns) / 100_000_000) % len(frames)]
            rgb = np.asarray(PILImage.open(rgb_path).convert("RGB"))
            depth = np.asarray(PILImage.open(depth_path)).astype(np.float32) / 5000.0
            rid = str(k)
            captured[rid] = (due, time.time_ns())
            k += 1
            yield pntr_client.Frame(rgb=rgb, depth=depth, intrinsics=intrinsics, request_id=rid)

    answers = []
    with pntr_client.Client(a.direct, frame_convention="ros") as client:
        print("ready", flush=True)
        for ans in client.localize_stream(camera()):
            due, loaded = captured[ans.request_id]
            now = time.time_ns()
            answers.append({"latency_ms": (now - due) * 1e-6, "from_loaded_ms": (now - loaded) * 1e-6,
                            "localized": bool(ans.localized)})
    Path(a.out).write_text(json.dumps({"direct": answers}))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--tum", required=True)
    ap.add_argument("--ros-from-map", nargs=4, type=float, required=True, metavar=("QW", "QX", "QY", "QZ"))
    ap.add_argument("--seconds", type=float, required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--relocalize-at", type=float, action="append", default=[])
    ap.add_argument("--initialpose-at", type=float, default=None, help="publish the true base pose on /initialpose then")
    ap.add_argument("--silent-at", type=float, default=None)
    ap.add_argument("--silent-for", type=float, default=0.0)
    ap.add_argument("--intrinsics", default=None, help="fx,fy,cx,cy (default: the folder's calibration.txt)")
    ap.add_argument("--direct", default=None, metavar="HOST:PORT")
    ap.add_argument("--rate-hz", type=float, default=5.0)
    a = ap.parse_args()

    frames, (fx, fy, cx, cy) = load(a.tum, [float(v) for v in a.intrinsics.split(",")] if a.intrinsics else None)
    if a.direct:
        return direct(a, frames, (fx, fy, cx, cy))
    w0, h0 = PILImage.open(frames[0][1]).size
    qw, qx, qy, qz = a.ros_from_map
    ros_from_map = (np.zeros(3), np.array([qx, qy, qz, qw]) / np.linalg.norm([qx, qy, qz, qw]))
    # Each frame's truth: the base in the ROS map frame, and the odometry that reports it.
    truth = []
    for _, _, _, (tr, q) in frames:
        map_from_base = compose(compose(ros_from_map, (tr, q / np.linalg.norm(q))), inverse(BASE_FROM_OPTICAL))
        truth.append(map_from_base)
    odom_from_map = inverse(MAP_FROM_ODOM)

    dp = DomainParticipant(0)
    sensor = Qos(Policy.Reliability.BestEffort, Policy.Durability.Volatile, Policy.History.KeepLast(5))
    reliable = Qos(Policy.Reliability.Reliable(duration(milliseconds=100)), Policy.Durability.Volatile, Policy.History.KeepLast(100))
    latched = Qos(Policy.Reliability.Reliable(duration(milliseconds=100)), Policy.Durability.TransientLocal, Policy.History.KeepLast(1))
    listen_latched = Qos(Policy.Reliability.Reliable(duration(milliseconds=100)), Policy.Durability.TransientLocal, Policy.History.KeepLast(100))

    def writer(name, kind, qos):
        return DataWriter(dp, Topic(dp, name, kind, qos=qos), qos=qos)

    def reader(name, kind, qos):
        return DataReader(dp, Topic(dp, name, kind, qos=qos), qos=qos)

    w_rgb = writer("rt/camera/color/image_raw", Image, sensor)
    w_rgbc = writer("rt/camera/color/image_raw/compressed", CompressedImage, sensor)
    w_depth = writer("rt/camera/aligned_depth_to_color/image_raw", Image, sensor)
    w_depthc = writer("rt/camera/aligned_depth_to_color/image_raw/compressedDepth", CompressedImage, sensor)
    w_info = writer("rt/camera/color/camera_info", CameraInfo, sensor)
    w_tf = writer("rt/tf", TFMessage, reliable)
    w_static = writer("rt/tf_static", TFMessage, latched)
    r_pose = reader("rt/pntr/pose", PoseWithCovarianceStamped, reliable)
    r_tf = reader("rt/tf", TFMessage, reliable)
    r_diag = reader("rt/diagnostics", DiagnosticArray, reliable)
    r_graph = reader("ros_discovery_info", ParticipantEntitiesInfo, listen_latched)
    w_initial = writer("rt/initialpose", PoseWithCovarianceStamped, Qos(Policy.Reliability.Reliable(duration(milliseconds=100)), Policy.History.KeepLast(1)))
    w_srv = writer("rq/pntr/relocalizeRequest", TriggerRequest, Qos(Policy.Reliability.Reliable(duration(milliseconds=100)), Policy.History.KeepLast(10)))
    r_srv = reader("rr/pntr/relocalizeReply", TriggerResponse, Qos(Policy.Reliability.Reliable(duration(milliseconds=100)), Policy.History.KeepLast(10)))

    def tf(ns, items):
        return TFMessage(transforms=[TransformStamped(
            header=Header(stamp=stamp_of(ns), frame_id=p), child_frame_id=c,
            transform=Transform(translation=Vector3(*map(float, tr)), rotation=Quaternion(*map(float, q))))
            for p, c, tr, q in items])

    t0_ns = time.time_ns()
    w_static.write(tf(t0_ns, STATIC))
    print("ready", flush=True)
    t0 = time.monotonic()
    report = {"frames": [], "poses": [], "map_odom": [], "diagnostics": [], "nodes": [], "services": [],
              "map_from_odom": [list(MAP_FROM_ODOM[0]), list(MAP_FROM_ODOM[1])]}
    stop = threading.Event()
    lock = threading.Lock()

    def listen():
        while not stop.is_set():
            now = time.monotonic() - t0
            got = False
            for m in r_pose.take(N=20):
                if not isinstance(m, PoseWithCovarianceStamped):
                    continue
                got = True
                p, q = m.pose.pose.position, m.pose.pose.orientation
                with lock:
                    report["poses"].append({"t": now, "recv_ns": time.time_ns(), "stamp_ns": m.header.stamp.sec * 10**9 + m.header.stamp.nanosec,
                                            "frame_id": m.header.frame_id, "p": [p.x, p.y, p.z], "q": [q.x, q.y, q.z, q.w],
                                            "covariance": list(m.pose.covariance)})
            for m in r_tf.take(N=50):
                if not isinstance(m, TFMessage):
                    continue
                for ts in m.transforms:
                    if ts.header.frame_id == "map" and ts.child_frame_id == "odom":
                        got = True
                        tr, q = ts.transform.translation, ts.transform.rotation
                        with lock:
                            report["map_odom"].append({"t": now, "stamp_ns": ts.header.stamp.sec * 10**9 + ts.header.stamp.nanosec,
                                                       "p": [tr.x, tr.y, tr.z], "q": [q.x, q.y, q.z, q.w]})
            for m in r_diag.take(N=10):
                if not isinstance(m, DiagnosticArray):
                    continue
                got = True
                for s in m.status:
                    with lock:
                        report["diagnostics"].append({"t": now, "level": s.level, "name": s.name, "message": s.message,
                                                      "values": {kv.key: kv.value for kv in s.values}})
            for m in r_graph.take(N=10):
                if not isinstance(m, ParticipantEntitiesInfo):
                    continue
                for n in m.node_entities_info_seq:
                    with lock:
                        report["nodes"].append({"t": now, "namespace": n.node_namespace, "name": n.node_name,
                                                "readers": len(n.reader_gid_seq), "writers": len(n.writer_gid_seq)})
            for m in r_srv.take(N=10):
                if not isinstance(m, TriggerResponse):
                    continue
                with lock:
                    report["services"].append({"t": now, "client": m.client, "seq": m.seq, "success": m.success, "message": m.message})
            if not got:
                time.sleep(0.005)

    listener = threading.Thread(target=listen, daemon=True)
    listener.start()

    period_ns, tick_ns = 100_000_000, 20_000_000
    relocalize = sorted(a.relocalize_at)
    client_id, seq = 0x0123456789ABCDEF, 0
    k = 0
    while True:
        tick = t0_ns + k * tick_ns
        elapsed = (tick - t0_ns) * 1e-9
        if elapsed > a.seconds:
            break
        sleep = (tick - time.time_ns()) * 1e-9
        if sleep > 0:
            time.sleep(sleep)
        if relocalize and elapsed >= relocalize[0]:
            relocalize.pop(0)
            seq += 1
            w_srv.write(TriggerRequest(client=client_id, seq=seq, structure_needs_at_least_one_member=0))
            with lock:
                report["services"].append({"t": time.monotonic() - t0, "asked": seq})
        # Written once, volatile, as RViz does: only once the node's reader is matched.
        if a.initialpose_at is not None and elapsed >= a.initialpose_at \
                and w_initial.get_publication_matched_status().current_count > 0:
            a.initialpose_at = None
            fi = (tick - t0_ns) / period_ns
            bp, bq = truth[int(fi) % len(frames)]
            cov = [0.0] * 36
            cov[0] = cov[7] = 0.25
            cov[35] = 0.07
            w_initial.write(PoseWithCovarianceStamped(header=Header(stamp=stamp_of(tick), frame_id="map"), pose=PoseWithCovariance(
                pose=Pose(position=Point(*map(float, bp)), orientation=Quaternion(*map(float, bq))), covariance=cov)))
            with lock:
                report["initialpose"] = {"t": time.monotonic() - t0, "p": list(bp)}
        k += 1
        if a.silent_at is not None and a.silent_at <= elapsed < a.silent_at + a.silent_for:
            continue
        # The drive, looped: frame i at i * 0.1 s.
        fi = (tick - t0_ns) / period_ns
        i0 = int(fi) % len(frames)
        i1 = (i0 + 1) % len(frames)
        s = fi - int(fi)
        (p0, q0), (p1, q1) = truth[i0], truth[i1]
        base = (p0 + s * (p1 - p0), slerp(q0, q1, s)) if i1 != 0 else truth[i0]
        odom_from_base = compose(odom_from_map, base)
        w_tf.write(tf(tick, [("odom", "base_link", *odom_from_base)]))
        if (tick - t0_ns) % period_ns:
            continue
        _, rgb_path, depth_path, _ = frames[i0]
        header = Header(stamp=stamp_of(tick), frame_id=OPTICAL)
        rgb = np.asarray(PILImage.open(rgb_path).convert("RGB"))
        h, w = rgb.shape[:2]
        # TUM depth is 5000 per metre; ROS 16UC1 is millimetres.
        depth = ((np.asarray(PILImage.open(depth_path)).astype(np.uint32) + 2) // 5).astype(np.uint16)
        w_info.write(CameraInfo(header=header, height=h, width=w, distortion_model="plumb_bob", d=[0.0] * 5,
                                k=[fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0], r=[1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0],
                                p=[fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0], binning_x=0, binning_y=0,
                                roi=RegionOfInterest(0, 0, 0, 0, False)))
        w_rgb.write(Image(header=header, height=h, width=w, encoding="rgb8", is_bigendian=0, step=w * 3, data=rgb.tobytes()))
        w_depth.write(Image(header=header, height=h, width=w, encoding="16UC1", is_bigendian=0, step=w * 2, data=depth.astype("<u2").tobytes()))
        written_ns = time.time_ns()
        jpeg = io.BytesIO()
        PILImage.fromarray(rgb).save(jpeg, "JPEG", quality=92)
        w_rgbc.write(CompressedImage(header=header, format="rgb8; jpeg compressed bgr8", data=jpeg.getvalue()))
        w_depthc.write(CompressedImage(header=header, format="16UC1; compressedDepth png", data=struct.pack("<iff", 0, 0.0, 0.0) + png16(depth)))
        bp, bq = base
        report["frames"].append({"t": time.monotonic() - t0, "stamp_ns": tick, "written_ns": written_ns, "p": list(bp), "q": list(bq)})

    time.sleep(1.0)
    stop.set()
    listener.join()
    Path(a.out).write_text(json.dumps(report))


if __name__ == "__main__":
    main()
