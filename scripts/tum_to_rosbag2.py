#!/usr/bin/env python3
"""Convert a TUM RGB-D folder into a ROS 2 bag folder (metadata.yaml + MCAP files).

Purpose: test recordings written the way ROS 2 (`ros2 bag record`, realsense2_camera,
image_transport, tf2) writes them, but by another tool than pntr's own writer, so the Rust
reader is checked against the ROS conventions rather than against itself. Only the pure-Python
`rosbags` package (CDR + MCAP), numpy and Pillow are used; no ROS install is needed.

Topics (log time of every message == its header stamp, messages written in time order):
  /camera/color/image_raw/compressed           sensor_msgs/msg/CompressedImage
      format 'rgb8; png compressed bgr8' (or 'rgb8; jpeg compressed bgr8', quality 90);
      a whole image file with its true colours: image_transport hands OpenCV's imencode a BGR matrix,
      which writes a standard PNG/JPEG (a standard decoder reads R,G,B).
  /camera/aligned_depth_to_color/image_raw/compressedDepth  sensor_msgs/msg/CompressedImage
      format '16UC1; compressedDepth png'; data = 12-byte ConfigHeader (int32 LE format 0,
      float32 depthQuantA 0, float32 depthQuantB 0) + 16-bit grey PNG in millimetres.
  /camera/color/camera_info                    sensor_msgs/msg/CameraInfo (plumb_bob, d = 0)
  /tf_static  tf2_msgs/msg/TFMessage, once, at the first stamp of the bag:
      base_link->camera_link (0.10, 0, 0.30), camera_link->camera_color_optical_frame (REP 103
      quaternion x=-0.5 y=0.5 z=-0.5 w=0.5, parent_from_child).
  /tf  map->odom (constant, 2 Hz) and odom->base_link (20 Hz grid anchored at the first image
      stamp + --tf-offset, extended so every image stamp is bracketed).  The chain
      map->odom->base_link->camera_link->camera_color_optical_frame equals the groundtruth
      world_from_camera (interpolated: lerp translation, slerp rotation) at every sample stamp.
  --odometry-topic T: nav_msgs/msg/Odometry of base_link in map at 20 Hz (stamps offset by
      --tf-offset) with /tf_static only: the camera's pose is the odometry's composed with the static
      base_link -> optical transforms.
  --no-tf --pose-topic T: no TF at all; geometry_msgs/msg/PoseStamped (frame_id 'map',
      world_from_camera of the optical frame) on T at each image stamp.
All colour/depth/camera_info messages of one frame carry the rgb stamp and frame_id
camera_color_optical_frame. Frames outside the groundtruth time range are dropped.
The bag looks like a robot's (REP 103, REP 105): its `map` frame is z-up, whatever the TUM world's
up axis (read from the cameras: their mean down axis, optical +y, points along -up; a y-up render,
a y-down KinectFusion world and a z-up mocap world all give a z-up map, so base_link stands upright),
and stamps that are not wall-clock time (before 2001, as a render's 0.1 s) are moved to start on
2026-01-01 UTC. --keep-tum-frame keeps the TUM world and stamps as they are (for comparing a bag's
map pose for pose with the folder's own map); the conversion is said on stderr.
Splitting (--max-messages-per-file N) follows rosbag2: files <bag>_0.mcap, <bag>_1.mcap, ...
of at most N messages each, every file registering all topics; metadata.yaml lists them all.

Usage: tum_to_rosbag2.py TUM_DIR OUT_BAG_DIR [--colour png|jpeg] [--max-messages-per-file N]
       [--tf-offset S] [--no-tf --pose-topic /ground_truth] [--bag-version 8|9] [--keep-tum-frame]
       tum_to_rosbag2.py --selftest
"""
import argparse, bisect, io, math, shutil, struct, sys, tempfile, zlib
from decimal import Decimal
from pathlib import Path

import numpy as np
from PIL import Image
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
from ruamel.yaml import YAML

TS = get_typestore(Stores.ROS2_JAZZY)
M = TS.types
COLOR, INFO = '/camera/color/image_raw/compressed', '/camera/color/camera_info'
DEPTH = '/camera/aligned_depth_to_color/image_raw/compressedDepth'
OPTICAL = 'camera_color_optical_frame'
IMG, TFM, POSE = 'sensor_msgs/msg/CompressedImage', 'tf2_msgs/msg/TFMessage', 'geometry_msgs/msg/PoseStamped'
STATIC = [('base_link', 'camera_link', (0.10, 0.0, 0.30), (0.0, 0.0, 0.0, 1.0)),
          ('camera_link', OPTICAL, (0.0, 0.0, 0.0), (-0.5, 0.5, -0.5, 0.5))]
