"""Semantic graph stage (Sec. III-A): objects from depth + labels, the incremental keyframe-anchored graph."""

from shgm_slam.graph.build import build_graph_from_sequence, select_keyframes
from shgm_slam.graph.extraction import ObjectObservations, extract_objects, extract_objects_from_config
from shgm_slam.graph.semantic_graph import GraphUpdate, NodeState, SemanticGraph, edges_within_radius

__all__ = [
    "GraphUpdate",
    "NodeState",
    "ObjectObservations",
    "SemanticGraph",
    "build_graph_from_sequence",
    "edges_within_radius",
    "extract_objects",
    "extract_objects_from_config",
    "select_keyframes",
]
