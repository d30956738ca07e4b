"""Compiled (numba) inner loops of the ray tracer and the sensor model.

The scene is packed into flat arrays (see :meth:`Scene.packed`): per primitive a type
(0 box ``lo, hi``; 1 sphere ``centre, radius``; 2 rectangle ``hx, hy`` in the plane z = 0,
two-sided), the owning object, the pose ``W_R_O`` / ``W_t_O`` and eight parameters (six
for the shape, then 1.0 where ``W_R_O`` is the identity). These
kernels compute exactly what the numpy reference code in ``scene.py`` computes (the tests
compare them); they exist because a laser frame needs ~15 000 traced rays in a few ms.
"""

from __future__ import annotations

import cmath
import math

import numpy as np
from numba import njit

EPS = 1e-7
BOX, SPHERE, RECT = 0, 1, 2


@njit(cache=True)
def _local(R, T, prm, p, x, y, z):
    qx, qy, qz = x - T[p, 0], y - T[p, 1], z - T[p, 2]
    if prm[p, 6] != 0.0:  # identity rotation
        return qx, qy, qz
    return (R[p, 0, 0] * qx + R[p, 1, 0] * qy + R[p, 2, 0] * qz,
            R[p, 0, 1] * qx + R[p, 1, 1] * qy + R[p, 2, 1] * qz,
            R[p, 0, 2] * qx + R[p, 1, 2] * qy + R[p, 2, 2] * qz)


@njit(cache=True)
def _local_dir(R, prm, p, x, y, z):
    if prm[p, 6] != 0.0:
        return x, y, z
    return (R[p, 0, 0] * x + R[p, 1, 0] * y + R[p, 2, 0] * z,
            R[p, 0, 1] * x + R[p, 1, 1] * y + R[p, 2, 1] * z,
            R[p, 0, 2] * x + R[p, 1, 2] * y + R[p, 2, 2] * z)


@njit(cache=True)
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


@njit(cache=True)
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


@njit(cache=True)
def _inv(x):
    return 1.0 / x if x != 0.0 else 0.0


@njit(cache=True)
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
def trace_blocked(ptype, R, T, prm, o, d, tmax, out):
    for i in range(o.shape[0]):
        out[i] = is_blocked(ptype, R, T, prm, o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1],
                            d[i, 2], tmax[i])


