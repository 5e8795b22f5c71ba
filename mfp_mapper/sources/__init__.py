"""Where scans come from: ROS bags, scan folders with pose files, KISS-ICP-estimated poses and
the simulator. Each is opened as a ``recording.Recording`` (``opener.open_recording``): clouds
with their pose source, the lidar extrinsic and the map frame, for the mapping loop."""
