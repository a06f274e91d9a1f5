"""The layout's rules, read from the code itself (AST of every module a package installs; tests excluded):

- runtime packages (tal_core, tal_control, tal_estimation, tal_perception, tal_sim_bridge) import only
  tal_core and tal_msgs among tal's packages: never the lab, sim2real or each other;
- tal_core's pure part imports no rclpy and no message package (only ``tal_core.ros`` may);
- tal_sim2real depends on the lab, the bridge and tal_core only;
- every import of a package is declared in its ``package.xml`` (exec_depend or depend).
"""

from __future__ import annotations

import ast
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RUNTIME = ("tal_core", "tal_control", "tal_estimation", "tal_perception", "tal_sim_bridge")
TAL = (*RUNTIME, "tal_lab", "tal_sim2real", "tal_msgs")
ALLOWED_TAL = {
    **{pkg: {"tal_core", "tal_msgs"} for pkg in RUNTIME},
    "tal_lab": set(TAL) - {"tal_lab", "tal_sim2real"},
    "tal_sim2real": {"tal_core", "tal_lab", "tal_sim_bridge", "tal_msgs"},
}
# Import name -> the key a package.xml declares it under (rosdep keys where they exist).
DEPENDENCY_KEY = {
    "numpy": "python3-numpy",
    "yaml": "python3-yaml",
    "scipy": "python3-scipy",
    "matplotlib": "python3-matplotlib",
    "torch": "python3-torch",
    "tqdm": "python3-tqdm",
    "osqp": "python3-osqp",
    "filterpy": "python3-filterpy",
    "mcap": "python3-mcap",
    "mcap_ros2": "python3-mcap",
    "onnxruntime": "python3-onnxruntime",
    "onnx": "python3-onnx",
    "psutil": "python3-psutil",
    "numba": "python3-numba",
    "proxsuite": "proxsuite",
    "daqp": "python3-daqp",
    "pinocchio": "pinocchio",
    "example_robot_data": "example-robot-data",
    "pybullet": "python3-pybullet",
    "pybullet_data": "python3-pybullet",
    "pybullet_utils": "python3-pybullet",
    "threadpoolctl": "python3-threadpoolctl",
    "mujoco": "python3-mujoco",
}
IGNORED = set(sys.stdlib_module_names) | {"__future__", "setuptools"}


def package_modules(pkg: str) -> list[Path]:
    return sorted(p for p in (ROOT / pkg / pkg).rglob("*.py"))


def imports_of(path: Path) -> set[str]:
    """Absolute module names imported anywhere in the file (function-level imports included)."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
    return names


def declared(pkg: str) -> set[str]:
    tree = ET.parse(ROOT / pkg / "package.xml")
    return {e.text.strip() for tag in ("depend", "exec_depend") for e in tree.getroot().iter(tag) if e.text}


@pytest.mark.parametrize("pkg", sorted(ALLOWED_TAL))
def test_tal_imports_follow_the_layers(pkg: str) -> None:
    wrong = {
        f"{path.relative_to(ROOT)}: {name}"
        for path in package_modules(pkg)
        for name in imports_of(path)
        if name.split(".")[0] in TAL and name.split(".")[0] != pkg and name.split(".")[0] not in ALLOWED_TAL[pkg]
    }
    assert not wrong, f"{pkg} imports packages its layer may not use:\n" + "\n".join(sorted(wrong))


def test_tal_core_pure_part_imports_no_ros() -> None:
    ros_side = ROOT / "tal_core" / "tal_core" / "ros"
    wrong = {
        f"{path.relative_to(ROOT)}: {name}"
        for path in package_modules("tal_core")
        if ros_side not in path.parents
        for name in imports_of(path)
        if name.split(".")[0] in {"rclpy", "tal_msgs"} or name.split(".")[0].endswith("_msgs")
        or name.startswith("tal_core.ros")
    }
    assert not wrong, "tal_core's pure part imports ROS:\n" + "\n".join(sorted(wrong))


@pytest.mark.parametrize("pkg", sorted(ALLOWED_TAL))
def test_every_import_is_declared_in_package_xml(pkg: str) -> None:
    keys = declared(pkg)
    missing = set()
    for path in package_modules(pkg):
        for name in imports_of(path):
            top = name.split(".")[0]
            if top in IGNORED or top == pkg:
                continue
            key = DEPENDENCY_KEY.get(top, top)
            if key not in keys:
                missing.add(f"{key} (import {name} in {path.relative_to(ROOT)})")
    assert not missing, f"{pkg}/package.xml does not declare:\n" + "\n".join(sorted(missing))


def test_the_check_sees_a_violation(tmp_path: Path) -> None:
    """The AST walk finds imports inside functions too (a lazy import is still a dependency)."""
    module = tmp_path / "m.py"
    module.write_text("def f():\n    from tal_lab.closed_loop import run_closed_loop\n    import torch\n")
    assert imports_of(module) == {"tal_lab.closed_loop", "torch"}