@njit(cache=True, inline='always')
def _camera_ray(cam, x, y):
    """Pixel ray (x, y, 1) in C traced off the two G1 mirrors, returned in W.

    ``cam`` packs: [0:9] G_R_C, [9:12] camera centre in G, [12:15] n1, [15] c1,
    [16:19] n2, [19] c2, [20:29] W_R_G, [29:32] W_t_G, [32:35] virtual camera centre in W.
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


@njit(cache=True, fastmath=True)
def _quantise_row(e, z, zoff, noisy, fw, r2, sh, ig, bl, tp, out_row):
    zero = np.float32(0.0)
    if noisy:
        for c in range(e.shape[0]):
            v = min(e[c], fw)
            v = v + np.sqrt(r2 + sh * max(v, zero)) * z[zoff + c]
            out_row[c] = min(max(v * ig + bl, zero), tp)
    else:
        for c in range(e.shape[0]):
            v = min(e[c], fw)
            out_row[c] = min(max(v * ig + bl, zero), tp)


@njit(cache=True, fastmath=True)
def sensor(bg, band, b0, z, full_well, shot, read2, inv_gain, black, top, out):
    """Compose the image in electrons and convert it to DN.

    Electrons = background ``bg`` (H, W) (or none when empty) + ``band`` on rows b0..;
    then clip at the full well, add shot/read noise with the N(0, 1) draws ``z`` (empty:
    no noise) and quantise with rounding to [0, top] in ``out``'s integer type (uint8 or
    uint16).
    """
    h, w = out.shape
    fw = np.float32(full_well)
    r2 = np.float32(read2)
    ig = np.float32(inv_gain)
    bl = np.float32(black + 0.5)
    tp = np.float32(top)
    sh = np.float32(1.0 if shot else 0.0)
    noisy = z.shape[0] > 0
    has_bg = bg.shape[0] > 0
    nb = band.shape[0]
    e = np.zeros(w, np.float32)
    for r in range(h):
        rb = r - b0
        in_band = 0 <= rb < nb
        if has_bg:
            for c in range(w):
                e[c] = bg[r, c]
            if in_band:
                for c in range(w):
                    e[c] += band[rb, c]
        elif in_band:
            for c in range(w):
                e[c] = band[rb, c]
        elif rb == nb or r == 0:
            e[:] = 0.0
        _quantise_row(e, z, r * w, noisy, fw, r2, sh, ig, bl, tp, out[r])


@njit(cache=True)
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


@njit(cache=True, inline='always')
def _until_plane(px, py, pz, ux, uy, uz, dist, nx, ny, nz, c):
    """Length of the segment p + t u, 0 < t < dist, up to where it meets the plane
    n . x + c = 0; ``dist`` when it does not."""
    den = ux * nx + uy * ny + uz * nz
    tm = dist
    if den != 0.0:
        t = -(px * nx + py * ny + pz * nz + c) / den
        if 0.0 < t < dist:
            tm = t
    return tm


@njit(cache=True, inline='always')
def _inside_fan(sheet, sx, sy, sz):
    """The offset s from a point to the fan's apex is on the inner side of both fan edges
    (``sheet`` layout of :func:`laser_windows`)."""
    if sx * sheet[7] + sy * sheet[8] + sz * sheet[9] > 0.0:
        return False
    if sx * sheet[10] + sy * sheet[11] + sz * sheet[12] > 0.0:
        return False
    return True


@njit(cache=True)
def _free(ptype, R, T, prm, px, py, pz, tx, ty, tz, mirror):
    """Nothing blocks the segment from p towards t, up to the mirror plane."""
    dx, dy, dz = tx - px, ty - py, tz - pz
    dist = math.sqrt(dx * dx + dy * dy + dz * dz)
    dx, dy, dz = dx / dist, dy / dist, dz / dist
    tm = _until_plane(px, py, pz, dx, dy, dz, dist, mirror[0], mirror[1], mirror[2],
                      mirror[3])
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
    if not _inside_fan(sheet, sx, sy, sz):
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


@njit(cache=True, inline='always')
def _clip_interval(lo, hi, g0, g1):
    """[lo, hi] cut to the parameters s with g0 + s g1 >= 0 (empty: hi = -inf)."""
    if g1 > 0:
        lo = max(lo, -g0 / g1)
    elif g1 < 0:
        hi = min(hi, -g0 / g1)
    elif g0 < 0:
        hi = -np.inf
    return lo, hi


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
            lo, hi = _clip_interval(lo, hi, g0, g1)
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
            lo, hi = _clip_interval(lo, hi, g0, g1)
        if not (hi > lo) or not math.isfinite(lo) or not math.isfinite(hi):
            continue
        A_out[m, 0], A_out[m, 1], A_out[m, 2] = px + lo * Dx, py + lo * Dy, pz + lo * Dz
        B_out[m, 0], B_out[m, 1], B_out[m, 2] = px + hi * Dx, py + hi * Dy, pz + hi * Dz
        N_out[m, 0], N_out[m, 1], N_out[m, 2] = nfx, nfy, nfz
        obj_out[m] = fobj[f]
        two_out[m] = two[f]
        m += 1
    return m


TEX_NONE, TEX_CHECKER, TEX_CIRCLES = 0, 1, 2


@njit(cache=True, inline='always')
def _checker_axis(t, n, s, w):
    k = math.floor(t / s)
    k = min(max(k, 0.0), n - 1.0)
    sign = 1.0 - 2.0 * (k % 2.0)
    lo_edge = t - k * s if k > 0 else np.inf
    hi_edge = (k + 1.0) * s - t if k < n - 1 else np.inf
    wave = sign * min(1.0, min(lo_edge, hi_edge) / (0.5 * w))
    inside = min(max(0.5 + min(t, n * s - t) / w, 0.0), 1.0)
    return wave, inside


@njit(cache=True, inline='always')
def albedo_at(tex, oR, oT, albedo, o, px, py, pz, foot):
    """Albedo of object o at world point p seen with a pixel footprint ``foot`` [m].

    ``tex[o]`` packs the texture: [0] kind (TEX_*), then for a checkerboard nx, ny,
    square size, dark albedo; for a circle board nx, ny, pitch, sub-pattern, small and big
    diameter, circle albedo. Same maths as SceneObject.albedo_local.
    """
    a = albedo[o]
    kind = tex[o, 0]
    if kind == TEX_NONE:
        return a
    qx, qy, qz = px - oT[o, 0], py - oT[o, 1], pz - oT[o, 2]
    lx = oR[o, 0, 0] * qx + oR[o, 1, 0] * qy + oR[o, 2, 0] * qz
    ly = oR[o, 0, 1] * qx + oR[o, 1, 1] * qy + oR[o, 2, 1] * qz
    lz = oR[o, 0, 2] * qx + oR[o, 1, 2] * qy + oR[o, 2, 2] * qz
    if abs(lz) >= 1e-6:
        return a
    w = max(foot, 1e-9)
    if kind == TEX_CHECKER:
        nx, ny, s = tex[o, 1], tex[o, 2], tex[o, 3]
        wx, ix = _checker_axis(lx + 0.5 * nx * s, nx, s, w)
        wy, iy = _checker_axis(ly + 0.5 * ny * s, ny, s, w)
        dark = ix * iy * (0.5 + 0.5 * wx * wy)
        return a + (tex[o, 4] - a) * dark
    nx, ny, pitch, sub = tex[o, 1], tex[o, 2], tex[o, 3], tex[o, 4]
    i = min(max(np.rint(lx / pitch + 0.5 * (nx - 1.0)), 0.0), nx - 1.0)
    j = min(max(np.rint(ly / pitch + 0.5 * (ny - 1.0)), 0.0), ny - 1.0)
    cx = (i - 0.5 * (nx - 1.0)) * pitch
    cy = (j - 0.5 * (ny - 1.0)) * pitch
    c = math.floor(sub / 2.0)
    big = (i % sub == c) and (j % sub == c)
    r = 0.5 * (tex[o, 6] if big else tex[o, 5])
    sd = r - math.sqrt((lx - cx) ** 2 + (ly - cy) ** 2)
    cover = min(max(0.5 + sd / w, 0.0), 1.0)
    return a + (tex[o, 7] - a) * cover


@njit(cache=True)
def ambient_pixels(ptype, R, T, prm, pobj, cam, xy, foot_scale, center, albedo, tex, oR, oT,
                   scale, light, directional, out):
    """Room-light signal of pixels: ``scale * albedo * ((1 - f) + f max(0, n . light))``.

    ``xy`` (n, 2) are undistorted normalised pixel coordinates; ``foot_scale`` is the pixel
    footprint angle [rad] used to anti-alias textures.
    """
    n = xy.shape[0]
    ox, oy, oz, dx, dy, dz, tb, pb, ab = _trace_closest(
        ptype, R, T, prm, cam, np.ascontiguousarray(xy[:, 0]), np.ascontiguousarray(xy[:, 1]))
    for i in range(n):
        p = pb[i]
        if p < 0:
            out[i] = 0.0
            continue
        t = tb[i]
        px, py, pz = ox[i] + t * dx[i], oy[i] + t * dy[i], oz[i] + t * dz[i]
        nx, ny, nz = _hit_normal(ptype, R, T, prm, p, ab[i], px, py, pz, dx[i], dy[i], dz[i])
        o = pobj[p]
        a = albedo[o]
        if tex[o, 0] != TEX_NONE:
            vx, vy, vz = px - center[0], py - center[1], pz - center[2]
            rng = math.sqrt(vx * vx + vy * vy + vz * vz)
            cos_v = abs(nx * vx + ny * vy + nz * vz) / rng
            foot = rng * foot_scale / max(cos_v, 0.2)
            a = albedo_at(tex, oR, oT, albedo, o, px, py, pz, foot)
        lam = nx * light[0] + ny * light[1] + nz * light[2]
        out[i] = scale * a * ((1.0 - directional) + directional * max(lam, 0.0))

# ---------------------------------------------------------------------------------------
# Structure-of-arrays passes: one primitive at a time over all rays (vectorisable loops).
# IEEE inf/NaN semantics are kept (no 'nnan'/'ninf' fast-math flags).
# The helpers of these passes are inline='always': inlined into the Numba IR of the
# kernels, they are compiled with the kernels' fast-math flags, exactly as if written out.
_FM = {'nsz', 'arcp', 'contract', 'afn', 'reassoc'}
#: ``ctr`` of :func:`_soa_local_ray` for no shift (x - 0.0 is x exactly; folded away).
_NO_SHIFT = (0.0, 0.0, 0.0)


@njit(cache=True, fastmath=_FM)
def soa_camera_rays(cam, xs, ys, ox, oy, oz, dx, dy, dz):
    """Pixel rays (x, y, 1) in C traced off the two G1 mirrors, into arrays (see
    :func:`_camera_ray` for ``cam``)."""
    g00, g01, g02, g10, g11, g12, g20, g21, g22 = (cam[0], cam[1], cam[2], cam[3], cam[4],
                                                   cam[5], cam[6], cam[7], cam[8])
    cx, cy, cz = cam[9], cam[10], cam[11]
    m1x, m1y, m1z, c1 = cam[12], cam[13], cam[14], cam[15]
    m2x, m2y, m2z, c2 = cam[16], cam[17], cam[18], cam[19]
    w00, w01, w02, w10, w11, w12, w20, w21, w22 = (cam[20], cam[21], cam[22], cam[23],
                                                   cam[24], cam[25], cam[26], cam[27], cam[28])
    wx, wy, wz = cam[29], cam[30], cam[31]
    o1 = cx * m1x + cy * m1y + cz * m1z
    for i in range(xs.shape[0]):
        x, y = xs[i], ys[i]
        inv = 1.0 / math.sqrt(x * x + y * y + 1.0)
        ax = (g00 * x + g01 * y + g02) * inv
        ay = (g10 * x + g11 * y + g12) * inv
        az = (g20 * x + g21 * y + g22) * inv
        dn = ax * m1x + ay * m1y + az * m1z
        t = (c1 - o1) / dn
        px, py, pz = cx + t * ax, cy + t * ay, cz + t * az
        ax, ay, az = ax - 2.0 * dn * m1x, ay - 2.0 * dn * m1y, az - 2.0 * dn * m1z
        dn = ax * m2x + ay * m2y + az * m2z
        t = (c2 - (px * m2x + py * m2y + pz * m2z)) / dn
        px, py, pz = px + t * ax, py + t * ay, pz + t * az
        ax, ay, az = ax - 2.0 * dn * m2x, ay - 2.0 * dn * m2y, az - 2.0 * dn * m2z
        ox[i] = w00 * px + w01 * py + w02 * pz + wx
        oy[i] = w10 * px + w11 * py + w12 * pz + wy
        oz[i] = w20 * px + w21 * py + w22 * pz + wz
        dx[i] = w00 * ax + w01 * ay + w02 * az
        dy[i] = w10 * ax + w11 * ay + w12 * az
        dz[i] = w20 * ax + w21 * ay + w22 * az


@njit(cache=True, inline='always')
def _soa_frame(R, T, p):
    """Pose of primitive p for the SoA passes: ``W_R_O`` as a row-major 9-tuple and
    ``W_t_O`` as a 3-tuple (hoisted out of the ray loops)."""
    rot = (R[p, 0, 0], R[p, 0, 1], R[p, 0, 2], R[p, 1, 0], R[p, 1, 1], R[p, 1, 2],
           R[p, 2, 0], R[p, 2, 1], R[p, 2, 2])
    return rot, (T[p, 0], T[p, 1], T[p, 2])


@njit(cache=True, inline='always')
def _soa_local_ray(rot, tr, ctr, ox, oy, oz, dx, dy, dz, i):
    """Ray i of the arrays (o, d) in the primitive's frame (see :func:`_soa_frame`),
    origin taken relative to the local point ``ctr``: (lx, ly, lz, ex, ey, ez) =
    (R^T (o - t) - ctr, R^T d)."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = rot
    tx, ty, tz = tr
    cx, cy, cz = ctr
    qx, qy, qz = ox[i] - tx, oy[i] - ty, oz[i] - tz
    lx = r00 * qx + r10 * qy + r20 * qz - cx
    ly = r01 * qx + r11 * qy + r21 * qz - cy
    lz = r02 * qx + r12 * qy + r22 * qz - cz
    ex = r00 * dx[i] + r10 * dy[i] + r20 * dz[i]
    ey = r01 * dx[i] + r11 * dy[i] + r21 * dz[i]
    ez = r02 * dx[i] + r12 * dy[i] + r22 * dz[i]
    return lx, ly, lz, ex, ey, ez


