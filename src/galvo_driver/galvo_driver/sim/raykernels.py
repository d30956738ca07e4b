"""Compiled (numba) inner loops of the ray tracer and the sensor model.

The scene is packed into flat arrays (see :meth:`Scene.packed`): per primitive a type
(0 box ``lo, hi``; 1 sphere ``centre, radius``; 2 rectangle ``hx, hy`` in the plane z = 0,
two-sided), the owning object, the pose ``W_R_O`` / ``W_t_O`` and eight parameters (six
for the shape, then 1.0 where ``W_R_O`` is the identity). These
kernels compute exactly what the numpy reference code in ``scene.py`` computes (the tests
compare them); they exist because a laser frame needs ~15 000 traced rays in a few ms.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

EPS = 1e-7
BOX, SPHERE, RECT = 0, 1, 2


@njit(cache=True, inline='always')
def _local(R, T, prm, p, x, y, z):
    qx, qy, qz = x - T[p, 0], y - T[p, 1], z - T[p, 2]
    if prm[p, 6] != 0.0:  # identity rotation
        return qx, qy, qz
    return (R[p, 0, 0] * qx + R[p, 1, 0] * qy + R[p, 2, 0] * qz,
            R[p, 0, 1] * qx + R[p, 1, 1] * qy + R[p, 2, 1] * qz,
            R[p, 0, 2] * qx + R[p, 1, 2] * qy + R[p, 2, 2] * qz)


@njit(cache=True, inline='always')
def _local_dir(R, prm, p, x, y, z):
    if prm[p, 6] != 0.0:
        return x, y, z
    return (R[p, 0, 0] * x + R[p, 1, 0] * y + R[p, 2, 0] * z,
            R[p, 0, 1] * x + R[p, 1, 1] * y + R[p, 2, 1] * z,
            R[p, 0, 2] * x + R[p, 1, 2] * y + R[p, 2, 2] * z)


@njit(cache=True, inline='always')
def _slab(lo, hi, o, d, inv):
    """Entry/exit of a ray with one slab (inv = 1/d); (t_near, t_far) or (inf, -inf)."""
    if d == 0.0:
        if o < lo or o > hi:
            return np.inf, -np.inf
        return -np.inf, np.inf
    t1 = (lo - o) * inv
    t2 = (hi - o) * inv
    if t1 > t2:
        return t2, t1
    return t1, t2


@njit(cache=True, inline='always')
def _box(prm, p, ox, oy, oz, dx, dy, dz, ix, iy, iz):
    """(t_in, t_out, axis of t_in) of a ray and an axis-aligned box (i* = 1/d*)."""
    a0, b0 = _slab(prm[p, 0], prm[p, 3], ox, dx, ix)
    a1, b1 = _slab(prm[p, 1], prm[p, 4], oy, dy, iy)
    a2, b2 = _slab(prm[p, 2], prm[p, 5], oz, dz, iz)
    t_in, ax = a0, 0
    if a1 > t_in:
        t_in, ax = a1, 1
    if a2 > t_in:
        t_in, ax = a2, 2
    return t_in, min(b0, b1, b2), ax


@njit(cache=True, inline='always')
def _inv(x):
    return 1.0 / x if x != 0.0 else 0.0


@njit(cache=True, inline='always')
def closest_hit(ptype, R, T, prm, ox, oy, oz, dx, dy, dz):
    """Closest primitive hit of one ray: (t, prim, nx, ny, nz), prim = -1 for none."""
    best = np.inf
    bp = -1
    bnx = bny = bnz = 0.0
    wix, wiy, wiz = _inv(dx), _inv(dy), _inv(dz)
    for p in range(ptype.shape[0]):
        lx, ly, lz = _local(R, T, prm, p, ox, oy, oz)
        ex, ey, ez = _local_dir(R, prm, p, dx, dy, dz)
        kind = ptype[p]
        if kind == BOX:
            if prm[p, 6] != 0.0:
                ix, iy, iz = wix, wiy, wiz
            else:
                ix, iy, iz = _inv(ex), _inv(ey), _inv(ez)
            t_in, t_out, ax = _box(prm, p, lx, ly, lz, ex, ey, ez, ix, iy, iz)
            if t_in <= t_out and t_in > EPS and t_in < best:
                best = t_in
                bp = p
                nx = ny = nz = 0.0
                if ax == 0:
                    nx = -1.0 if ex > 0 else 1.0
                elif ax == 1:
                    ny = -1.0 if ey > 0 else 1.0
                else:
                    nz = -1.0 if ez > 0 else 1.0
                bnx, bny, bnz = nx, ny, nz
        elif kind == SPHERE:
            cx, cy, cz, r = prm[p, 0], prm[p, 1], prm[p, 2], prm[p, 3]
            qx, qy, qz = lx - cx, ly - cy, lz - cz
            b = qx * ex + qy * ey + qz * ez
            c = qx * qx + qy * qy + qz * qz - r * r
            disc = b * b - c
            if disc >= 0.0:
                t = -b - math.sqrt(disc)
                if t > EPS and t < best:
                    best = t
                    bp = p
                    bnx = (qx + t * ex) / r
                    bny = (qy + t * ey) / r
                    bnz = (qz + t * ez) / r
        else:
            if ez != 0.0:
                t = -lz / ez
                if t > EPS and t < best:
                    x = lx + t * ex
                    y = ly + t * ey
                    if abs(x) <= prm[p, 0] and abs(y) <= prm[p, 1]:
                        best = t
                        bp = p
                        bnx = 0.0
                        bny = 0.0
                        bnz = -1.0 if ez > 0 else 1.0
    if bp >= 0:
        wx = R[bp, 0, 0] * bnx + R[bp, 0, 1] * bny + R[bp, 0, 2] * bnz
        wy = R[bp, 1, 0] * bnx + R[bp, 1, 1] * bny + R[bp, 1, 2] * bnz
        wz = R[bp, 2, 0] * bnx + R[bp, 2, 1] * bny + R[bp, 2, 2] * bnz
        return best, bp, wx, wy, wz
    return best, bp, 0.0, 0.0, 0.0


@njit(cache=True, inline='always')
def is_blocked(ptype, R, T, prm, ox, oy, oz, dx, dy, dz, tmax):
    """Whether a surface or a solid's interior lies on the segment (see Scene.occluded)."""
    wix, wiy, wiz = _inv(dx), _inv(dy), _inv(dz)
    for p in range(ptype.shape[0]):
        lx, ly, lz = _local(R, T, prm, p, ox, oy, oz)
        ex, ey, ez = _local_dir(R, prm, p, dx, dy, dz)
        kind = ptype[p]
        if kind == BOX:
            if prm[p, 6] != 0.0:
                ix, iy, iz = wix, wiy, wiz
            else:
                ix, iy, iz = _inv(ex), _inv(ey), _inv(ez)
            t_in, t_out, _ = _box(prm, p, lx, ly, lz, ex, ey, ez, ix, iy, iz)
            if t_in <= t_out and t_out > EPS and t_in < tmax:
                return True
        elif kind == SPHERE:
            qx, qy, qz = lx - prm[p, 0], ly - prm[p, 1], lz - prm[p, 2]
            r = prm[p, 3]
            b = qx * ex + qy * ey + qz * ez
            c = qx * qx + qy * qy + qz * qz - r * r
            disc = b * b - c
            if disc > 0.0:
                root = math.sqrt(disc)
                if -b + root > EPS and -b - root < tmax:
                    return True
        else:
            if ez != 0.0:
                t = -lz / ez
                if t > EPS and t < tmax:
                    if abs(lx + t * ex) <= prm[p, 0] and abs(ly + t * ey) <= prm[p, 1]:
                        return True
    return False