MAP_ODOM = (np.array([0.5, -0.2, 0.0]), np.array([0.0, 0.0, math.sin(math.radians(5)), math.cos(math.radians(5))]))
ODOM_NS, MAP_NS, PAIR_NS = 50_000_000, 500_000_000, 20_000_000
# Stamps before this (2001-09-09) are not wall-clock time; they are moved to start at ROBOT_EPOCH_NS.
WALL_CLOCK_NS, ROBOT_EPOCH_NS = 10**18, 1_767_225_600 * 10**9  # 2026-01-01T00:00:00Z


# ---- rigid transforms: (t[3], q[4] as x,y,z,w), meaning parent_from_child ----
def qmul(a, b):
    ax, ay, az, aw = a; bx, by, bz, bw = b
    return np.array([aw*bx + ax*bw + ay*bz - az*by, aw*by - ax*bz + ay*bw + az*bx,
                     aw*bz + ax*by - ay*bx + az*bw, aw*bw - ax*bx - ay*by - az*bz])

qconj = lambda q: np.array([-q[0], -q[1], -q[2], q[3]])
qrot = lambda q, v: qmul(qmul(q, np.array([*v, 0.0])), qconj(q))[:3]
compose = lambda a, b: (a[0] + qrot(a[1], b[0]), qmul(a[1], b[1]) / np.linalg.norm(qmul(a[1], b[1])))  # a * b
inverse = lambda a: (-qrot(qconj(a[1]), a[0]), qconj(a[1]))

def slerp(q0, q1, a):
    d = float(q0 @ q1)
    if d < 0: q1, d = -q1, -d
    if d > 1 - 1e-12: q = q0 + a * (q1 - q0)
    else:
        th = math.acos(min(d, 1.0))
        q = (math.sin((1 - a) * th) * q0 + math.sin(a * th) * q1) / math.sin(th)
    return q / np.linalg.norm(q)

def interp(stamps, poses, t):
    """Pose at integer-ns stamp t (lerp translation, slerp rotation); None outside the range."""
    i = bisect.bisect_left(stamps, t)
    if i < len(stamps) and stamps[i] == t: return poses[i]
    if i == 0 or i == len(stamps): return None
    a = (t - stamps[i-1]) / (stamps[i] - stamps[i-1])
    (t0, q0), (t1, q1) = poses[i-1], poses[i]
    return t0 + a * (t1 - t0), slerp(q0, q1, a)

BASE_OPTICAL = compose(*[(np.array(t), np.array(q)) for _, _, t, q in STATIC])

def rotation_to_z(up):
    """The shortest rotation (x,y,z,w) taking the unit vector `up` to +z."""
    c = float(np.clip(up[2], -1.0, 1.0))
    axis = np.cross(up, [0.0, 0.0, 1.0])
    if np.linalg.norm(axis) < 1e-12:  # up is +z (identity) or -z (half a turn about x)
        return np.array([0.0, 0.0, 0.0, 1.0]) if c > 0 else np.array([1.0, 0.0, 0.0, 0.0])
    axis = axis / np.linalg.norm(axis); half = math.acos(c) / 2
    return np.array([*(axis * math.sin(half)), math.cos(half)])

def world_up(poses):
    """The TUM world's up axis as a signed unit axis: against the cameras' mean down axis (optical +y)."""
    down = np.mean([qrot(q, (0.0, 1.0, 0.0)) for _, q in poses], axis=0)
    k = int(np.argmax(np.abs(down)))
    if abs(down[k]) < 0.9 * np.linalg.norm(down):
        print(f'warning: the cameras look steeply up or down, or the world is not axis-aligned (mean down axis '
              f'{np.round(down / np.linalg.norm(down), 2).tolist()}): the up axis read from them may be wrong; '
              'check base_link in the bag, or give --keep-tum-frame', file=sys.stderr)
    up = np.zeros(3); up[k] = -math.copysign(1.0, down[k])
    return up

def to_robot_frame(frames, gt):
    """A z-up `map` (REP 103) and wall-clock stamps: (frames, gt, what was done, in words)."""
    (stamps, poses), said = gt, []
    up = world_up(poses)
    r = rotation_to_z(up)
    if not np.allclose(r, [0, 0, 0, 1]):
        poses = [(qrot(r, t), qmul(r, q)) for t, q in poses]
        said.append(f"the TUM world's {'+-'[int(up.sum() < 0)]}{'xyz'[int(np.argmax(np.abs(up)))]} up turned to the map's +z (REP 103)")
    shift = ROBOT_EPOCH_NS if frames[0][0] < WALL_CLOCK_NS else 0
    if shift:
        said.append(f'stamps moved by +{shift // 10**9} s to start on 2026-01-01 UTC')
    frames = [(t + shift, *rest) for t, *rest in frames]
    return frames, ([t + shift for t in stamps], poses), said


