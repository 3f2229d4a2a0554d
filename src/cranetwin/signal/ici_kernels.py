"""Compiled LPA-ICI passes over a cylinder's pair of chamber pressures.

Inputs travel as records (named tuples of arrays, which numba passes as plain structs):

- :class:`Signals`: pA, pB [Pa] and the force f = a1·pA − a2·pB [N], each shape (n,).
- :class:`Windows`: per ICI window k (increasing, shape (nw,)): the half-width, the centre
  filter's even-polynomial coefficients h_j = e0 + e1·j², their sum Σh, and the interval
  half-width γ·sd_k [N]; ``ring_max``: half-widths up to it are summed ring by ring, longer
  ones read off prefix sums.
- :class:`Centred`: one signal's prefix sums over a block, centred on the block's middle and
  its mean c (``s_r[t] = Σ (k − mid)^r·(y[k] − c)``, r = 0, 1, 2), and :class:`Block` the three
  signals' sums with the block's first index ``start`` and middle ``mid``.
- :class:`EndFits`: the polynomial fitted to the first/last w samples of each window for the
  samples where the window does not fit (coefficients in offset/half, shape (nw, p+1)).
- :class:`SgWindows`: the general (polyorder > 3) kernel's filters.

Indices cast with ``U`` (uint64) are known >= 0: numba then skips its negative-index
wraparound (a select per access), ≈ 30 % of the pass.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt
from numba import njit

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
U = np.uint64


class Signals(NamedTuple):
    """pA, pB [Pa] and f = a1·pA − a2·pB [N], each shape (n,)."""

    pa: F64
    pb: F64
    f: F64


class Windows(NamedTuple):
    """The ICI windows' centre filters h_j = e0 + e1·j² (|j| <= half), each shape (nw,)."""

    halves: I64
    e0: F64
    e1: F64
    hsum: F64
    gs: F64
    """γ·sd per window [N]: the confidence intervals' half-widths."""
    ring_max: int


class Centred(NamedTuple):
    """Prefix sums s_r[t] = Σ_{k=start}^{start+t−1} (k − mid)^r·(y[k] − c), r = 0, 1, 2."""

    s0: F64
    s1: F64
    s2: F64
    c: float


class Block(NamedTuple):
    """The prefix sums of pA, pB and f over one block (samples start … of the block)."""

    start: int
    a: Centred
    b: Centred
    f: Centred


class EndFits(NamedTuple):
    """End-polynomial coefficients, shape (nw, p+1) each: l = first w samples, r = last w."""

    la: F64
    lb: F64
    lf: F64
    ra: F64
    rb: F64
    rf: F64


class SgWindows(NamedTuple):
    """The general kernel's filters: windows (nw,), padded centre filters (nw, wmax), edge
    operators (nw, wmax//2, wmax), even-polynomial coefficients (nw, p//2+1), sd (nw,)."""

    wins: I64
    hs: F64
    lefts: F64
    rights: F64
    even: F64
    sds: F64


@njit(cache=True, fastmath=True)
def _sg_at(y, i, w, h, left, right):  # type: ignore[no-untyped-def]
    """Savitzky–Golay smoothed value (deriv 0) at sample i, window w (as
    :func:`cranetwin.signal.savgol.savgol_smooth`; fastmath only reorders the sums)."""
    n = y.shape[0]
    half = w // 2
    acc = 0.0
    if i < half:
        for j in range(w):
            acc += left[i, j] * y[j]
    elif i >= n - half:
        r = i - (n - half)
        for j in range(w):
            acc += right[r, j] * y[n - w + j]
    else:  # centre filters of values are symmetric: h[j] = h[w-1-j]
        acc = h[half] * y[i]
        for j in range(half):
            acc += h[j] * (y[i - half + j] + y[i + half - j])
    return acc


