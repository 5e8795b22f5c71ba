"""The core: the model, the exact voxel traversal, the block store, the Mapper, the 2D grid
projection and the scan likelihood. No file I/O; imports neither ROS nor rosbags."""