# ---- TUM input ----
def to_ns(s):
    return int(Decimal(s) * 1_000_000_000)

def read_lines(path):
    rows = [ln.split() for ln in Path(path).read_text().splitlines()]
    return [r for r in rows if r and not r[0].startswith('#')]

def load_tum(d):
    d = Path(d)
    rgb = [(to_ns(r[0]), d / r[1]) for r in read_lines(d / 'rgb.txt')]
    depth = sorted((to_ns(r[0]), d / r[1]) for r in read_lines(d / 'depth.txt'))
    gt = sorted((to_ns(r[0]), (np.array(r[1:4], float), np.array(r[4:8], float))) for r in read_lines(d / 'groundtruth.txt'))
    fx, fy, cx, cy = map(float, read_lines(d / 'calibration.txt')[0][:4])
    dstamps, used, frames = [s for s, _ in depth], set(), []
    for t, path in sorted(rgb):
        i = bisect.bisect_left(dstamps, t)
        j = min((k for k in (i - 1, i) if 0 <= k < len(depth)), key=lambda k: abs(dstamps[k] - t), default=None)
        if j is not None and j not in used and abs(dstamps[j] - t) <= PAIR_NS:
            used.add(j); frames.append((t, path, depth[j][1]))
    gts, gtp = [s for s, _ in gt], [(p[0], p[1] / np.linalg.norm(p[1])) for _, p in gt]
    kept = [f for f in frames if interp(gts, gtp, f[0]) is not None]
    if len(kept) < len(frames): print(f'dropped {len(frames) - len(kept)} frames outside groundtruth', file=sys.stderr)
    return kept, (gts, gtp), (fx, fy, cx, cy)


# ---- encoders ----
def png(a):
    """Minimal PNG encoder: uint8 HxWx3 (colour type 2) or uint16 HxW (grey, 16 bit big-endian)."""
    a = np.ascontiguousarray(a)
    h, w = a.shape[:2]
    bits, ctype = (16, 0) if a.dtype == np.uint16 else (8, 2 if a.ndim == 3 else 0)
    rows = np.frombuffer(a.astype('>u2' if bits == 16 else np.uint8).tobytes(), np.uint8).reshape(h, -1)
    raw = np.hstack([np.zeros((h, 1), np.uint8), rows]).tobytes()
    chunk = lambda tag, data: struct.pack('>I', len(data)) + tag + data + struct.pack('>I', zlib.crc32(tag + data))
    return (b'\x89PNG\r\n\x1a\n' + chunk(b'IHDR', struct.pack('>IIBBBBB', w, h, bits, ctype, 0, 0, 0))
            + chunk(b'IDAT', zlib.compress(raw, 6)) + chunk(b'IEND', b''))

def encode_colour(rgb, kind):
    img = np.ascontiguousarray(rgb)  # imencode of a BGR matrix writes a standard file: true colours
    if kind == 'png': return png(img)
    bio = io.BytesIO(); Image.fromarray(img).save(bio, 'JPEG', quality=90); return bio.getvalue()


