"""Training SSIM (3DGS zero-padded form): numba kernels for the value and its analytic gradient.

Why: at 400x400 the autograd SSIM of ``pidg.metrics`` (depthwise ``conv2d`` on 15 maps, then its
backward) was the largest single item of a CPU training step. SSIM only needs separable Gaussian blurs, and its
gradient w.r.t. the prediction is three more blurs of closed-form maps:

  s = A1 A2 / (B1 B2),  A1 = 2 mu_p mu_g + C1,  A2 = 2 cov + C2,  B1 = mu_p^2 + mu_g^2 + C1,  B2 = var_p + var_g + C2
  with mu = blur(x), var_p = blur(p^2) - mu_p^2, cov = blur(p g) - mu_p mu_g. Then
  dS/dp = blur(dS/dmu_p) + 2 p blur(dS/dE_pp) + g blur(dS/dE_pg)      (the zero-padded blur is self-adjoint)
  dS/dmu_p = 2 mu_g (A2 - A1) / (B1 B2) - 2 mu_p s (1/B1 - 1/B2),  dS/dE_pp = -s / B2,  dS/dE_pg = 2 A1 / (B1 B2).

B2 only needs var_p + var_g = blur(p^2 + g^2) - mu_p^2 - mu_g^2, so four maps are blurred: p, g, q = p^2 + g^2 and
p g (dS/dE_pp above is dS/dE_q: dq/dp = 2p as well).

Structure. The [H, W, C] images are read in place as rows of W*C floats (channels interleaved, no transposed
copy). The blur is separable and its passes commute, so the vertical pass runs first, on whole rows (every element
of a row is independent and the loads are contiguous), then the horizontal one with its taps C elements apart.
One kernel makes the value and the gradient in a single sweep down the image; at each row t it does:

1. the vertical pass of the four maps: the 11 input rows around t are loaded into registers and the four sums
   formed there (22 loads and 67 multiply-adds per element, the symmetric taps paired), into a row buffer with
   2R zero pixels on each side;
2. the horizontal pass and the SSIM formula: s (summed into the value) and the three derivative maps;
3. the horizontal blur of the derivative maps, into ring buffers holding the last 11 rows;
4. as soon as the rings hold the rows y - R .. y + R of some row y: the vertical blur of the three maps at y,
   combined with p and g, which is the gradient row y.

So the forward returns the value and has dS/dp ready (the backward only multiplies it by the incoming gradient),
and nothing image-sized is written but that gradient: the working set per thread is a few rows. When no gradient
is needed (``torch.no_grad``, or ``pred`` not requiring one) steps 3-4 and the derivative maps are skipped.

Why this shape (each measured): the loops over a row vectorise (AVX2 FMA) only if (a) indices are unsigned, as
numba's negative-index wraparound kept LLVM from vectorising, (b) ``error_model="numpy"``, as the python model's
zero-division check in the SSIM formula did too, (c) a loop stores to rows of one buffer at a compile-time
distance (``_CAP``) or to separate arrays: rows at a run-time distance made LLVM give up on its overlap checks.
(b) kept the previous version's SSIM formula loop scalar, (a) and (c) drafts of these kernels. The single sweep
also keeps the working set in cache: the previous version (and a draft of this one) wrote three image-sized
derivative maps in the forward and read them back in the backward, and in the draft that traffic, not the
arithmetic, set the backward's time (0.8 ms at 400x400x3 for ~0.35 ms of FMAs).

Details. Rows whose window is cut by the image edge read the nearest edge row (which the window covers anyway)
with weight 0, so one loop serves every row; rows with the whole window inside take constant taps. A row wider
than a scratch row (``_CAP``) is done in segments, each with a halo of 2R pixels: R for the SSIM's horizontal
blur, R for the derivative maps'. Work is split into bands of ``_BAND`` rows, a contiguous range of bands per
thread; a thread also works out the derivative maps of the R rows on either side of its range (their gradient
rows need them; the same operations as the neighbour's, hence the same bits). Each band sums its SSIM values (per
column in float32, then the band in float64) into its own slot and the slots are summed in a fixed order. Only
multiply-add contraction is allowed (no reassociation), so value and gradient do not depend on the number of
threads and are the same bit for bit from run to run.

``pidg.metrics.ssim(..., padding="zeros")`` is the readable autograd reference the tests compare with.
"""
from __future__ import annotations

