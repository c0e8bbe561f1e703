"""The layout's one hard rule: only nodes/ and cli/ import ROS; everything else is plain Python."""

import ast
from pathlib import Path

import aefabmap_ros

PACKAGE_DIR = Path(aefabmap_ros.__file__).parent
ROS_FOLDERS = ("nodes", "cli")  # rclpy and the generated message packages are allowed here only
ROS_MODULES = ("rclpy", "aefabmap_msgs", "sensor_msgs", "std_msgs", "builtin_interfaces", "nav_msgs",
               "geometry_msgs", "tf2_msgs", "rosidl_runtime_py")


def imported_top_levels(path: Path) -> set[str]:
    """Top-level names of every module ``path`` imports, at module level or inside functions."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module.split(".")[0])
    return names


def test_only_nodes_and_cli_import_ros():
    offenders = {}
    for path in sorted(PACKAGE_DIR.rglob("*.py")):
        relative = path.relative_to(PACKAGE_DIR)
        if relative.parts[0] in ROS_FOLDERS:
            continue
        ros = imported_top_levels(path) & set(ROS_MODULES)
        if ros:
            offenders[str(relative)] = sorted(ros)
    assert offenders == {}


def test_the_rule_catches_an_import_inside_a_function(tmp_path):
    module = tmp_path / "m.py"
    module.write_text("def f():\n    from rclpy.node import Node\n    return Node\n")
    assert "rclpy" in imported_top_levels(module)


def test_every_folder_of_the_package_is_a_package():
    folders = {path.parent for path in PACKAGE_DIR.rglob("*.py")}
    assert [str(f) for f in sorted(folders) if not (f / "__init__.py").exists()] == []


def test_every_package_lists_its_modules_in_all():
    """``__all__`` of each package names exactly its modules and subpackages (a new module is listed)."""
    stale = {}
    for init in sorted(PACKAGE_DIR.rglob("__init__.py")):
        folder = init.parent
        present = {p.stem for p in folder.glob("*.py") if p.stem != "__init__"}
        present |= {p.name for p in folder.iterdir() if (p / "__init__.py").is_file()}
        namespace: dict[str, list[str]] = {}
        exec(compile(init.read_text(), str(init), "exec"), namespace)  # only the listing, no submodule imports
        listed = set(namespace.get("__all__", [])) - {"__version__"}
        if listed != present:
            stale[str(folder.relative_to(PACKAGE_DIR))] = sorted(listed ^ present)
    assert stale == {}