@njit(cache=True)
def ici_pair_general(pa, pb, a1, a2, ops, gamma, out):  # type: ignore[no-untyped-def]
    """Per sample: pA, pB and force a1·pA − a2·pB estimates of increasing window until the ICI
    intervals stop intersecting; keeps the last window whose intervals all intersect (any
    polyorder; ``ops`` a :class:`SgWindows`, ``out`` (n, 2)). Interior centre filters are even
    polynomials in the offset j, h_j = Σ_m even[k, m]·j^(2m), so nested windows' estimates
    come from ring sums Σ j^(2m)(y[i−j] + y[i+j]) accumulated as the window grows: all
    windows of a sample cost one pass over the largest."""
    n = pa.shape[0]
    nw = ops.wins.shape[0]
    even = ops.even
    nm = even.shape[1]
    sa = np.zeros(nm)
    sb = np.zeros(nm)
    for i in range(n):
        lo = -np.inf
        hi = np.inf
        for m in range(nm):
            sa[m] = 0.0
            sb[m] = 0.0
        done = -1  # ring sums hold offsets 0 … done
        pa_prev = pa[i]
        pb_prev = pb[i]
        for k in range(nw):
            w = ops.wins[k]
            half = w // 2
            if i < half or i >= n - half:
                ea = _sg_at(pa, i, w, ops.hs[k], ops.lefts[k], ops.rights[k])
                eb = _sg_at(pb, i, w, ops.hs[k], ops.lefts[k], ops.rights[k])
            else:
                for jj in range(done + 1, half + 1):
                    if jj == 0:
                        sa[0] += pa[i]
                        sb[0] += pb[i]
                    else:
                        ya = pa[i - jj] + pa[i + jj]
                        yb = pb[i - jj] + pb[i + jj]
                        pw = 1.0
                        j2 = float(jj * jj)
                        for m in range(nm):
                            sa[m] += pw * ya
                            sb[m] += pw * yb
                            pw *= j2
                done = half
                ea = 0.0
                eb = 0.0
                for m in range(nm):
                    ea += even[k, m] * sa[m]
                    eb += even[k, m] * sb[m]
            e = a1 * ea - a2 * eb
            lo = max(lo, e - gamma * ops.sds[k])
            hi = min(hi, e + gamma * ops.sds[k])
            if lo > hi and k > 0:
                break
            pa_prev = ea
            pb_prev = eb
            if lo > hi:  # k == 0: keep the first window
                break
        out[i, 0] = pa_prev
        out[i, 1] = pb_prev


@njit(cache=True, fastmath=True)
def _centred_prefix(y, c, start, length, mid, s):  # type: ignore[no-untyped-def]
    """Fill the :class:`Centred` sums ``s`` (s_r[0 … length]) of y − c over samples
    start … start + length − 1, offsets measured from ``mid``."""
    p0, p1, p2 = s.s0, s.s1, s.s2
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    p0[0] = 0.0
    p1[0] = 0.0
    p2[0] = 0.0
    for t in range(length):
        k = start + t
        z = y[U(k)] - c
        u = float(k - mid)
        s0 += z
        s1 += u * z
        s2 += u * u * z
        p0[t + 1] = s0
        p1[t + 1] = s1
        p2[t + 1] = s2


@njit(cache=True, fastmath=True, inline="always")
def _intersect(k, e, g, lo, hi):  # type: ignore[no-untyped-def]
    """The ICI rule's running intersection after window k: [e − g, e + g] for the first
    window, else its intersection with [lo, hi] (empty when lo > hi: stop)."""
    if k == 0:
        return e - g, e + g
    return max(lo, e - g), min(hi, e + g)


@njit(cache=True, fastmath=True, inline="always")
def _window_sum(s, k, win, r, q, x):  # type: ignore[no-untyped-def]
    """Centre-filter estimate of window k from the :class:`Centred` sums ``s`` between prefix
    indices q and r (x = sample − block middle): e0·Σz + e1·Σj²z + c·Σh, with
    Σj²z[i+j] = S2 − 2x·S1 + x²·S0."""
    z0 = s.s0[r] - s.s0[q]
    return (win.e0[k] * z0 + win.e1[k] * (s.s2[r] - s.s2[q] - 2.0 * x * (s.s1[r] - s.s1[q])
                                          + x * x * z0) + win.hsum[k] * s.c)


