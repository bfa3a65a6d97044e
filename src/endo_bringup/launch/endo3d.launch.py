r"""The endo3d graph for a full ROS 2 install: ``ros2 launch``.

The same four nodes, parameter file and topic remaps as ``endo-launch live``
(``endo_bringup.graph.NODES``; ``tests/test_launch_file.py`` checks that the two
agree). Start your camera driver and tracker driver yourself, then::

    ros2 launch endo_bringup endo3d.launch.py                 # after colcon build
    ros2 launch launch/endo3d.launch.py params_file:=my.yaml  # from a clone
    ros2 launch endo_bringup endo3d.launch.py image_topic:=/camera/image_raw \\
        camera_info_topic:=/camera/camera_info tracker_topic:=/ndi/scope/pose

Arguments:
    params_file: ROS parameter file for every node (default: the shipped
        config/endo3d.yaml, every parameter at its default).
    namespace: put the nodes and every graph topic under it (/rig1/endoscope/...).
    image_topic, camera_info_topic, tracker_topic: your drivers' topics.
    respawn: restart a node that dies (true/false).

Before starting the nodes on one computer, nothing to do for large images:
each node gives itself endo3d's Fast DDS large-frame profile (README, "Large
images over DDS").
"""

from pathlib import Path  # noqa: I001  (ruff takes the repository's launch/ for this package)

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

#: config/ beside launch/, in a clone and in share/endo_bringup alike (the
#: repository's launch/ and config/ link into the package: not resolved here).
DEFAULT_PARAMS = str(Path(__file__).absolute().parent.parent / "config" / "endo3d.yaml")


def generate_launch_description() -> LaunchDescription:
    """The launch arguments and the four nodes."""
    params_file = LaunchConfiguration("params_file")
    namespace = LaunchConfiguration("namespace")
    respawn = LaunchConfiguration("respawn")  # "true"/"false", typed by launch

    def graph(topic: str) -> list:
        """A graph topic under the namespace (unchanged when the namespace is empty)."""
        return [namespace, topic]

    image_raw = LaunchConfiguration("image_topic")
    camera_info = LaunchConfiguration("camera_info_topic")
    tracker_pose = LaunchConfiguration("tracker_topic")
    return LaunchDescription([
        DeclareLaunchArgument(
            "params_file", default_value=DEFAULT_PARAMS,
            description="ROS parameter file for every node",
        ),
        DeclareLaunchArgument(
            "namespace", default_value="",
            description="namespace of the nodes and the graph's topics, e.g. /rig1",
        ),
        DeclareLaunchArgument(
            "image_topic", default_value=graph("/endoscope/image_raw"),
            description="the camera driver's image topic",
        ),
        DeclareLaunchArgument(
            "camera_info_topic", default_value=graph("/endoscope/camera_info"),
            description="the camera driver's camera_info topic",
        ),
        DeclareLaunchArgument(
            "tracker_topic", default_value=graph("/tracker/pose"),
            description="the tracker driver's PoseStamped topic",
        ),
        DeclareLaunchArgument(
            "respawn", default_value="false", description="restart a node that dies"
        ),
        Node(
            package="endo_calib",
            executable="endo-photometric-correction",
            name="photometric_correction",
            namespace=namespace,
            parameters=[params_file],
            remappings=[
                ("/endoscope/image_raw", image_raw),
                ("/endoscope/image_corrected", graph("/endoscope/image_corrected")),
            ],
            output="screen",
            respawn=respawn,
            respawn_delay=1.0,
        ),
        Node(
            package="endo_sfs",
            executable="endo-sfs",
            name="sfs",
            namespace=namespace,
            parameters=[params_file],
            remappings=[
                ("/endoscope/image_corrected", graph("/endoscope/image_corrected")),
                ("/endoscope/camera_info", camera_info),
                ("/endoscope/depth_relative", graph("/endoscope/depth_relative")),
            ],
            output="screen",
            respawn=respawn,
            respawn_delay=1.0,
        ),
        Node(
            package="endo_tracker_bridge",
            executable="endo-tracker-bridge",
            name="tracker_bridge",
            namespace=namespace,
            parameters=[params_file],
            remappings=[
                ("/tracker/pose", tracker_pose),
                ("/endoscope/pose", graph("/endoscope/pose")),
                ("/tracker/marker_pose", graph("/tracker/marker_pose")),
            ],
            output="screen",
            respawn=respawn,
            respawn_delay=1.0,
        ),
        Node(
            package="endo_flow",
            executable="endo-flow",
            name="flow",
            namespace=namespace,
            parameters=[params_file],
            remappings=[
                ("/endoscope/depth_relative", graph("/endoscope/depth_relative")),
                ("/endoscope/image_corrected", graph("/endoscope/image_corrected")),
                ("/endoscope/camera_info", camera_info),
                ("/endoscope/pose", graph("/endoscope/pose")),
                ("/endoscope/scale", graph("/endoscope/scale")),
                ("/endoscope/depth", graph("/endoscope/depth")),
                ("/endoscope/points", graph("/endoscope/points")),
                ("/endoscope/map", graph("/endoscope/map")),
            ],
            output="screen",
            respawn=respawn,
            respawn_delay=1.0,
        ),
    ])
