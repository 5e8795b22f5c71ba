"""Packaging: package.xml, setup.py/setup.cfg, requirements, scripts, and a real colcon build."""

from __future__ import annotations

import ast
import configparser
import importlib.util
import os
import re
import runpy
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[2]
PKG = "mfp_mapper"

EXEC_DEPENDS = {
    "rclpy",
    "rcl_interfaces",
    "builtin_interfaces",
    "sensor_msgs",
    "nav_msgs",
    "std_msgs",
    "std_srvs",
    "diagnostic_msgs",
    "tf2_msgs",
    "launch",
    "launch_ros",
    "ament_index_python",
    "python3-numpy",
    "python3-numba",
    "python3-matplotlib",
    "python3-yaml",
    "python3-tqdm",
    "python3-scipy",
}
MODULE_KEYS = {  # third-party module imported -> its rosdep key (None: deliberately not listed)
    "numpy": "python3-numpy",
    "numba": "python3-numba",
    "llvmlite": "python3-numba",  # no key of its own; numba depends on it
    "matplotlib": "python3-matplotlib",
    "yaml": "python3-yaml",
    "tqdm": "python3-tqdm",
    "scipy": "python3-scipy",
    "plyfile": "python3-plyfile",
    "rosbags": None,  # pip only: see the comment in package.xml
    "dask": None,  # offline fleet mapping only (--workers/--scheduler): see package.xml
    "distributed": None,
    "kiss_icp": None,  # optional, pip only (replay --odometry kiss-icp): see package.xml
    **{
        name: name
        for name in (
            "rclpy", "rcl_interfaces", "builtin_interfaces", "sensor_msgs", "nav_msgs",
            "std_msgs", "std_srvs", "diagnostic_msgs", "geometry_msgs", "tf2_msgs",
            "mfp_mapper_msgs", "launch", "launch_ros", "ament_index_python", "lifecycle_msgs",
        )
    },
}  # fmt: skip
AHEAD_OF_USE: set[str] = set()
"""Keys listed before the code that needs them lands."""
CONSOLE_SCRIPTS = {
    "mfp_mapper": "mfp_mapper.ros.node:main",
    "mfp-mapper": "mfp_mapper.cli:main",
}


@pytest.fixture(scope="module")
def package_xml() -> ET.Element:
    return ET.parse(ROOT / "package.xml").getroot()


@pytest.fixture(scope="module")
def setup_kwargs() -> dict[str, Any]:
    """The keyword arguments setup.py passes to setuptools.setup (without running it)."""
    import setuptools

    captured: dict[str, Any] = {}
    real_setup = setuptools.setup
    setuptools.setup = lambda **kw: captured.update(kw)
    cwd = os.getcwd()
    try:
        os.chdir(ROOT)
        runpy.run_path(str(ROOT / "setup.py"), run_name="__main__")
    finally:
        os.chdir(cwd)
        setuptools.setup = real_setup
    assert captured, "setup.py did not call setuptools.setup"
    return captured


def _texts(root: ET.Element, tag: str) -> list[str]:
    return [(e.text or "").strip() for e in root.findall(tag)]


# --- package.xml ------------------------------------------------------------------------------


def test_package_xml_identity(package_xml: ET.Element) -> None:
    assert package_xml.tag == "package"
    assert package_xml.get("format") == "3"
    assert _texts(package_xml, "name") == [PKG]
    assert re.fullmatch(r"\d+\.\d+\.\d+", _texts(package_xml, "version")[0])
    assert _texts(package_xml, "license") == ["Apache-2.0"]
    assert package_xml.findall("maintainer"), "a maintainer is required"
    assert _texts(package_xml, "export/build_type") == ["ament_python"]


def test_package_xml_dependencies(package_xml: ET.Element) -> None:
    exec_deps = set(_texts(package_xml, "exec_depend")) | set(_texts(package_xml, "depend"))
    missing = EXEC_DEPENDS - exec_deps
    assert not missing, f"exec_depend missing: {sorted(missing)}"
    assert "python3-pytest" in _texts(package_xml, "test_depend")
    # rosbags is pip-installed (README), not a rosdep key of this package.
    all_deps = {e.text for e in package_xml.iter() if e.tag.endswith("depend")}
    assert not any("rosbags" in (d or "") for d in all_deps)


