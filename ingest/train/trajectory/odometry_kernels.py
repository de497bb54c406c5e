"""Compiled (numba) per-point loops of the odometry's Gauss-Newton solve.

Each iteration of `ingest.train.trajectory.odometry` moves a chunk's few thousand points
with the knot chain and accumulates the point-to-plane normal equations. In
numpy that would be a (N, 3, 3) rotation stack per iteration (as
`RigTrajectory.pose` builds) and a dense (N, 12) Jacobian, a dozen passes over
the points; here it is one pass each. The chain's formula is the module doc's of
`ingest.train.trajectory.rig_trajectory`: R(t) p = R_k G_k^T G(t) Exp(f e_k) p with
e_k = Log(E_k), position linear between the knots.

Kernels are compiled on first use and cached on disk (`cache=True`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from scipy.spatial.transform import Rotation

from calibration.linalg3 import DEGENERATE_GAP
from calibration.types import F64, I64, Bool
from ingest.train.trajectory.clouds import GyroTrack


@njit(cache=True, nogil=True)
def _chain_points(pts, seg, f, rel, R_knot, p_knot, err, a_out, world_out):  # type: ignore[no-untyped-def]  # pragma: no cover
    for i in range(pts.shape[0]):
        k = seg[i]
        fi = f[i]
        wx, wy, wz = fi * err[k, 0], fi * err[k, 1], fi * err[k, 2]
        th2 = wx * wx + wy * wy + wz * wz
        if th2 < 1e-12:  # series of sin(th)/th and (1 - cos(th))/th^2
            s = 1.0 - th2 / 6.0
            c = 0.5 - th2 / 24.0
        else:
            th = math.sqrt(th2)
            s = math.sin(th) / th
            c = (1.0 - math.cos(th)) / th2
        x, y, z = pts[i, 0], pts[i, 1], pts[i, 2]
        cx, cy, cz = wy * z - wz * y, wz * x - wx * z, wx * y - wy * x  # w x p
        ccx, ccy, ccz = wy * cz - wz * cy, wz * cx - wx * cz, wx * cy - wy * cx  # w x (w x p)
        y0, y1, y2 = x + s * cx + c * ccx, y + s * cy + c * ccy, z + s * cz + c * ccz
        for r in range(3):  # a = R_k rel (Exp(f e) p)
            v = 0.0
            for m in range(3):
                v += R_knot[k, r, m] * (rel[i, m, 0] * y0 + rel[i, m, 1] * y1 + rel[i, m, 2] * y2)
            a_out[i, r] = v
            world_out[i, r] = v + p_knot[k, r] + fi * (p_knot[k + 1, r] - p_knot[k, r])


def chain_points(pts: F64, seg: I64, f: F64, rel: F64, R_knot: F64, p_knot: F64, err: F64) -> tuple[F64, F64]:
    """(rotated (N, 3), world (N, 3)) of points `pts` (cam0, N x 3) on the knot chain.

    Point i lies in segment `seg[i]` at fraction `f[i]`, with the gyro's turn
    `rel[i]` (3, 3) from the segment's start; `R_knot` (K, 3, 3) and `p_knot`
    (K, 3) are the knots, `err` (K - 1, 3) each segment's spread mismatch
    Log(E_k). rotated = R(t) p, world = R(t) p + p(t).
    """
    a = np.empty((len(pts), 3))
    world = np.empty((len(pts), 3))
    if len(pts):
        _chain_points(np.ascontiguousarray(pts, np.float64), seg, f, np.ascontiguousarray(rel, np.float64),
                      np.ascontiguousarray(R_knot), np.ascontiguousarray(p_knot), np.ascontiguousarray(err),
                      a, world)  # fmt: skip
    return a, world


@njit(cache=True, nogil=True)
def _plane_system(a, world, j, planar, normal, map_xyz, seg, f, free, min_points, min_scale, H, g, r, used):  # type: ignore[no-untyped-def]  # pragma: no cover
    m = 0
    for i in range(j.shape[0]):  # the residuals of the points matched to a planar map point
        q = j[i]
        if q < 0 or not planar[q]:
            continue
        d0, d1, d2 = world[i, 0] - map_xyz[q, 0], world[i, 1] - map_xyz[q, 1], world[i, 2] - map_xyz[q, 2]
        r[m] = normal[q, 0] * d0 + normal[q, 1] * d1 + normal[q, 2] * d2
        used[m] = i
        m += 1
    if m < min_points:
        return m, math.nan
    scale = max(1.4826 * np.median(np.abs(r[:m])), min_scale)
    n_free = free.shape[0]
    J = np.zeros(6 * n_free)
    sum_w = 0.0
    sum_wr2 = 0.0
    for t in range(m):
        i, q, ri = used[t], j[used[t]], r[t]
        wi = 1.0 / (1.0 + (ri / scale) ** 2)  # Cauchy weights: gross outliers (movers, wrong matches) fade
        sum_w += wi
        sum_wr2 += wi * ri * ri
        n0, n1, n2 = normal[q, 0], normal[q, 1], normal[q, 2]
        rot0 = a[i, 1] * n2 - a[i, 2] * n1
        rot1 = a[i, 2] * n0 - a[i, 0] * n2
        rot2 = a[i, 0] * n1 - a[i, 1] * n0
        for u in range(n_free):  # knot k ends segment k - 1 (weight f) and starts segment k (1 - f)
            k = free[u]
            wt = 0.0
            if seg[i] == k - 1:
                wt = f[i]
            elif seg[i] == k:
                wt = 1.0 - f[i]
            J[6 * u + 0] = rot0 * wt
            J[6 * u + 1] = rot1 * wt
            J[6 * u + 2] = rot2 * wt
            J[6 * u + 3] = n0 * wt
            J[6 * u + 4] = n1 * wt
            J[6 * u + 5] = n2 * wt
        for p in range(6 * n_free):
            if J[p] == 0.0:
                continue
            g[p] += wi * J[p] * ri
            for c in range(6 * n_free):
                H[p, c] += wi * J[p] * J[c]
    return m, math.sqrt(sum_wr2 / sum_w)


def plane_system(
    a: F64, world: F64, j: I64, planar: Bool, normal: F64, map_xyz: F64, seg: I64, f: F64, free: I64,
    min_points: int = 50, min_scale_m: float = 0.005,
) -> tuple[F64, F64, float, int]:  # fmt: skip
    """One Gauss-Newton step of point-to-plane ICP: (J^T W J, J^T W r, weighted RMS residual m, points used).

    Point i (rotated `a[i]`, placed `world[i]`, both (N, 3)) matched to map
    point `j[i]` (-1: none) counts where that one is `planar`; its residual is
    r = n . (world - map_xyz[j]) along the map point's `normal`, its weight
    Cauchy's, 1 / (1 + (r / s)^2) with s = 1.4826 median |r| (at least
    `min_scale_m`), so gross outliers (movers, wrong matches) fade. It lies in
    segment `seg[i]` at fraction `f[i]` and moves with the knots `free` (6
    unknowns each: rotation vector, then translation, both in the world
    frame); its Jacobian is (a x n, n) times its weight between the two knots
    of its segment. With fewer than `min_points` used the system is zeros and
    the residual NaN. One compiled pass over the points, where numpy would
    make a dozen.
    """
    size = 6 * len(free)
    H, g = np.zeros((size, size)), np.zeros(size)
    r, used = np.empty(len(j)), np.empty(len(j), np.int64)
    m, residual = _plane_system(
        a, world, j, planar, normal, map_xyz, seg, f, np.asarray(free, np.int64), min_points, min_scale_m,
        H, g, r, used,
    )  # fmt: skip
    return H, g, float(residual), int(m)


@njit(cache=True, nogil=True)
def _node_walk(t, nodes, a, g):  # type: ignore[no-untyped-def]  # pragma: no cover
    j = 0
    last = nodes.shape[0] - 2
    for i in range(t.shape[0]):
        ti = min(max(t[i], nodes[0]), nodes[-1])
        while j < last and nodes[j + 1] <= ti:  # walked from the last point's node: points come in time
            j += 1
        while j > 0 and nodes[j] > ti:
            j -= 1
        a[i] = j
        g[i] = (ti - nodes[j]) / max(nodes[j + 1] - nodes[j], 1)


def node_fractions(t: I64, nodes: I64) -> tuple[I64, F64]:
    """Each time's node before it and its fraction to the next, on the ascending node times `nodes`.

    Times are clamped to the nodes' span; a time on a node takes that node
    (fraction 0), the last node's time the last interval's end (fraction 1).
    The search walks from the previous point's node, so points that come
    roughly in time (a cloud's sweeps) cost a step or two each.
    """
    a = np.empty(len(t), np.int64)
    g = np.empty(len(t), np.float64)
    _node_walk(np.ascontiguousarray(t, np.int64), np.ascontiguousarray(nodes, np.int64), a, g)
    return a, g


@njit(cache=True, nogil=True)
def _blend_points(pts, a, g, R_n, p_n, out):  # type: ignore[no-untyped-def]  # pragma: no cover
    for i in range(pts.shape[0]):
        j = a[i]
        gi = g[i]
        for r in range(3):
            v = p_n[j, r] + gi * (p_n[j + 1, r] - p_n[j, r])
            for m in range(3):
                v += (R_n[j, r, m] + gi * (R_n[j + 1, r, m] - R_n[j, r, m])) * pts[i, m]
            out[i, r] = v


def blend_points(pts: F64, a: I64, g: F64, R_n: F64, p_n: F64) -> F64:
    """World points (N, 3): each point's pose blended linearly between nodes `a[i]` and `a[i] + 1` by `g[i]`.

    `RigTrajectory.pose`'s node grid applied to the points without forming a (N, 3, 3) stack.
    """
    out = np.empty((len(pts), 3))
    if len(pts):
        _blend_points(np.ascontiguousarray(pts), a, np.ascontiguousarray(g), R_n, p_n, out)
    return out


@njit(cache=True, nogil=True, inline="always")
def _det_shifted(c, lam):  # type: ignore[no-untyped-def]  # pragma: no cover
    """(det(C - lam I), its derivative in lam) of a symmetric 3x3 `c`."""
    c00, c11, c22 = c[0, 0] - lam, c[1, 1] - lam, c[2, 2] - lam
    a01, a02, a12 = c[0, 1], c[0, 2], c[1, 2]
    m0, m1, m2 = c11 * c22 - a12 * a12, c00 * c22 - a02 * a02, c00 * c11 - a01 * a01
    return c00 * m0 - a01 * (a01 * c22 - a12 * a02) + a02 * (a01 * a12 - c11 * a02), -(m0 + m1 + m2)


@njit(cache=True, nogil=True, inline="always")
def _polished(c, lam, scale):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Two Newton steps on det(C - lam I), each taken only while small against `scale` (`linalg3._newton`)."""
    for _ in range(2):
        det, slope = _det_shifted(c, lam)
        if slope != 0.0:
            step = det / slope
            if math.isfinite(step) and abs(step) <= 1e-6 * scale:
                lam -= step
    return lam


@njit(cache=True, nogil=True)
def _planes(xyz, idx, gap, cov, evals, vec, ok):  # type: ignore[no-untyped-def]  # pragma: no cover
    k = idx.shape[1]
    m = np.empty((3, 3))
    for i in range(idx.shape[0]):
        c = cov[i]
        mean = np.zeros(3)
        for t in range(k):
            for a in range(3):
                mean[a] += xyz[idx[i, t], a]
        mean /= k
        c[:] = 0.0
        for t in range(k):
            for a in range(3):
                for b in range(a, 3):
                    c[a, b] += (xyz[idx[i, t], a] - mean[a]) * (xyz[idx[i, t], b] - mean[b])
        for a in range(3):
            for b in range(a, 3):
                c[a, b] /= k
                c[b, a] = c[a, b]
        # eigenvalues: the trigonometric method, Newton-polished (`calibration.linalg3.sym3_eigvals`)
        q = (c[0, 0] + c[1, 1] + c[2, 2]) / 3.0
        b00, b11, b22 = c[0, 0] - q, c[1, 1] - q, c[2, 2] - q
        p = math.sqrt((b00**2 + b11**2 + b22**2 + 2.0 * (c[0, 1] ** 2 + c[0, 2] ** 2 + c[1, 2] ** 2)) / 6.0)
        safe = p if p > 0 else 1.0
        det = (
            b00 * (b11 * b22 - c[1, 2] * c[1, 2])
            - c[0, 1] * (c[0, 1] * b22 - c[1, 2] * c[0, 2])
            + c[0, 2] * (c[0, 1] * c[1, 2] - b11 * c[0, 2])
        ) / safe**3
        phi = math.acos(min(max(det / 2.0, -1.0), 1.0)) / 3.0
        hi = _polished(c, q + 2.0 * p * math.cos(phi), p)
        lo = _polished(c, q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0), p)
        evals[i, 0], evals[i, 1], evals[i, 2] = lo, 3.0 * q - hi - lo, hi
        # eigenvector of the smallest: the largest cross product of two rows of C - lo I (`sym3_smallest`)
        m[:] = c
        for a in range(3):
            m[a, a] -= lo
        best = -1.0
        for u, v in ((0, 1), (0, 2), (1, 2)):
            x = m[u, 1] * m[v, 2] - m[u, 2] * m[v, 1]
            y = m[u, 2] * m[v, 0] - m[u, 0] * m[v, 2]
            z = m[u, 0] * m[v, 1] - m[u, 1] * m[v, 0]
            if x * x + y * y + z * z > best:
                best, vec[i, 0], vec[i, 1], vec[i, 2] = x * x + y * y + z * z, x, y, z
        size = math.sqrt(best)
        ok[i] = size > gap * (hi - lo) ** 2
        if ok[i]:
            vec[i, 0], vec[i, 1], vec[i, 2] = vec[i, 0] / size, vec[i, 1] / size, vec[i, 2] / size


