"""Fixtures for the io tests."""

from __future__ import annotations

import pytest

from _ros_bags import BagFactory


@pytest.fixture(params=["ros1", "ros2-sqlite3", "ros2-mcap"])
def bags(request: pytest.FixtureRequest) -> BagFactory:
    """A bag factory for each of ROS1, ROS2 sqlite3, ROS2 mcap."""
    kind = str(request.param)
    if kind == "ros1":
        return BagFactory(1)
    return BagFactory(2, storage=kind.split("-")[1])
