"""`--ros2`: publish `/joint_states` for ROS 2 nodes on rmw_zenoh, in the ROS domain the
environment names (`ROS_DOMAIN_ID`, as every ROS 2 node reads it; default 0)."""

import argparse
import os

MAX_DOMAIN = 232  # the largest ROS_DOMAIN_ID ROS 2 accepts


class _Ros2Domain(argparse.Action):
    """Sets the option to the ROS domain number, read from ROS_DOMAIN_ID while parsing so a
    bad value is refused like any bad option (one line, exit 2) before anything opens."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        text = os.environ.get("ROS_DOMAIN_ID", "").strip() or "0"
        if not text.isdigit() or int(text) > MAX_DOMAIN:
            parser.error(f"{option_string}: ROS_DOMAIN_ID={text!r}: expected an integer "
                         f"0..{MAX_DOMAIN}")
        setattr(namespace, self.dest, int(text))


def add_ros2_argument(parser: argparse.ArgumentParser) -> None:
    """`--ros2`; afterwards `args.ros2` is the ROS domain, or None without the option."""
    parser.add_argument(
        "--ros2", action=_Ros2Domain, nargs=0, default=None,
        help="also publish sensor_msgs/msg/JointState on /joint_states as rmw_zenoh does "
             "(ROS 2 Jazzy; domain from ROS_DOMAIN_ID, default 0), so that `ros2 topic echo "
             "/joint_states` sees the joints on a machine whose rmw_zenoh router this session "
             "reaches (e.g. --connect tcp/localhost:7447)")
