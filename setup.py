"""ament_python package definition of aefabmap_ros (also a plain pip-installable package)."""

from glob import glob
from pathlib import Path

from setuptools import find_packages, setup

PACKAGE = "aefabmap_ros"


def pinned(requirements: str) -> list[str]:
    """The requirement lines of a requirements file beside this one (none where it is absent)."""
    path = Path(__file__).parent / requirements
    lines = path.read_text().splitlines() if path.is_file() else []
    return [line.split("#")[0].strip() for line in lines if line.split("#")[0].strip()]


# Console scripts: every node and tool. Nodes are also runnable with `ros2 run aefabmap_ros <name>`.
CONSOLE_SCRIPTS = [
    "feature_node = aefabmap_ros.nodes.feature_node:main",
    "quantizer_node = aefabmap_ros.nodes.quantizer_node:main",
    "fabmap_node = aefabmap_ros.nodes.fabmap_node:main",
    "verifier_node = aefabmap_ros.nodes.verifier_node:main",
    "pose_graph_node = aefabmap_ros.nodes.pose_graph_node:main",
    "closure_view_node = aefabmap_ros.nodes.closure_view_node:main",
    "feature_server_node = aefabmap_ros.nodes.feature_server_node:main",
    "aefabmap_robot_pipeline = aefabmap_ros.nodes.robot_pipeline:main",
    "aefabmap_pipeline = aefabmap_ros.nodes.pipeline:main",
    "aefabmap_launch = aefabmap_ros.cli.launch:main",
    "aefabmap_train = aefabmap_ros.cli.train:main",
    "aefabmap_eval = aefabmap_ros.cli.evaluate:main",
    "aefabmap_replay = aefabmap_ros.cli.replay:main",
    "aefabmap_record = aefabmap_ros.cli.record:main",
    "aefabmap_synth = aefabmap_ros.cli.synth:main",
    "aefabmap_gt = aefabmap_ros.cli.gt:main",
    "aefabmap_bag = aefabmap_ros.cli.bag:main",
    "aefabmap_demo = aefabmap_ros.cli.demo:main",
    "aefabmap_bench = aefabmap_ros.cli.bench:main",
    "aefabmap_ate = aefabmap_ros.cli.ate:main",
    "aefabmap_view = aefabmap_ros.cli.view:main",
    "aefabmap_words = aefabmap_ros.cli.words:main",
    "aefabmap_map = aefabmap_ros.cli.map:main",
    "aefabmap_model = aefabmap_ros.cli.model:main",
]

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob(f"{PACKAGE}/config/*.yaml") + glob(f"{PACKAGE}/config/*.xml")
         + glob(f"{PACKAGE}/config/*.json")),
        (f"share/{PACKAGE}/launch", glob("launch/*.py")),
    ],
    # The YAML files are package data too: the CLIs find them beside the code in every kind of install.
    package_data={PACKAGE: ["config/*.yaml", "config/*.xml", "config/*.json", "py.typed"]},
    install_requires=["setuptools"],
    # Training, evaluation and tests (torch, faiss, scikit-learn, ...): pip install -e ".[train]". What the nodes
    # need, the ROS wheels included, is requirements-runtime.txt (scripts/setup.sh installs both).
    extras_require={"train": pinned("requirements-train.txt")},
    zip_safe=True,
    maintainer="aefabmap_ros developers",
    maintainer_email="aefabmap@example.org",
    description="Online visual loop-closure detection for SLAM: AE-FABMAP for ROS 2 Jazzy.",
    license="BSD-3-Clause",
    entry_points={"console_scripts": CONSOLE_SCRIPTS},
)