@njit(cache=True, inline='always')
def _soa_slab_box(lx, ly, lz, ex, ey, ez, a0, a1, a2, b0, b1, b2):
    """Slab test of the local ray l + t e with the box [a, b] (no component of e may be
    zero): (t_in, t_out, axis of the entry face)."""
    ix, iy, iz = 1.0 / ex, 1.0 / ey, 1.0 / ez
    t1, t2 = (a0 - lx) * ix, (b0 - lx) * ix
    nx_, fx_ = min(t1, t2), max(t1, t2)
    t1, t2 = (a1 - ly) * iy, (b1 - ly) * iy
    ny_, fy_ = min(t1, t2), max(t1, t2)
    t1, t2 = (a2 - lz) * iz, (b2 - lz) * iz
    nz_, fz_ = min(t1, t2), max(t1, t2)
    tin = max(nx_, max(ny_, nz_))
    tout = min(fx_, min(fy_, fz_))
    ax = 0 if (nx_ >= ny_ and nx_ >= nz_) else (1 if ny_ >= nz_ else 2)
    return tin, tout, ax


@njit(cache=True, fastmath=_FM)
def soa_closest(ptype, R, T, prm, ox, oy, oz, dx, dy, dz, tb, pb, ab):
    """Closest hits of rays (o, d) given as coordinate arrays; writes t (inf: none),
    primitive (-1: none) and, for boxes, the slab axis of the entry face."""
    n = ox.shape[0]
    for i in range(n):
        tb[i] = np.inf
        pb[i] = -1
        ab[i] = 0
    for p in range(ptype.shape[0]):
        kind = ptype[p]
        rot, tr = _soa_frame(R, T, p)
        a0, a1, a2 = prm[p, 0], prm[p, 1], prm[p, 2]
        b0, b1, b2 = prm[p, 3], prm[p, 4], prm[p, 5]
        if kind == BOX:
            for i in range(n):
                lx, ly, lz, ex, ey, ez = _soa_local_ray(rot, tr, _NO_SHIFT, ox, oy, oz, dx, dy,
                                                        dz, i)
                tin, tout, ax = _soa_slab_box(lx, ly, lz, ex, ey, ez, a0, a1, a2, b0, b1, b2)
                hit = (tin <= tout) and (tin > EPS) and (tin < tb[i])
                tb[i] = tin if hit else tb[i]
                pb[i] = p if hit else pb[i]
                ab[i] = ax if hit else ab[i]
        elif kind == SPHERE:
            cx, cy, cz, r = a0, a1, a2, b0
            for i in range(n):
                lx, ly, lz, ex, ey, ez = _soa_local_ray(rot, tr, (cx, cy, cz), ox, oy, oz, dx,
                                                        dy, dz, i)
                b = lx * ex + ly * ey + lz * ez
                disc = b * b - (lx * lx + ly * ly + lz * lz - r * r)
                t = -b - math.sqrt(max(disc, 0.0))
                hit = (disc >= 0.0) and (t > EPS) and (t < tb[i])
                tb[i] = t if hit else tb[i]
                pb[i] = p if hit else pb[i]
        else:
            for i in range(n):
                lx, ly, lz, ex, ey, ez = _soa_local_ray(rot, tr, _NO_SHIFT, ox, oy, oz, dx, dy,
                                                        dz, i)
                t = -lz / ez
                hit = ((t > EPS) and (t < tb[i]) and (abs(lx + t * ex) <= a0)
                       and (abs(ly + t * ey) <= a1))
                tb[i] = t if hit else tb[i]
                pb[i] = p if hit else pb[i]


