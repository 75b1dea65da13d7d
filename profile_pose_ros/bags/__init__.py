"""rosbag2 files through the `rosbags` library, without ROS: a splitting, flushing writer that a crash
cannot ruin, recovery of what a crash left, and reading a bag in time order. The bag_recorder and
bag_player nodes and profile_pose replay are thin glue around this."""
from .reader import BagError, BagInfo, bag_info, read_messages
from .writer import BagWriter, recover

__all__ = ["BagError", "BagInfo", "BagWriter", "bag_info", "read_messages", "recover"]