@njit(cache=True)
def trace_closest(ptype, R, T, prm, o, d, t_out, prim_out, n_out):
    """Closest hits of rays o (n, 3) + t d (n, 3), world frame."""
    for i in range(o.shape[0]):
        t, p, nx, ny, nz = closest_hit(ptype, R, T, prm, o[i, 0], o[i, 1], o[i, 2],
                                       d[i, 0], d[i, 1], d[i, 2])
        t_out[i] = t
        prim_out[i] = p
        n_out[i, 0] = nx
        n_out[i, 1] = ny
        n_out[i, 2] = nz


@njit(cache=True)
def trace_blocked(ptype, R, T, prm, o, d, tmax, out):
    for i in range(o.shape[0]):
        out[i] = is_blocked(ptype, R, T, prm, o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1],
                            d[i, 2], tmax[i])


@njit(cache=True, inline='always')
def _camera_ray(cam, x, y):
    """Pixel ray (x, y, 1) in C traced off the two G1 mirrors, returned in W.

    ``cam`` packs: [0:9] G_R_C, [9:12] camera centre in G, [12:15] n1, [15] c1,
    [16:19] n2, [19] c2, [20:29] W_R_G, [29:32] W_t_G.
    """
    inv = 1.0 / math.sqrt(x * x + y * y + 1.0)
    dx = (cam[0] * x + cam[1] * y + cam[2]) * inv
    dy = (cam[3] * x + cam[4] * y + cam[5]) * inv
    dz = (cam[6] * x + cam[7] * y + cam[8]) * inv
    ox, oy, oz = cam[9], cam[10], cam[11]
    for k in range(2):
        b = 12 + 4 * k
        nx, ny, nz, c = cam[b], cam[b + 1], cam[b + 2], cam[b + 3]
        dn = dx * nx + dy * ny + dz * nz
        t = (c - (ox * nx + oy * ny + oz * nz)) / dn
        ox, oy, oz = ox + t * dx, oy + t * dy, oz + t * dz
        dx, dy, dz = dx - 2.0 * dn * nx, dy - 2.0 * dn * ny, dz - 2.0 * dn * nz
    wox = cam[20] * ox + cam[21] * oy + cam[22] * oz + cam[29]
    woy = cam[23] * ox + cam[24] * oy + cam[25] * oz + cam[30]
    woz = cam[26] * ox + cam[27] * oy + cam[28] * oz + cam[31]
    wdx = cam[20] * dx + cam[21] * dy + cam[22] * dz
    wdy = cam[23] * dx + cam[24] * dy + cam[25] * dz
    wdz = cam[26] * dx + cam[27] * dy + cam[28] * dz
    return wox, woy, woz, wdx, wdy, wdz


