"""H's sparsity pattern from the variables' blocks (``solver._pattern.csc_pattern``, used by
``Problem.sparse_pattern``) against the definition: every entry code of every factor's JᵀJ,
sorted and made unique; and a problem's H against the dense JᵀJ."""

from __future__ import annotations

import numpy as np
import pytest

from spdslam.solver._pattern import csc_pattern


def _by_sorting(n, groups):
    """The pattern by its definition: the sorted unique entry codes (col·n + row, row ≥ col)
    of every factor and the diagonal; each factor entry's slot by search."""
    codes = []
    for B, d, _ in groups:
        cols = np.concatenate([np.where(B[:, [p]] >= 0, B[:, [p]] + np.arange(dp), -1) for p, dp in enumerate(d)],
                              axis=1)
        iu, ju = np.triu_indices(cols.shape[1])
        gi, gj = cols[:, iu], cols[:, ju]
        ok = (gi >= 0) & (gj >= 0)
        codes.append(np.where(ok, np.minimum(gi, gj) * n + np.maximum(gi, gj), -1))
    u = np.unique(np.concatenate([c[c >= 0] for c in codes] + [np.arange(n) * (n + 1)]))
    nnz = len(u)
    hslots = []
    for c, (_, _, nf_pad) in zip(codes, groups):
        s = np.where(c >= 0, np.searchsorted(u, c), nnz)
        out = np.full((nf_pad, c.shape[1]), nnz)
        out[: len(s)] = s
        hslots.append(out.ravel())
    cols, rows = np.divmod(u, n)
    return dict(nnz=nnz, indptr=np.searchsorted(cols, np.arange(n + 1)), indices=rows, rows=rows, cols=cols,
                diag=np.searchsorted(u, np.arange(n) * (n + 1)), hslots=hslots)


@pytest.mark.parametrize("seed", range(6))
def test_the_block_pattern_is_the_sorted_pattern(seed):
    """Random variables of dimensions 1–9 in shuffled order, some fixed; groups of one to
    three variables in any order of offsets (padded rows, factors touching fixed ones)."""
    rng = np.random.default_rng(seed)
    V = int(rng.integers(3, 40))
    dims = rng.integers(1, 10, size=V)
    free = rng.random(V) > 0.2
    free[rng.integers(V)] = True
    perm = rng.permutation(V)  # the order of the blocks in the tangent space
    off = np.full(V, -1)
    o = 0
    for v in perm:
        if free[v]:
            off[v], o = o, o + dims[v]
    n = o
    groups = []
    touched = np.zeros(V, bool)
    for _ in range(int(rng.integers(1, 5))):
        k = int(rng.integers(1, 4))
        # a position holds variables of one dimension (one type)
        pool = [np.flatnonzero(dims == dims[rng.integers(V)]) for _ in range(k)]
        nf = int(rng.integers(1, 30))
        vs = np.stack([rng.choice(pl, size=nf) for pl in pool], axis=1)
        keep = np.array([len(set(r)) == k for r in vs])
        vs = vs[keep]
        if not len(vs):
            continue
        touched[vs.ravel()] = True
        d = np.array([dims[pl[0]] for pl in pool])
        groups.append((off[vs], d, len(vs) + int(rng.integers(0, 5))))
    # every free variable is touched (a problem leaves out the others): a one-variable group
    lone = np.flatnonzero(free & ~touched)
    for v in lone:
        groups.append((np.array([[off[v]]]), np.array([dims[v]]), 1))
    if n == 0:
        return
    got = csc_pattern(n, off[free], dims[free], groups)
    want = _by_sorting(n, groups)
    for key in ("nnz", "indptr", "indices", "rows", "cols", "diag"):
        assert np.array_equal(np.asarray(got[key]), np.asarray(want[key])), key
    for a, b in zip(got["hslots"], want["hslots"]):
        assert np.array_equal(a, b)


def test_blocks_that_do_not_tile_are_refused():
    with pytest.raises(ValueError, match="tile"):
        csc_pattern(10, np.array([0, 6]), np.array([6, 6]), [])


def test_pairs_that_all_touch_a_fixed_variable():
    """A group of pairs each with one fixed variable (an odometry chain from a fixed first
    pose, of one factor): no pair block, only the free variables' own blocks."""
    off = np.array([-1, 0, 6])
    groups = [(np.array([[-1, 0]]), np.array([6, 6]), 2), (np.array([[0], [6]]), np.array([6, 6])[:1], 2)]
    got = csc_pattern(12, off[1:], np.array([6, 6]), groups)
    want = _by_sorting(12, groups)
    for key in ("nnz", "indptr", "indices", "rows", "cols", "diag"):
        assert np.array_equal(np.asarray(got[key]), np.asarray(want[key])), key
    for a, b in zip(got["hslots"], want["hslots"]):
        assert np.array_equal(a, b)
