"""Descriptor dispatch and the Eq. 1 similarity as one masked sparse product."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.config import DescriptorConfig, DescriptorKind
from shgm_slam.descriptors import DESCRIPTOR_BUILDERS, compute_descriptors, similarity
from shgm_slam.descriptors.histogram import semantic_histogram
from shgm_slam.labels import NUM_CLASSES
from shgm_slam.types import GraphArrays


def _random_graph(seed: int, n: int = 40) -> GraphArrays:
    rng = np.random.default_rng(seed)
    pos = rng.uniform(0, 60, (n, 3))
    d = np.linalg.norm(pos[:, None] - pos[None], axis=2)
    i, j = np.nonzero(np.triu(d < 15, k=1))
    return GraphArrays(np.arange(n), rng.integers(0, 5, n), pos, np.ones(n), np.stack([i, j], axis=1))


def test_every_kind_has_a_builder():
    assert set(DESCRIPTOR_BUILDERS) == set(DescriptorKind)
    g = _random_graph(0)
    dims = {DescriptorKind.HISTOGRAM: NUM_CLASSES**2, DescriptorKind.NEIGHBOR_VECTOR: NUM_CLASSES,
            DescriptorKind.RANDOM_WALK: NUM_CLASSES**3}  # fmt: skip
    for kind, dim in dims.items():
        d = compute_descriptors(g, DescriptorConfig(kind=kind))
        assert d.kind is kind and d.counts.shape == (len(g), dim) and len(d) == len(g)


def test_histogram_config_is_forwarded():
    g = _random_graph(1)
    d = compute_descriptors(g, DescriptorConfig(path_length=4, count_backtracking=False))
    np.testing.assert_array_equal(d.counts.toarray(), semantic_histogram(g, 4, False).toarray())


@pytest.mark.parametrize("same_label_only", [True, False])
def test_similarity_is_the_masked_cosine(same_label_only):
    a, b = _random_graph(2), _random_graph(3)
    da, db = compute_descriptors(a, DescriptorConfig()), compute_descriptors(b, DescriptorConfig())
    S = similarity(da, db, same_label_only).toarray()
    A, B = da.counts.toarray(), db.counts.toarray()
    na, nb = np.linalg.norm(A, axis=1), np.linalg.norm(B, axis=1)
    expected = (A @ B.T) / np.maximum(np.outer(na, nb), 1e-300)  # Eq. 1
    if same_label_only:
        expected *= a.label_ids[:, None] == b.label_ids[None, :]
    np.testing.assert_allclose(S, expected, atol=1e-12)
    assert S.max() <= 1.0 and S.min() >= 0.0
    self_scores = similarity(da, da, same_label_only).toarray().diagonal()
    np.testing.assert_allclose(self_scores[na > 0], 1.0)


def test_similarity_refuses_mixed_kinds():
    g = _random_graph(4)
    with pytest.raises(ValueError, match="cannot compare"):
        similarity(compute_descriptors(g, DescriptorConfig()),
                   compute_descriptors(g, DescriptorConfig(kind=DescriptorKind.NEIGHBOR_VECTOR)))  # fmt: skip