@njit(cache=True)
def camera_rays(cam, xy, o_out, d_out):
    for i in range(xy.shape[0]):
        ox, oy, oz, dx, dy, dz = _camera_ray(cam, xy[i, 0], xy[i, 1])
        o_out[i, 0], o_out[i, 1], o_out[i, 2] = ox, oy, oz
        d_out[i, 0], d_out[i, 1], d_out[i, 2] = dx, dy, dz


@njit(cache=True)
def trace_pixels_closest(ptype, R, T, prm, cam, xy, t_out, prim_out, n_out, p_out):
    """Camera rays for normalised pixel coordinates, traced into the scene."""
    for i in range(xy.shape[0]):
        ox, oy, oz, dx, dy, dz = _camera_ray(cam, xy[i, 0], xy[i, 1])
        t, p, nx, ny, nz = closest_hit(ptype, R, T, prm, ox, oy, oz, dx, dy, dz)
        t_out[i] = t
        prim_out[i] = p
        n_out[i, 0], n_out[i, 1], n_out[i, 2] = nx, ny, nz
        if p >= 0:
            p_out[i, 0], p_out[i, 1], p_out[i, 2] = ox + t * dx, oy + t * dy, oz + t * dz
        else:
            p_out[i, 0] = p_out[i, 1] = p_out[i, 2] = np.nan


@njit(cache=True)
def laser_pixels(ptype, R, T, prm, cam, grid, rows, cols, sheet, sigma, val_out, prim_out,
                 p_out):
    """Laser irradiance factor of window pixels (before albedo and speckle).

    ``sheet`` packs: [0:4] centre plane, [4:7] virtual apex, [7:10] and [10:13] inward
    edge normals, [13:17] last G2 mirror plane. The value is
    ``cos(incidence) / distance * exp(-delta^2 / (2 sigma^2))`` where the point is lit
    (facing the apex, inside the fan, segment to the G2 mirror free), else 0.
    """
    for i in range(rows.shape[0]):
        x = grid[rows[i], cols[i], 0]
        y = grid[rows[i], cols[i], 1]
        ox, oy, oz, dx, dy, dz = _camera_ray(cam, x, y)
        t, p, nx, ny, nz = closest_hit(ptype, R, T, prm, ox, oy, oz, dx, dy, dz)
        prim_out[i] = p
        val_out[i] = 0.0
        if p < 0:
            p_out[i, 0] = p_out[i, 1] = p_out[i, 2] = np.nan
            continue
        px, py, pz = ox + t * dx, oy + t * dy, oz + t * dz
        p_out[i, 0], p_out[i, 1], p_out[i, 2] = px, py, pz
        delta = sheet[0] * px + sheet[1] * py + sheet[2] * pz + sheet[3]
        if abs(delta) >= 5.0 * sigma:
            continue
        sx, sy, sz = sheet[4] - px, sheet[5] - py, sheet[6] - pz
        dist = math.sqrt(sx * sx + sy * sy + sz * sz)
        cos_i = (nx * sx + ny * sy + nz * sz) / dist
        if cos_i <= 0.0:
            continue
        if sx * sheet[7] + sy * sheet[8] + sz * sheet[9] > 0.0:
            continue
        if sx * sheet[10] + sy * sheet[11] + sz * sheet[12] > 0.0:
            continue
        ux, uy, uz = sx / dist, sy / dist, sz / dist
        den = ux * sheet[13] + uy * sheet[14] + uz * sheet[15]
        tm = dist
        if den != 0.0:
            tmm = -(px * sheet[13] + py * sheet[14] + pz * sheet[15] + sheet[16]) / den
            if tmm > 0.0 and tmm < dist:
                tm = tmm
        if is_blocked(ptype, R, T, prm, px, py, pz, ux, uy, uz, tm - EPS):
            continue
        val_out[i] = cos_i / dist * math.exp(-0.5 * (delta / sigma) ** 2)