@njit(cache=True, fastmath=True, inline="always")
def _pair_at_window(pa, pb, i, h, e, x, ring_max, start, sa, sb):  # type: ignore[no-untyped-def]
    """(pA, pB) at interior sample i by the centre filter of half-width h, e = (e0, e1, Σh)
    of its h_j = e0 + e1·j²: directly from the ring of samples up to ``ring_max``, else from
    the :class:`Centred` prefix sums sa, sb of pA, pB of the block from ``start``
    (x = i − block middle)."""
    e0k, e1k, hk = e
    if h <= ring_max:
        sa0 = pa[U(i)]
        sb0 = pb[U(i)]
        sa2 = 0.0
        sb2 = 0.0
        for jj in range(1, h + 1):
            ya = pa[U(i - jj)] + pa[U(i + jj)]
            yb = pb[U(i - jj)] + pb[U(i + jj)]
            j2 = float(jj * jj)
            sa0 += ya
            sa2 += j2 * ya
            sb0 += yb
            sb2 += j2 * yb
        return e0k * sa0 + e1k * sa2, e0k * sb0 + e1k * sb2
    r = U(i + h + 1 - start)
    q = U(i - h - start)
    fa0, fa1, fa2, ca = sa
    fb0, fb1, fb2, cb = sb
    za0 = fa0[r] - fa0[q]
    zb0 = fb0[r] - fb0[q]
    ea = (e0k * za0 + e1k * (fa2[r] - fa2[q] - 2.0 * x * (fa1[r] - fa1[q]) + x * x * za0)
          + hk * ca)
    eb = (e0k * zb0 + e1k * (fb2[r] - fb2[q] - 2.0 * x * (fb1[r] - fb1[q]) + x * x * zb0)
          + hk * cb)
    return ea, eb


@njit(cache=True, fastmath=True)
def _ici_interior(sig, i0, m, x0, win, blk, work, out):  # type: ignore[no-untyped-def]
    """The window choice of :func:`ici_pair_prefix` for samples i0 … i0+m−1 of one prefix
    block, all interior (every window fits), vectorised across the samples: each window's
    force estimate is formed for every sample, the intervals' running intersection updated,
    and the windows counted while it is non-empty (it only shrinks, so the count is the
    early-stopping scan's last accepted window); pA, pB are then estimated at it per sample.
    x0 = i0 − (block middle); work: scratch (8, block), row 7 = 0, 1, 2, …."""
    f = sig.f
    halves, e0, e1, hsum, gs, ring_max = win
    start = blk.start
    ff0, ff1, ff2, cf = blk.f
    pa, pb, sa, sb = sig.pa, sig.pb, blk.a, blk.b
    nw = halves.shape[0]
    s0 = work[0, :m]
    s2 = work[1, :m]
    lo_a = work[2, :m]
    hi_a = work[3, :m]
    lo_b = work[4, :m]
    hi_b = work[5, :m]
    cnt = work[6, :m]
    xo = work[7, :m]  # 0, 1, 2, …
    fc = f[U(i0) : U(i0 + m)]
    for t in range(m):
        s0[t] = fc[t]
        s2[t] = 0.0
    ring = 0
    k = 0
    while k < nw and halves[k] <= ring_max:
        h = halves[k]
        for jj in range(ring + 1, h + 1):
            j2 = float(jj * jj)
            fl = f[U(i0 - jj) : U(i0 - jj + m)]
            fr = f[U(i0 + jj) : U(i0 + jj + m)]
            for t in range(m):
                yy = fl[t] + fr[t]
                s0[t] += yy
                s2[t] += j2 * yy
        ring = h
        a = e0[k]
        b = e1[k]
        g = gs[k]
        if k == 0:
            for t in range(m):
                e = a * s0[t] + b * s2[t]
                lo_b[t] = e - g
                hi_b[t] = e + g
                cnt[t] = 0.0
        else:
            for t in range(m):
                e = a * s0[t] + b * s2[t]
                lo = max(lo_a[t], e - g)
                hi = min(hi_a[t], e + g)
                lo_b[t] = lo
                hi_b[t] = hi
                cnt[t] += np.float64(lo <= hi)
        lo_a, lo_b = lo_b, lo_a
        hi_a, hi_b = hi_b, hi_a
        k += 1
    while k < nw:
        h = halves[k]
        a = e0[k]
        b = e1[k]
        g = gs[k]
        c = hsum[k] * cf
        r0 = U(i0 + h + 1 - start)
        q0 = U(i0 - h - start)
        p0r = ff0[r0 : r0 + U(m)]
        p0q = ff0[q0 : q0 + U(m)]
        p1r = ff1[r0 : r0 + U(m)]
        p1q = ff1[q0 : q0 + U(m)]
        p2r = ff2[r0 : r0 + U(m)]
        p2q = ff2[q0 : q0 + U(m)]
        for t in range(m):
            x = x0 + xo[t]
            z0 = p0r[t] - p0q[t]
            e = a * z0 + b * (p2r[t] - p2q[t] - 2.0 * x * (p1r[t] - p1q[t]) + x * x * z0) + c
            lo = max(lo_a[t], e - g)
            hi = min(hi_a[t], e + g)
            lo_b[t] = lo
            hi_b[t] = hi
            cnt[t] += np.float64(lo <= hi)
        lo_a, lo_b = lo_b, lo_a
        hi_a, hi_b = hi_b, hi_a
        k += 1
    for t in range(m):
        i = i0 + t
        kk = int(cnt[t])
        ea, eb = _pair_at_window(pa, pb, i, halves[kk], (e0[kk], e1[kk], hsum[kk]), x0 + t,
                                 ring_max, start, sa, sb)
        out[U(i), 0] = ea
        out[U(i), 1] = eb


