#!/usr/bin/env python3
"""Rewrite a ROS 2 bag with one fault a team meets in real recordings, using the Python `rosbags`
package (never pntr's own writer): the bag pntr's tests read is then one another tool wrote.

Usage: bag_faults.py IN_BAG OUT_BAG FAULT

FAULT:
  two-parents   every odom -> base_link transform on /tf is followed 5 ms later by a
                map -> base_link one from "another localizer" (0.4 m off in x): base_link has two
                parents, as when a second localizer publishes the body's pose.
  info-frame    the colour CameraInfo belongs to another camera: frame_id
                camera_depth_optical_frame and its focal length 1.2 times the colour camera's.
  renamed       realsense-ros 4.x's topic names: /camera/camera/color/... instead of /camera/color/...
  bad-poses     among the odom -> base_link transforms, the 10th has a NaN position, the 20th an
                all-zero quaternion, the 30th a NaN in its quaternion, and every 7th a quaternion
                scaled by 1.003 (within tf2's tolerance: normalised, not left out).
  zero-poses    every geometry_msgs/msg/PoseStamped has an all-zero quaternion (a pose publisher
                that never filled the orientation in).
"""
import math
import sys
from pathlib import Path

from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

TS = get_typestore(Stores.ROS2_JAZZY)
M = TS.types


def rewrite(src, dst, fault):
    with Reader(src) as r, Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        def topic(name):
            if fault == 'renamed' and name.startswith('/camera/'):
                return '/camera/camera/' + name[len('/camera/'):]
            return name
        conns = {c.id: w.add_connection(topic(c.topic), c.msgtype, typestore=TS) for c in r.connections}
        odom_seen = 0
        for c, t, raw in r.messages():
            msg = TS.deserialize_cdr(raw, c.msgtype)
            later = []
            if fault == 'info-frame' and c.msgtype == 'sensor_msgs/msg/CameraInfo':
                msg.header.frame_id = 'camera_depth_optical_frame'
                k, p = msg.k.copy(), msg.p.copy()  # the decoded arrays are read-only views
                k[0] *= 1.2
                k[4] *= 1.2
                p[0] *= 1.2
                p[5] *= 1.2
                msg.k, msg.p = k, p
            if fault == 'zero-poses' and c.msgtype == 'geometry_msgs/msg/PoseStamped':
                o = msg.pose.orientation
                o.x = o.y = o.z = o.w = 0.0
            if c.topic == '/tf':
                for x in msg.transforms:
                    if (x.header.frame_id, x.child_frame_id) != ('odom', 'base_link'):
                        continue
                    odom_seen += 1
                    q, p = x.transform.rotation, x.transform.translation
                    if fault == 'bad-poses':
                        if odom_seen == 10:
                            p.x = math.nan
                        elif odom_seen == 20:
                            q.x = q.y = q.z = q.w = 0.0
                        elif odom_seen == 30:
                            q.w = math.nan
                        elif odom_seen % 7 == 0:
                            q.x, q.y, q.z, q.w = (v * 1.003 for v in (q.x, q.y, q.z, q.w))
                    if fault == 'two-parents':
                        stamp = x.header.stamp
                        ns = stamp.sec * 10**9 + stamp.nanosec + 5_000_000
                        other = M['geometry_msgs/msg/TransformStamped'](
                            header=M['std_msgs/msg/Header'](
                                stamp=M['builtin_interfaces/msg/Time'](sec=ns // 10**9, nanosec=ns % 10**9),
                                frame_id='map'),
                            child_frame_id='base_link',
                            transform=M['geometry_msgs/msg/Transform'](
                                translation=M['geometry_msgs/msg/Vector3'](x=p.x + 0.4, y=p.y, z=p.z),
                                rotation=M['geometry_msgs/msg/Quaternion'](x=q.x, y=q.y, z=q.z, w=q.w)))
                        later.append((t + 5_000_000, M['tf2_msgs/msg/TFMessage'](transforms=[other])))
            w.write(conns[c.id], t, TS.serialize_cdr(msg, c.msgtype))
            for lt, lm in later:
                w.write(conns[c.id], lt, TS.serialize_cdr(lm, c.msgtype))


def main():
    if len(sys.argv) != 4 or sys.argv[3] not in ('two-parents', 'info-frame', 'bad-poses', 'renamed', 'zero-poses'):
        sys.exit(__doc__)
    rewrite(Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3])


if __name__ == '__main__':
    main()