import numba
import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from pidg.metrics import SSIM_K, SSIM_WIN_SIGMA, SSIM_WIN_SIZE

_BAND = 8  # rows per band: the unit of the value's fixed-order sum
_MIN_BANDS = 4  # bands per thread at least: a thread also works out R rows on either side of its share
_K = SSIM_WIN_SIZE  # taps
_R = SSIM_WIN_SIZE // 2
# Floats per row of the per-thread scratch buffers. A compile-time constant on purpose: LLVM then knows how far
# apart the rows of a buffer are, proves the stores to its rows independent and vectorises the loops; with a row
# length known only at run time it gave up on the runtime alias checks (scalar code, 2x slower, measured).
_CAP = 4096
# Contract multiply-adds into FMAs, nothing reassociated: each output is one fixed sequence of operations (the same
# on every run of a build), and the loops over a row vectorise across elements without reordering any sum.
_FASTMATH = {"contract", "nsz", "arcp"}


def gaussian_window_1d(size: int = SSIM_WIN_SIZE, sigma: float = SSIM_WIN_SIGMA) -> np.ndarray:
    x = np.arange(size, dtype=np.float64) - size // 2
    k = np.exp(-(x**2) / (2.0 * sigma**2))
    return (k / k.sum()).astype(np.float32)


_WINDOW = gaussian_window_1d()
assert _WINDOW.shape == (11,) and np.array_equal(_WINDOW, _WINDOW[::-1])  # the kernels' taps are written out
# Globals: numba compiles them in as constants.
_TAPS = tuple(np.float32(w) for w in _WINDOW)
_W0, _W1, _W2, _W3, _W4, _W5 = _TAPS[:6]


@njit(cache=True, inline="always")
def _u(i):  # pragma: no cover - compiled
    """An index known to be >= 0, as unsigned: numba then emits no negative-index wraparound, whose select kept
    LLVM from vectorising the row loops (scalar code, measured)."""
    return np.uint64(i)


@njit(cache=True, inline="always")
def _tap(r, height, w):  # pragma: no cover - compiled
    """Row r of the vertical window and its weight; a row outside the image reads the nearest edge row, weight 0."""
    if r < 0:
        return 0, np.float32(0.0)
    if r >= height:
        return height - 1, np.float32(0.0)
    return r, w


@njit(cache=True, inline="always")
def _window_rows(y, height):  # pragma: no cover - compiled
    """The 11 rows of the vertical window at output row y and their weights (zero padding: weight 0 outside)."""
    t0, t1, t2 = _tap(y - 5, height, _TAPS[0]), _tap(y - 4, height, _TAPS[1]), _tap(y - 3, height, _TAPS[2])
    t3, t4, t5 = _tap(y - 2, height, _TAPS[3]), _tap(y - 1, height, _TAPS[4]), _tap(y, height, _TAPS[5])
    t6, t7, t8 = _tap(y + 1, height, _TAPS[6]), _tap(y + 2, height, _TAPS[7]), _tap(y + 3, height, _TAPS[8])
    t9, t10 = _tap(y + 4, height, _TAPS[9]), _tap(y + 5, height, _TAPS[10])
    rows = (t0[0], t1[0], t2[0], t3[0], t4[0], t5[0], t6[0], t7[0], t8[0], t9[0], t10[0])
    weights = (t0[1], t1[1], t2[1], t3[1], t4[1], t5[1], t6[1], t7[1], t8[1], t9[1], t10[1])
    return rows, weights


@njit(cache=True, inline="always")
def _column(a, rows, e):  # pragma: no cover - compiled
    """a[rows[k], e] for the 11 window rows."""
    e = _u(e)
    return (
        a[rows[0], e], a[rows[1], e], a[rows[2], e], a[rows[3], e], a[rows[4], e], a[rows[5], e],
        a[rows[6], e], a[rows[7], e], a[rows[8], e], a[rows[9], e], a[rows[10], e],
    )  # fmt: skip


