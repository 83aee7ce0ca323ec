"""Compiled (numba) kernels for landmark-patch alignment: the same arithmetic as the numpy path, a window at a time.

:func:`services.prebuild.patches.align_to_patches` spends most of a tracked P&L frame: per call ~240 windows, each
a template warped from its stored patch (2-7 templates with motion blur) and ~8 Gauss-Newton steps, every step a
15x15 bilinear sample of the live frame. In numpy each of those is a whole-array pass with its own temporaries and
one ``cv2.remap`` per step; here each window is finished in registers and a small buffer.

Optional: the light client's base install has no numba, and :mod:`services.prebuild.patches` falls back to numpy
when this module cannot be imported, or with ``CRISTAL_KERNELS=numpy`` (:mod:`services.kernels`). Bilinear samples
are OpenCV 5.0's ``remap`` (INTER_LINEAR, float32) bit for bit on an FMA CPU: two lerps along x, one along y, each
fused. The alignment sums accumulate in float64 where numpy's einsum accumulates in float32, so the two paths agree
to ~1e-5 px, not bit for bit (``tests/test_patches.py::test_compiled_and_numpy_alignment_agree``).
"""

from __future__ import annotations

import numba as nb
import numpy as np

__all__ = ["homographies", "warp_template", "align_windows"]


@nb.njit(cache=True, inline="always", fastmath={"contract"})
def _lerp(a, b, t):
    return a + t * (b - a)