@njit(cache=True)
def _bilinear_taps(n_out, n_src, step):
    """cv2.resize INTER_LINEAR source taps for upscaling n_src -> n_out by ``step``."""
    i0 = np.empty(n_out, np.int64)
    i1 = np.empty(n_out, np.int64)
    w = np.empty(n_out, np.float32)
    for k in range(n_out):
        x = (k + 0.5) / step - 0.5
        if x < 0.0:
            x = 0.0
        if x > n_src - 1:
            x = float(n_src - 1)
        j = int(math.floor(x))
        if j > n_src - 2:
            j = max(n_src - 2, 0)
        i0[k] = j
        i1[k] = min(j + 1, n_src - 1)
        w[k] = np.float32(x - j)
    return i0, i1, w


@njit(cache=True, fastmath=True)
def _quantise_row(e, z, zoff, noisy, fw, r2, sh, ig, bl, tp, out_row):
    zero = np.float32(0.0)
    if noisy:
        for c in range(e.shape[0]):
            v = min(e[c], fw)
            v = v + np.sqrt(r2 + sh * max(v, zero)) * z[zoff + c]
            out_row[c] = np.uint8(min(max(v * ig + bl, zero), tp))
    else:
        for c in range(e.shape[0]):
            v = min(e[c], fw)
            out_row[c] = np.uint8(min(max(v * ig + bl, zero), tp))


@njit(cache=True, fastmath=True)
def sensor(bg_full, bg_coarse, step, band, b0, z, full_well, shot, read2, inv_gain, black,
           top, out):
    """Compose the image in electrons and convert it to DN.

    Electrons = background (``bg_full`` (H, W), or ``bg_coarse`` upsampled bilinearly by
    ``step`` as cv2.resize does, or none when both are empty) + ``band`` on rows b0..;
    then clip at the full well, add shot/read noise with the N(0, 1) draws ``z`` (empty:
    no noise) and quantise with rounding to [0, top].
    """
    h, w = out.shape
    fw = np.float32(full_well)
    r2 = np.float32(read2)
    ig = np.float32(inv_gain)
    bl = np.float32(black + 0.5)
    tp = np.float32(top)
    sh = np.float32(1.0 if shot else 0.0)
    noisy = z.shape[0] > 0
    full = bg_full.shape[0] > 0
    coarse = bg_coarse.shape[0] > 0
    nb = band.shape[0]
    e = np.zeros(w, np.float32)
    if coarse:
        x0, x1, wx = _bilinear_taps(w, bg_coarse.shape[1], step)
        y0, y1, wy = _bilinear_taps(h, bg_coarse.shape[0], step)
        line = np.empty(bg_coarse.shape[1], np.float32)
    for r in range(h):
        if full:
            for c in range(w):
                e[c] = bg_full[r, c]
        elif coarse:
            a, b = np.float32(1.0) - wy[r], wy[r]
            for k in range(line.shape[0]):
                line[k] = a * bg_coarse[y0[r], k] + b * bg_coarse[y1[r], k]
            for c in range(w):
                e[c] = line[x0[c]] + wx[c] * (line[x1[c]] - line[x0[c]])
        rb = r - b0
        if 0 <= rb < nb:
            if full or coarse:
                for c in range(w):
                    e[c] += band[rb, c]
            else:
                for c in range(w):
                    e[c] = band[rb, c]
        elif not (full or coarse) and rb == nb:
            e[:] = 0.0
        _quantise_row(e, z, r * w, noisy, fw, r2, sh, ig, bl, tp, out[r])