@njit(cache=True, inline="always", fastmath=_FASTMATH, error_model="numpy")
def _products(a, b):  # pragma: no cover - compiled
    return (
        a[0] * b[0], a[1] * b[1], a[2] * b[2], a[3] * b[3], a[4] * b[4], a[5] * b[5],
        a[6] * b[6], a[7] * b[7], a[8] * b[8], a[9] * b[9], a[10] * b[10],
    )  # fmt: skip


@njit(cache=True, inline="always", fastmath=_FASTMATH, error_model="numpy")
def _sum_of_squares(a, b):  # pragma: no cover - compiled
    return (
        a[0] * a[0] + b[0] * b[0], a[1] * a[1] + b[1] * b[1], a[2] * a[2] + b[2] * b[2], a[3] * a[3] + b[3] * b[3],
        a[4] * a[4] + b[4] * b[4], a[5] * a[5] + b[5] * b[5], a[6] * a[6] + b[6] * b[6], a[7] * a[7] + b[7] * b[7],
        a[8] * a[8] + b[8] * b[8], a[9] * a[9] + b[9] * b[9], a[10] * a[10] + b[10] * b[10],
    )  # fmt: skip


@njit(cache=True, inline="always", fastmath=_FASTMATH, error_model="numpy")
def _dot(x, w):  # pragma: no cover - compiled
    """The vertical pass of one element: sum_k w[k] x[k], in tap order."""
    return (
        w[0] * x[0] + w[1] * x[1] + w[2] * x[2] + w[3] * x[3] + w[4] * x[4] + w[5] * x[5]
        + w[6] * x[6] + w[7] * x[7] + w[8] * x[8] + w[9] * x[9] + w[10] * x[10]
    )  # fmt: skip


@njit(cache=True, inline="always", fastmath=_FASTMATH, error_model="numpy")
def _hsum(buf, j, u, step):  # pragma: no cover - compiled
    """The horizontal pass of one element: sum_k w_k buf[j, u + k step] over a zero-padded row, the symmetric
    taps paired (6 multiplies instead of 11)."""
    return (
        _W0 * (buf[j, _u(u)] + buf[j, _u(u + 10 * step)]) + _W1 * (buf[j, _u(u + step)] + buf[j, _u(u + 9 * step)])
        + _W2 * (buf[j, _u(u + 2 * step)] + buf[j, _u(u + 8 * step)])
        + _W3 * (buf[j, _u(u + 3 * step)] + buf[j, _u(u + 7 * step)])
        + _W4 * (buf[j, _u(u + 4 * step)] + buf[j, _u(u + 6 * step)]) + _W5 * buf[j, _u(u + 5 * step)]
    )  # fmt: skip


@njit(cache=True, inline="always", fastmath=_FASTMATH, error_model="numpy")
def _symmetric(x):  # pragma: no cover - compiled
    """sum_k w_k x[k] with the constant taps, symmetric ones paired."""
    return (
        _W0 * (x[0] + x[10]) + _W1 * (x[1] + x[9]) + _W2 * (x[2] + x[8]) + _W3 * (x[3] + x[7])
        + _W4 * (x[4] + x[6]) + _W5 * x[5]
    )  # fmt: skip


@njit(cache=True, inline="always", fastmath=_FASTMATH, error_model="numpy")
def _symmetric_sum_of_squares(a, b):  # pragma: no cover - compiled
    """sum_k w_k (a[k]^2 + b[k]^2), symmetric taps paired: 4 multiply-adds per pair, then 6 for the taps."""
    return (
        _W0 * (((b[0] * b[0] + a[0] * a[0]) + a[10] * a[10]) + b[10] * b[10])
        + _W1 * (((b[1] * b[1] + a[1] * a[1]) + a[9] * a[9]) + b[9] * b[9])
        + _W2 * (((b[2] * b[2] + a[2] * a[2]) + a[8] * a[8]) + b[8] * b[8])
        + _W3 * (((b[3] * b[3] + a[3] * a[3]) + a[7] * a[7]) + b[7] * b[7])
        + _W4 * (((b[4] * b[4] + a[4] * a[4]) + a[6] * a[6]) + b[6] * b[6])
        + _W5 * (b[5] * b[5] + a[5] * a[5])
    )  # fmt: skip


