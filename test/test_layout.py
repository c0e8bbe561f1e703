"""The layout's rules: only nodes/ and cli/ import ROS; every import goes down the layers; the subpackages
form no import cycle; the message conversions run without gtsam."""

import ast
import graphlib
import subprocess
import sys
from collections.abc import Iterable, Mapping
from pathlib import Path

import pytest

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


# Lowest first. A module imports its own subpackage and strictly lower layers only, so a reader can take in
# a layer knowing only the ones below it, and a robot that runs a node needs only what lies under that node.
# datasets/ makes synthetic recordings together with their ground truth, which evaluation defines: it sits
# above evaluation. cli/ starts the nodes and speaks their topics (launch table, QoS, message stamps): it
# sits above nodes. config/ holds parameter YAML only, read by path (io.config_files), never imported.
LAYERS: tuple[tuple[str, ...], ...] = (
    ("errors", "stamps"),
    ("io", "features"),
    ("vocabulary", "fabmap", "verification"),
    ("model",),
    ("evaluation", "backend", "visualization"),
    ("datasets",),
    ("nodes",),
    ("cli",),
)
# (importing file, imported module) -> why an import against the layers stays and how it goes. None today.
ALLOWED_CROSSINGS: dict[tuple[str, str], str] = {}


def layer_of(name: str) -> int:
    """The layer of a subpackage or top-level module (its first name inside the package)."""
    for level, names in enumerate(LAYERS):
        if name in names:
            return level
    raise KeyError(f"{name} is in no layer of LAYERS")


def package_imports(path: Path, package_dir: Path) -> set[str]:
    """Modules of the package ``path`` imports, absolute or relative, at module level or inside functions:
    ``from aefabmap_ros import io`` counts as ``aefabmap_ros.io``."""
    package = package_dir.name
    here = [package, *path.relative_to(package_dir).with_suffix("").parts]
    if here[-1] == "__init__":
        here.append("")  # a package's relative imports start from the package itself
    modules: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            modules.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            above = here[: len(here) - node.level]
            base = ".".join([*above, node.module or ""]).strip(".") if node.level else node.module or ""
            modules.add(base)
            if base == package:
                modules.update(f"{package}.{alias.name}" for alias in node.names)
    return {m for m in modules if m.startswith(f"{package}.")}


def first_name(relative: Path) -> str:
    """The subpackage (or top-level module) a file of the package belongs to."""
    return relative.parts[0] if len(relative.parts) > 1 else relative.stem


def subpackage_imports(package_dir: Path) -> dict[tuple[str, str], str]:
    """(importing file relative to the package, imported module) -> the imported module's subpackage, for
    every import of another subpackage."""
    crossings = {}
    for path in sorted(package_dir.rglob("*.py")):
        relative = path.relative_to(package_dir)
        for module in package_imports(path, package_dir):
            target = module.split(".")[1]
            if target != first_name(relative):
                crossings[(relative.as_posix(), module)] = target
    return crossings


def upward_imports(package_dir: Path) -> set[tuple[str, str]]:
    """(file, module) of every import of the same or a higher layer than the file's own."""
    return {(file, module) for (file, module), target in subpackage_imports(package_dir).items()
            if layer_of(target) >= layer_of(first_name(Path(file)))}


def import_cycle(edges: Iterable[tuple[str, str]]) -> list[str]:
    """One cycle of the directed graph (importer -> imported), [] when there is none."""
    graph: dict[str, set[str]] = {}
    for source, target in edges:
        graph.setdefault(source, set()).add(target)
    try:
        tuple(graphlib.TopologicalSorter(graph).static_order())
    except graphlib.CycleError as error:
        return list(error.args[1])
    return []


def test_every_subpackage_has_a_layer():
    names = {first_name(path.relative_to(PACKAGE_DIR)) for path in PACKAGE_DIR.rglob("*.py")} - {"__init__"}
    assert sorted(n for n in names if all(n not in layer for layer in LAYERS)) == []


def test_every_import_goes_down_the_layers():
    assert upward_imports(PACKAGE_DIR) - set(ALLOWED_CROSSINGS) == set()


def test_every_allowed_crossing_is_still_there():
    """An allowance whose import is gone is deleted, so the list only names what is left to fix."""
    assert set(ALLOWED_CROSSINGS) - upward_imports(PACKAGE_DIR) == set()


def test_the_subpackages_import_no_cycle():
    edges = {(first_name(Path(file)), target) for (file, _), target in subpackage_imports(PACKAGE_DIR).items()}
    assert import_cycle(edges) == []


def write_modules(root: Path, sources: Mapping[str, str]) -> Path:
    """A package ``aefabmap_ros`` under ``root`` with the given files (relative path -> source)."""
    package = root / "aefabmap_ros"
    for relative, source in sources.items():
        path = package / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(source)
    return package


def test_the_rule_catches_imports_up_and_sideways_absolute_relative_and_in_functions(tmp_path):
    package = write_modules(tmp_path, {
        "io/upward.py": "def f():\n    from aefabmap_ros.evaluation.metrics import recall\n    return recall\n",
        "io/relative.py": "from ..fabmap import chowliu\n",
        "io/sideways.py": "from aefabmap_ros import features\n",
        "io/own.py": "from . import upward\nfrom aefabmap_ros.io import relative\nfrom aefabmap_ros.errors import E\n",
        "cli/top.py": "import aefabmap_ros.nodes.common\nfrom aefabmap_ros.datasets.synth import town\n",
    })
    assert upward_imports(package) == {
        ("io/upward.py", "aefabmap_ros.evaluation.metrics"),
        ("io/relative.py", "aefabmap_ros.fabmap"),
        ("io/sideways.py", "aefabmap_ros.features"),
    }


def test_a_cycle_is_found_and_a_tree_has_none():
    assert sorted(set(import_cycle([("io", "fabmap"), ("fabmap", "model"), ("model", "io"), ("cli", "io")]))) \
        == ["fabmap", "io", "model"]
    assert import_cycle([("cli", "nodes"), ("nodes", "io"), ("cli", "io")]) == []


def import_without_gtsam(*modules: str) -> subprocess.CompletedProcess[str]:
    """Import ``modules`` in a fresh interpreter where any import of gtsam raises; it prints the backend
    modules that got loaded."""
    probe = (
        "import importlib, sys\n"
        "sys.modules['gtsam'] = None\n"
        f"for name in {list(modules)!r}:\n"
        "    importlib.import_module(name)\n"
        "print(sorted(m for m in sys.modules if m.startswith('aefabmap_ros.backend')))\n"
    )
    return subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)


def test_the_detection_nodes_and_message_conversions_import_without_gtsam_or_the_backend():
    """A robot running the feature, quantizer and FAB-MAP nodes needs neither gtsam nor the example backend."""
    pytest.importorskip("aefabmap_msgs.msg")
    result = import_without_gtsam("aefabmap_ros.nodes.messages", "aefabmap_ros.nodes.feature_node",
                                  "aefabmap_ros.nodes.quantizer_node", "aefabmap_ros.nodes.fabmap_node")
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]"


def test_the_gtsam_probe_fails_on_the_modules_that_need_gtsam():
    pytest.importorskip("aefabmap_msgs.msg")
    for module in ("aefabmap_ros.nodes.gtsam_poses", "aefabmap_ros.backend.pose_graph"):
        result = import_without_gtsam(module)
        assert result.returncode != 0 and "import of gtsam halted" in result.stderr, module