# ---- messages ----
def header(t, frame):
    return M['std_msgs/msg/Header'](stamp=M['builtin_interfaces/msg/Time'](sec=t // 10**9, nanosec=t % 10**9), frame_id=frame)

def xyz(kind, v):
    return M[f'geometry_msgs/msg/{kind}'](**{k: float(x) for k, x in zip('xyzw', v)})

def tf_msg(t, items):
    return M[TFM](transforms=[M['geometry_msgs/msg/TransformStamped'](
        header=header(t, p), child_frame_id=c, transform=M['geometry_msgs/msg/Transform'](
            translation=xyz('Vector3', tr), rotation=xyz('Quaternion', q))) for p, c, tr, q in items])

def make_msg(kind, t, data, colour, calib):
    if kind == 'colour':
        rgb = np.asarray(Image.open(data).convert('RGB'))
        return M[IMG](header=header(t, OPTICAL), format=f'rgb8; {colour} compressed bgr8',
                      data=np.frombuffer(encode_colour(rgb, colour), np.uint8))
    if kind == 'depth':
        mm = ((np.asarray(Image.open(data)).astype(np.uint32) + 2) // 5).astype(np.uint16)  # round(v / 5)
        payload = struct.pack('<iff', 0, 0.0, 0.0) + png(mm)
        return M[IMG](header=header(t, OPTICAL), format='16UC1; compressedDepth png', data=np.frombuffer(payload, np.uint8))
    if kind == 'info':
        (w, h), (fx, fy, cx, cy) = Image.open(data).size, calib
        return M['sensor_msgs/msg/CameraInfo'](
            header=header(t, OPTICAL), height=h, width=w, distortion_model='plumb_bob', d=np.zeros(5),
            k=np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1.0]), r=np.eye(3).ravel(),
            p=np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1.0, 0]), binning_x=0, binning_y=0,
            roi=M['sensor_msgs/msg/RegionOfInterest'](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
    if kind == 'odom':
        zero3 = xyz('Vector3', (0.0, 0.0, 0.0))
        return M['nav_msgs/msg/Odometry'](
            header=header(t, 'map'), child_frame_id='base_link',
            pose=M['geometry_msgs/msg/PoseWithCovariance'](pose=M['geometry_msgs/msg/Pose'](
                position=xyz('Point', data[0]), orientation=xyz('Quaternion', data[1])), covariance=np.zeros(36)),
            twist=M['geometry_msgs/msg/TwistWithCovariance'](
                twist=M['geometry_msgs/msg/Twist'](linear=zero3, angular=zero3), covariance=np.zeros(36)))
    if kind == 'pose':
        return M[POSE](header=header(t, 'map'), pose=M['geometry_msgs/msg/Pose'](
            position=xyz('Point', data[0]), orientation=xyz('Quaternion', data[1])))
    return tf_msg(t, data)  # 'tf' / 'tf_static': data = [(parent, child, t, q)]

def qos(durability=QosDurability.VOLATILE, depth=10):
    inf = QosTime(9223372036, 854775807)
    return Qos(QosHistory.KEEP_LAST, depth, QosReliability.RELIABLE, durability, inf, inf,
               QosLiveliness.AUTOMATIC, inf, False)


def build_events(frames, gt, tf_offset_ns, pose_topic, odom_topic=None):
    """[(stamp_ns, priority, topic, kind, data)] sorted in time order. With `odom_topic`: the body's
    nav_msgs/Odometry in map (20 Hz) and /tf_static only."""
    ev = []
    if odom_topic:
        first, last = frames[0][0], frames[-1][0]
        anchor = first + tf_offset_ns
        for k in range((first - anchor) // ODOM_NS, -((anchor - last) // ODOM_NS) + 1):
            ts = anchor + k * ODOM_NS
            wc = interp(*gt, ts)
            if wc is not None:  # map_from_base = world_from_cam * inv(base_from_optical)
                ev.append((ts, 1, odom_topic, 'odom', compose(wc, inverse(BASE_OPTICAL))))
        for t, rgb_path, depth_path in frames:
            ev += [(t, 2, INFO, 'info', rgb_path), (t, 3, COLOR, 'colour', rgb_path), (t, 4, DEPTH, 'depth', depth_path)]
        ev.append((min(e[0] for e in ev), 0, '/tf_static', 'tf_static', STATIC))
        return sorted(ev, key=lambda e: e[:2])
    for t, rgb_path, depth_path in frames:
        ev += [(t, 2, INFO, 'info', rgb_path), (t, 3, COLOR, 'colour', rgb_path), (t, 4, DEPTH, 'depth', depth_path)]
        if pose_topic: ev.append((t, 1, pose_topic, 'pose', interp(*gt, t)))
    if not pose_topic:
        first, last = frames[0][0], frames[-1][0]
        anchor = first + tf_offset_ns  # 20 Hz odom grid; brackets every image stamp
        for k in range((first - anchor) // ODOM_NS, -((anchor - last) // ODOM_NS) + 1):
            ts = anchor + k * ODOM_NS
            wc = interp(*gt, ts)
            if wc is not None:  # odom_from_base = inv(map_from_odom) * world_from_cam * inv(base_from_optical)
                ob = compose(compose(inverse(MAP_ODOM), wc), inverse(BASE_OPTICAL))
                ev.append((ts, 1, '/tf', 'tf', [('odom', 'base_link', *ob)]))
        start, end = min(e[0] for e in ev), max(e[0] for e in ev)
        for j in range(-((start - end) // MAP_NS) + 1):
            ev.append((start + j * MAP_NS, 1, '/tf', 'tf', [('map', 'odom', *MAP_ODOM)]))
        ev.append((start, 0, '/tf_static', 'tf_static', STATIC))
    return sorted(ev, key=lambda e: e[:2])


def write_bag(events, out, topics, max_per_file, version, colour, calib):
    """Write like rosbag2: <name>_<i>.mcap splits of <= N messages, one merged metadata.yaml."""
    out = Path(out)
    out.mkdir(parents=True)  # must not exist beforehand
    n = max_per_file or len(events)
    yaml = YAML(typ='safe'); yaml.default_flow_style, yaml.width, metas = False, 4096, []
    for i in range(0, len(events), n):
        part = out / f'{out.name}_{i // n}'
        with Writer(part, version=version, storage_plugin=StoragePlugin.MCAP) as w:
            conns = {tp: w.add_connection(tp, ty, typestore=TS, offered_qos_profiles=[q]) for tp, (ty, q) in topics.items()}
            for t, _, topic, kind, data in events[i:i + n]:
                w.write(conns[topic], t, TS.serialize_cdr(make_msg(kind, t, data, colour, calib), topics[topic][0]))
        (part / f'{part.name}.mcap').rename(out / f'{part.name}.mcap')
        metas.append(yaml.load((part / 'metadata.yaml').read_text())['rosbag2_bagfile_information'])
        shutil.rmtree(part)
    info = metas[0]
    files = [f for m in metas for f in m['files']]
    start = min(f['starting_time']['nanoseconds_since_epoch'] for f in files)
    end = max(f['starting_time']['nanoseconds_since_epoch'] + f['duration']['nanoseconds'] for f in files)
    info.update(relative_file_paths=[f['path'] for f in files], files=files, message_count=sum(f['message_count'] for f in files),
                starting_time={'nanoseconds_since_epoch': start}, duration={'nanoseconds': end - start})
    for k, tw in enumerate(info['topics_with_message_count']):
        tw['message_count'] = sum(m['topics_with_message_count'][k]['message_count'] for m in metas)
    with (out / 'metadata.yaml').open('w') as fh:
        yaml.dump({'rosbag2_bagfile_information': info}, fh)


def convert(tum_dir, out, colour='png', max_per_file=None, tf_offset='0', pose_topic=None, version=9,
            odom_topic=None, keep_tum_frame=False):
    frames, gt, calib = load_tum(tum_dir)
    if not frames:
        sys.exit(f'{tum_dir}: no colour frame with depth within 20 ms and a ground-truth pose')
    if not keep_tum_frame:
        frames, gt, said = to_robot_frame(frames, gt)
        for line in said: print(line, file=sys.stderr)
    topics = {COLOR: (IMG, qos()), DEPTH: (IMG, qos()), INFO: ('sensor_msgs/msg/CameraInfo', qos())}
    if odom_topic: topics.update({odom_topic: ('nav_msgs/msg/Odometry', qos()),
                                  '/tf_static': (TFM, qos(QosDurability.TRANSIENT_LOCAL, 1))})
    elif pose_topic: topics[pose_topic] = (POSE, qos())
    else: topics.update({'/tf': (TFM, qos(depth=100)), '/tf_static': (TFM, qos(QosDurability.TRANSIENT_LOCAL, 1))})
    events = build_events(frames, gt, to_ns(tf_offset), pose_topic, odom_topic)
    write_bag(events, out, topics, max_per_file, version, colour, calib)
    return len(events)


def selftest():
    """Build a 20-frame 64x48 TUM folder, convert it three ways, read the bags back with rosbags."""
    rng, tmp = np.random.default_rng(7), Path(tempfile.mkdtemp(prefix='tum2bag_'))
    tum, t0, nf, w, h = tmp / 'tum', to_ns('1305031102.175304'), 20, 64, 48
    (tum / 'rgb').mkdir(parents=True); (tum / 'depth').mkdir()
    om, v, q0 = np.array([0.3, -0.8, 0.4]), np.array([0.4, 0.1, -0.05]), np.array([0.1, 0.2, 0.3, 0.927])
    def truth(t):  # world_from_optical; base moves at constant velocity and rotation rate: lerp/slerp-exact
        s = (t - t0) / 1e9; ang = np.linalg.norm(om) * s
        qb = qmul(q0 / np.linalg.norm(q0), np.array([*(om / np.linalg.norm(om) * math.sin(ang / 2)), math.cos(ang / 2)]))
        return compose(compose(MAP_ODOM, (np.array([1.0, 2.0, 0.0]) + v * s, qb)), BASE_OPTICAL)
    sec = lambda t: f'{t // 10**9}.{t % 10**9 // 1000:06d}'
    rgbs, depths, lines = {}, {}, {'rgb': ['# rgb'], 'depth': ['# depth']}
    for t in range(t0, t0 + nf * ODOM_NS, ODOM_NS):  # 20 Hz frames, depth 3 ms after rgb
        rgbs[t] = np.dstack([rng.integers(lo, lo + 60, (h, w)) for lo in (180, 90, 0)]).astype(np.uint8)
        depths[t] = (rng.integers(5000, 20001, (h, w)) * (rng.random((h, w)) > 0.05)).astype(np.uint16)
        for k, name, img in (('rgb', sec(t), rgbs[t]), ('depth', sec(t + 3_000_000), depths[t])):
            (tum / k / f'{name}.png').write_bytes(png(img)); lines[k].append(f'{name} {k}/{name}.png')
    for k in lines: (tum / f'{k}.txt').write_text('\n'.join(lines[k]) + '\n')
    gt = [' '.join([sec(t)] + [f'{x:.17g}' for x in np.concatenate(truth(t))])  # 40 Hz, beyond the images
          for t in range(t0 - 100_000_000, t0 + nf * ODOM_NS + 100_000_000, 25_000_000)]
    (tum / 'groundtruth.txt').write_text('# timestamp tx ty tz qx qy qz qw\n' + '\n'.join(gt) + '\n')
    (tum / 'calibration.txt').write_text('50.0 50.0 31.5 23.5\n')

    def check(name, cond, detail=''):
        print(f'  [{"ok" if cond else "FAIL"}] {name} {detail}'); assert cond, name
    def read(bag):
        with Reader(bag) as r:
            msgs = [(c.topic, t, TS.deserialize_cdr(raw, c.msgtype)) for c, t, raw in r.messages()]
            return msgs, {c.topic: (c.msgtype, c.msgcount) for c in r.connections}
    def pose_err(est, t):
        ref = truth(t); qe = qmul(qconj(ref[1]), est[1])
        return max(np.linalg.norm(est[0] - ref[0]), 2 * math.atan2(np.linalg.norm(qe[:3]), abs(qe[3])))
    vec = lambda *xs: np.array([float(x) for x in xs])
    def tf_samples(msgs):
        """The static transforms by child, and the (stamps, transforms) of map->odom and odom->base_link."""
        static, samples = {}, {'odom': ([], []), 'map': ([], [])}
        for topic, t, m in msgs:
            for x in (m.transforms if topic.startswith('/tf') else []):
                tr, q = x.transform.translation, x.transform.rotation
                tq = (vec(tr.x, tr.y, tr.z), vec(q.x, q.y, q.z, q.w))
                if topic == '/tf_static': static[x.child_frame_id] = tq
                else: samples[x.header.frame_id][0].append(t); samples[x.header.frame_id][1].append(tq)
        return static, samples
    def tf_check(msgs, label):
        static, samples = tf_samples(msgs)
        img_t = [t for topic, t, _ in msgs if topic == COLOR]
        err = max(pose_err(compose(compose(compose(interp(*samples['map'], t), interp(*samples['odom'], t)),
                                           static['camera_link']), static[OPTICAL]), t) for t in img_t)
        gap = min(abs(s - t) for s in samples['odom'][0] for t in img_t) / 1e6
        check(f'TF chain == groundtruth at {len(img_t)} image stamps ({label}; nearest odom sample {gap:.1f} ms away)',
              err < 1e-6, f'max err {err:.1e} m|rad')
    stamp = lambda topic, m: (m.transforms[0] if topic.startswith('/tf') else m).header.stamp

    print(f'selftest in {tmp}')
    check('REP 103 body_from_optical: z->x, x->-y, y->-z', np.allclose([qrot(BASE_OPTICAL[1], e) for e in np.eye(3)],
                                                                      [[0, -1, 0], [0, 0, -1], [1, 0, 0]]))
    bag = tmp / 'bag_png'
    convert(tum, bag, 'png', max_per_file=25, keep_tum_frame=True)
    msgs, conns = read(bag)
    meta = YAML(typ='safe').load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    want = {COLOR: (IMG, 20), DEPTH: (IMG, 20), INFO: ('sensor_msgs/msg/CameraInfo', 20), '/tf': (TFM, 23), '/tf_static': (TFM, 1)}
    check('png bag (v9, split 25): topics/types/counts', conns == want, str(conns))
    check('split: 4 files, listed in metadata.yaml, all read', meta['relative_file_paths'] == [f'bag_png_{i}.mcap' for i in range(4)]
          and sorted(p.name for p in bag.iterdir()) == meta['relative_file_paths'] + ['metadata.yaml']
          and len(msgs) == meta['message_count'] == sum(f['message_count'] for f in meta['files']) == 84, str(meta['relative_file_paths']))
    fs = [(f['starting_time']['nanoseconds_since_epoch'], f['duration']['nanoseconds']) for f in meta['files']]
    check('split: file time ranges ordered, bag start/duration cover them', all(a + d <= b for (a, d), (b, _) in zip(fs, fs[1:]))
          and meta['starting_time']['nanoseconds_since_epoch'] == fs[0][0] == msgs[0][1] and fs[0][0] + meta['duration']['nanoseconds'] == msgs[-1][1])
    check('log time == header stamp, time-ordered', all(t == stamp(tp, m).sec * 10**9 + stamp(tp, m).nanosec for tp, t, m in msgs)
          and [t for _, t, _ in msgs] == sorted(t for _, t, _ in msgs))
    check('compressedDepth: 12-byte header + 16-bit PNG == round(v/5) mm', all(
        m.format == '16UC1; compressedDepth png' and struct.unpack('<iff', bytes(m.data[:12])) == (0, 0.0, 0.0)
        and np.array_equal(np.asarray(Image.open(io.BytesIO(bytes(m.data[12:])))), np.rint(depths[t] / 5)) for tp, t, m in msgs if tp == DEPTH))
    check('colour PNG decodes to the original colours', all(m.format == 'rgb8; png compressed bgr8' and m.header.frame_id == OPTICAL
          and np.array_equal(np.asarray(Image.open(io.BytesIO(bytes(m.data)))), rgbs[t]) for tp, t, m in msgs if tp == COLOR))
    info = next(m for tp, _, m in msgs if tp == INFO)
    check('camera_info', (info.width, info.height, info.distortion_model, list(info.d), list(info.k), list(info.p)) ==
          (64, 48, 'plumb_bob', [0] * 5, [50, 0, 31.5, 0, 50, 23.5, 0, 0, 1], [50, 0, 31.5, 0, 0, 50, 23.5, 0, 0, 0, 1, 0]))
    tf_check(msgs, 'tf-offset 0')

    bag = tmp / 'bag_jpeg'
    convert(tum, bag, 'jpeg', tf_offset='0.025', version=8, keep_tum_frame=True)
    msgs, conns = read(bag)
    check('jpeg bag (v8, tf-offset 0.025): counts', conns['/tf'] == (TFM, 24) and conns[COLOR] == (IMG, 20), str(conns))
    err = max(abs((np.asarray(Image.open(io.BytesIO(bytes(m.data)))) - rgbs[t].astype(float)).mean(axis=(0, 1))).max()
              for tp, t, m in msgs if tp == COLOR and m.format == 'rgb8; jpeg compressed bgr8')
    check('JPEG decodes to the original colours', err < 3, f'(max per-channel mean difference {err:.2f}; R/B swapped: ~180)')
    tf_check(msgs, 'tf-offset 0.025, interpolated')

    bag = tmp / 'bag_pose'
    convert(tum, bag, 'png', pose_topic='/ground_truth', keep_tum_frame=True)
    msgs, conns = read(bag)
    check('pose bag: no TF, PoseStamped per frame', set(conns) == {COLOR, DEPTH, INFO, '/ground_truth'} and conns['/ground_truth'] == (POSE, 20))
    err = max(pose_err((vec(m.pose.position.x, m.pose.position.y, m.pose.position.z), vec(m.pose.orientation.x, m.pose.orientation.y,
              m.pose.orientation.z, m.pose.orientation.w)), t) for tp, t, m in msgs if tp == '/ground_truth' and m.header.frame_id == 'map')
    check('PoseStamped (frame map) == groundtruth', err < 1e-6, f'max err {err:.1e} m|rad')

    # A render's y-up world and stamps from 0.1 s, as `pntr synth` writes them: by default the bag's
    # map is z-up with base_link upright, and its stamps are wall-clock time.
    yup = tmp / 'tum_yup'
    shutil.copytree(tum, yup)
    def level(t):  # world_from_optical of a level camera turning about the world's +y
        a = 0.4 * (t - t0) / 1e9  # half a turn about z (optical y to the world's -y), then the yaw
        return np.array([1.0 + 0.1 * a, 1.3, -2.0]), qmul([0.0, math.sin(a / 2), 0.0, math.cos(a / 2)], [0.0, 0.0, 1.0, 0.0])
    new_sec = lambda t: sec(t - t0 + 100_000_000)  # 0.100000, 0.150000, ...
    for k in ('rgb', 'depth'):
        rows = [ln.split() for ln in (yup / f'{k}.txt').read_text().splitlines()[1:]]
        (yup / f'{k}.txt').write_text('# ' + k + '\n' + ''.join(f'{new_sec(to_ns(r[0]))} {r[1]}\n' for r in rows))
    (yup / 'groundtruth.txt').write_text('# timestamp tx ty tz qx qy qz qw\n' + ''.join(
        ' '.join([new_sec(t)] + [f'{x:.17g}' for x in np.concatenate(level(t))]) + '\n'
        for t in range(t0 - 100_000_000, t0 + nf * ODOM_NS + 100_000_000, 25_000_000) if t - t0 + 100_000_000 >= 0))
    bag = tmp / 'bag_robot'
    convert(yup, bag, 'png')
    msgs, conns = read(bag)
    img_t = [t for tp, t, _ in msgs if tp == COLOR]
    check('robot bag: stamps on 2026-01-01 UTC, the TUM times kept after it',
          img_t[0] == ROBOT_EPOCH_NS + 100_000_000 and all(b - a == ODOM_NS for a, b in zip(img_t, img_t[1:])), str(img_t[:2]))
    static, samples = tf_samples(msgs)
    to_z = rotation_to_z(np.array([0.0, 1.0, 0.0]))
    worst_up = worst_pose = 0.0
    for t in img_t:
        base = compose(interp(*samples['map'], t), interp(*samples['odom'], t))
        worst_up = max(worst_up, float(np.linalg.norm(qrot(base[1], (0, 0, 1)) - [0, 0, 1])))
        cam = compose(compose(base, static['camera_link']), static[OPTICAL])
        ref = level(t - ROBOT_EPOCH_NS - 100_000_000 + t0)
        ref = (qrot(to_z, ref[0]), qmul(to_z, ref[1]))
        qe = qmul(qconj(ref[1]), cam[1])
        worst_pose = max(worst_pose, np.linalg.norm(cam[0] - ref[0]), 2 * math.atan2(np.linalg.norm(qe[:3]), abs(qe[3])))
    check('robot bag: base_link upright in a z-up map (REP 103)', worst_up < 1e-6, f'max |z_base - z_map| {worst_up:.1e}')
    check("robot bag: TF chain == the TUM poses turned y-up -> z-up", worst_pose < 1e-6, f'max err {worst_pose:.1e} m|rad')
    shutil.rmtree(tmp)
    print('selftest passed')


def main(argv=None):
    ap = argparse.ArgumentParser(
        description=__doc__.split('\n')[0],
        epilog='Topics: /camera/color/image_raw/compressed, /camera/aligned_depth_to_color/image_raw/compressedDepth, '
               '/camera/color/camera_info; TF: map -> odom -> base_link -> camera_link -> camera_color_optical_frame.')
    ap.add_argument('tum_dir', nargs='?', help='the TUM RGB-D folder (rgb.txt, depth.txt, groundtruth.txt, calibration.txt)')
    ap.add_argument('out_bag_dir', nargs='?', help='the rosbag2 folder to write (must not exist)')
    ap.add_argument('--colour', choices=['png', 'jpeg'], default='png', help='CompressedImage format of the colour topic')
    ap.add_argument('--max-messages-per-file', type=int, help='split the bag into .mcap files of at most this many messages')
    ap.add_argument('--tf-offset', default='0', help='seconds between image stamps and odom->base_link samples')
    ap.add_argument('--no-tf', action='store_true', help='no TF: poses as PoseStamped of the optical frame on --pose-topic')
    ap.add_argument('--pose-topic', help='with --no-tf: the PoseStamped topic (default /ground_truth)')
    ap.add_argument('--odometry-topic', help='poses as nav_msgs/Odometry of base_link in map (20 Hz) with /tf_static, no /tf')
    ap.add_argument('--bag-version', type=int, choices=[8, 9], default=9, help='rosbag2 metadata version')
    ap.add_argument('--keep-tum-frame', action='store_true',
                    help="keep the TUM world as the map frame and the TUM stamps (default: a z-up map, REP 103, and wall-clock stamps)")
    ap.add_argument('--selftest', action='store_true', help='write small bags into a temporary folder and check them')
    a = ap.parse_args(argv)
    if a.selftest: return selftest()
    if not (a.tum_dir and a.out_bag_dir): ap.error('TUM_DIR and OUT_BAG_DIR are required')
    if a.pose_topic and not a.no_tf: ap.error('--pose-topic requires --no-tf')
    n = convert(a.tum_dir, a.out_bag_dir, a.colour, a.max_messages_per_file, a.tf_offset,
                (a.pose_topic or '/ground_truth') if a.no_tf else None, a.bag_version, a.odometry_topic,
                a.keep_tum_frame)
    print(f'wrote {n} messages to {a.out_bag_dir}')


if __name__ == '__main__':
    main()
