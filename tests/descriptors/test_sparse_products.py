"""The numpy sparse products of the descriptors and the Eq. 1 scores equal scipy's products entry for entry
(a row's entry order is the summation order of the Eq. 1 scores, so it decides their last bits)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from shgm_slam.config import DescriptorConfig, DescriptorKind
from shgm_slam.descriptors import compute_descriptors, score_entries, similarity, sparse_graph, unit_rows
from shgm_slam.descriptors.histogram import semantic_histogram
from shgm_slam.descriptors.sparse_graph import (
    adjacency_matrix,
    csr_arrays,
    prepend_label,
    product_with_transpose,
    sparse_product,
)
from shgm_slam.types import GraphArrays


def _graph(seed: int) -> GraphArrays:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(0, 60))
    edges = rng.integers(0, max(n, 1), (int(rng.integers(0, 3 * n + 1)), 2)) if n > 1 else np.zeros((0, 2))
    edges = edges[edges[:, 0] != edges[:, 1]].astype(np.int64)
    return GraphArrays(np.arange(n), rng.integers(0, 19, n), rng.uniform(0, 50, (n, 3)), np.ones(n), edges)


def _assert_same_csr(got: sp.csr_matrix, expected: sp.csr_matrix) -> None:
    assert got.shape == expected.shape
    np.testing.assert_array_equal(got.indptr, expected.indptr)
    np.testing.assert_array_equal(got.indices, expected.indices)
    np.testing.assert_array_equal(got.data, expected.data)


def _scipy_histogram(g: GraphArrays, path_length: int) -> sp.csr_matrix:
    rows = np.concatenate([g.edges[:, 0], g.edges[:, 1]])
    cols = np.concatenate([g.edges[:, 1], g.edges[:, 0]])
    A = sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(len(g), len(g)))
    A.sum_duplicates()
    A.data[:] = 1.0
    W = sp.csr_matrix(np.ones((len(g), 1)))
    for _ in range(path_length - 1):
        W = (A @ prepend_label(W, np.asarray(g.label_ids), 19)).tocsr()
    return W


@pytest.mark.parametrize("seed", range(12))
def test_histogram_and_adjacency_equal_scipy_products(seed):
    g = _graph(seed)
    expected_a = sp.csr_matrix((np.ones(2 * len(g.edges)), (np.r_[g.edges[:, 0], g.edges[:, 1]],
                                np.r_[g.edges[:, 1], g.edges[:, 0]])), shape=(len(g), len(g)))  # fmt: skip
    expected_a.sum_duplicates()
    expected_a.data[:] = 1.0
    _assert_same_csr(adjacency_matrix(g), expected_a)
    for path_length in (2, 3, 4):
        _assert_same_csr(semantic_histogram(g, path_length), _scipy_histogram(g, path_length))


@pytest.mark.parametrize("kind", list(DescriptorKind))
def test_unit_rows_equal_the_diagonal_product(kind):
    for seed in range(6):
        counts = compute_descriptors(_graph(seed), DescriptorConfig(kind=kind)).counts
        norms = np.sqrt(np.asarray(counts.multiply(counts).sum(axis=1)).ravel())
        scale = np.divide(1.0, norms, out=np.zeros_like(norms), where=norms > 0)
        _assert_same_csr(unit_rows(counts), sp.csr_matrix(sp.diags(scale) @ counts))


def test_sparse_product_of_floats_equals_scipy_to_the_last_bit():
    rng = np.random.default_rng(7)
    for _ in range(20):
        A = sp.random(30, 40, density=0.2, random_state=rng, format="csr")
        X = sp.random(40, 25, density=0.2, random_state=rng, format="csr")
        A.data, X.data = rng.normal(size=A.nnz), rng.normal(size=X.nnz)
        indptr, indices, data = sparse_product(csr_arrays(A), csr_arrays(X), 30, 25)
        _assert_same_csr(sp.csr_matrix((data, indices, indptr), shape=(30, 25)), (A @ X).tocsr())


def _scipy_scores(ua: sp.csr_matrix, ub: sp.csr_matrix) -> sp.csr_matrix:
    """The straightforward Eq. 1 product of unit rows with scipy (as ``similarity`` computed it before)."""
    scores = (ua @ ub.T).tocsr()
    scores.data = np.minimum(scores.data, 1.0)
    scores.eliminate_zeros()
    return scores


@pytest.mark.parametrize("kind", list(DescriptorKind))
@pytest.mark.parametrize("same_label_only", [True, False])
def test_score_entries_equal_scipys_product_to_the_last_bit(kind, same_label_only):
    cfg = DescriptorConfig(kind=kind)
    for seed in range(8):
        da, db = compute_descriptors(_graph(seed), cfg), compute_descriptors(_graph(seed + 100), cfg)
        ua, ub = unit_rows(da.counts), unit_rows(db.counts)
        if same_label_only:
            ua, ub = prepend_label(ua, da.label_ids, 19), prepend_label(ub, db.label_ids, 19)
        expected = _scipy_scores(ua, ub).tocoo()
        rows_a, rows_b, scores = score_entries(da, db, same_label_only)
        got = sorted(zip(rows_a.tolist(), rows_b.tolist(), scores.tolist(), strict=True))
        assert got == sorted(zip(expected.row.tolist(), expected.col.tolist(), expected.data.tolist(), strict=True))
        np.testing.assert_array_equal(similarity(da, db, same_label_only).toarray(), expected.toarray())


@pytest.mark.parametrize("scipy_pairs", [sparse_graph.SCIPY_PRODUCT_PAIRS, 0])
def test_product_with_transpose_of_floats_equals_scipy_to_the_last_bit(scipy_pairs, monkeypatch):
    monkeypatch.setattr(sparse_graph, "SCIPY_PRODUCT_PAIRS", scipy_pairs)  # both ways of computing it
    rng = np.random.default_rng(3)
    for n_a, n_b, width in [(30, 25, 40), (1, 7, 5000), (12, 0, 9), (0, 4, 3), (20, 20, 1)]:
        A = sp.random(n_a, width, density=0.3, random_state=rng, format="csr")
        B = sp.random(n_b, width, density=0.05, random_state=rng, format="csr")
        A.data, B.data = rng.normal(size=A.nnz), rng.normal(size=B.nnz)
        indptr, indices, data = product_with_transpose(csr_arrays(A), csr_arrays(B), n_a, n_b)
        got = sp.csr_matrix((data, indices, indptr), shape=(n_a, n_b))
        expected = (A @ B.T).tocsr()
        expected.eliminate_zeros()
        got.sort_indices(), expected.sort_indices()
        _assert_same_csr(got, expected)