@njit(cache=True, fastmath=_FM)
def soa_blocked(ptype, R, T, prm, ox, oy, oz, dx, dy, dz, tmax, out):
    """Segments o + t d, 0 < t < tmax, blocked by a surface or a solid's interior."""
    n = ox.shape[0]
    for i in range(n):
        out[i] = False
    for p in range(ptype.shape[0]):
        kind = ptype[p]
        rot, tr = _soa_frame(R, T, p)
        a0, a1, a2 = prm[p, 0], prm[p, 1], prm[p, 2]
        b0, b1, b2 = prm[p, 3], prm[p, 4], prm[p, 5]
        for i in range(n):
            lx, ly, lz, ex, ey, ez = _soa_local_ray(rot, tr, _NO_SHIFT, ox, oy, oz, dx, dy, dz, i)
            if kind == BOX:
                tin, tout, _ = _soa_slab_box(lx, ly, lz, ex, ey, ez, a0, a1, a2, b0, b1, b2)
                hit = (tin <= tout) and (tout > EPS) and (tin < tmax[i])
            elif kind == SPHERE:
                qx, qy, qz = lx - a0, ly - a1, lz - a2
                b = qx * ex + qy * ey + qz * ez
                disc = b * b - (qx * qx + qy * qy + qz * qz - b0 * b0)
                root = math.sqrt(max(disc, 0.0))
                hit = (disc > 0.0) and (-b + root > EPS) and (-b - root < tmax[i])
            else:
                t = -lz / ez
                hit = ((t > EPS) and (t < tmax[i]) and (abs(lx + t * ex) <= a0)
                       and (abs(ly + t * ey) <= a1))
            out[i] = out[i] or hit


@njit(cache=True, inline='always')
def _ray_arrays(n):
    """Uninitialised coordinate arrays (x, y, z of origins, then of directions) of n rays."""
    return np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty(n)


@njit(cache=True, inline='always')
def _trace_closest(ptype, R, T, prm, cam, xs, ys):
    """Pixel rays (x, y, 1) off the G1 mirrors (:func:`soa_camera_rays`) and their closest
    hits (:func:`soa_closest`): (ox, oy, oz, dx, dy, dz, t, primitive, box axis), each (n,)."""
    n = xs.shape[0]
    ox, oy, oz, dx, dy, dz = _ray_arrays(n)
    soa_camera_rays(cam, xs, ys, ox, oy, oz, dx, dy, dz)
    tb = np.empty(n)
    pb = np.empty(n, np.int64)
    ab = np.empty(n, np.int64)
    soa_closest(ptype, R, T, prm, ox, oy, oz, dx, dy, dz, tb, pb, ab)
    return ox, oy, oz, dx, dy, dz, tb, pb, ab


