"""Configuration, the lowest layer: the settings sections (``sections``: the one definition of
every setting), what derives from them (``schema``: ``SETTINGS``, ``NodeConfig``, the YAML;
``replay_options``: ``ReplayOptions`` and the replay's flags) and the ROS parameter-file
reader. Imports nothing else of mfp_mapper."""
