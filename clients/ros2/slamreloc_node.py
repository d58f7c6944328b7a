"""A ROS 2 node that forwards camera images to `slamreloc serve` and publishes the answers.

    ros2 run ... or: python3 slamreloc_node.py --ros-args -p server:=127.0.0.1:50051 \\
        -p map:=kitchen -r image:=/camera/color/image_raw -r camera_info:=/camera/color/camera_info

Subscribes `image` (sensor_msgs/Image, or sensor_msgs/CompressedImage with -p compressed:=true)
and `camera_info` (sensor_msgs/CameraInfo, optional: without it the map's camera is used);
publishes `~/pose` (geometry_msgs/PoseStamped: world_from_cam, the map's frame `map_frame`,
the image's stamp) for every image localized, at most `rate_hz` requests a second.

NOT TESTED under ROS: ROS 2 is not installable where slamreloc's tests run. What is tested
(tests/test_service.py) is everything below `rclpy`: message -> image bytes and camera
(`slamreloc.datasets.rosbag.colour_file`, `camera_from_info`, the same code that reads bags)
-> `Client.localize` -> the pose.
"""

from __future__ import annotations

import time

import rclpy
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from slamreloc.client import Client, RemoteError
from slamreloc.datasets.rosbag import camera_from_info, colour_file
from slamreloc.errors import InputError


class SlamrelocNode(Node):
    def __init__(self):
        super().__init__("slamreloc")
        self.declare_parameter("server", "127.0.0.1:50051")
        self.declare_parameter("map", "")
        self.declare_parameter("token", "")
        self.declare_parameter("map_frame", "map")
        self.declare_parameter("compressed", False)
        self.declare_parameter("rate_hz", 5.0)
        p = {name: self.get_parameter(name).value for name in
             ("server", "map", "token", "map_frame", "compressed", "rate_hz")}
        self.map, self.map_frame, self.period = p["map"], p["map_frame"], 1.0 / p["rate_hz"]
        self.client = Client(p["server"], token=p["token"] or None)
        self.info: CameraInfo | None = None
        self.last = 0.0
        self.pub = self.create_publisher(PoseStamped, "~/pose", 10)
        self.create_subscription(CameraInfo, "camera_info", self.on_info, 1)
        kind = CompressedImage if p["compressed"] else Image
        self.create_subscription(kind, "image", self.on_image, 1)  # depth 1: newest only

    def on_info(self, msg: CameraInfo) -> None:
        self.info = msg

    def on_image(self, msg) -> None:
        now = time.monotonic()
        if now - self.last < self.period:
            return
        self.last = now
        try:
            data, _, size = colour_file(msg, "image")
            camera = camera_from_info(self.info, size, "camera_info") if self.info else None
            result = self.client.localize(data, camera=camera, map=self.map)
        except (RemoteError, InputError) as err:
            self.get_logger().warning(f"not localized: {err}")
            return
        if not result.localized:
            self.get_logger().info(f"not localized: {result.response.detail}")
            return
        pose = result.world_from_cam
        out = PoseStamped()
        out.header.stamp, out.header.frame_id = msg.header.stamp, self.map_frame
        (out.pose.position.x, out.pose.position.y, out.pose.position.z) = map(
            float, pose.translation)
        q = pose.quat_xyzw()
        (out.pose.orientation.x, out.pose.orientation.y, out.pose.orientation.z,
         out.pose.orientation.w) = map(float, q)
        self.pub.publish(out)


def main() -> None:
    rclpy.init()
    node = SlamrelocNode()
    try:
        rclpy.spin(node)
    finally:
        node.client.close()
        node.destroy_node()
        rclpy.shutdown()


if __name__ == "__main__":
    main()
