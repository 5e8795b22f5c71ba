"""Ask a running mfp_mapper node what its map says: ``python query_client.py [NODE]``.

Run it where the node's ROS_DOMAIN_ID is (with the node's .venv active, or a sourced ROS 2
workspace holding mfp_mapper). It asks ``~/query`` about one point and one straight segment
and prints the answers; ``mfp-mapper call segment ...`` does the same from a shell.
"""

import sys

from mfp_mapper.ros.client import NodeClient

node = sys.argv[1] if len(sys.argv) > 1 else "mfp_mapper"
with NodeClient(node, timeout=10.0) as client:
    answer = client.query(
        points=[(0.1, 0.1, 1.3)],  # x, y, z in the map frame
        segments=[(-1.0, -1.1, 1.3, -7.0, -1.1, 1.3)],  # from x0, y0, z0 to x1, y1, z1
    )
if not answer.success:
    sys.exit(f"the node refused the query: {answer.message}")
for row in answer.points:
    if row["observed"]:
        print(f"{row['point']}: DoO {row['degree_of_occupancy']:.3f} ± {row['std']:.3f}")
    else:
        print(f"{row['point']}: unknown (never observed)")
for seg in answer.segments:
    print(
        f"{seg['start']} -> {seg['end']}: clear with probability "
        f"{seg['clear_probability']:.3f}, {seg['unknown_length']:.2f} m never observed"
    )