def neighbourhood_planes(xyz: F64, idx: I64) -> tuple[F64, F64]:
    """Ascending eigenvalues (N, 3, m^2) of each neighbourhood's covariance and the unit eigenvector (N, 3)
    of the smallest: the plane through the points `xyz[idx[i]]` (idx: N x k), covariance divided by k.

    `planes.neighbour_covariances` and `calibration.linalg3.sym3_smallest` in
    one compiled pass, without the (N, k, 3) gather; rows where the two
    smallest eigenvalues (nearly) coincide go to `np.linalg.eigh`, as there.
    """
    n = len(idx)
    cov, evals, vec, ok = np.empty((n, 3, 3)), np.empty((n, 3)), np.empty((n, 3)), np.ones(n, np.bool_)
    if n:
        _planes(np.ascontiguousarray(xyz, np.float64), np.ascontiguousarray(idx, np.int64), DEGENERATE_GAP,
                cov, evals, vec, ok)  # fmt: skip
    if not ok.all():
        w, v = np.linalg.eigh(cov[~ok])
        evals[~ok], vec[~ok] = w, v[:, :, 0]
    return evals, vec


@njit(cache=True, nogil=True, inline="always")
def _track_at(stamps, rotations, steps, t, out):  # type: ignore[no-untyped-def]  # pragma: no cover
    """GyroTrack.at for one time, into out (3, 3): R_k Exp(frac s_k), Rodrigues with its series near zero."""
    n = stamps.shape[0]
    tc = min(max(t, stamps[0]), stamps[n - 1])
    k = min(max(np.searchsorted(stamps, tc, side="right") - 1, 0), n - 2)
    frac = (tc - stamps[k]) / (stamps[k + 1] - stamps[k])
    x, y, z = steps[k, 0] * frac, steps[k, 1] * frac, steps[k, 2] * frac
    th2 = x * x + y * y + z * z
    if th2 < 1e-8:
        a = 1.0 - th2 / 6.0
        b = 0.5 - th2 / 24.0
    else:
        th = math.sqrt(th2)
        a = math.sin(th) / th
        b = (1.0 - math.cos(th)) / th2
    E = np.empty((3, 3))
    E[0, 0] = 1.0 - b * (y * y + z * z)
    E[1, 1] = 1.0 - b * (x * x + z * z)
    E[2, 2] = 1.0 - b * (x * x + y * y)
    E[0, 1] = b * x * y - a * z
    E[1, 0] = b * x * y + a * z
    E[0, 2] = b * x * z + a * y
    E[2, 0] = b * x * z - a * y
    E[1, 2] = b * y * z - a * x
    E[2, 1] = b * y * z + a * x
    for r in range(3):
        for c in range(3):
            out[r, c] = (
                rotations[k, r, 0] * E[0, c] + rotations[k, r, 1] * E[1, c] + rotations[k, r, 2] * E[2, c]
            )