def _imported_modules() -> set[str]:
    """Top-level third-party modules imported anywhere in mfp_mapper/ and launch/ (ast)."""
    stdlib = set(sys.stdlib_module_names) | {"__future__"}
    found: set[str] = set()
    for path in [*(ROOT / PKG).rglob("*.py"), *(ROOT / "launch").glob("*.py")]:
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                found.update(a.name.split(".")[0] for a in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                found.add(node.module.split(".")[0])
    return found - stdlib - {PKG}


def test_package_xml_lists_exactly_what_is_imported(package_xml: ET.Element) -> None:
    modules = _imported_modules()
    unknown = modules - set(MODULE_KEYS)
    assert not unknown, f"imported modules without a rosdep key in MODULE_KEYS: {unknown}"
    needed = {MODULE_KEYS[m] for m in modules} - {None}
    listed = set(_texts(package_xml, "exec_depend")) | set(_texts(package_xml, "depend"))
    assert needed - listed == set(), "imported but not in package.xml"
    assert listed - needed - AHEAD_OF_USE == set(), "in package.xml but imported nowhere"
    assert {"rclpy", "launch_ros", "python3-yaml", "python3-numba"} <= needed  # the scan works
    assert listed >= AHEAD_OF_USE, "a key listed ahead of its use is missing"


def test_requirements_hold_the_imported_pypi_packages() -> None:
    text = (ROOT / "requirements.txt").read_text()
    assert re.search(r"^PyYAML==", text, re.M), "yaml is imported: pin PyYAML"
    assert "visualization" not in text and "visualization_msgs" not in _imported_modules()


def test_package_xml_validates_with_catkin_pkg() -> None:
    catkin_pkg = pytest.importorskip("catkin_pkg.package", reason="catkin_pkg not installed")
    package = catkin_pkg.parse_package(str(ROOT / "package.xml"))
    package.validate()
    assert package.name == PKG
    assert package.get_build_type() == "ament_python"


def test_license_file_is_apache() -> None:
    text = (ROOT / "LICENSE").read_text()
    assert "Apache License" in text and "Version 2.0" in text


# --- setup.py / setup.cfg ---------------------------------------------------------------------


def test_setup_matches_package_xml(setup_kwargs: dict[str, Any], package_xml: ET.Element) -> None:
    assert setup_kwargs["name"] == PKG
    assert setup_kwargs["version"] == _texts(package_xml, "version")[0]
    assert setup_kwargs["license"] == "Apache-2.0"
    assert PKG in setup_kwargs["packages"]
    assert not any(p.startswith(("test", "benchmarks")) for p in setup_kwargs["packages"])


def test_setup_data_files(setup_kwargs: dict[str, Any]) -> None:
    data = {dest: list(files) for dest, files in setup_kwargs["data_files"]}
    marker = f"resource/{PKG}"
    assert data["share/ament_index/resource_index/packages"] == [marker]
    assert (ROOT / marker).is_file() and (ROOT / marker).stat().st_size == 0
    assert data[f"share/{PKG}"] == ["package.xml"]
    for sub, patterns in (("config", ("*.yaml", "*.xml", "*.rviz")), ("launch", ("*.launch.py",))):
        on_disk = sorted(
            f"{sub}/{p.name}" for pattern in patterns for p in (ROOT / sub).glob(pattern)
        )
        assert sorted(data.get(f"share/{PKG}/{sub}", [])) == on_disk
    assert (
        f"share/{PKG}/config" in data
        and "config/fastdds_large_data.xml" in data[f"share/{PKG}/config"]
    )
    for files in data.values():
        for f in files:
            assert (ROOT / f).is_file(), f


def test_console_scripts_declared(setup_kwargs: dict[str, Any]) -> None:
    declared = {}
    for spec in setup_kwargs["entry_points"]["console_scripts"]:
        name, target = (s.strip() for s in spec.split("=", 1))
        declared[name] = target
    assert declared == CONSOLE_SCRIPTS


def _top_level_names(tree: ast.Module) -> set[str]:
    names: set[str] = set()
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Assign):
            names.update(t.id for t in node.targets if isinstance(t, ast.Name))
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names.update((a.asname or a.name).split(".")[0] for a in node.names)
    return names


@pytest.mark.parametrize("script", sorted(CONSOLE_SCRIPTS))
def test_console_script_target_exists(script: str) -> None:
    module, func = CONSOLE_SCRIPTS[script].split(":")
    path = ROOT / (module.replace(".", "/") + ".py")
    if not path.exists():  # a package: its __init__ holds the name
        path = ROOT / module.replace(".", "/") / "__init__.py"
    assert path.exists(), f"{module} (console script {script}) does not exist"
    top_level = _top_level_names(ast.parse(path.read_text(), filename=str(path)))
    assert func in top_level, f"{path.relative_to(ROOT)} has no top-level {func}()"
    assert importlib.util.find_spec(module) is not None


def test_setup_cfg_script_dir() -> None:
    cfg = configparser.ConfigParser()
    cfg.read(ROOT / "setup.cfg")
    assert cfg.get("develop", "script_dir") == f"$base/lib/{PKG}"
    assert cfg.get("install", "install_scripts") == f"$base/lib/{PKG}"


# --- requirements, scripts ----------------------------------------------------------------


