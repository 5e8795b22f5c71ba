"""ROS-free sensing: PointCloud2 parsing on plain buffers, poses and transforms, de-skew and
the one scan pipeline that turns a parsed cloud into placed rays (or a drop with a reason)."""
