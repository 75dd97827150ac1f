"""A ROS 2 peer for PoseFlow's tests, built on the PyPI `zenoh-ros2-sdk`
(an rmw_zenoh-compatible client independent of PoseFlow's own code): it
listens for PoseFlow's pose topics and, optionally, plays a BOP split as a
ROS 2 camera (colour rgb8, depth 32FC1 in metres, CameraInfo, and a mono8
label image of object ids from the visible masks).

    python ros2_peer.py --endpoint tcp/127.0.0.1:PORT --msgs DIR --out FILE
        [--objects 1,5] [--expect N] [--play SPLIT_DIR] [--domain D]

It listens on the endpoint (PoseFlow's stages connect to it), prints
`ready` once subscribed, plays the split once the camera's subscriptions
are visible in the ROS graph, and writes what it received as JSON once
`--expect` poses came (or after --timeout seconds).
"""

import argparse
import json
import os
import sys
import threading
import time
from pathlib import Path

FIRST_STAMP_S = 1_765_000_000


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--endpoint", required=True)
    ap.add_argument("--msgs", required=True, help="directory of .msg files (package/msg/Name.msg)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--domain", type=int, default=0)
    ap.add_argument("--objects", default="", help="object ids whose pose topics to read")
    ap.add_argument("--expect", type=int, default=0, help="poses (and as many pose arrays) to wait for")
    ap.add_argument("--play", help="a BOP split directory to publish as a camera")
    ap.add_argument("--timeout", type=float, default=600.0)
    args = ap.parse_args()

    # The SDK connects to a router; here it listens instead, and PoseFlow's
    # stages connect to it.
    os.environ["ZENOH_CONFIG_OVERRIDE"] = (
        f'listen/endpoints=["{args.endpoint}"];connect/endpoints=[];scouting/multicast/enabled=false'
    )
    from zenoh_ros2_sdk import ROS2Publisher, ROS2Subscriber
    from zenoh_ros2_sdk.message_registry import get_registry

    get_registry(args.msgs)
    received = {"poses": [], "arrays": [], "published": []}
    lock = threading.Lock()
    done = threading.Event()

    def check_done():
        if args.expect and min(len(received["poses"]), len(received["arrays"])) >= args.expect:
            done.set()

    def stamp_ns(header):
        return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec

    def on_pose(topic):
        def callback(msg):
            p = msg.pose.pose
            entry = {
                "topic": topic,
                "stamp_ns": stamp_ns(msg.header),
                "frame_id": msg.header.frame_id,
                "position": [p.position.x, p.position.y, p.position.z],
                "orientation": [p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w],
                "covariance": [float(v) for v in msg.pose.covariance],
            }
            with lock:
                received["poses"].append(entry)
                check_done()
        return callback

    def on_array(topic):
        def callback(msg):
            poses = [[q.position.x, q.position.y, q.position.z,
                      q.orientation.x, q.orientation.y, q.orientation.z, q.orientation.w] for q in msg.poses]
            with lock:
                received["arrays"].append({"topic": topic, "stamp_ns": stamp_ns(msg.header), "poses": poses})
                check_done()
        return callback

    common = dict(domain_id=args.domain, router_ip="127.0.0.1", router_port=7447)
    subscribers = []
    for obj in [int(o) for o in args.objects.split(",") if o]:
        base = f"/poseflow/obj_{obj:06d}"
        subscribers.append(ROS2Subscriber(f"{base}/pose", "geometry_msgs/msg/PoseWithCovarianceStamped",
                                          on_pose(f"{base}/pose"), **common))
        subscribers.append(ROS2Subscriber(f"{base}/hypotheses", "geometry_msgs/msg/PoseArray",
                                          on_array(f"{base}/hypotheses"), **common))
    print("ready", flush=True)

    if args.play:
        received["published"] = play(Path(args.play), args.domain, common, ROS2Publisher, args.timeout)
        print(f"played {len(received['published'])} images", flush=True)

    if args.expect:
        done.wait(args.timeout)
    else:
        time.sleep(1.0)
    with lock:
        Path(args.out).write_text(json.dumps(received))
    print(f"received {len(received['poses'])} poses, {len(received['arrays'])} pose arrays", flush=True)
    # The SDK's Zenoh threads would keep the interpreter alive.
    os._exit(0)


