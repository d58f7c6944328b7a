"""Descriptor matching (`match_descriptors`) against a brute-force float64 reference, across the
query / database blocks it works in."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from slamreloc.features import matcher
from slamreloc.features.matcher import match_descriptors


def unit(x):
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def reference(query, db, ratio, mutual, points, same_point_m):
    """Pairs by the definition, and the queries whose decision is too close to call in float32
    (ratio within 1e-4 of the threshold, or near-tied neighbours)."""
    sim = query.astype(np.float64) @ db.astype(np.float64).T
    order = np.argsort(-sim, axis=1, kind="stable")[:, :2]
    top = np.take_along_axis(sim, order, 1)
    dist = np.sqrt(np.clip(2 - 2 * top, 0, None))
    keep = dist[:, 0] < ratio * dist[:, 1]
    unsure = np.abs(dist[:, 0] - ratio * dist[:, 1]) < 1e-4
    unsure |= top[:, 0] - top[:, 1] < 1e-5
    if points is not None:
        gap = np.linalg.norm(points[order[:, 0]] - points[order[:, 1]], axis=1)
        keep |= gap < same_point_m
    if mutual:
        col = np.sort(sim, axis=0)
        unsure |= (col[-1] - col[-2] < 1e-5)[order[:, 0]]
        keep &= sim.argmax(0)[order[:, 0]] == np.arange(len(query))
    return np.flatnonzero(keep), order[keep, 0], unsure


@settings(max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(0, 40), m=st.integers(0, 60),
       dim=st.sampled_from([4, 8, 32]), ratio=st.sampled_from([0.7, 0.8, 0.9]),
       mutual=st.booleans(), with_points=st.booleans(),
       query_block=st.integers(2, 50), db_chunk=st.integers(2, 70))
def test_matches_follow_the_definition_in_any_blocks(monkeypatch, seed, n, m, dim, ratio,
                                                     mutual, with_points, query_block,
                                                     db_chunk):
    rng = np.random.default_rng(seed)
    db = unit(rng.normal(size=(m, dim)))
    query = unit(rng.normal(size=(n, dim)))
    planted = min(n, m) // 2  # half the queries are noisy copies of database entries
    if planted:
        noise = 0.05 * rng.normal(size=(planted, dim))
        query[:planted] = unit(db[rng.permutation(m)[:planted]] + noise)
    points = rng.normal(size=(m, 3)).astype(np.float32) if with_points else None
    if with_points and m >= 4:
        points[1] = points[0] + 0.01  # one 3D point seen twice
        db[1] = unit(db[:1] + 0.01 * rng.normal(size=(1, dim)))[0]
    monkeypatch.setattr(matcher, "QUERY_BLOCK", query_block)
    monkeypatch.setattr(matcher, "DB_CHUNK", db_chunk)

    got = match_descriptors(query, db, ratio, mutual, points, 0.05)

    assert got.shape[1] == 2 and got.dtype == np.int64
    if n < 2 or m < 2:
        assert len(got) == 0
        return
    assert np.all(np.diff(got[:, 0]) > 0)  # one match per query, by ascending query index
    qi, dj, unsure = reference(query, db, ratio, mutual, points, 0.05)
    sure_got = got[~unsure[got[:, 0]]]
    sure_ref = np.stack([qi, dj], 1)[~unsure[qi]]
    assert sure_got.tolist() == sure_ref.tolist()


def test_mutual_check_and_same_point_exception():
    rng = np.random.default_rng(0)
    db = unit(rng.standard_normal((50, 8)))
    points = rng.standard_normal((50, 3)).astype(np.float32)
    query = db[[3, 7, 7]] + 0.01  # two queries want entry 7: only the nearer one is mutual
    query[2] += 0.05
    query = unit(query)
    assert match_descriptors(query, db, 0.8).tolist() == [[0, 3], [1, 7]]
    assert match_descriptors(query, db, 0.8, mutual=False).tolist() == [[0, 3], [1, 7], [2, 7]]
    # a near-duplicate entry fails the ratio test unless both entries are one 3D point
    db[8] = unit(db[7:8] + 1e-3)[0]
    assert match_descriptors(query, db, 0.8, mutual=False).tolist() == [[0, 3]]
    points[8] = points[7] + 0.01
    got = match_descriptors(query, db, 0.8, mutual=False, db_points=points, same_point_m=0.05)
    assert got[:, 0].tolist() == [0, 1, 2] and set(got[1:, 1]) <= {7, 8}


@pytest.mark.parametrize("n, m", [(0, 5), (1, 5), (5, 1)])
def test_too_few_descriptors_give_no_match(n, m):
    rng = np.random.default_rng(1)
    query, db = rng.normal(size=(n, 8)).astype(np.float32), unit(rng.normal(size=(m, 8)))
    assert match_descriptors(query, db, 0.8).shape == (0, 2)