@njit(cache=True, inline='always')
def _hit_normal(ptype, R, T, prm, p, ax, px, py, pz, dx, dy, dz):
    """World normal, facing the ray, of primitive p at the hit point p (box: entry axis)."""
    kind = ptype[p]
    if kind == BOX:
        e = R[p, 0, ax] * dx + R[p, 1, ax] * dy + R[p, 2, ax] * dz
        s = -1.0 if e > 0 else 1.0
        return s * R[p, 0, ax], s * R[p, 1, ax], s * R[p, 2, ax]
    if kind == SPHERE:
        cx = R[p, 0, 0] * prm[p, 0] + R[p, 0, 1] * prm[p, 1] + R[p, 0, 2] * prm[p, 2] + T[p, 0]
        cy = R[p, 1, 0] * prm[p, 0] + R[p, 1, 1] * prm[p, 1] + R[p, 1, 2] * prm[p, 2] + T[p, 1]
        cz = R[p, 2, 0] * prm[p, 0] + R[p, 2, 1] * prm[p, 1] + R[p, 2, 2] * prm[p, 2] + T[p, 2]
        r = prm[p, 3]
        return (px - cx) / r, (py - cy) / r, (pz - cz) / r
    e = R[p, 0, 2] * dx + R[p, 1, 2] * dy + R[p, 2, 2] * dz
    s = -1.0 if e > 0 else 1.0
    return s * R[p, 0, 2], s * R[p, 1, 2], s * R[p, 2, 2]


@njit(cache=True, inline='always')
def _window_pixels(grid, cols, v0, half):
    """Pixels of the row windows (see :func:`laser_windows`), clipped to the image: their
    rows and columns, and their normalised coordinates (x, y) from ``grid``, each (n,)."""
    H = grid.shape[0]
    n = 0
    for j in range(cols.shape[0]):
        n += max(min(v0[j] + half[j], H - 1) - max(v0[j] - half[j], 0) + 1, 0)
    rows = np.empty(n, np.int64)
    cc = np.empty(n, np.int64)
    k = 0
    for j in range(cols.shape[0]):
        for r in range(max(v0[j] - half[j], 0), min(v0[j] + half[j], H - 1) + 1):
            rows[k] = r
            cc[k] = cols[j]
            k += 1
    xs = np.empty(n)
    ys = np.empty(n)
    for i in range(n):
        xs[i] = grid[rows[i], cc[i], 0]
        ys[i] = grid[rows[i], cc[i], 1]
    return rows, cc, xs, ys


@njit(cache=True, inline='always')
def _fresnel(cos_i, n, k):
    """Unpolarised Fresnel reflectance from air onto index n + ik (materials.fresnel)."""
    c = min(max(cos_i, 0.0), 1.0)
    eta = complex(n, k)
    ct = cmath.sqrt(eta * eta - (1.0 - c * c)) / eta
    rs = (c - eta * ct) / (c + eta * ct)
    rp = (eta * c - ct) / (eta * c + ct)
    return 0.5 * (abs(rs) ** 2 + abs(rp) ** 2)


@njit(cache=True, inline='always')
def _smith_g1(cv, a):
    t2 = (1.0 - cv * cv) / (cv * cv)
    return 2.0 / (1.0 + math.sqrt(1.0 + a * a * t2))


@njit(cache=True, inline='always')
def specular_term(mat, nx, ny, nz, lx, ly, lz, vx, vy, vz):
    """pi times the GGX Cook-Torrance BRDF (materials.specular_reflectance) of the packed
    material row ``mat`` for unit normal n, light direction l and view direction v."""
    if mat[6] <= 0.0:
        return 0.0
    ci = nx * lx + ny * ly + nz * lz
    co = nx * vx + ny * vy + nz * vz
    if ci <= 0.0 or co <= 0.0:
        return 0.0
    hx, hy, hz = lx + vx, ly + vy, lz + vz
    hn = math.sqrt(hx * hx + hy * hy + hz * hz)
    hx, hy, hz = hx / hn, hy / hn, hz / hn
    a = mat[1]
    ch = nx * hx + ny * hy + nz * hz
    if ch <= 0.0:
        return 0.0
    a2 = a * a
    den = ch * ch * (a2 - 1.0) + 1.0
    d = a2 / (math.pi * den * den)
    f = _fresnel(lx * hx + ly * hy + lz * hz, mat[2], mat[3])
    g = _smith_g1(ci, a) * _smith_g1(co, a)
    return math.pi * d * f * g / (4.0 * ci * co)


@njit(cache=True, inline='always')
def _subsurface(mat, sigma, nx, ny, nz, ux, uy, uz, sheet):
    """(share, sigma, shift) of a material's subsurface glow (materials.subsurface_shift):
    u is the unit direction from the surface to the light."""
    ell = mat[4]
    if ell <= 0.0 or mat[5] <= 0.0:
        return 0.0, sigma, 0.0
    dn = -(ux * nx + uy * ny + uz * nz)  # incident d = -u
    tx, ty, tz = -ux - dn * nx, -uy - dn * ny, -uz - dn * nz
    shift = ell / mat[2] * (tx * sheet[0] + ty * sheet[1] + tz * sheet[2])
    return mat[5], math.sqrt(sigma * sigma + ell * ell), shift


@njit(cache=True, inline='always')
def reach_of(mat, sigma):
    """Distance from the sheet's centre plane beyond which a material's stripe is dark."""
    if mat[4] > 0.0 and mat[5] > 0.0:
        return 5.0 * math.sqrt(sigma * sigma + mat[4] * mat[4]) + mat[4]
    return 5.0 * sigma