@njit(cache=True, inline='always')
def _project(VTW, intr, x, y, z):
    """World point -> (u, v, depth) through the virtual camera (plumb_bob distortion)."""
    X = VTW[0, 0] * x + VTW[0, 1] * y + VTW[0, 2] * z + VTW[0, 3]
    Y = VTW[1, 0] * x + VTW[1, 1] * y + VTW[1, 2] * z + VTW[1, 3]
    Z = VTW[2, 0] * x + VTW[2, 1] * y + VTW[2, 2] * z + VTW[2, 3]
    xn = X / Z
    yn = Y / Z
    k1, k2, p1, p2, k3 = intr[4], intr[5], intr[6], intr[7], intr[8]
    r2 = xn * xn + yn * yn
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn)
    yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn
    return intr[0] * xd + intr[2], intr[1] * yd + intr[3], Z


@njit(cache=True)
def inside_solid(ptype, R, T, prm, x, y, z, tol):
    """Whether a world point lies strictly inside a box or sphere (by more than tol)."""
    for p in range(ptype.shape[0]):
        lx, ly, lz = _local(R, T, prm, p, x, y, z)
        if ptype[p] == BOX:
            if (prm[p, 0] + tol < lx < prm[p, 3] - tol and prm[p, 1] + tol < ly < prm[p, 4] - tol
                    and prm[p, 2] + tol < lz < prm[p, 5] - tol):
                return True
        elif ptype[p] == SPHERE:
            dx, dy, dz = lx - prm[p, 0], ly - prm[p, 1], lz - prm[p, 2]
            if math.sqrt(dx * dx + dy * dy + dz * dz) < prm[p, 3] - tol:
                return True
    return False


@njit(cache=True)
def _free(ptype, R, T, prm, px, py, pz, tx, ty, tz, mirror):
    """Nothing blocks the segment from p towards t, up to the mirror plane."""
    dx, dy, dz = tx - px, ty - py, tz - pz
    dist = math.sqrt(dx * dx + dy * dy + dz * dz)
    dx, dy, dz = dx / dist, dy / dist, dz / dist
    den = dx * mirror[0] + dy * mirror[1] + dz * mirror[2]
    tm = dist
    if den != 0.0:
        t = -(px * mirror[0] + py * mirror[1] + pz * mirror[2] + mirror[3]) / den
        if 0.0 < t < dist:
            tm = t
    return not is_blocked(ptype, R, T, prm, px, py, pz, dx, dy, dz, tm - EPS)


@njit(cache=True)
def _accept(ptype, R, T, prm, VTW, intr, center, cam_mirror, sheet, x, y, z, nx, ny, nz,
            two_sided, near):
    """Checks of a candidate stripe point; returns (ok, v, nx, ny, nz) with the normal
    turned towards the camera for two-sided faces."""
    u, v, depth = _project(VTW, intr, x, y, z)
    if depth <= near or v < -0.5 or v > intr[10] - 0.5:
        return False, v, nx, ny, nz
    fc = nx * (center[0] - x) + ny * (center[1] - y) + nz * (center[2] - z)
    if two_sided and fc < 0:
        nx, ny, nz, fc = -nx, -ny, -nz, -fc
    if fc <= 0.0:
        return False, v, nx, ny, nz
    sx, sy, sz = sheet[4] - x, sheet[5] - y, sheet[6] - z
    if nx * sx + ny * sy + nz * sz <= 0.0:
        return False, v, nx, ny, nz
    if sx * sheet[7] + sy * sheet[8] + sz * sheet[9] > 0.0:
        return False, v, nx, ny, nz
    if sx * sheet[10] + sy * sheet[11] + sz * sheet[12] > 0.0:
        return False, v, nx, ny, nz
    if inside_solid(ptype, R, T, prm, x, y, z, 1e-9):
        return False, v, nx, ny, nz
    if not _free(ptype, R, T, prm, x, y, z, center[0], center[1], center[2], cam_mirror):
        return False, v, nx, ny, nz
    if not _free(ptype, R, T, prm, x, y, z, sheet[4], sheet[5], sheet[6], sheet[13:17]):
        return False, v, nx, ny, nz
    return True, v, nx, ny, nz