@njit(cache=True, inline="always", fastmath=_FASTMATH, error_model="numpy")
def _symmetric_products(a, b):  # pragma: no cover - compiled
    """sum_k w_k a[k] b[k], symmetric taps paired."""
    return (
        _W0 * (a[0] * b[0] + a[10] * b[10]) + _W1 * (a[1] * b[1] + a[9] * b[9]) + _W2 * (a[2] * b[2] + a[8] * b[8])
        + _W3 * (a[3] * b[3] + a[7] * b[7]) + _W4 * (a[4] * b[4] + a[6] * b[6]) + _W5 * (a[5] * b[5])
    )  # fmt: skip


@njit(cache=True, inline="always", fastmath=_FASTMATH, error_model="numpy")
def _vertical_4maps(p, g, t, lo, hi, base, vert):  # pragma: no cover - compiled
    """vert[:, e - base] = the vertical blur of p, g, p^2 + g^2, p g at element e of row t, e in [lo, hi): 22 loads,
    the four sums in registers. Rows whose window lies inside the image take the constant taps, symmetric ones
    paired (67 multiplies and adds per element instead of 77, and no registers held by the weights); the others
    take the window's rows with weight 0 outside the image."""
    rows, weights = _window_rows(t, p.shape[0])
    if weights[0] != 0.0 and weights[10] != 0.0:
        for e in range(lo, hi):
            a = _column(p, rows, e)
            b = _column(g, rows, e)
            i = _u(e - base)
            vert[0, i] = _symmetric(a)
            vert[1, i] = _symmetric(b)
            vert[2, i] = _symmetric_sum_of_squares(a, b)
            vert[3, i] = _symmetric_products(a, b)
    else:
        for e in range(lo, hi):
            a = _column(p, rows, e)
            b = _column(g, rows, e)
            i = _u(e - base)
            vert[0, i] = _dot(a, weights)
            vert[1, i] = _dot(b, weights)
            vert[2, i] = _dot(_sum_of_squares(a, b), weights)
            vert[3, i] = _dot(_products(a, b), weights)


@njit(cache=True, inline="always", fastmath=_FASTMATH, error_model="numpy")
def _ssim_terms(vert, u, step, c1, c2):  # pragma: no cover - compiled
    """(mu_p, mu_g, A1, A2, B1, B2) at u, SSIM = A1 A2 / (B1 B2), from the horizontal pass of the rows of ``vert``."""
    m0 = _hsum(vert, 0, u, step)  # mu_p
    m1 = _hsum(vert, 1, u, step)  # mu_g
    mq = _hsum(vert, 2, u, step)  # E[p^2 + g^2]
    mr = _hsum(vert, 3, u, step)  # E[p g]
    mpg = m0 * m1
    msq = m0 * m0 + m1 * m1
    a1 = np.float32(2.0) * mpg + c1
    a2 = np.float32(2.0) * (mr - mpg) + c2
    b1 = msq + c1
    b2 = (mq - msq) + c2
    return m0, m1, a1, a2, b1, b2


@njit(cache=True, inline="always", fastmath=_FASTMATH, error_model="numpy")
def _ssim_values(vert, count, step, c1, c2, out):  # pragma: no cover - compiled
    """out[3, u] = SSIM at u for u < count, from the horizontal pass of the four rows of ``vert``."""
    for u in range(count):
        _, _, a1, a2, b1, b2 = _ssim_terms(vert, u, step, c1, c2)
        out[3, _u(u)] = a1 * a2 * (np.float32(1.0) / (b1 * b2))  # as below: the same bits with or without them