@nb.njit(cache=True, nogil=True)
def homographies(Ks, src_T_cw, src, normals, idx, P_w, R, t, K, out):
    """:func:`services.prebuild.patches._homographies` a landmark at a time: for each landmark ``idx[m]`` at ``P_w[m]``
    with world normal ``normals[idx[m]]`` and source keyframe ``src_T_cw[src[idx[m]]]`` (intrinsics ``Ks``), the
    live-to-source homography through its tangent plane from the live camera (``R``, ``t``, ``K``), scaled to
    H[2, 2] = 1, into ``out`` (M, 3, 3) float64."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    ki = np.array([[1 / fx, 0.0, -cx / fx], [0.0, 1 / fy, -cy / fy], [0.0, 0.0, 1.0]])
    A = np.empty((3, 3))
    G = np.empty((3, 3))
    KG = np.empty((3, 3))
    xc, nc = np.empty(3), np.empty(3)
    for m in range(idx.shape[0]):
        lm = idx[m]
        S = src_T_cw[src[lm]]
        for i in range(3):
            xc[i] = P_w[m, 0] * R[i, 0] + P_w[m, 1] * R[i, 1] + P_w[m, 2] * R[i, 2] + t[i]
            nc[i] = normals[lm, 0] * R[i, 0] + normals[lm, 1] * R[i, 1] + normals[lm, 2] * R[i, 2]
        dpl = nc[0] * xc[0] + nc[1] * xc[1] + nc[2] * xc[2]
        for i in range(3):
            for j in range(3):
                A[i, j] = S[i, 0] * R[j, 0] + S[i, 1] * R[j, 1] + S[i, 2] * R[j, 2]
        for i in range(3):
            b = S[i, 3] - (A[i, 0] * t[0] + A[i, 1] * t[1] + A[i, 2] * t[2])
            for j in range(3):
                G[i, j] = dpl * A[i, j] + b * nc[j]
        for i in range(3):
            for j in range(3):
                KG[i, j] = Ks[i, 0] * G[0, j] + Ks[i, 1] * G[1, j] + Ks[i, 2] * G[2, j]
        for i in range(3):
            for j in range(3):
                out[m, i, j] = KG[i, 0] * ki[0, j] + KG[i, 1] * ki[1, j] + KG[i, 2] * ki[2, j]
        h22 = out[m, 2, 2]
        if not abs(h22) > 1e-12:
            h22 = 1e-12
        for i in range(3):
            for j in range(3):
                out[m, i, j] /= h22


@nb.njit(cache=True, nogil=True)
def warp_template(patches, idx, H, u0, ups, vps, half, out):
    """The stored ``patches[idx]`` (uint8) seen through the live-to-source homographies ``H`` (M, 3, 3) float32 in the
    (2 half + 1)^2 windows at ``u0`` (M, 2) float32; ``ups``/``vps`` (M,) float32: each landmark's projection in its
    source keyframe (the stored patch's centre). Writes ``out`` (M, k^2) float32. The numpy path's float32 operations
    in its order, the sample rows offset as in its one remap over the stacked patches (float32 rounding included).
    Samples are clipped to the patch, so the row or column past its edge gets weight 0: here it is 0."""
    m_count = idx.shape[0]
    k = 2 * half + 1
    s = patches.shape[1]
    hs = np.float32((s - 1) / 2.0)
    top = np.float32(s - 1)
    buf = np.zeros((s + 1, s + 1), np.float32)
    us, vs = np.empty(k, np.float32), np.empty(k, np.float32)
    for m in range(m_count):
        h = H[m]
        src = patches[idx[m]]
        for i in range(s):
            for j in range(s):
                buf[i, j] = src[i, j]
        row_off = np.float32(m) * np.float32(s)
        for i in range(k):
            gy = u0[m, 1] + np.float32(i - half)
            for j in range(k):  # the row's source pixels first (vectorises), then its samples
                gx = u0[m, 0] + np.float32(j - half)
                wz = h[2, 0] * gx + (h[2, 1] * gy + h[2, 2])
                if not abs(wz) > np.float32(1e-6):
                    wz = np.float32(1e-6)
                us[j] = (h[0, 0] * gx + (h[0, 1] * gy + h[0, 2])) / wz
                vs[j] = (h[1, 0] * gx + (h[1, 1] * gy + h[1, 2])) / wz
            for j in range(k):
                px, py = us[j] - ups[m] + hs, vs[j] - vps[m] + hs
                px = min(px if px > 0 else np.float32(0.0), top)  # clipped to the patch; NaN (a degenerate warp) to 0
                py = min(py if py > 0 else np.float32(0.0), top) + row_off
                fx, fy = np.floor(px), np.floor(py)
                ax, ay = px - fx, py - fy
                x0, r0 = int(fx), int(fy) - m * s  # 0 <= r0 <= s - 1: row_off and s - 1 + row_off are exact
                t = _lerp(buf[r0, x0], buf[r0, x0 + 1], ax)
                b = _lerp(buf[r0 + 1, x0], buf[r0 + 1, x0 + 1], ax)
                out[m, i * k + j] = _lerp(t, b, ay)


@nb.njit(cache=True)
def _sample_window(img, cx, cy, r, rows, w):
    """``img`` (float32) bilinearly sampled on the (2 r + 1)^2 pixel grid centred at (cx, cy) into ``w``, as
    cv2.remap(INTER_LINEAR, BORDER_REPLICATE) samples it (every sample shares the centre's sub-pixel offset; the
    float32 sums cx + j that remap is given can differ from it in the last bit). ``rows``: scratch (2 r + 2, 2 r + 1)."""
    h, wd = img.shape
    fx, fy = np.floor(cx), np.floor(cy)
    ax, ay = cx - fx, cy - fy
    x0, y0 = int(fx) - r, int(fy) - r
    n = 2 * r + 1
    inside = x0 >= 0 and y0 >= 0 and x0 + n < wd and y0 + n < h
    for i in range(n + 1):  # each image row once, lerped along x
        y = min(max(y0 + i, 0), h - 1)
        if inside:
            for j in range(n):
                rows[i, j] = _lerp(img[y, x0 + j], img[y, x0 + j + 1], ax)
        else:
            for j in range(n):
                rows[i, j] = _lerp(img[y, min(max(x0 + j, 0), wd - 1)], img[y, min(max(x0 + j + 1, 0), wd - 1)], ax)
    for i in range(n):
        for j in range(n):
            w[i, j] = _lerp(rows[i, j], rows[i + 1, j], ay)


@nb.njit(cache=True, nogil=True, fastmath={"reassoc", "contract"})
def align_windows(gray, u0, T, half, iterations, d, ok, zncc, abc):
    """Gauss-Newton on each window's shift ``d`` (M, 2) float32, in place: the live frame ``gray`` (float32) sampled
    in the (2 half + 1)^2 window at ``u0 + d``, zero-mean unit-variance, against the normalised template ``T`` (M, k^2).
    Clears ``ok`` (M,) where a window's gradient structure is an edge; writes each window's last zero-mean normalised
    correlation ``zncc`` (M,) and gradient structure ``abc`` (M, 3) (sum gx^2, gx gy, gy^2 of the normalised window).
    A window stops after ``iterations`` steps, or once a step moves it less than 0.01 px."""
    m_count = u0.shape[0]
    k = 2 * half + 1
    kk = k * k
    ke = k + 2
    w = np.empty((ke, ke), np.float32)
    rows = np.empty((ke + 1, ke), np.float32)
    wf, gxf, gyf = np.empty(kk, np.float32), np.empty(kk, np.float32), np.empty(kk, np.float32)
    for m in range(m_count):
        st = stt = 0.0
        for q in range(kk):
            st += T[m, q]
            stt += T[m, q] * T[m, q]
        for _ in range(iterations):
            cx, cy = u0[m, 0] + d[m, 0], u0[m, 1] + d[m, 1]
            if not (abs(cx) < 1e6 and abs(cy) < 1e6):  # NaN or absurd (a landmark at the camera): nothing to sample
                ok[m] = False
                zncc[m] = -1.0
                break
            _sample_window(gray, cx, cy, half + 1, rows, w)
            # one pass of sums; the zero-mean unit-variance window (w - mean) / sd enters them by linearity:
            # sum g ra = (sum g w - mean sum g) / sd - sum g T, sum ra^2 = kk var / sd^2 - 2 (sum w T - mean sum T) / sd + sum T^2
            q = 0
            for i in range(1, k + 1):  # the window and its central differences, flattened (the sums below vectorise)
                for j in range(1, k + 1):
                    wf[q] = w[i, j]
                    gxf[q] = w[i, j + 1] - w[i, j - 1]
                    gyf[q] = w[i + 1, j] - w[i - 1, j]
                    q += 1
            sw = sww = sxx = sxy = syy = sxw = syw = sx1 = sy1 = sxt = syt = swt = 0.0
            for q in range(kk):
                wv, gx, gy, tv = float(wf[q]), float(gxf[q]), float(gyf[q]), float(T[m, q])
                sw += wv
                sww += wv * wv
                sxx += gx * gx
                sxy += gx * gy
                syy += gy * gy
                sxw += gx * wv
                syw += gy * wv
                sx1 += gx
                sy1 += gy
                sxt += gx * tv
                syt += gy * tv
                swt += wv * tv
            mean = sw / kk
            var = max(sww / kk - mean * mean, 0.0)
            sd = np.sqrt(var) + 1e-6
            s1 = 0.5 / sd
            sgx = (sxw - mean * sx1) / sd - sxt
            sgy = (syw - mean * sy1) / sd - syt
            srr = kk * var / (sd * sd) - 2.0 * (swt - mean * st) / sd + stt
            s2 = s1 * s1
            aa, bb, cc = sxx * s2, sxy * s2, syy * s2
            ga, gb = sgx * s1, sgy * s1
            abc[m, 0], abc[m, 1], abc[m, 2] = aa, bb, cc
            zncc[m] = 1.0 - 0.5 * srr / kk
            det = aa * cc - bb * bb
            if not det > 1e-3 * (aa + cc) ** 2:  # an edge: along it the shift is free
                ok[m] = False
                break
            sx = -(cc * ga - bb * gb) / det
            sy = -(aa * gb - bb * ga) / det
            d[m, 0] += np.float32(sx)
            d[m, 1] += np.float32(sy)
            if max(abs(sx), abs(sy)) < 0.01:
                break
