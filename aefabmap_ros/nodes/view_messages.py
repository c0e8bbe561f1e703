"""The viewer's pure drawings (visualization/) as ROS messages: markers and JPEG pictures."""

from __future__ import annotations

from typing import Any

from builtin_interfaces.msg import Duration
from geometry_msgs.msg import Point
from sensor_msgs.msg import CompressedImage
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from aefabmap_ros.visualization.graph_markers import MarkerSpec, Shape

_MARKER_TYPES = {Shape.SPHERE_LIST: Marker.SPHERE_LIST, Shape.LINE_LIST: Marker.LINE_LIST,
                 Shape.LINE_STRIP: Marker.LINE_STRIP}


def marker_array(specs: list[MarkerSpec], frame_id: str, stamp: Any) -> MarkerArray:
    """One ADD marker per spec (id 0 of its namespace: each replaces the last one of its namespace)."""
    return MarkerArray(markers=[_marker(spec, frame_id, stamp) for spec in specs])


def _marker(spec: MarkerSpec, frame_id: str, stamp: Any) -> Marker:
    marker = Marker(ns=spec.namespace, id=0, type=_MARKER_TYPES[spec.shape], action=Marker.ADD,
                    lifetime=Duration())  # 0: until replaced
    marker.header.frame_id, marker.header.stamp = frame_id, stamp
    marker.pose.orientation.w = 1.0
    marker.scale.x = marker.scale.y = marker.scale.z = spec.width_m
    marker.points = [Point(x=float(x), y=float(y), z=float(z)) for x, y, z in spec.points]
    marker.colors = [ColorRGBA(r=float(r), g=float(g), b=float(b), a=float(a)) for r, g, b, a in spec.colours]
    if len(spec.colours):
        marker.color = marker.colors[0]
    return marker


def jpeg_message(jpeg: bytes, stamp: Any, frame_id: str) -> CompressedImage:
    message = CompressedImage(format="jpeg", data=jpeg)
    message.header.stamp, message.header.frame_id = stamp, frame_id
    return message
