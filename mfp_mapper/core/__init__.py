"""The ROS-free core: the model, the exact voxel traversal, the block store, the Mapper,
map files and the 2D grid projection. Imports neither ROS nor rosbags."""
