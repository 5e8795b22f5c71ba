"""Map files and tiled maps: reading (checked before anything is allocated), writing."""
