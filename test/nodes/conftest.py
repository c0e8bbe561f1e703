"""Fixtures of the node tests."""

from collections.abc import Iterator

import pytest


@pytest.fixture(scope="module")
def ros_context() -> Iterator[None]:
    """rclpy initialised for a module whose tests create nodes in this process."""
    rclpy = pytest.importorskip("rclpy")
    rclpy.init()
    yield
    rclpy.try_shutdown()