@njit(cache=True, inline='always')
def _lit_candidates(ptype, R, T, prm, pobj, mats, ox, oy, oz, dx, dy, dz, tb, pb, ab, sheet,
                    sigma, scale):
    """Traced pixels whose hit point the laser may reach (within reach of the sheet,
    facing the apex, inside the fan), with their shadow segments towards the last G2
    mirror. Returns (m, pixel index, segment start x, y, z, unit direction x, y, z, length,
    stripe value before speckle and albedo, normal x, y, z); the arrays are valid up to m."""
    n = ox.shape[0]
    m = 0
    idx = np.empty(n, np.int64)
    sx_, sy_, sz_, ux_, uy_, uz_ = _ray_arrays(n)
    nx_, ny_, nz_, tm_, val_, _ = _ray_arrays(n)
    for i in range(n):
        p = pb[i]
        if p < 0:
            continue
        t = tb[i]
        mat = mats[pobj[p]]
        px, py, pz = ox[i] + t * dx[i], oy[i] + t * dy[i], oz[i] + t * dz[i]
        delta = sheet[0] * px + sheet[1] * py + sheet[2] * pz + sheet[3]
        if abs(delta) >= reach_of(mat, sigma):
            continue
        nx, ny, nzz = _hit_normal(ptype, R, T, prm, p, ab[i], px, py, pz, dx[i], dy[i], dz[i])
        sx, sy, sz = sheet[4] - px, sheet[5] - py, sheet[6] - pz
        dist = math.sqrt(sx * sx + sy * sy + sz * sz)
        cos_i = (nx * sx + ny * sy + nzz * sz) / dist
        if cos_i <= 0.0:
            continue
        if not _inside_fan(sheet, sx, sy, sz):
            continue
        ux, uy, uz = sx / dist, sy / dist, sz / dist
        tm = _until_plane(px, py, pz, ux, uy, uz, dist, sheet[13], sheet[14], sheet[15],
                          sheet[16])
        idx[m] = i
        sx_[m], sy_[m], sz_[m] = px, py, pz
        ux_[m], uy_[m], uz_[m] = ux, uy, uz
        nx_[m], ny_[m], nz_[m] = nx, ny, nzz
        tm_[m] = tm - EPS
        share, sig_s, shift = _subsurface(mat, sigma, nx, ny, nzz, ux, uy, uz, sheet)
        if share > 0.0:
            val_[m] = scale * cos_i / dist * (
                (1.0 - share) * math.exp(-0.5 * (delta / sigma) ** 2)
                + share * sigma / sig_s * math.exp(-0.5 * ((delta - shift) / sig_s) ** 2))
        else:
            val_[m] = scale * cos_i / dist * math.exp(-0.5 * (delta / sigma) ** 2)
        m += 1
    return m, idx, sx_, sy_, sz_, ux_, uy_, uz_, tm_, val_, nx_, ny_, nz_


@njit(cache=True, inline='always')
def _draw_lit(pobj, albedo, tex, oR, oT, mats, cam, pb, rows, cc, idx, px_, py_, pz_, ux_,
              uy_, uz_, nx_, ny_, nz_, val_, blocked, speckle, z, zoff, band, b0, foot_scale):
    """Write the unblocked candidates into ``band``: value times the speckle factor (draws
    from ``z`` cyclically from ``zoff``) times the albedo at the point, plus the material's
    specular term towards the camera. Returns the count."""
    nz_draws = z.shape[0]
    kz = zoff
    drawn = 0
    for q in range(blocked.shape[0]):
        if blocked[q]:
            continue
        i = idx[q]
        val = val_[q]
        if speckle > 0.0:
            f = 1.0 + speckle * z[kz % nz_draws]
            kz += 1
            val *= f if f > 0.0 else 0.0
        o = pobj[pb[i]]
        a = albedo[o]
        if tex[o, 0] != TEX_NONE:
            px, py, pz = px_[q], py_[q], pz_[q]
            vx, vy, vz = px - cam[32], py - cam[33], pz - cam[34]
            foot = math.sqrt(vx * vx + vy * vy + vz * vz) * foot_scale
            a = albedo_at(tex, oR, oT, albedo, o, px, py, pz, foot)
        if mats[o, 6] > 0.0:
            vx, vy, vz = cam[32] - px_[q], cam[33] - py_[q], cam[34] - pz_[q]
            vn = math.sqrt(vx * vx + vy * vy + vz * vz)
            a = a + specular_term(mats[o], nx_[q], ny_[q], nz_[q], ux_[q], uy_[q], uz_[q],
                                  vx / vn, vy / vn, vz / vn)
        band[rows[i] - b0, cc[i]] = val * a
        drawn += 1
    return drawn


@njit(cache=True)
def laser_windows(ptype, R, T, prm, pobj, albedo, tex, oR, oT, mats, cam, grid, cols, v0, half,
                  sheet, sigma, scale, speckle, z, zoff, band, b0, foot_scale):
    """Render the laser stripe into ``band`` (rows b0.. of the image), window by window.

    Window j covers rows v0[j] - half[j] .. v0[j] + half[j] of column cols[j]. A pixel's
    ray is traced off the G1 mirrors into the scene; its value is
    ``scale * albedo * cos(incidence) / distance * exp(-delta^2 / 2 sigma^2)`` times the
    speckle factor ``max(0, 1 + speckle * z)`` where the laser reaches the hit point (it
    faces the fan's apex, lies inside the fan, and the segment to the last G2 mirror is
    free), else the pixel is left alone. ``sheet`` packs: [0:4] centre plane, [4:7]
    virtual apex, [7:10] and [10:13] inward edge normals, [13:17] last G2 mirror plane.
    Objects with a material (``mats``, materials.pack) add their specular term to the
    albedo and, if translucent, their subsurface glow to the profile.
    Returns the number of pixels drawn.
    """
    rows, cc, xs, ys = _window_pixels(grid, cols, v0, half)
    ox, oy, oz, dx, dy, dz, tb, pb, ab = _trace_closest(ptype, R, T, prm, cam, xs, ys)
    m, idx, sx_, sy_, sz_, ux_, uy_, uz_, tm_, val_, nx_, ny_, nz_ = _lit_candidates(
        ptype, R, T, prm, pobj, mats, ox, oy, oz, dx, dy, dz, tb, pb, ab, sheet, sigma, scale)
    blocked = np.empty(m, np.bool_)
    soa_blocked(ptype, R, T, prm, sx_[:m], sy_[:m], sz_[:m], ux_[:m], uy_[:m], uz_[:m],
                tm_[:m], blocked)
    return _draw_lit(pobj, albedo, tex, oR, oT, mats, cam, pb, rows, cc, idx, sx_, sy_, sz_,
                     ux_, uy_, uz_, nx_, ny_, nz_, val_, blocked, speckle, z, zoff, band, b0,
                     foot_scale)