@njit(cache=True, nogil=True)
def _track_between(stamps, rotations, steps, t0, t1, out):  # type: ignore[no-untyped-def]  # pragma: no cover
    A = np.empty((3, 3))
    B = np.empty((3, 3))
    for i in range(t1.shape[0]):
        _track_at(stamps, rotations, steps, t0[i], A)
        _track_at(stamps, rotations, steps, t1[i], B)
        for r in range(3):
            for c in range(3):
                out[i, r, c] = A[0, r] * B[0, c] + A[1, r] * B[1, c] + A[2, r] * B[2, c]


def gyro_between(gyro: GyroTrack, t0_ns: I64, t1_ns: I64) -> F64:
    """`GyroTrack.between` (R(t0)^T R(t1), N x 3 x 3; `t0_ns` may be one time) in one compiled pass."""
    t1 = np.atleast_1d(np.asarray(t1_ns, np.int64))
    t0 = np.ascontiguousarray(np.broadcast_to(np.asarray(t0_ns, np.int64), t1.shape))
    if len(gyro.stamps_ns) < 2:
        return gyro.between(t0, t1)
    out = np.empty((len(t1), 3, 3))
    _track_between(gyro.stamps_ns, np.ascontiguousarray(gyro.rotations), gyro.steps, t0, t1, out)
    return out


def log_rotations(R: F64) -> F64:
    """Rotation vectors (N, 3) of rotation matrices (N, 3, 3): angle from atan2, exact near zero.

    For the chain's mismatches, which are small; angles near pi (where the
    skew part vanishes) go to scipy.
    """
    vee = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    s = 0.5 * np.linalg.norm(vee, axis=1)  # sin(theta)
    theta = np.arctan2(s, 0.5 * (np.trace(R, axis1=1, axis2=2) - 1.0))
    scale = np.where(s > 1e-12, theta / np.maximum(s, 1e-300), 1.0 + theta**2 / 6.0)
    out: F64 = 0.5 * scale[:, None] * vee
    far = theta > 3.0
    if far.any():
        out[far] = Rotation.from_matrix(R[far]).as_rotvec()
    return out
