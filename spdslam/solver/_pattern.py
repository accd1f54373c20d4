"""The sparsity pattern of H = JᵀJ from the variables' blocks, without sorting its entries.

The free variables' tangent coordinates tile [0, n) in contiguous blocks (variable v:
columns o_v … o_v + d_v − 1). H's lower triangle in CSC holds, for every column block u,
its diagonal block (rows c … o_u + d_u − 1 of column c = o_u + i) and one d_u × d_w block
for every variable w after u that shares a factor with u (its rows o_w … o_w + d_w − 1).
With the pairs (u, w) sorted by (o_u, o_w), R_u = Σ d_w over u's pairs and C_k = Σ d_w over
the pairs of u before pair k, column c = o_u + i holds L_c = (d_u − i) + R_u entries, and

    diagonal block:  (o_u + i, o_u + j), i ≤ j  at  indptr[o_u + i] + (j − i),
    pair k = (u, w): (o_u + i, o_w + j)         at  indptr[o_u + i] + (d_u − i) + C_k + j,

so every slot is a formula: the work is that of the block pairs (one sort of one key per
pair of variables sharing a factor) and of writing the entries, not a sort of the factors'
n·D(D+1)/2 entry codes (docs/performance.md). The result equals the entry-sorted pattern
(each column's rows increasing) that CHOLMOD reads.
"""

from __future__ import annotations

import numpy as np

__all__ = ["csc_pattern"]


def csc_pattern(n: int, offsets: np.ndarray, dims: np.ndarray, groups) -> dict:
    """The lower-triangular CSC pattern of H (``Problem.sparse_pattern``'s dict).

    ``offsets`` (V,), ``dims`` (V,): the free variables' first tangent coordinate and
    dimension (the blocks tile [0, n)); ``groups``: per factor group (B (nf, k) the block
    offset of each of its k variables, −1 where fixed; d (k,) their dimensions; nf_pad)."""
    order = np.argsort(offsets, kind="stable")
    off = np.asarray(offsets, np.int64)[order]
    dim = np.asarray(dims, np.int64)[order]
    V = len(off)
    if int(dim.sum()) != n or (V and (off[0] != 0 or np.any(off[1:] != off[:-1] + dim[:-1]))):
        raise ValueError("the variables' blocks do not tile the tangent space")
    # the pairs (u, w), o_u < o_w, of variables that share a factor, sorted by (o_u, o_w)
    keys = [np.zeros(0, np.int64)]
    for B, _, _ in groups:
        for p in range(B.shape[1]):
            for q in range(p + 1, B.shape[1]):
                a, b = B[:, p], B[:, q]
                ok = (a >= 0) & (b >= 0)
                keys.append(np.minimum(a, b)[ok] * n + np.maximum(a, b)[ok])
    pk = np.unique(np.concatenate(keys))
    plo, phi = np.divmod(pk, n)
    bu, bw = np.searchsorted(off, plo), np.searchsorted(off, phi)
    du, dw = dim[bu], dim[bw]
    R = np.bincount(bu, weights=dw, minlength=V).astype(np.int64)
    before = np.cumsum(dw) - dw
    C = before - before[np.searchsorted(bu, bu)]  # Σ d_w of u's earlier pairs (bu sorted)
    # columns
    col_block = np.repeat(np.arange(V), dim)
    i_col = np.arange(n, dtype=np.int64) - off[col_block]
    indptr = np.zeros(n + 1, np.int64)
    np.cumsum(dim[col_block] - i_col + R[col_block], out=indptr[1:])
    nnz = int(indptr[-1])
    rows = np.empty(nnz, np.int64)
    cols = np.empty(nnz, np.int64)
    for d in np.unique(dim):  # diagonal blocks, by dimension
        o = off[dim == d][:, None]
        i, j = np.triu_indices(int(d))
        s = indptr[o + i] + (j - i)
        rows[s], cols[s] = o + j, o + i
    for a, b in set(zip(du.tolist(), dw.tolist())):  # pair blocks, by shape
        sel = np.flatnonzero((du == a) & (dw == b))
        i, j = (x.ravel() for x in np.meshgrid(np.arange(a), np.arange(b), indexing="ij"))
        c = plo[sel][:, None] + i
        s = indptr[c] + (a - i) + C[sel][:, None] + j
        rows[s], cols[s] = phi[sel][:, None] + j, c
    base = indptr[off]
    hslots = tuple(_slots(B, d, nf_pad, pk, n, off, base, R, C, nnz) for B, d, nf_pad in groups)
    return dict(nnz=nnz, indptr=indptr.astype(np.int32), indices=rows.astype(np.int32), rows=rows, cols=cols,
                diag=indptr[:-1].copy(), hslots=hslots)


