"""Recording: a ROS-free rosbag2 writer (MCAP storage, :mod:`.rosbag_writer`) and the ``recorder`` node."""
