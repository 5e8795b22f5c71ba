"""Configuration: the one settings schema, the typed sections derived from it, the replay's
options and the ROS parameter-file reader. Imports nothing else of mfp_mapper."""