def _slots(B, d, nf_pad, pk, n, off, base, R, C, nnz) -> np.ndarray:
    """Flat (nf_pad·D(D+1)/2,) slot of each upper-triangle entry (s, t) of each factor's
    JᵀJ (local columns s ≤ t; nnz where a variable is fixed or the row is padding), from
    per-factor block numbers. A group's position a always holds a variable of dimension
    d_a, so column o_u + i starts at indptr[o_u] + i·R_u + (i·d_a − i(i − 1)/2): one
    per-factor term (indptr[o_u], plus C_k in a pair block), one per-factor factor (R_u) of
    the entry's i and one per-entry constant."""
    d = np.asarray(d, np.int64)
    k, D = len(d), int(d.sum())
    start = np.concatenate([[0], np.cumsum(d)[:-1]])
    pos = np.repeat(np.arange(k), d)
    idx = np.arange(D) - start[pos]
    su, tu = np.triu_indices(D)
    p, q, i, j = pos[su], pos[tu], idx[su], idx[tu]
    nf = len(B)
    out = np.full((nf_pad, len(su)), nnz, np.int64)
    free = B >= 0
    blk = np.searchsorted(off, np.where(free, B, 0))  # each position's variable block
    b0, r0 = base[blk], R[blk]  # (nf, k): indptr[o_u] and R_u of each position's variable

    def block(a, ii, jj, shift, rows):
        """Slots (len(rows), len(ii)) of the entries (column o_u + ii, row offset jj past the
        column's diagonal part) of position a's variable u in the factors ``rows``."""
        const = ii * d[a] - ii * (ii - 1) // 2 + jj
        return (b0[rows, a] + shift)[:, None] + r0[rows, a][:, None] * ii + const

    for a in range(k):
        for b in range(a, k):
            e = np.flatnonzero((p == a) & (q == b))
            if e.size == 0:
                continue
            ie, je = i[e], j[e]
            if a == b:  # a variable's own block, i ≤ j: (j − i) past the column's start
                ok = free[:, a]
                val = block(a, ie, je - ie, 0, slice(None))
            else:  # the pair's column block is the variable of the smaller offset
                ok = free[:, a] & free[:, b]
                kp = np.zeros(nf, np.int64)
                kp[ok] = np.searchsorted(pk, np.minimum(B[ok, a], B[ok, b]) * n + np.maximum(B[ok, a], B[ok, b]))
                Ck = C[kp] if C.size else np.zeros(nf, np.int64)  # no pair: every one has a fixed variable
                first = B[:, a] < B[:, b]
                val = np.empty((nf, e.size), np.int64)
                fa, fb = np.flatnonzero(first), np.flatnonzero(~first)
                # a's column i, row o_b + j: past a's d_a − i diagonal rows; b's column j likewise
                val[fa] = block(a, ie, d[a] - ie + je, Ck[fa], fa)
                val[fb] = block(b, je, d[b] - je + ie, Ck[fb], fb)
            val[~ok] = nnz
            out[:nf, e] = val
    return out.ravel()