@njit(cache=True, fastmath=True, inline="always")
def _end_poly(coef, k, i, h, n):  # type: ignore[no-untyped-def]
    """Window k's end polynomial (coefficients ``coef[k]`` in offset/half) at sample i: the
    left end's if i < h, else the right end's (Horner)."""
    np1 = coef.shape[1]
    u = (i - h) / h if i < h else (i - (n - 1 - h)) / h
    e = coef[k, np1 - 1]
    for m in range(np1 - 2, -1, -1):
        e = e * u + coef[k, m]
    return e


@njit(cache=True, fastmath=True)
def end_fits(sig, halves, fits):  # type: ignore[no-untyped-def]
    """:class:`EndFits` of pA, pB and f: ``fits`` (nw, p+1, wmax) applied to the first and
    last w samples of each window."""
    pa, pb, f = sig.pa, sig.pb, sig.f
    n = pa.shape[0]
    nw = halves.shape[0]
    np1 = fits.shape[1]
    cla = np.zeros((nw, np1))
    clb = np.zeros((nw, np1))
    cra = np.zeros((nw, np1))
    crb = np.zeros((nw, np1))
    clf = np.zeros((nw, np1))
    crf = np.zeros((nw, np1))
    for k in range(nw):
        w = 2 * halves[k] + 1
        if w == 1:
            continue
        for m in range(np1):
            for j in range(w):
                fw = fits[k, m, j]
                cla[k, m] += fw * pa[j]
                clb[k, m] += fw * pb[j]
                cra[k, m] += fw * pa[n - w + j]
                crb[k, m] += fw * pb[n - w + j]
                clf[k, m] += fw * f[j]
                crf[k, m] += fw * f[n - w + j]
    return EndFits(cla, clb, clf, cra, crb, crf)


@njit(cache=True, fastmath=True)
def _ici_near_end(sig, i, x, win, blk, ends, out):  # type: ignore[no-untyped-def]
    """The window choice and (pA, pB) of one sample that not every window fits around (or of
    a block too short for :func:`_ici_interior`): the windows in increasing order by ring
    sums, prefix sums, then end polynomials, until the intervals stop intersecting."""
    f = sig.f
    n = f.shape[0]
    halves = win.halves
    nw = halves.shape[0]
    hmax = halves[nw - 1]
    lim = min(i, n - 1 - i)
    kin = nw  # windows 0 … kin−1 fit around sample i
    if lim < hmax:
        kin = 0
        while kin < nw and halves[kin] <= lim:
            kin += 1
    s0 = f[i]
    s2 = 0.0
    ring = 0
    lo = -1.0
    hi = 1.0
    k = 0
    kk = 0
    stopped = False
    while k < kin and halves[k] <= win.ring_max:
        h = halves[k]
        for jj in range(ring + 1, h + 1):
            yy = f[U(i - jj)] + f[U(i + jj)]
            s0 += yy
            s2 += float(jj * jj) * yy
        ring = h
        e = win.e0[k] * s0 + win.e1[k] * s2
        lo, hi = _intersect(k, e, win.gs[k], lo, hi)
        if lo > hi:
            stopped = True
            break
        kk = k
        k += 1
    if not stopped:
        while k < kin:
            h = halves[k]
            e = _window_sum(blk.f, k, win, U(i + h + 1 - blk.start), U(i - h - blk.start), x)
            lo, hi = _intersect(k, e, win.gs[k], lo, hi)
            if lo > hi:
                stopped = True
                break
            kk = k
            k += 1
    if not stopped:
        while k < nw:
            e = _end_poly(ends.lf if i < halves[k] else ends.rf, k, i, halves[k], n)
            lo, hi = _intersect(k, e, win.gs[k], lo, hi)
            if lo > hi:
                break
            kk = k
            k += 1
    h = halves[kk]
    if kk >= kin:  # an end polynomial
        if i < h:
            ea = _end_poly(ends.la, kk, i, h, n)
            eb = _end_poly(ends.lb, kk, i, h, n)
        else:
            ea = _end_poly(ends.ra, kk, i, h, n)
            eb = _end_poly(ends.rb, kk, i, h, n)
    else:
        ea, eb = _pair_at_window(sig.pa, sig.pb, i, h, (win.e0[kk], win.e1[kk], win.hsum[kk]),
                                 x, win.ring_max, blk.start, blk.a, blk.b)
    out[i, 0] = ea
    out[i, 1] = eb