@njit(cache=True)
def segment_crossings(ptype, R, T, prm, VTW, intr, center, cam_mirror, sheet, A, B, nrm, two,
                      fobj, near, X_out, N_out, obj_out, col_out, u_out, v_out):
    """Stripe points on straight segments A->B (world): for every integer column between
    the projected ends, the point projecting exactly onto it, if it passes ``_accept``.

    ``intr`` packs (fx, fy, cx, cy, k1, k2, p1, p2, k3, width, height). Returns the count
    written to the outputs (which need room for sum of the column spans).
    """
    fx, cx = intr[0], intr[2]
    distorted = intr[4] != 0 or intr[5] != 0 or intr[6] != 0 or intr[7] != 0 or intr[8] != 0
    m = 0
    for k in range(A.shape[0]):
        ax, ay, az = A[k, 0], A[k, 1], A[k, 2]
        dx, dy, dz = B[k, 0] - ax, B[k, 1] - ay, B[k, 2] - az
        ua, _, za = _project(VTW, intr, ax, ay, az)
        ub, _, zb = _project(VTW, intr, B[k, 0], B[k, 1], B[k, 2])
        if za <= 0 or zb <= 0:
            continue
        lo = max(math.ceil(min(ua, ub)), 0.0)
        hi = min(math.floor(max(ua, ub)), intr[9] - 1)
        # the segment in camera coordinates for the pinhole start
        Xa = VTW[0, 0] * ax + VTW[0, 1] * ay + VTW[0, 2] * az + VTW[0, 3]
        Za = VTW[2, 0] * ax + VTW[2, 1] * ay + VTW[2, 2] * az + VTW[2, 3]
        Xd = VTW[0, 0] * dx + VTW[0, 1] * dy + VTW[0, 2] * dz
        Zd = VTW[2, 0] * dx + VTW[2, 1] * dy + VTW[2, 2] * dz
        c = lo
        while c <= hi:
            xc = (c - cx) / fx
            den = Xd - xc * Zd
            s = -(Xa - xc * Za) / den if den != 0.0 else 0.5
            if distorted:
                for _ in range(2):
                    f0, _, _ = _project(VTW, intr, ax + s * dx, ay + s * dy, az + s * dz)
                    h = 1e-6
                    f1, _, _ = _project(VTW, intr, ax + (s + h) * dx, ay + (s + h) * dy,
                                        az + (s + h) * dz)
                    der = (f1 - f0) / h
                    if der != 0.0:
                        s -= (f0 - c) / der
            x, y, z = ax + s * dx, ay + s * dy, az + s * dz
            u, v, _ = _project(VTW, intr, x, y, z)
            if -1e-9 <= s <= 1.0 + 1e-9 and abs(u - c) < 1e-6:
                ok, v, nx, ny, nz = _accept(ptype, R, T, prm, VTW, intr, center, cam_mirror,
                                            sheet, x, y, z, nrm[k, 0], nrm[k, 1], nrm[k, 2],
                                            two[k], near)
                if ok and m < X_out.shape[0]:
                    X_out[m, 0], X_out[m, 1], X_out[m, 2] = x, y, z
                    N_out[m, 0], N_out[m, 1], N_out[m, 2] = nx, ny, nz
                    obj_out[m] = fobj[k]
                    col_out[m] = int(c)
                    u_out[m] = u
                    v_out[m] = v
                    m += 1
            c += 1.0
    return m