@njit(cache=True)
def reflection_windows(ptype, R, T, prm, pobj, albedo, mats, cam, grid, cols, v0, half, vsheet,
                       face, fmat, light, sigma, scale, band, b0):
    """Render the stripe that one specular face throws onto the scene (one bounce).

    ``vsheet`` is the laser sheet mirrored through the face's plane (layout of
    :func:`laser_windows`; [13:17] is the face's plane). ``face`` packs the face: centre
    (3), axes e1 (3), e2 (3), half sizes (2), outward normal (3); ``fmat`` its packed
    material; ``light`` the real sheet (its apex and last G2 mirror). A window pixel's hit
    Y is lit if the segment from Y towards the mirrored apex crosses the face at a point Z
    inside it, Y lies in front of the face, faces the mirrored apex and lies inside the
    mirrored fan, nothing blocks Y-Z, and Z is lit by the laser (faces the apex, nothing
    on the segment to the last G2 mirror). Its value is ``scale * a(Y) * cos(incidence) /
    distance * F(theta_Z) * sigma/sigma_r * exp(-delta^2 / 2 sigma_r^2)``: the face's
    Fresnel reflectance at Z, the sheet widened by the lobe (angular spread sqrt(2) alpha
    over the distance L = |YZ|: ``sigma_r^2 = sigma^2 + 2 alpha^2 L^2``, the energy kept),
    delta the distance of Y from the mirrored sheet's centre plane. Pixels are assigned
    (not added) in ``band``. Returns the number drawn.
    """
    rows, cc, xs, ys = _window_pixels(grid, cols, v0, half)
    ox, oy, oz, dx, dy, dz, tb, pb, ab = _trace_closest(ptype, R, T, prm, cam, xs, ys)
    cx, cy, cz = face[0], face[1], face[2]
    fnx, fny, fnz = face[11], face[12], face[13]
    alpha = fmat[1]
    drawn = 0
    for i in range(xs.shape[0]):
        p = pb[i]
        if p < 0:
            continue
        t = tb[i]
        px, py, pz = ox[i] + t * dx[i], oy[i] + t * dy[i], oz[i] + t * dz[i]
        if fnx * (px - cx) + fny * (py - cy) + fnz * (pz - cz) <= 1e-9:
            continue  # behind the face or on its plane
        sx, sy, sz = vsheet[4] - px, vsheet[5] - py, vsheet[6] - pz
        dist = math.sqrt(sx * sx + sy * sy + sz * sz)
        ux, uy, uz = sx / dist, sy / dist, sz / dist
        den = fnx * ux + fny * uy + fnz * uz
        if den >= 0.0:
            continue
        L = (fnx * (cx - px) + fny * (cy - py) + fnz * (cz - pz)) / den
        if not 0.0 < L < dist:
            continue
        zx, zy, zz = px + L * ux, py + L * uy, pz + L * uz
        qa = (zx - cx) * face[3] + (zy - cy) * face[4] + (zz - cz) * face[5]
        qb = (zx - cx) * face[6] + (zy - cy) * face[7] + (zz - cz) * face[8]
        if abs(qa) > face[9] or abs(qb) > face[10]:
            continue
        sig_r = math.sqrt(sigma * sigma + 2.0 * alpha * alpha * L * L)
        delta = vsheet[0] * px + vsheet[1] * py + vsheet[2] * pz + vsheet[3]
        if abs(delta) >= 5.0 * sig_r:
            continue
        nx, ny, nz = _hit_normal(ptype, R, T, prm, p, ab[i], px, py, pz, dx[i], dy[i], dz[i])
        cos_i = nx * ux + ny * uy + nz * uz
        if cos_i <= 0.0 or not _inside_fan(vsheet, sx, sy, sz):
            continue
        if is_blocked(ptype, R, T, prm, px, py, pz, ux, uy, uz, L - EPS):
            continue
        wx, wy, wz = light[4] - zx, light[5] - zy, light[6] - zz
        wd = math.sqrt(wx * wx + wy * wy + wz * wz)
        wx, wy, wz = wx / wd, wy / wd, wz / wd
        cos_z = fnx * wx + fny * wy + fnz * wz
        if cos_z <= 0.0:
            continue
        tm = _until_plane(zx, zy, zz, wx, wy, wz, wd, light[13], light[14], light[15],
                          light[16])
        if is_blocked(ptype, R, T, prm, zx, zy, zz, wx, wy, wz, tm - EPS):
            continue
        o = pobj[p]
        a = albedo[o]
        if mats[o, 6] > 0.0:
            vx, vy, vz = cam[32] - px, cam[33] - py, cam[34] - pz
            vn = math.sqrt(vx * vx + vy * vy + vz * vz)
            a = a + specular_term(mats[o], nx, ny, nz, ux, uy, uz, vx / vn, vy / vn, vz / vn)
        val = (scale * a * cos_i / dist * _fresnel(cos_z, fmat[2], fmat[3]) * sigma / sig_r
               * math.exp(-0.5 * (delta / sig_r) ** 2))
        band[rows[i] - b0, cc[i]] = val
        drawn += 1
    return drawn


