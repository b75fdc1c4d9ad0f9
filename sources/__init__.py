"""Readers of recorded rows: ROS 1 / ROS 2 bags and the BUP20-style PNG folder."""