@njit(cache=True)
def circle_crossings(ptype, R, T, prm, VTW, intr, center, cam_mirror, sheet, cc, rho, e1, e2,
                     sc, samples, obj, near, X_out, N_out, obj_out, col_out, u_out, v_out):
    """Like :func:`segment_crossings` for the circle cc + rho (cos phi e1 + sin phi e2) on
    the sphere of centre sc; returns the count written."""
    m = 0
    two_pi = 2.0 * math.pi
    step = two_pi / samples
    uprev = np.nan
    for i in range(samples + 1):
        ph = i * step
        x = cc[0] + rho * (math.cos(ph) * e1[0] + math.sin(ph) * e2[0])
        y = cc[1] + rho * (math.cos(ph) * e1[1] + math.sin(ph) * e2[1])
        z = cc[2] + rho * (math.cos(ph) * e1[2] + math.sin(ph) * e2[2])
        u, _, depth = _project(VTW, intr, x, y, z)
        if depth <= near:
            u = np.nan
        if i > 0 and not (math.isnan(u) or math.isnan(uprev)):
            lo = max(math.floor(min(uprev, u)) + 1.0, 0.0)
            hi = min(math.floor(max(uprev, u)), intr[9] - 1)
            c = lo
            while c <= hi:
                w = (c - uprev) / (u - uprev)
                phi = ph - step + w * step
                for _ in range(4):
                    px = cc[0] + rho * (math.cos(phi) * e1[0] + math.sin(phi) * e2[0])
                    py = cc[1] + rho * (math.cos(phi) * e1[1] + math.sin(phi) * e2[1])
                    pz = cc[2] + rho * (math.cos(phi) * e1[2] + math.sin(phi) * e2[2])
                    f0, _, _ = _project(VTW, intr, px, py, pz)
                    h = 1e-7
                    qx = cc[0] + rho * (math.cos(phi + h) * e1[0] + math.sin(phi + h) * e2[0])
                    qy = cc[1] + rho * (math.cos(phi + h) * e1[1] + math.sin(phi + h) * e2[1])
                    qz = cc[2] + rho * (math.cos(phi + h) * e1[2] + math.sin(phi + h) * e2[2])
                    f1, _, _ = _project(VTW, intr, qx, qy, qz)
                    der = (f1 - f0) / h
                    if der != 0.0:
                        phi -= (f0 - c) / der
                px = cc[0] + rho * (math.cos(phi) * e1[0] + math.sin(phi) * e2[0])
                py = cc[1] + rho * (math.cos(phi) * e1[1] + math.sin(phi) * e2[1])
                pz = cc[2] + rho * (math.cos(phi) * e1[2] + math.sin(phi) * e2[2])
                uu, vv, _ = _project(VTW, intr, px, py, pz)
                if abs(uu - c) < 1e-6:
                    nx, ny, nz = px - sc[0], py - sc[1], pz - sc[2]
                    nn = math.sqrt(nx * nx + ny * ny + nz * nz)
                    ok, vv, nx, ny, nz = _accept(ptype, R, T, prm, VTW, intr, center,
                                                 cam_mirror, sheet, px, py, pz, nx / nn,
                                                 ny / nn, nz / nn, False, near)
                    if ok and m < X_out.shape[0]:
                        X_out[m, 0], X_out[m, 1], X_out[m, 2] = px, py, pz
                        N_out[m, 0], N_out[m, 1], N_out[m, 2] = nx, ny, nz
                        obj_out[m] = obj
                        col_out[m] = int(c)
                        u_out[m] = uu
                        v_out[m] = vv
                        m += 1
                c += 1.0
        uprev = u
    return m


@njit(cache=True)
def laser_windows(ptype, R, T, prm, pobj, albedo, textured, cam, grid, cols, v0, half, sheet,
                  sigma, scale, speckle, z, zoff, band, b0, tex_rc, tex_p, tex_val, tex_obj):
    """Render the laser stripe into ``band`` (rows b0.. of the image), window by window.

    Window j covers rows v0[j] - half[j] .. v0[j] + half[j] of column cols[j]. A pixel's
    value is ``scale * albedo * cos(incidence) / distance * exp(-delta^2 / 2 sigma^2)``
    times the speckle factor ``max(0, 1 + speckle * z)`` where the laser reaches its hit
    point (see :func:`laser_pixels`), else it is left alone. Pixels on textured objects are
    returned in ``tex_*`` without the albedo instead; the count of those is returned.
    """
    H = grid.shape[0]
    nz = z.shape[0]
    k = zoff
    m = 0
    for j in range(cols.shape[0]):
        c = cols[j]
        r0 = max(v0[j] - half[j], 0)
        r1 = min(v0[j] + half[j], H - 1)
        for r in range(r0, r1 + 1):
            ox, oy, oz, dx, dy, dz = _camera_ray(cam, grid[r, c, 0], grid[r, c, 1])
            t, p, nx, ny, nzz = closest_hit(ptype, R, T, prm, ox, oy, oz, dx, dy, dz)
            if p < 0:
                continue
            px, py, pz = ox + t * dx, oy + t * dy, oz + t * dz
            delta = sheet[0] * px + sheet[1] * py + sheet[2] * pz + sheet[3]
            if abs(delta) >= 5.0 * sigma:
                continue
            sx, sy, sz = sheet[4] - px, sheet[5] - py, sheet[6] - pz
            dist = math.sqrt(sx * sx + sy * sy + sz * sz)
            cos_i = (nx * sx + ny * sy + nzz * sz) / dist
            if cos_i <= 0.0:
                continue
            if sx * sheet[7] + sy * sheet[8] + sz * sheet[9] > 0.0:
                continue
            if sx * sheet[10] + sy * sheet[11] + sz * sheet[12] > 0.0:
                continue
            ux, uy, uz = sx / dist, sy / dist, sz / dist
            den = ux * sheet[13] + uy * sheet[14] + uz * sheet[15]
            tm = dist
            if den != 0.0:
                tmm = -(px * sheet[13] + py * sheet[14] + pz * sheet[15] + sheet[16]) / den
                if 0.0 < tmm < dist:
                    tm = tmm
            if is_blocked(ptype, R, T, prm, px, py, pz, ux, uy, uz, tm - EPS):
                continue
            val = scale * cos_i / dist * math.exp(-0.5 * (delta / sigma) ** 2)
            if speckle > 0.0:
                f = 1.0 + speckle * z[k % nz]
                k += 1
                val *= f if f > 0.0 else 0.0
            o = pobj[p]
            if textured[o]:
                if m < tex_val.shape[0]:
                    tex_rc[m, 0], tex_rc[m, 1] = r, c
                    tex_p[m, 0], tex_p[m, 1], tex_p[m, 2] = px, py, pz
                    tex_val[m] = val
                    tex_obj[m] = o
                    m += 1
            else:
                band[r - b0, c] = val * albedo[o]
    return m