@njit(cache=True, inline="always", fastmath=_FASTMATH, error_model="numpy")
def _ssim_values_and_derivatives(vert, count, step, c1, c2, out):  # pragma: no cover - compiled
    """Like _ssim_values, and out[0..2, u] = dS/dmu_p, dS/dE[p^2] (= dS/dB2), dS/dE[p g] (one division)."""
    for u in range(count):
        m0, m1, a1, a2, b1, b2 = _ssim_terms(vert, u, step, c1, c2)
        inv_b1b2 = np.float32(1.0) / (b1 * b2)
        inv_b1 = b2 * inv_b1b2
        inv_b2 = b1 * inv_b1b2
        s = a1 * a2 * inv_b1b2
        i = _u(u)
        out[0, i] = np.float32(2.0) * m1 * (a2 - a1) * inv_b1b2 - np.float32(2.0) * m0 * s * (inv_b1 - inv_b2)
        out[1, i] = -s * inv_b2
        out[2, i] = np.float32(2.0) * a1 * inv_b1b2
        out[3, i] = s


@njit(cache=True, inline="always")
def _slots(rows):  # pragma: no cover - compiled
    """Where the window rows live in a ring buffer of _K rows (row r in slot r % _K)."""
    return (
        rows[0] % _K, rows[1] % _K, rows[2] % _K, rows[3] % _K, rows[4] % _K, rows[5] % _K,
        rows[6] % _K, rows[7] % _K, rows[8] % _K, rows[9] % _K, rows[10] % _K,
    )  # fmt: skip


@njit(cache=True, inline="always", fastmath=_FASTMATH, error_model="numpy")
def _gradient_row(p, g, ring0, ring1, ring2, y, scale, grad):  # pragma: no cover - compiled
    """grad[y] = scale * (blur(d_mu) + 2 p blur(d_q) + g blur(d_pg)) at row y: the vertical pass over the x-blurred
    derivative maps held in the ring buffers (33 loads, three sums in registers), combined with p and g."""
    rows, weights = _window_rows(y, p.shape[0])
    slots = _slots(rows)
    for e in range(p.shape[1]):
        e0 = _dot(_column(ring0, slots, e), weights)
        e1 = _dot(_column(ring1, slots, e), weights)
        e2 = _dot(_column(ring2, slots, e), weights)
        i = _u(e)
        grad[y, i] = scale * (e0 + np.float32(2.0) * p[y, i] * e1 + g[y, i] * e2)


