"""ROS 1 / ROS 2 / mcap recordings in and out, through the `rosbags` library (see docs/capture-sources.md)."""