@pytest.mark.parametrize("name", ["requirements.txt", "requirements-dev.txt"])
def test_requirements_are_pinned(name: str) -> None:
    lines = [line.split("#", 1)[0].strip() for line in (ROOT / name).read_text().splitlines()]
    reqs = [line for line in lines if line]
    assert reqs
    for req in reqs:
        assert re.fullmatch(r"[A-Za-z0-9_.\-]+==[A-Za-z0-9_.\-]+", req), f"not pinned: {req}"


def test_runtime_requirements_cover_the_ros_wheels() -> None:
    text = (ROOT / "requirements.txt").read_text()
    for dist in ("ros-rclpy", "ros-sensor-msgs", "ros-rmw-fastrtps-cpp", "numpy", "numba"):
        assert re.search(rf"^{re.escape(dist)}==", text, re.M), dist
    assert re.search(r"^rosbags==", text, re.M)


@pytest.mark.parametrize("script", ["run", ".ci/run", "scripts/colcon_check.sh"])
def test_shell_scripts(script: str) -> None:
    path = ROOT / script
    assert os.access(path, os.X_OK), f"{script} is not executable"
    assert path.read_text().startswith("#!/usr/bin/env bash\n")
    subprocess.run(["bash", "-n", str(path)], check=True)


# --- colcon -------------------------------------------------------------------------------


@pytest.mark.slow
def test_colcon_build_installs_the_package() -> None:
    if os.environ.get("MFP_COLCON_CHECK_SEPARATE") == "1":
        pytest.skip("the colcon build check runs as its own step of ./run test")
    if importlib.util.find_spec("colcon_core") is None or shutil.which("bash") is None:
        pytest.skip("colcon (colcon-common-extensions) is not installed in this Python")
    env = dict(os.environ, PYTHON=sys.executable)
    proc = subprocess.run(
        ["bash", str(ROOT / "scripts" / "colcon_check.sh")],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
        stdin=subprocess.DEVNULL,
    )
    if proc.returncode == 3:
        pytest.skip(proc.stderr.strip())
    assert proc.returncode == 0, proc.stdout + proc.stderr


# --- RViz -------------------------------------------------------------------------------------


def test_rviz_config_shows_the_node_outputs() -> None:
    """config/mfp_mapper.rviz: DoO cloud coloured by its field, std cloud, projected map
    and TF, on the topics the node publishes, transient-local like the node's map outputs."""
    yaml = pytest.importorskip("yaml")
    config = yaml.safe_load((ROOT / "config" / "mfp_mapper.rviz").read_text())
    displays = {d["Class"]: d for d in config["Visualization Manager"]["Displays"]}
    by_topic = {
        d["Topic"]["Value"]: d for d in config["Visualization Manager"]["Displays"] if "Topic" in d
    }
    node_source = "".join(p.read_text() for p in (ROOT / "mfp_mapper" / "ros").glob("*.py"))
    for topic, channel in (
        ("/mfp_mapper/degree_of_occupancy", "degree_of_occupancy"),
        ("/mfp_mapper/std", "std"),
        ("/mfp_mapper/projected_map", None),
    ):
        display = by_topic[topic]
        assert f'"~/{topic.rsplit("/", 1)[1]}"' in node_source, topic
        assert display["Topic"]["Durability Policy"] == "Transient Local"
        if channel is not None:
            assert display["Class"] == "rviz_default_plugins/PointCloud2"
            assert display["Color Transformer"] == "Intensity"
            assert display["Channel Name"] == channel
            assert f'"{channel}"' in node_source
    assert "rviz_default_plugins/TF" in displays and "rviz_default_plugins/Map" in displays
    assert by_topic["/mfp_mapper/projected_map"]["Class"] == "rviz_default_plugins/Map"


def test_launch_file_has_an_rviz_argument() -> None:
    tree = ast.parse((ROOT / "launch" / "mfp_mapper.launch.py").read_text())
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call)]
    declared = {
        c.args[0].value
        for c in calls
        if getattr(c.func, "id", None) == "DeclareLaunchArgument" and c.args
        if isinstance(c.args[0], ast.Constant)
    }
    assert {"rviz", "rviz_config"} <= declared
    rviz_nodes = [
        c
        for c in calls
        if getattr(c.func, "id", None) == "Node"
        and any(k.arg == "package" and getattr(k.value, "value", "") == "rviz2" for k in c.keywords)
    ]
    assert len(rviz_nodes) == 1
    keywords = {k.arg: k.value for k in rviz_nodes[0].keywords}
    assert "IfCondition" in ast.dump(keywords["condition"])
    assert "mfp_mapper.rviz" in (ROOT / "launch" / "mfp_mapper.launch.py").read_text()


def test_one_version(package_xml: ET.Element) -> None:
    """package.xml, setup.py and ``mfp_mapper.__version__`` (``--version``) agree."""
    import mfp_mapper

    setup_text = (ROOT / "setup.py").read_text()
    found = re.search(r'version="([^"]+)"', setup_text)
    assert found is not None
    assert package_xml.findtext("version") == found.group(1) == mfp_mapper.__version__
