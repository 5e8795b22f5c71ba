"""Packaging for mfp_mapper (ament_python: ``colcon build`` and plain ``pip install .``).

Data files are globbed so the package builds whatever subset of ``config/`` and
``launch/`` exists.
"""

from __future__ import annotations

import os
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "mfp_mapper"
HERE = os.path.dirname(os.path.abspath(__file__))


def _files(pattern: str) -> list[str]:
    """Files matching ``pattern``, relative to this directory, sorted."""
    return sorted(p for p in glob(pattern, root_dir=HERE) if os.path.isfile(os.path.join(HERE, p)))


data_files = [
    ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
    (f"share/{PACKAGE}", ["package.xml"]),
]
for _dest, _patterns in (
    ("config", ("config/*.yaml", "config/*.xml", "config/*.rviz")),
    ("launch", ("launch/*.launch.py",)),
):
    _found = [f for pattern in _patterns for f in _files(pattern)]
    if _found:
        data_files.append((f"share/{PACKAGE}/{_dest}", _found))

setup(
    name=PACKAGE,
    version="0.2.0",
    packages=find_packages(exclude=["test", "test.*", "benchmarks", "benchmarks.*"]),
    data_files=data_files,
    install_requires=["setuptools"],
    python_requires=">=3.10",
    zip_safe=True,
    maintainer="mfp_mapper maintainers",
    maintainer_email="maintainers@users.noreply.h-seed-bdcc34ee.example",
    description=(
        "3D lidar mapping with the mean-free-path model: degree of occupancy per voxel "
        "with its uncertainty (Berquin & Zell 2021)."
    ),
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "mfp_mapper = mfp_mapper.ros.node:main",
            "mfp-mapper = mfp_mapper.cli:main",
        ],
    },
)