@njit(cache=True)
def window_halves(X, N, col, v, WRV, center, plane, sigma, psf, intr, out):
    """Half height [px] of the row window around each true stripe point.

    The pixel rays at v - 1 and v + 1 of the column are cut with the surface's tangent
    plane at X; the change of the distance to the sheet per pixel gives the stripe's sigma
    in pixels, and the window covers 3.5 of those, plus half a pixel for rounding v
    (clipped to 2..40); ``sigma`` (n,) is each point's stripe sigma [m]. The blur is
    applied to the drawn band afterwards, so it needs no margin here (``psf`` is unused,
    kept for the signature).
    """
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    for i in range(X.shape[0]):
        x = (col[i] - cx) / fx
        num = (N[i, 0] * (X[i, 0] - center[0]) + N[i, 1] * (X[i, 1] - center[1])
               + N[i, 2] * (X[i, 2] - center[2]))
        d_sheet = 0.0
        for sgn in (1.0, -1.0):
            y = (v[i] + sgn - cy) / fy
            dx = WRV[0, 0] * x + WRV[0, 1] * y + WRV[0, 2]
            dy = WRV[1, 0] * x + WRV[1, 1] * y + WRV[1, 2]
            dz = WRV[2, 0] * x + WRV[2, 1] * y + WRV[2, 2]
            den = N[i, 0] * dx + N[i, 1] * dy + N[i, 2] * dz
            t = num / den if den != 0.0 else np.inf
            d_sheet += sgn * t * (plane[0] * dx + plane[1] * dy + plane[2] * dz)
        slope = 0.5 * abs(d_sheet)
        h = 40.0
        if slope > 0.0 and math.isfinite(slope):
            h = min(max(math.ceil(3.5 * sigma[i] / slope + 0.5), 2.0), 40.0)
        out[i] = int(h)


@njit(cache=True)
def _mirror_plane(mir, theta):
    """Mirror packed as [axis point (3), reference normal (3), binormal (3), offset]:
    (n, c) of its surface n . x = c at angle theta (see galvo.Mirror.plane)."""
    c, s = math.cos(theta), math.sin(theta)
    nx = mir[3] * c + mir[6] * s
    ny = mir[4] * c + mir[7] * s
    nz = mir[5] * c + mir[8] * s
    return nx, ny, nz, nx * mir[0] + ny * mir[1] + nz * mir[2] - mir[9]


@njit(cache=True)
def laser_sheet(pan, tilt, laser, half_angle, W_T_G2, theta_pan, theta_tilt, out):
    """Packed laser sheet in W (layout of ``sheet`` in :func:`laser_windows`) for G2 mirror
    angles: the fan's apex, central and edge rays reflected off the two mirror planes.

    ``laser`` packs [apex (3), central direction (3), fan normal (3), spread (3)] in G2.
    Same maths as ``Rig.laser_sheet_G`` (the tests compare them).
    """
    sx, sy, sz = laser[0], laser[1], laser[2]
    ch, sh = math.cos(half_angle), math.sin(half_angle)
    dirs = np.empty((4, 3))
    for k in range(3):
        dirs[0, k] = laser[3 + k]
        dirs[1, k] = ch * laser[3 + k] + sh * laser[9 + k]
        dirs[2, k] = ch * laser[3 + k] - sh * laser[9 + k]
        dirs[3, k] = laser[6 + k]
    ok = True
    for mir, th in ((pan, theta_pan), (tilt, theta_tilt)):
        nx, ny, nz, c = _mirror_plane(mir, th)
        dn0 = dirs[0, 0] * nx + dirs[0, 1] * ny + dirs[0, 2] * nz
        t = (c - (sx * nx + sy * ny + sz * nz)) / dn0
        ok = ok and t > 0.0
        f = 2.0 * (sx * nx + sy * ny + sz * nz - c)
        sx, sy, sz = sx - f * nx, sy - f * ny, sz - f * nz
        for r in range(4):
            dn = dirs[r, 0] * nx + dirs[r, 1] * ny + dirs[r, 2] * nz
            dirs[r, 0] -= 2.0 * dn * nx
            dirs[r, 1] -= 2.0 * dn * ny
            dirs[r, 2] -= 2.0 * dn * nz
    tnx, tny, tnz, tc = _mirror_plane(tilt, theta_tilt)
    R = W_T_G2[:3, :3].copy()
    t = W_T_G2[:3, 3].copy()
    src = R @ np.array([sx, sy, sz]) + t
    normal = R @ dirs[3]
    normal /= math.sqrt(normal[0] ** 2 + normal[1] ** 2 + normal[2] ** 2)
    central = R @ dirs[0]
    out[0:3] = normal
    out[3] = -(normal[0] * src[0] + normal[1] * src[1] + normal[2] * src[2])
    out[4:7] = src
    for k in range(2):
        e = R @ dirs[1 + k]
        en = np.array([normal[1] * e[2] - normal[2] * e[1], normal[2] * e[0] - normal[0] * e[2],
                       normal[0] * e[1] - normal[1] * e[0]])
        en /= math.sqrt(en[0] ** 2 + en[1] ** 2 + en[2] ** 2)
        if en[0] * central[0] + en[1] * central[1] + en[2] * central[2] < 0.0:
            en = -en
        out[7 + 3 * k:10 + 3 * k] = en
    mn = R @ np.array([tnx, tny, tnz])
    out[13:16] = mn
    out[16] = -(tc + mn[0] * t[0] + mn[1] * t[1] + mn[2] * t[2])
    out[17:20] = central
    return ok
