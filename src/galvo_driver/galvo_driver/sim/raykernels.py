"""Compiled (numba) inner loops of the ray tracer and the sensor model.

The scene is packed into flat arrays (see :meth:`Scene.packed`): per primitive a type
(0 box ``lo, hi``; 1 sphere ``centre, radius``; 2 rectangle ``hx, hy`` in the plane z = 0,
two-sided), the owning object, the pose ``W_R_O`` / ``W_t_O`` and six parameters. These
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
def _local(R, T, p, x, y, z):
    qx, qy, qz = x - T[p, 0], y - T[p, 1], z - T[p, 2]
    return (R[p, 0, 0] * qx + R[p, 1, 0] * qy + R[p, 2, 0] * qz,
            R[p, 0, 1] * qx + R[p, 1, 1] * qy + R[p, 2, 1] * qz,
            R[p, 0, 2] * qx + R[p, 1, 2] * qy + R[p, 2, 2] * qz)


@njit(cache=True, inline='always')
def _local_dir(R, p, x, y, z):
    return (R[p, 0, 0] * x + R[p, 1, 0] * y + R[p, 2, 0] * z,
            R[p, 0, 1] * x + R[p, 1, 1] * y + R[p, 2, 1] * z,
            R[p, 0, 2] * x + R[p, 1, 2] * y + R[p, 2, 2] * z)


@njit(cache=True, inline='always')
def _slab(lo, hi, o, d):
    """Entry/exit of a ray with one slab; returns (t_near, t_far) or (inf, -inf)."""
    if d == 0.0:
        if o < lo or o > hi:
            return np.inf, -np.inf
        return -np.inf, np.inf
    t1 = (lo - o) / d
    t2 = (hi - o) / d
    if t1 > t2:
        return t2, t1
    return t1, t2


@njit(cache=True, inline='always')
def _box(prm, p, ox, oy, oz, dx, dy, dz):
    """(t_in, t_out, axis of t_in) of a ray and an axis-aligned box."""
    a0, b0 = _slab(prm[p, 0], prm[p, 3], ox, dx)
    a1, b1 = _slab(prm[p, 1], prm[p, 4], oy, dy)
    a2, b2 = _slab(prm[p, 2], prm[p, 5], oz, dz)
    t_in, ax = a0, 0
    if a1 > t_in:
        t_in, ax = a1, 1
    if a2 > t_in:
        t_in, ax = a2, 2
    return t_in, min(b0, b1, b2), ax


@njit(cache=True, inline='always')
def closest_hit(ptype, R, T, prm, ox, oy, oz, dx, dy, dz):
    """Closest primitive hit of one ray: (t, prim, nx, ny, nz), prim = -1 for none."""
    best = np.inf
    bp = -1
    bnx = bny = bnz = 0.0
    for p in range(ptype.shape[0]):
        lx, ly, lz = _local(R, T, p, ox, oy, oz)
        ex, ey, ez = _local_dir(R, p, dx, dy, dz)
        kind = ptype[p]
        if kind == BOX:
            t_in, t_out, ax = _box(prm, p, lx, ly, lz, ex, ey, ez)
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
    for p in range(ptype.shape[0]):
        lx, ly, lz = _local(R, T, p, ox, oy, oz)
        ex, ey, ez = _local_dir(R, p, dx, dy, dz)
        kind = ptype[p]
        if kind == BOX:
            t_in, t_out, _ = _box(prm, p, lx, ly, lz, ex, ey, ez)
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
def sensor(img, z, full_well, shot, read2, inv_gain, black, top, out):
    """Electrons to DN: clip at full well, add noise (z: N(0,1) draws or empty), quantise."""
    h, w = img.shape
    noisy = z.shape[0] > 0
    for r in range(h):
        for c in range(w):
            e = img[r, c]
            if e > full_well:
                e = full_well
            if noisy:
                var = read2 + (e if shot and e > 0 else 0.0)
                e = e + math.sqrt(var) * z[r * w + c]
            dn = e * inv_gain + black
            if dn <= 0.0:
                out[r, c] = 0
            elif dn >= top:
                out[r, c] = np.uint8(top)
            else:
                out[r, c] = np.uint8(int(dn + 0.5))
