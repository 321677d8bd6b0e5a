import itertools

import numpy as np

from lunarloc.association import clipper_clique, max_clique, putative_associations


def brute_force_clique(n, edges):
    adj = np.zeros((n, n), bool)
    for a, b in edges:
        adj[a, b] = adj[b, a] = True
    for k in range(n, 0, -1):
        for sub in itertools.combinations(range(n), k):
            if all(adj[a, b] for a, b in itertools.combinations(sub, 2)):
                return k
    return 0


def is_clique(c, edges):
    es = {tuple(sorted(e)) for e in edges}
    return all(tuple(sorted((a, b))) in es for a, b in itertools.combinations(c, 2))


def test_exact_max_clique_matches_brute_force(rng):
    for _ in range(60):
        n = int(rng.integers(2, 13))
        A = np.triu(rng.random((n, n)) < rng.uniform(0.1, 0.9), 1)
        eu, ev = np.nonzero(A)
        c = max_clique(n, eu, ev)
        edges = list(zip(eu, ev))
        assert len(c) == max(brute_force_clique(n, edges), 1 if n else 0)
        assert is_clique(c, edges)


def test_max_clique_finds_planted_clique_in_large_sparse_graph(rng):
    n, m = 20000, 100000
    eu, ev = rng.integers(0, n, m), rng.integers(0, n, m)
    keep = eu != ev
    planted = rng.choice(n, 15, replace=False)
    pu, pv = np.triu_indices(15, 1)
    eu = np.r_[eu[keep], planted[pu]]
    ev = np.r_[ev[keep], planted[pv]]
    c = max_clique(n, eu, ev)
    assert sorted(c) == sorted(planted)
    # a lower bound at the clique size means "nothing larger": empty result
    assert len(max_clique(n, eu, ev, lower_bound=15)) == 0


def test_clipper_returns_a_clique_and_finds_planted(rng):
    n = 300
    eu, ev = rng.integers(0, n, 600), rng.integers(0, n, 600)
    keep = eu != ev
    planted = rng.choice(n, 12, replace=False)
    pu, pv = np.triu_indices(12, 1)
    eu = np.r_[eu[keep], planted[pu]]
    ev = np.r_[ev[keep], planted[pv]]
    c = clipper_clique(n, eu, ev, np.ones(len(eu)))
    assert is_clique(c, list(zip(eu, ev)))
    assert len(set(c) & set(planted)) >= 10


def test_putative_associations_size_pruning():
    assoc, node_of = putative_associations(3, 4)
    assert assoc.shape == (12, 2) and node_of.max() == 11
    assoc, node_of = putative_associations(
        2, 2, np.array([1.0, 2.0]), np.array([1.1, 4.0]), max_size_ratio=1.5
    )
    assert {tuple(map(int, a)) for a in assoc} == {(0, 0)}  # 2/1.1 and 4/2 exceed 1.5
    assert node_of[0, 1] == -1