@njit(cache=True, fastmath=True)
def ici_pair_prefix(pa, pb, a1, a2, win, fits, block, out):  # type: ignore[no-untyped-def]
    """:func:`ici_pair_general` for polyorder <= 3 at O(1) per sample and window.

    The windows are decided on the force f = a1·pA − a2·pB (Savitzky–Golay is linear, so its
    estimates are a1·pA − a2·pB of the pressures', to rounding); pA and pB are estimated
    once, at the chosen window. Interior centre filters are h_j = e0 + e1·j², so an estimate
    is e0·Σy + e1·Σj²y over |j| <= half. Windows up to ``win.ring_max`` half-width grow these
    sums ring by ring; longer ones read them off prefix sums: with z = y − c (c the block's
    mean, added back as c·Σh), Σj²z[i+j] = S2 − 2x·S1 + x²·S0, S_r = Σ u^r z over the
    window. Rounding stays at the data's level because the prefix sums restart every
    ``block`` samples with u, x measured from the block's middle (|x| <= block/2,
    |u| <= block/2 + half) and serve only windows long enough that x²/half² stays small. At
    the ends (i < half or i >= n − half) the estimate is the polynomial fitted to the
    first/last w samples (``fits``: (p+1, w) per window, in offset/half), evaluated at the
    sample. Every sample goes through the windows in increasing order until its intervals
    stop intersecting; ``out`` (n, 2) gets the last accepted window's pA, pB.

    Args:
        pa, pb: Chamber pressures, shape (n,) [Pa]; a1, a2: areas [m²].
        win: :class:`Windows`; fits: shape (nw, p+1, wmax); block: samples per prefix block.
        out: Smoothed (pA, pB), shape (n, 2) [Pa], written.
    """
    n = pa.shape[0]
    nw = win.halves.shape[0]
    hmax = win.halves[nw - 1]
    sig = Signals(pa, pb, a1 * pa - a2 * pb)
    ends = end_fits(sig, win.halves, fits)
    size = block + 2 * hmax + 1
    bufs = [np.empty(size) for _ in range(9)]
    work = np.empty((8, block))
    for t in range(block):
        work[7, t] = float(t)
    for b0 in range(0, n, block):
        nb = min(block, n - b0)
        mid = b0 + nb // 2
        start = max(0, b0 - hmax)
        end = min(n, b0 + nb + hmax)
        ca = 0.0
        cb = 0.0
        for t in range(start, end):
            ca += pa[t]
            cb += pb[t]
        ca /= end - start
        cb /= end - start
        blk = Block(start, Centred(bufs[0], bufs[1], bufs[2], ca),
                    Centred(bufs[3], bufs[4], bufs[5], cb),
                    Centred(bufs[6], bufs[7], bufs[8], a1 * ca - a2 * cb))
        _centred_prefix(pa, ca, start, end - start, mid, blk.a)
        _centred_prefix(pb, cb, start, end - start, mid, blk.b)
        _centred_prefix(sig.f, blk.f.c, start, end - start, mid, blk.f)
        i0 = max(b0, hmax)  # samples i0 … i1−1 of the block are interior for every window
        i1 = min(b0 + nb, n - hmax)
        if i1 > i0:
            _ici_interior(sig, i0, i1 - i0, float(i0 - mid), win, blk, work, out)
        for i in range(b0, b0 + nb):
            if i0 <= i < i1:
                continue
            _ici_near_end(sig, i, float(i - mid), win, blk, ends, out)
