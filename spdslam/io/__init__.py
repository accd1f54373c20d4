"""File formats: TORO / g2o 3-D pose graphs."""

from .g2o import Edge, PoseGraph, parse_g2o, pose_graph_factors, read_g2o, rpy_to_quaternion

__all__ = ["Edge", "PoseGraph", "read_g2o", "parse_g2o", "pose_graph_factors", "rpy_to_quaternion"]