@njit(cache=True)
def sheet_segments(center, e1, e2, half, normal, fobj, two, plane, hs, viewer, source,
                   max_length, A_out, B_out, N_out, obj_out, two_out):
    """Segments where the plane cuts each rectangular face (see Scene.sheet_segments)."""
    Nx, Ny, Nz, e = plane[0], plane[1], plane[2], plane[3]
    m = 0
    for f in range(center.shape[0]):
        nfx, nfy, nfz = normal[f, 0], normal[f, 1], normal[f, 2]
        fv = (nfx * (viewer[0] - center[f, 0]) + nfy * (viewer[1] - center[f, 1])
              + nfz * (viewer[2] - center[f, 2]))
        fs = (nfx * (source[0] - center[f, 0]) + nfy * (source[1] - center[f, 1])
              + nfz * (source[2] - center[f, 2]))
        if two[f]:
            if fv * fs <= 0.0:
                continue
        elif fv <= 0.0 or fs <= 0.0:
            continue
        alpha = e1[f, 0] * Nx + e1[f, 1] * Ny + e1[f, 2] * Nz
        beta = e2[f, 0] * Nx + e2[f, 1] * Ny + e2[f, 2] * Nz
        ab2 = alpha * alpha + beta * beta
        if ab2 <= 1e-24:
            continue
        gamma = -(center[f, 0] * Nx + center[f, 1] * Ny + center[f, 2] * Nz + e)
        a0 = gamma * alpha / ab2
        b0 = gamma * beta / ab2
        sab = math.sqrt(ab2)
        da, db = -beta / sab, alpha / sab
        lo, hi = -max_length, max_length
        # |a0 + s da| <= half0, |b0 + s db| <= half1, then the half-spaces
        for g0, g1 in ((half[f, 0] - a0, -da), (half[f, 0] + a0, da),
                       (half[f, 1] - b0, -db), (half[f, 1] + b0, db)):
            if g1 > 0:
                lo = max(lo, -g0 / g1)
            elif g1 < 0:
                hi = min(hi, -g0 / g1)
            elif g0 < 0:
                hi = -np.inf
        px = center[f, 0] + a0 * e1[f, 0] + b0 * e2[f, 0]
        py = center[f, 1] + a0 * e1[f, 1] + b0 * e2[f, 1]
        pz = center[f, 2] + a0 * e1[f, 2] + b0 * e2[f, 2]
        Dx = da * e1[f, 0] + db * e2[f, 0]
        Dy = da * e1[f, 1] + db * e2[f, 1]
        Dz = da * e1[f, 2] + db * e2[f, 2]
        for k in range(hs.shape[0]):
            qx, qy, qz = hs[k, 0, 0], hs[k, 0, 1], hs[k, 0, 2]
            wx, wy, wz = hs[k, 1, 0], hs[k, 1, 1], hs[k, 1, 2]
            g0 = (px - qx) * wx + (py - qy) * wy + (pz - qz) * wz
            g1 = Dx * wx + Dy * wy + Dz * wz
            if g1 > 0:
                lo = max(lo, -g0 / g1)
            elif g1 < 0:
                hi = min(hi, -g0 / g1)
            elif g0 < 0:
                hi = -np.inf
        if not (hi > lo) or not math.isfinite(lo) or not math.isfinite(hi):
            continue
        A_out[m, 0], A_out[m, 1], A_out[m, 2] = px + lo * Dx, py + lo * Dy, pz + lo * Dz
        B_out[m, 0], B_out[m, 1], B_out[m, 2] = px + hi * Dx, py + hi * Dy, pz + hi * Dz
        N_out[m, 0], N_out[m, 1], N_out[m, 2] = nfx, nfy, nfz
        obj_out[m] = fobj[f]
        two_out[m] = two[f]
        m += 1
    return m
