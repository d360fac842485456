"""Tests of the contiguous graph split (dran_edge.dran.partition)."""

import numpy as np

from dran_edge.dran.partition import contiguous_owner, partition_contiguous


def _ring_with_chords(n: int) -> np.ndarray:
    odo = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1)
    chords = np.array([[0, n - 1], [2, n // 2], [n // 3, 2 * n // 3]])
    return np.concatenate([odo, chords])


def test_owner_is_contiguous_and_balanced():
    owner = contiguous_owner(103, 5)
    assert np.all(np.diff(owner) >= 0)
    sizes = np.bincount(owner)
    assert sizes.size == 5 and sizes.max() - sizes.min() <= 1


def test_every_edge_counted_once_globally_and_twice_if_inter_robot():
    n = 40
    edges = _ring_with_chords(n)
    part = partition_contiguous(edges, n, 4)
    intra = np.concatenate([p.intra_edges for p in part.parts])
    inter = np.concatenate([p.inter_edges for p in part.parts])
    assert np.unique(intra).size == intra.size
    counts = np.bincount(inter, minlength=len(edges))
    cross = part.owner[edges[:, 0]] != part.owner[edges[:, 1]]
    assert np.all(counts[cross] == 2) and np.all(counts[~cross] == 0)
    assert np.unique(np.concatenate([intra, inter])).size == len(edges)


def test_separators_anchors_and_neighbours_are_consistent():
    n = 40
    edges = _ring_with_chords(n)
    part = partition_contiguous(edges, n, 4)
    for p in part.parts:
        assert np.all(part.owner[p.separators] == p.robot_id)
        assert np.all(part.owner[p.anchors] != p.robot_id)
        for q in p.neighbours:
            other = part.parts[q]
            assert p.robot_id in other.neighbours
            # what q needs from p is exactly p's separators that appear among q's anchors
            assert set(p.separators_for[q].tolist()) == set(
                other.anchors[part.owner[other.anchors] == p.robot_id].tolist()
            )
    # robot 0 and robot 3 are linked by the loop-closing chord (0, n-1)
    assert 3 in part.parts[0].neighbours
