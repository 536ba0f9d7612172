"""ROS logs: ROS 1 bags, ROS 2 bags (sqlite3, MCAP) and MCAP files, and the ROS sensor messages."""
