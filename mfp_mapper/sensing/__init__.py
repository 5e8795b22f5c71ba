"""ROS-free sensing: PointCloud2 parsing on plain buffers, poses and the TF buffer, de-skew,
no-return recovery and placement: a parsed cloud becomes placed rays (or a drop with a reason).
Never touches the Mapper."""
