"""Where scans come from: ROS bags, scan folders with pose files, KISS-ICP-estimated poses and
the simulator. Each yields clouds with their pose source for the mapping loop."""
