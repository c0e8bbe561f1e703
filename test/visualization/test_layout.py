import json

from aefabmap_ros.io.config_files import shipped_config
from aefabmap_ros.nodes.launch_table import VIEW_TOPICS
from aefabmap_ros.visualization.layout import layout_json


def _strings(value: object) -> list[str]:
    if isinstance(value, dict):
        return [s for key, item in value.items() for s in [key, *_strings(item)]]
    if isinstance(value, list):
        return [s for item in value for s in _strings(item)]
    return [value] if isinstance(value, str) else []


def test_the_shipped_layout_is_the_generated_one():
    assert shipped_config("foxglove_layout.json").read_text() == layout_json()


def test_every_topic_the_layout_shows_is_served_by_the_live_view_and_recorded_by_the_demo():
    layout = json.loads(layout_json())
    shown = {text.split(".")[0].lstrip("/") for text in _strings(layout) if text.startswith("/")}
    assert shown and shown <= set(VIEW_TOPICS)
