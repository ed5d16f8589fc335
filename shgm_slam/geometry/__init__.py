"""Batched SE(3) algebra, weighted rigid alignment and pinhole camera geometry (pure numpy)."""