def play(split, domain, common, ROS2Publisher, timeout):
    """Publishes every image of every scene of a BOP split; returns the stamps."""
    import numpy as np
    from PIL import Image as PilImage

    topics = {
        "color": "/camera/camera/color/image_raw",
        "depth": "/camera/camera/aligned_depth_to_color/image_raw",
        "info": "/camera/camera/color/camera_info",
        "labels": "/camera/labels",
    }
    pubs = {name: ROS2Publisher(topic, "sensor_msgs/msg/CameraInfo" if name == "info" else "sensor_msgs/msg/Image",
                                **common) for name, topic in topics.items()}
    block_when_congested(pubs.values())
    started = time.time()
    wait_for_subscriptions(pubs["color"].session_mgr.session, domain, topics.values(), timeout)
    log(f"the camera's subscriptions are in the ROS graph after {time.time() - started:.1f} s")
    # A subscription's token can be seen before its data route is in place.
    deadline = time.time() + timeout
    while not all(p.pub.matching_status.matching for p in pubs.values()):
        if time.time() > deadline:
            sys.exit("the camera's subscriptions never matched the publishers")
        time.sleep(0.05)
    log(f"the camera's subscriptions matched after {time.time() - started:.1f} s")
    types = pubs["color"].session_mgr.store.types
    Header, Time = types["std_msgs/msg/Header"], types["builtin_interfaces/msg/Time"]
    Roi = pubs["info"].session_mgr.store.types["sensor_msgs/msg/RegionOfInterest"]

    stamps, count = [], 0
    for scene in sorted(p for p in split.iterdir() if p.is_dir()):
        cameras = json.loads((scene / "scene_camera.json").read_text())
        gts = json.loads((scene / "scene_gt.json").read_text())
        for im in sorted(cameras, key=int):
            cam = cameras[im]
            rgb = np.asarray(PilImage.open(scene / "rgb" / f"{int(im):06d}.png").convert("RGB"))
            raw = np.asarray(PilImage.open(scene / "depth" / f"{int(im):06d}.png")).astype(np.float64)
            # The BOP reader's arithmetic, so the metres are the same floats.
            depth = (raw * (cam["depth_scale"] / 1000.0)).astype(np.float32)
            labels = np.zeros(rgb.shape[:2], np.uint8)
            for k, gt in enumerate(gts[im]):
                mask = scene / "mask_visib" / f"{int(im):06d}_{k:06d}.png"
                if mask.exists():
                    labels[np.asarray(PilImage.open(mask)) > 0] = gt["obj_id"]
            h, w = labels.shape
            stamp = Time(sec=FIRST_STAMP_S + count, nanosec=0)
            header = Header(stamp=stamp, frame_id="camera_color_optical_frame")
            k = [float(v) for v in cam["cam_K"]]
            p = [k[0], 0.0, k[2], 0.0, 0.0, k[4], k[5], 0.0, 0.0, 0.0, 1.0, 0.0]
            pubs["info"].publish(header=header, height=h, width=w, distortion_model="plumb_bob",
                                 d=np.zeros(5), k=np.array(k), r=np.eye(3).ravel(), p=np.array(p),
                                 binning_x=0, binning_y=0,
                                 roi=Roi(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
            image = lambda data, enc, step: dict(header=header, height=h, width=w, encoding=enc, is_bigendian=0,
                                                 step=step, data=np.frombuffer(data.tobytes(), np.uint8))
            pubs["depth"].publish(**image(depth, "32FC1", 4 * w))
            pubs["labels"].publish(**image(labels, "mono8", w))
            pubs["color"].publish(**image(np.ascontiguousarray(rgb), "rgb8", 3 * w))
            stamps.append(stamp.sec * 1_000_000_000)
            count += 1
            log(f"published image {count} ({scene.name}/{im})")
            time.sleep(0.05)
    return stamps


def block_when_congested(publishers):
    """Declares each publisher's Zenoh publisher again with congestion control
    Block, as rmw_zenoh does for a reliable topic. The SDK looks its enum up
    as `zenoh.qos.CongestionControl`, which zenoh-python 1.10 does not have,
    and so declares Zenoh's default, Drop: while the graph's stages start
    and fill both cores, a whole image was then dropped on the way to the
    camera, which waited for it for ever."""
    import zenoh

    for publisher in publishers:
        publisher.pub.undeclare()
        publisher.pub = publisher.session_mgr.session.declare_publisher(
            publisher.keyexpr, congestion_control=zenoh.CongestionControl.BLOCK
        )


def log(line):
    """Progress on stderr, which the tests pass through."""
    print(f"ros2_peer: {line}", file=sys.stderr, flush=True)


def wait_for_subscriptions(session, domain, topics, timeout):
    """Waits until a subscription of every topic is in the ROS graph."""
    wanted = {t.replace("/", "%") for t in topics}
    deadline = time.time() + timeout
    while time.time() < deadline:
        seen = set()
        for reply in session.liveliness().get(f"@ros2_lv/{domain}/**"):
            if reply.ok is not None:
                parts = str(reply.ok.key_expr).split("/")
                if len(parts) > 10 and parts[5] == "MS":
                    seen.add(parts[9])
        if wanted <= seen:
            return
        time.sleep(0.1)
    sys.exit(f"no subscriptions to {sorted(wanted)} within {timeout} s")


if __name__ == "__main__":
    main()
