"""The map server: mirrored graphs, cross-robot matching, the fused pose graph, its node process."""