@njit(cache=True, nogil=True, fastmath=_FASTMATH, error_model="numpy")
def _ssim_rows(p, g, n_ch, seg, c1, c2, scale, band0, band1, band_sums, grad):  # pragma: no cover - compiled
    """Bands [band0, band1) (one thread's share of _ssim_forward): their value sums and gradient rows."""
    height, length = p.shape
    rc = _R * n_ch  # R pixels, in elements
    with_grad = grad.shape[0] > 0
    y0, y1 = band0 * _BAND, min(height, band1 * _BAND)
    # the gradient of rows [y0, y1) needs the derivative maps of R more rows on either side
    t0, t1 = (max(0, y0 - _R), min(height, y1 + _R)) if with_grad else (y0, y1)
    # (every element of these that a loop reads has been written before, halo zeros included)
    vert = np.empty((4, _CAP), dtype=np.float32)  # rows: p, g, p^2 + g^2, p g blurred vertically
    out = np.empty((4, _CAP), dtype=np.float32)  # rows: dS/dmu_p, dS/dE[p^2], dS/dE[p g], s
    col = np.zeros(length, dtype=np.float32)
    ring_len = length if with_grad else 0  # three arrays: LLVM can then check them for overlap (one 3-D array's
    ring0 = np.empty((_K, ring_len), dtype=np.float32)  # rows at a run-time distance kept the loop scalar)
    ring1 = np.empty((_K, ring_len), dtype=np.float32)
    ring2 = np.empty((_K, ring_len), dtype=np.float32)
    next_y = y0  # the next gradient row to emit
    for t in range(t0, t1):
        slot = t % _K
        for s0 in range(0, length, seg):
            n = min(length, s0 + seg) - s0
            # vert[:, i] is element s0 - 2rc + i, i < n + 4rc; zero outside the row
            base = s0 - 2 * rc
            lo, hi = max(0, base), min(length, s0 + n + 2 * rc)
            for j in range(4):
                for i in range(lo - base):
                    vert[j, i] = np.float32(0.0)
                for i in range(hi - base, n + 4 * rc):
                    vert[j, i] = np.float32(0.0)
            _vertical_4maps(p, g, t, lo, hi, base, vert)
            # out[:, u] is element s0 - rc + u, u < n + 2rc: the derivative maps' halo for their horizontal blur
            if with_grad:
                _ssim_values_and_derivatives(vert, n + 2 * rc, n_ch, c1, c2, out)
                for j in range(3):  # the derivative maps are zero outside the image
                    for u in range(max(0, rc - s0)):
                        out[j, u] = np.float32(0.0)
                    for u in range(length - s0 + rc, n + 2 * rc):
                        out[j, u] = np.float32(0.0)
                for v in range(n):
                    i = _u(s0 + v)
                    ring0[slot, i] = _hsum(out, 0, v, n_ch)
                    ring1[slot, i] = _hsum(out, 1, v, n_ch)
                    ring2[slot, i] = _hsum(out, 2, v, n_ch)
            else:
                _ssim_values(vert, n + 2 * rc, n_ch, c1, c2, out)
            if y0 <= t < y1:
                for v in range(n):
                    col[_u(s0 + v)] += out[3, _u(rc + v)]
        if y0 <= t < y1 and (t + 1 == y1 or (t + 1) % _BAND == 0):
            # the band's sum: four interleaved float64 partial sums, a fixed order and no long chain of adds
            s_0 = s_1 = s_2 = s_3 = 0.0
            n4 = length - length % 4
            for e in range(0, n4, 4):
                s_0 += col[e]
                s_1 += col[e + 1]
                s_2 += col[e + 2]
                s_3 += col[e + 3]
            for e in range(n4, length):
                s_0 += col[e]
            band_sums[t // _BAND] = (s_0 + s_1) + (s_2 + s_3)
            for e in range(length):
                col[e] = np.float32(0.0)
        # emit the gradient rows whose window of derivative rows is now complete
        while with_grad and next_y < y1 and min(next_y + _R, height - 1) <= t:
            _gradient_row(p, g, ring0, ring1, ring2, next_y, scale, grad)
            next_y += 1


@njit(parallel=True, cache=True, nogil=True)
def _ssim_forward(p, g, n_ch, seg, c1, c2, scale, n_threads, band_sums, grad):  # pragma: no cover - compiled
    """p, g [H, W*C] -> band_sums [n_bands]: the SSIM map summed over each band of _BAND rows (float64); and, when
    grad is [H, W*C] (not empty), grad = scale * dS/dp. Each thread takes a contiguous range of bands, and works
    out the derivative maps of the R rows on either side of it as well (their gradient rows need them)."""
    n_bands = band_sums.shape[0]
    n_chunks = max(1, min(n_threads, n_bands // _MIN_BANDS))
    for chunk in prange(n_chunks):
        band0, band1 = chunk * n_bands // n_chunks, (chunk + 1) * n_bands // n_chunks
        _ssim_rows(p, g, n_ch, seg, c1, c2, scale, band0, band1, band_sums, grad)


@njit(cache=True, nogil=True, fastmath=_FASTMATH, error_model="numpy")
def _blur_rows(maps, job0, job1, out):  # pragma: no cover - compiled
    """Rows [job0, job1) of the maps [M, H, W] flattened to M*H rows: see _blur_maps."""
    height, width = maps.shape[1], maps.shape[2]
    row = np.zeros((1, width + 2 * _R), dtype=np.float32)
    for job in range(job0, job1):
        m, y = job // height, job % height
        rows, weights = _window_rows(y, height)
        src = maps[m]
        for x in range(width):
            row[0, _u(_R + x)] = _dot(_column(src, rows, x), weights)
        for x in range(width):
            out[m, y, _u(x)] = _hsum(row, 0, x, 1)


@njit(parallel=True, cache=True, nogil=True)
def _blur_maps(maps, n_threads, out):  # pragma: no cover - compiled
    """out = the zero-padded separable blur of maps [M, H, W], one row at a time: the vertical pass into a row
    padded by R zeros per side, then the horizontal pass (the same helpers as the SSIM kernels)."""
    n_rows = maps.shape[0] * maps.shape[1]
    n_chunks = min(n_threads, n_rows)
    for chunk in prange(n_chunks):
        _blur_rows(maps, chunk * n_rows // n_chunks, (chunk + 1) * n_rows // n_chunks, out)


def _rows(t: Tensor) -> np.ndarray:
    """[H, W, C] tensor -> [H, W*C] float32 rows (a view when it already is contiguous float32)."""
    height, width, n_ch = t.shape
    return t.detach().to(torch.float32).contiguous().numpy().reshape(height, width * n_ch)


def blur(maps: Tensor) -> Tensor:
    """[M, H, W] float32 -> same shape, blurred by the 11-tap sigma-1.5 Gaussian with zero padding."""
    src = maps.detach().to(torch.float32).contiguous().numpy()
    out = np.empty_like(src)
    _blur_maps(src, numba.get_num_threads(), out)
    return torch.from_numpy(out)


def _segment(length: int, n_ch: int) -> int:
    """Elements per row segment: the whole row when it fits the scratch rows with its halo of 4R pixels."""
    seg = (_CAP - 4 * _R * n_ch) // n_ch * n_ch
    if seg < n_ch:
        raise ValueError(f"fused_ssim: at most {_CAP // (4 * _R + 1)} channels, got {n_ch}")
    return max(1, min(length, seg))


class _FusedSSIM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pred: Tensor, gt: Tensor) -> Tensor:  # type: ignore[override]
        p, g = _rows(pred), _rows(gt)
        n_ch = pred.shape[2]
        band_sums = np.empty((p.shape[0] + _BAND - 1) // _BAND, dtype=np.float64)
        need_grad = ctx.needs_input_grad[0]
        grad = np.empty(p.shape if need_grad else (0, 0), dtype=np.float32)
        c1, c2 = np.float32(SSIM_K[0] ** 2), np.float32(SSIM_K[1] ** 2)
        scale = np.float32(1.0 / max(p.size, 1))
        _ssim_forward(p, g, n_ch, _segment(p.shape[1], n_ch), c1, c2, scale, numba.get_num_threads(), band_sums, grad)
        # d(mean SSIM)/d pred, made with the value: the backward only scales it
        ctx.grad = torch.from_numpy(grad).view(pred.shape) if need_grad else None
        return torch.tensor(band_sums.sum() / p.size, dtype=pred.dtype)

    @staticmethod
    def backward(ctx, grad_out: Tensor):  # type: ignore[override]
        if ctx.grad is None:
            return None, None
        return (ctx.grad * grad_out).to(grad_out.dtype), None


def fused_ssim(pred: Tensor, gt: Tensor) -> Tensor:
    """Mean zero-padded SSIM of ``pred`` vs ``gt`` (one [H, W, C] image each, same shape), float32.

    Differentiable in ``pred`` only (the ground truth is data); the gradient is made with the value when ``pred``
    requires one. CPU tensors, any size and up to 195 channels; the value equals
    ``metrics.ssim(pred, gt, padding="zeros")`` up to float32 rounding.
    """
    if pred.shape != gt.shape:
        raise ValueError(f"fused_ssim: pred and gt shapes differ: {tuple(pred.shape)} vs {tuple(gt.shape)}")
    if pred.dim() != 3:
        raise ValueError(f"fused_ssim: expected one image [H, W, C], got shape {tuple(pred.shape)}")
    if pred.device.type != "cpu":
        raise ValueError("fused_ssim: CPU tensors only (use metrics.ssim on other devices)")
    return _FusedSSIM.apply(pred, gt)
