"""Corner detection, the closed form and the refinement: the estimator's only implementation of them, in the
subset of Python numba compiles (profile_kernel.estimate joins them into one call per profile).

The same source runs prebuilt, JIT-compiled or uncompiled (loader.py); tools/numpy_baseline.py is the plain numpy
baseline Table III times against, not a second implementation to keep equal. Hand-written loops stand where a
numpy call would allocate or make several passes on the per-profile path.
"""
from __future__ import annotations

import math

import numpy as np

from .codes import (CF_DEGENERATE, CF_RANK, CORNER_NOT_BETWEEN, CORNERS_NOT_INCREASING, JIT, MAX_GLINT_RUN, O_EPS,
                    O_FLOOR, O_GAP, O_MAXFACE, O_MAXOFF, O_MINANGLE, O_MINSEG, O_NOISE, O_PASSES, O_ROBUST, O_SIGFLOOR,
                    O_SPIKE, O_THR, O_TRIM, OK, POLISH_COST_TOLERANCE, POLISH_STEP_TOLERANCE, POLISH_STEPS,
                    REWEIGHT_CHI2, REWEIGHT_HOPELESS_CHI2, REWEIGHT_ROUNDS, SINGULAR, STEEP_SEGMENT, TOO_FEW_POINTS,
                    WRONG_CORNER_COUNT, X_NOT_INCREASING)
from .kernel import kernel

# ----------------------------------------------------------------------------- corner detection
@kernel(**JIT)
def _first_argmax(values):
    """The first index of max(values), for values >= 0 (no NaN), in two passes that beat one
    compare-and-keep-index pass: the maximum of the bit patterns (non-negative doubles order as their
    int64 bits, and an integer max vectorises), then the first index holding it."""
    bits = values.view(np.int64)
    top = np.int64(0)
    for i in range(bits.shape[0]):
        top = max(top, bits[i])
    for i in range(bits.shape[0]):
        if bits[i] == top:
            return i
    return -1  # empty


@kernel(**JIT)
def _rdp(px, pz, epsilon, keep, stack, scratch):
    n = px.shape[0]
    keep[:n] = False
    keep[0] = True
    keep[n - 1] = True
    stack[0] = 0
    stack[1] = n - 1
    top = 1
    while top > 0:
        top -= 1
        first = stack[2 * top]
        last = stack[2 * top + 1]
        if last - first < 2:
            continue
        ax = px[first]
        az = pz[first]
        c0 = px[last] - ax
        c1 = pz[last] - az
        length = math.hypot(c0, c1)
        # argmax of |cross| is argmax of the distance (length is constant): no division per point
        best = -1.0
        split = -1
        # Loops over views from 0, not range(first + 1, last): an index numba cannot prove non-negative
        # gets a wraparound check that stops LLVM vectorising.
        x = px[first + 1:last]
        z = pz[first + 1:last]
        if length > 0:
            distance = scratch[:last - first - 1]  # |cross|: one vectorised pass
            for i in range(x.shape[0]):
                distance[i] = abs(c0 * (z[i] - az) - c1 * (x[i] - ax))
            split = _first_argmax(distance)
            best = distance[split] / length
        else:
            for i in range(x.shape[0]):
                d = math.hypot(x[i] - ax, z[i] - az)
                if d > best:
                    best = d
                    split = i
        split += first + 1
        if best > epsilon:
            keep[split] = True
            stack[2 * top] = first
            stack[2 * top + 1] = split
            stack[2 * top + 2] = split
            stack[2 * top + 3] = last
            top += 2


@kernel(**JIT)
def _lane_dot(a, b):
    """sum(a * b) with four accumulators: one accumulator waits on the add's latency at every element."""
    m = a.shape[0]
    s0 = s1 = s2 = s3 = 0.0
    i = 0
    while i + 4 <= m:
        s0 += a[i] * b[i]
        s1 += a[i + 1] * b[i + 1]
        s2 += a[i + 2] * b[i + 2]
        s3 += a[i + 3] * b[i + 3]
        i += 4
    for j in range(i, m):
        s0 += a[j] * b[j]
    return (s0 + s1) + (s2 + s3)


@kernel(**JIT)
def _lane_sums(a, b):
    """(sum(a), sum(b)) in one pass, four accumulators each (see _lane_dot)."""
    m = a.shape[0]
    a0 = a1 = a2 = a3 = 0.0
    b0 = b1 = b2 = b3 = 0.0
    i = 0
    while i + 4 <= m:
        a0 += a[i]
        a1 += a[i + 1]
        a2 += a[i + 2]
        a3 += a[i + 3]
        b0 += b[i]
        b1 += b[i + 1]
        b2 += b[i + 2]
        b3 += b[i + 3]
        i += 4
    for j in range(i, m):
        a0 += a[j]
        b0 += b[j]
    return (a0 + a1) + (a2 + a3), (b0 + b1) + (b2 + b3)


@kernel(**JIT)
def _fit_line(px, pz, first, last, opt, out, k, work, index_work):
    """Fill out[k] = (first, last, slope, x_mean, z_mean, sxx, n_used, sigma, x_min, x_max).

    Least squares on the segment (its ends trimmed), then, when robust, refits without the points whose residual
    exceeds max(threshold x 1.4826 x their median, floor), until the rejected set repeats or the passes run out.
    The rejected points are few, so the sums run over every point (vectorised passes, four accumulators) and the
    rejected points' terms are then taken off. work ((3, >= m) float) and index_work ((2, >= m) int64) are
    scratch, allocated once per profile by the caller."""
    count = last - first + 1
    trim = int(opt[O_TRIM] * count)
    lo = first + trim
    hi = last - trim + 1
    if hi - lo < 2:
        lo = first
        hi = last + 1
    m = hi - lo
    x = px[lo:hi]
    z = pz[lo:hi]
    dev = work[0, :m]  # x - x_mean
    res = work[1, :m]  # z - z_mean, then |residual|
    rejected = index_work[0, :m]  # indices into x, ascending
    new_rejected = index_work[1, :m]
    n_rejected = 0
    sum_x, sum_z = _lane_sums(x, z)
    slope = 0.0
    x_mean = 0.0
    z_mean = 0.0
    sxx = 0.0
    n_used = 0
    passes = int(opt[O_PASSES]) if opt[O_ROBUST] > 0 else 1
    for iteration in range(passes):
        cnt = m - n_rejected
        sx = sum_x
        sz = sum_z
        for j in range(n_rejected):
            sx -= x[rejected[j]]
            sz -= z[rejected[j]]
        xm = sx / cnt
        zm = sz / cnt
        for i in range(m):
            dev[i] = x[i] - xm
            res[i] = z[i] - zm
        s = _lane_dot(dev, dev)
        sxz = _lane_dot(dev, res)
        for j in range(n_rejected):
            d = dev[rejected[j]]
            s -= d * d
            sxz -= d * res[rejected[j]]
        if s <= 0:
            break
        sl = sxz / s
        slope, x_mean, z_mean, sxx, n_used = sl, xm, zm, s, cnt
        if iteration == passes - 1:
            break
        for i in range(m):
            res[i] = abs(z[i] - (slope * dev[i] + z_mean))
        largest = res[_first_argmax(res)]
        # The rule keeps |r| <= max(thr * 1.4826 * median, floor). If that bound provably exceeds the
        # largest residual, every point is kept and the median need not be computed: median >= c holds
        # when fewer than half of the kept |r| are below c (exact, O(n)); rounding is monotonic.
        c = largest / (opt[O_THR] * 1.4826)
        all_kept = max(opt[O_THR] * (1.4826 * c), opt[O_FLOOR]) >= largest
        if all_kept and opt[O_FLOOR] < largest:
            below = 0
            for i in range(m):
                below += res[i] < c
            for j in range(n_rejected):
                below -= res[rejected[j]] < c
            all_kept = below <= (cnt - 1) // 2
        if all_kept:
            limit = np.inf
        else:
            kept = work[2, :cnt]
            at = 0
            j = 0
            for i in range(m):
                if j < n_rejected and rejected[j] == i:
                    j += 1
                else:
                    kept[at] = res[i]
                    at += 1
            limit = max(opt[O_THR] * (1.4826 * np.median(kept)), opt[O_FLOOR])
        n_new = 0
        for i in range(m):
            if not res[i] <= limit:
                new_rejected[n_new] = i
                n_new += 1
        same = n_new == n_rejected
        if same:
            for j in range(n_new):
                if new_rejected[j] != rejected[j]:
                    same = False
                    break
        if same or m - n_new < 2:
            break
        rejected, new_rejected = new_rejected, rejected
        n_rejected = n_new
    sigma = 0.0
    if n_used > 2:
        for i in range(m):
            res[i] = z[i] - (slope * (x[i] - x_mean) + z_mean)
        ss = _lane_dot(res, res)
        for j in range(n_rejected):
            ss -= res[rejected[j]] * res[rejected[j]]
        sigma = math.sqrt(max(ss, 0.0) / (n_used - 2))
    out[k, 0] = first
    out[k, 1] = last
    out[k, 2] = slope
    out[k, 3] = x_mean
    out[k, 4] = z_mean
    out[k, 5] = sxx
    out[k, 6] = n_used
    out[k, 7] = sigma
    out[k, 8] = px[first]
    out[k, 9] = px[last]


@kernel(**JIT)
def _median5(a, b, c, d, e):
    """The median of five values without sorting (it runs for every suspect point). The smallest of any four
    has three above it, so it is not the median: drop it twice, and the median is the least of the last three."""
    if a > b:
        a, b = b, a
    if c > d:
        c, d = d, c
    if a < c:
        a = e
        if a > b:
            a, b = b, a
    else:
        c = e
        if c > d:
            c, d = d, c
    return min(b, c) if a < c else min(a, d)


@kernel(**JIT)
def _off_its_neighbours(pz, i, distance):
    """Whether point i lies more than `distance` off the line through its two neighbours (a glint suspect)."""
    return abs(pz[i] - 0.5 * (pz[i - 1] + pz[i + 1])) > distance


@kernel(**JIT)
def _displaced_run_end(px, pz, outer, anchor, i, n, threshold):
    """Where a glint of several points starting at i ends: the first j (at least two points after the anchor,
    at most MAX_GLINT_RUN after i) such that every point from i to j - 1 lies more than `threshold` off the line
    through the points `anchor` and j, and `outer` and j + 1 lie within it (the line is the face's, not the
    glint's); -1 if there is none. anchor and outer are the last two points before i that were not dropped
    (i - 1 and i - 2 unless a glint just was). A corner inside the run bends the face by its slope change
    times a few pitches, far below the threshold."""
    for j in range(max(i + 1, anchor + 3), min(i + MAX_GLINT_RUN, n - 2) + 1):
        if not px[j] > px[anchor]:
            return -1
        slope = (pz[j] - pz[anchor]) / (px[j] - px[anchor])
        if not (abs(pz[outer] - pz[anchor] - slope * (px[outer] - px[anchor])) <= threshold and
                abs(pz[j + 1] - pz[anchor] - slope * (px[j + 1] - px[anchor])) <= threshold):
            continue
        off = True
        for m in range(i, j):
            if not abs(pz[m] - pz[anchor] - slope * (px[m] - px[anchor])) > threshold:
                off = False
                break
        if off:
            return j
    return -1


@kernel(**JIT)
def _drop_spikes(px, pz, n, threshold):
    """Remove, in place, the points more than `threshold` off the median depth of their five neighbours in scan
    order, and the glints of up to MAX_GLINT_RUN points side by side (_displaced_run_end); returns how many
    remain. A glint's depth is unrelated to the face's: left in, RDP breaks the face at it, and a break next to
    a corner leaves a short segment across the corner, fitted at an in-between slope and kept as an extra
    face. A median of five keeps a face's points (a straight run is its own median, at any slope) and a
    corner's within its slope change times the point pitch; two glints side by side still go; it tests only
    points off the line through their two neighbours by half the threshold. A specular glint often lights a
    few neighbouring pixels, and three or more side by side are their own median: where the profile steps more
    than the threshold from the last point kept, the points from there on are tested as one run (measured from
    the last point kept, a second glint right after a first is found too). A profile with such a run has a
    suspect (the face point before it is off the line through its neighbours).

    Most profiles have no such point: they are counted first, in a loop without branches (it vectorises), and
    a profile without any returns at once; the rest are moved only from the first spike on."""
    if n < 5:
        return n
    half = 0.5 * threshold
    suspects = 0
    for i in range(2, n - 2):
        suspects += _off_its_neighbours(pz, i, half)
    if suspects == 0:
        return n
    spike = np.zeros(n, dtype=np.bool_)
    first = n
    outer, anchor = 0, 1  # the last two points kept before i
    for i in range(2, n - 2):
        if spike[i]:
            continue
        if _off_its_neighbours(pz, i, half) and abs(
                pz[i] - _median5(pz[i - 2], pz[i - 1], pz[i], pz[i + 1], pz[i + 2])) > threshold:
            spike[i] = True
            first = min(first, i)
            continue
        if abs(pz[i] - pz[anchor]) > threshold:
            end = _displaced_run_end(px, pz, outer, anchor, i, n, threshold)
            if end > i:
                spike[i:end] = True
                first = min(first, i)
                continue
        outer, anchor = anchor, i
    kept = first
    for i in range(first, n):
        if not spike[i]:
            px[kept] = px[i]
            pz[kept] = pz[i]
            kept += 1
    return kept


@kernel(**JIT)
def profile_gaps(points, pitches, gaps):
    """The spacing of the valid points' x (the median step) and, in gaps (rows (x before, x after), widest
    first), up to gaps.shape[0] of the steps wider than `pitches` spacings; returns (valid points, gaps found,
    spacing). A partial view's first question (partial_kernel.py), in one pass where numpy's valid-point mask,
    diff and median took three."""
    n_all = points.shape[0]
    steps = np.empty(max(n_all - 1, 0))
    xs = np.empty(n_all)
    n = 0
    for i in range(n_all):
        if math.isfinite(points[i, 0]) and math.isfinite(points[i, 1]):
            xs[n] = points[i, 0]
            if n > 0:
                steps[n - 1] = xs[n] - xs[n - 1]
            n += 1
    if n < 2:
        return n, 0, np.nan
    pitch = np.median(steps[:n - 1])
    kept = gaps.shape[0]
    found = 0
    for k in range(n - 1):
        if not steps[k] > pitches * pitch:
            continue
        at = min(found, kept)  # the new gap's place among the widest, by insertion
        while at > 0 and steps[k] > gaps[at - 1, 1] - gaps[at - 1, 0]:
            at -= 1
        if at < kept:
            for j in range(min(found, kept - 1), at, -1):
                gaps[j, :] = gaps[j - 1, :]
            gaps[at, 0] = xs[k]
            gaps[at, 1] = xs[k + 1]
            found = min(found + 1, kept)
    return n, found, pitch


@kernel(**JIT)
def _segments(points, opt):
    """What every detection of one profile shares, whatever corner count it asks for: the valid points (glints
    dropped) and the line fits of their RDP segments before any are merged. A partial view asks for several
    counts and gaps (partial_kernel.py), and this is most of a detection's time. Returns (px, pz, increasing,
    lines, count, work, index_work): x strictly increasing or not (no segments then), the first `count` rows of
    lines (rows as _fit_line's), and _fit_line's scratch for the merges."""
    n_all = points.shape[0]
    px = np.empty(n_all)
    pz = np.empty(n_all)
    n = 0
    for i in range(n_all):
        if math.isfinite(points[i, 0]) and math.isfinite(points[i, 1]):
            px[n] = points[i, 0]
            pz[n] = points[i, 1]
            n += 1
    if opt[O_SPIKE] > 0:
        n = _drop_spikes(px, pz, n, opt[O_SPIKE])
    px = px[:n]
    pz = pz[:n]
    work = np.empty((3, n))
    index_work = np.empty((2, n), dtype=np.int64)
    increasing = True
    for i in range(n - 1):
        if px[i + 1] - px[i] <= 0:
            increasing = False
            break
    min_seg = int(opt[O_MINSEG])
    if not increasing or n < max(2 * min_seg, 2):  # no corner count can be detected (too few points for one)
        return px, pz, increasing, np.empty((1, 10)), 0, work, index_work
    keep = np.empty(n, dtype=np.bool_)
    stack = np.empty(2 * n + 4, dtype=np.int64)
    _rdp(px, pz, opt[O_EPS], keep, stack, np.empty(n))
    n_vertices = 0
    for i in range(n):
        if keep[i]:
            n_vertices += 1
    lines = np.empty((max(n_vertices - 1, 1), 10))
    count = 0
    prev = -1
    for i in range(n):
        if keep[i]:
            if prev >= 0 and i - prev + 1 >= min_seg:
                _fit_line(px, pz, prev, i, opt, lines, count, work, index_work)
                count += 1
            prev = i
    return px, pz, increasing, lines, count, work, index_work


@kernel(**JIT)
def _detect(points, n_corners, opt, corners, jac, line_var, info, lines_out):
    """Corner detection; returns (status, n_lines, fit_rms). info carries numbers for the reason; lines_out
    ((n_corners + 1, 10), rows as _fit_line's) gets the face fits when it succeeds."""
    return _detect_in(_segments(points, opt), n_corners, opt, corners, jac, line_var, info, lines_out)


@kernel(**JIT)
def _detect_in(segments, n_corners, opt, corners, jac, line_var, info, lines_out):
    """_detect from the profile's _segments; opt may differ from theirs in what only merging and the corners
    read (the gap a face hides behind, O_GAP)."""
    px, pz, increasing, fitted, fitted_count, work, index_work = segments
    n = px.shape[0]
    min_seg = int(opt[O_MINSEG])
    needed = (n_corners + 1) * min_seg
    if n < needed:
        info[0] = n
        info[1] = needed
        return TOO_FEW_POINTS, 0, np.nan
    if not increasing:
        return X_NOT_INCREASING, 0, np.nan
    lines = fitted.copy()  # merged below; the segments serve the profile's next detection too
    count = fitted_count
    # merge nearly collinear neighbours, closest pair first
    while count > 1:
        best = np.inf
        j = -1
        for k in range(count - 1):
            if lines[k, 9] < opt[O_GAP] < lines[k + 1, 8]:
                continue  # a gap hides a face between these two (hidden_face.py): never one face
            a = lines[k, 2]
            b = lines[k + 1, 2]
            gap = abs(math.atan((a - b) / (1.0 + a * b)))
            if gap < best:
                best = gap
                j = k
        if not best < opt[O_MINANGLE]:
            break
        _fit_line(px, pz, int(lines[j, 0]), int(lines[j + 1, 1]), opt, lines, j, work, index_work)
        for k in range(j + 1, count - 1):
            lines[k, :] = lines[k + 1, :]
        count -= 1
    start = 0
    while start < count and abs(math.atan(lines[start, 2])) > opt[O_MAXFACE]:
        start += 1
    stop = count
    while stop > start and abs(math.atan(lines[stop - 1, 2])) > opt[O_MAXFACE]:
        stop -= 1
    for k in range(start, stop):
        if abs(math.atan(lines[k, 2])) > opt[O_MAXFACE]:
            info[0] = k - start
            info[1] = lines[k, 3]
            return STEEP_SEGMENT, 0, np.nan
    n_lines = stop - start
    if n_lines != n_corners + 1:
        info[0] = max(n_lines - 1, 0)
        info[1] = n_lines
        return WRONG_CORNER_COUNT, 0, np.nan
    # a gap hides a face: the corner between the faces either side of it is virtual (hidden_face.py)
    virtual = -1
    if math.isfinite(opt[O_GAP]):
        for i in range(n_corners):
            if lines[start + i, 9] < opt[O_GAP] < lines[start + i + 1, 8]:
                virtual = i
    jac[:, :] = 0.0
    for i in range(n_corners):
        a = lines[start + i]
        b = lines[start + i + 1]
        dm = a[2] - b[2]
        ba = a[4] - a[2] * a[3]
        bb = b[4] - b[2] * b[3]
        x = (bb - ba) / dm
        z = a[2] * (x - a[3]) + a[4]
        corners[i, 0] = x
        corners[i, 1] = z
        d0 = (a[3] - x) / dm
        d1 = -1.0 / dm
        d2 = (x - b[3]) / dm
        d3 = 1.0 / dm
        jac[2 * i, 2 * i] = d0
        jac[2 * i, 2 * i + 1] = d1
        jac[2 * i, 2 * i + 2] = d2
        jac[2 * i, 2 * i + 3] = d3
        jac[2 * i + 1, 2 * i] = a[2] * d0 + (x - a[3])
        jac[2 * i + 1, 2 * i + 1] = a[2] * d1 + 1.0
        jac[2 * i + 1, 2 * i + 2] = a[2] * d2
        jac[2 * i + 1, 2 * i + 3] = a[2] * d3
        low = a[9] - opt[O_MAXOFF]
        high = b[8] + opt[O_MAXOFF]
        if i == virtual:  # where two faces' planes cross, which may be anywhere along their lines
            low = -np.inf
            high = np.inf
        if not (low <= x <= high) or not (math.isfinite(x) and math.isfinite(z)):
            info[0] = i
            info[1] = x
            info[2] = a[9]
            info[3] = b[8]
            return CORNER_NOT_BETWEEN, 0, np.nan
    for i in range(n_corners - 1):
        before = i - 1 if i == virtual else i  # the real corners keep their order around a virtual one
        if before >= 0 and i + 1 != virtual and corners[i + 1, 0] - corners[before, 0] <= 0:
            return CORNERS_NOT_INCREASING, 0, np.nan
    used = 0.0
    ss = 0.0
    for k in range(n_lines):
        line = lines[start + k]
        sigma = opt[O_NOISE] if opt[O_NOISE] > 0 else max(line[7], opt[O_SIGFLOOR])
        line_var[2 * k] = sigma * sigma / line[5]
        line_var[2 * k + 1] = sigma * sigma / line[6]
        used += line[6] - 2
        ss += line[7] * line[7] * (line[6] - 2)
        lines_out[k, :] = line
    return OK, n_lines, math.sqrt(ss / max(1.0, used))


# ----------------------------------------------------------------------------- pose
@kernel(**JIT)
def _residuals(q, u, w, corners, rot, t, r):
    for i in range(corners.shape[0]):
        px = corners[i, 0]
        pz = corners[i, 1]
        mx = px * rot[0, 0] + pz * rot[0, 2] + t[0]
        my = px * rot[1, 0] + pz * rot[1, 2] + t[1]
        mz = px * rot[2, 0] + pz * rot[2, 2] + t[2]
        r[2 * i] = mx - u[i] * my - q[i, 0]
        r[2 * i + 1] = mz - w[i] * my - q[i, 2]


@kernel(**JIT)
def _jacobian(u, w, corners, rot, jac):
    """d r / d [delta, t] for R <- R exp([delta]x): rows C_i [-R [p]x, I]."""
    for i in range(corners.shape[0]):
        px = corners[i, 0]
        pz = corners[i, 1]
        # R [p]x with p = (px, 0, pz): columns = R @ [[0,-pz,0],[pz,0,-px],[0,px,0]]
        for row in range(3):
            m0 = rot[row, 1] * pz
            m1 = -rot[row, 0] * pz + rot[row, 2] * px
            m2 = -rot[row, 1] * px
            if row == 0:
                a0, a1, a2 = m0, m1, m2
            elif row == 1:
                b0, b1, b2 = m0, m1, m2
            else:
                c0, c1, c2 = m0, m1, m2
        jac[2 * i, 0] = -(a0 - u[i] * b0)
        jac[2 * i, 1] = -(a1 - u[i] * b1)
        jac[2 * i, 2] = -(a2 - u[i] * b2)
        jac[2 * i + 1, 0] = -(c0 - w[i] * b0)
        jac[2 * i + 1, 1] = -(c1 - w[i] * b1)
        jac[2 * i + 1, 2] = -(c2 - w[i] * b2)
        jac[2 * i, 3] = 1.0
        jac[2 * i, 4] = -u[i]
        jac[2 * i, 5] = 0.0
        jac[2 * i + 1, 3] = 0.0
        jac[2 * i + 1, 4] = -w[i]
        jac[2 * i + 1, 5] = 1.0


@kernel(**JIT)
def _residual_covariance(u, w, rot, corner_cov, out):
    """out = M C M^T with M block-diagonal, M_i = C_i R[:, (0, 2)] (see residuals.residual_covariance)."""
    n = u.shape[0]
    m = np.empty((n, 2, 2))
    for i in range(n):
        for col in range(2):
            c = 0 if col == 0 else 2
            m[i, 0, col] = rot[0, c] - u[i] * rot[1, c]
            m[i, 1, col] = rot[2, c] - w[i] * rot[1, c]
    for i in range(n):
        for j in range(n):
            for a in range(2):
                for b in range(2):
                    acc = 0.0
                    for c in range(2):
                        for d in range(2):
                            acc += m[i, a, c] * corner_cov[2 * i + c, 2 * j + d] * m[j, b, d]
                    out[2 * i + a, 2 * j + b] = acc


@kernel(**JIT)
def _cholesky(a, low):
    """low = L with a = L L^T; False if a is not positive definite."""
    n = a.shape[0]
    for j in range(n):
        s = a[j, j]
        for k in range(j):
            s -= low[j, k] * low[j, k]
        if not s > 0:
            return False
        low[j, j] = math.sqrt(s)
        for i in range(j + 1, n):
            s = a[i, j]
            for k in range(j):
                s -= low[i, k] * low[j, k]
            low[i, j] = s / low[j, j]
        for i in range(j):
            low[i, j] = 0.0
    return True


@kernel(**JIT)
def _cholesky_solve(low, b, x):
    n = b.shape[0]
    for i in range(n):
        s = b[i]
        for k in range(i):
            s -= low[i, k] * x[k]
        x[i] = s / low[i, i]
    for i in range(n - 1, -1, -1):
        s = x[i]
        for k in range(i + 1, n):
            s -= low[k, i] * x[k]
        x[i] = s / low[i, i]


@kernel(**JIT)
def _spd_inverse(a, out):
    """out = a^-1 for a symmetric positive definite a, as L^-T L^-1 from its Cholesky factor (half the
    work of n triangular solves); False if a is not positive definite."""
    n = a.shape[0]
    low = np.empty((n, n))
    if not _cholesky(a, low):
        return False
    inv = np.zeros((n, n))  # L^-1, lower triangular
    for j in range(n):
        inv[j, j] = 1.0 / low[j, j]
        for i in range(j + 1, n):
            s = 0.0
            for k in range(j, i):
                s -= low[i, k] * inv[k, j]
            inv[i, j] = s / low[i, i]
    for i in range(n):
        for j in range(i + 1):
            s = 0.0
            for k in range(i, n):  # (L^-T L^-1)[i, j] = sum_k inv[k, i] inv[k, j], k >= max(i, j)
                s += inv[k, i] * inv[k, j]
            out[i, j] = s
            out[j, i] = s
    return True


@kernel(**JIT)
def _normal_equations(jac, weight, r, jw, hessian, gradient):
    n2 = jac.shape[0]
    for a in range(6):
        for j in range(n2):
            acc = 0.0
            for i in range(n2):
                acc += jac[i, a] * weight[i, j]
            jw[a, j] = acc
    for a in range(6):
        for b in range(6):
            acc = 0.0
            for j in range(n2):
                acc += jw[a, j] * jac[j, b]
            hessian[a, b] = acc
        acc = 0.0
        for j in range(n2):
            acc += jw[a, j] * r[j]
        gradient[a] = acc


@kernel(**JIT)
def _matmul(a, b, out, transpose_b):
    """out = a @ b (or a @ b.T) for the small matrices here, without a BLAS call's overhead."""
    rows, inner = a.shape
    cols = b.shape[0] if transpose_b else b.shape[1]
    for i in range(rows):
        for j in range(cols):
            acc = 0.0
            for k in range(inner):
                acc += a[i, k] * (b[j, k] if transpose_b else b[k, j])
            out[i, j] = acc


@kernel(**JIT)
def _matmul3(a, b, out):
    for i in range(3):
        for j in range(3):
            out[i, j] = a[i, 0] * b[0, j] + a[i, 1] * b[1, j] + a[i, 2] * b[2, j]


@kernel(**JIT)
def _so3_exp(v, out):
    """Rodrigues: I + a K + b K^2 with K = [v]x, written out (no temporaries: it runs every iteration)."""
    x, y, z = v[0], v[1], v[2]
    theta2 = x * x + y * y + z * z
    if theta2 < 1e-16:
        a, b = 1.0, 0.5
    else:
        theta = math.sqrt(theta2)
        a, b = math.sin(theta) / theta, (1.0 - math.cos(theta)) / theta2
    # K^2 = v v^T - theta2 I
    out[0, 0] = 1.0 + b * (x * x - theta2)
    out[1, 1] = 1.0 + b * (y * y - theta2)
    out[2, 2] = 1.0 + b * (z * z - theta2)
    out[0, 1] = -a * z + b * x * y
    out[1, 0] = a * z + b * x * y
    out[0, 2] = a * y + b * x * z
    out[2, 0] = -a * y + b * x * z
    out[1, 2] = -a * x + b * y * z
    out[2, 1] = a * x + b * y * z


@kernel(**JIT)
def _quadratic(r, weight):
    n = r.shape[0]
    acc = 0.0
    for i in range(n):
        s = 0.0
        for j in range(n):
            s += weight[i, j] * r[j]
        acc += r[i] * s
    return acc


@kernel(**JIT)
def _householder_lstsq(a, b, x):
    """Least-squares solution of a x = b (rows >= columns) by Householder QR; returns the numerical rank."""
    m, n = a.shape
    if m < n:
        return m
    qa = a.copy()
    qb = b.copy()
    for k in range(n):
        norm = 0.0
        for i in range(k, m):
            norm += qa[i, k] * qa[i, k]
        norm = math.sqrt(norm)
        if norm == 0.0:
            continue
        alpha = -norm if qa[k, k] >= 0 else norm
        v = qa[k:, k].copy()
        v[0] -= alpha
        vnorm2 = 0.0
        for i in range(m - k):
            vnorm2 += v[i] * v[i]
        if vnorm2 == 0.0:
            continue
        for j in range(k, n):
            dot = 0.0
            for i in range(m - k):
                dot += v[i] * qa[k + i, j]
            f = 2.0 * dot / vnorm2
            for i in range(m - k):
                qa[k + i, j] -= f * v[i]
        dot = 0.0
        for i in range(m - k):
            dot += v[i] * qb[k + i]
        f = 2.0 * dot / vnorm2
        for i in range(m - k):
            qb[k + i] -= f * v[i]
    biggest = 0.0
    for k in range(n):
        biggest = max(biggest, abs(qa[k, k]))
    tol = np.finfo(np.float64).eps * max(m, n) * biggest
    rank = 0
    for k in range(n):
        if abs(qa[k, k]) > tol:
            rank += 1
    if rank < n:
        return rank
    for i in range(n - 1, -1, -1):
        s = qb[i]
        for k in range(i + 1, n):
            s -= qa[i, k] * x[k]
        x[i] = s / qa[i, i]
    return rank


@kernel(**JIT)
def _polar_rotation(m, out):
    """out = U V^T of m = U S V^T (the rotation nearest m) by Newton's polar iteration A <- (A + A^-T) / 2,
    when det(m) > 0 and it converges: the same rotation as the SVD's to rounding, without a LAPACK call
    that costs more than the iteration. False otherwise (a reflection is nearer, or m is near singular): use the SVD."""
    a = np.empty((3, 3))
    cof = np.empty((3, 3))
    a[:, :] = m
    for _ in range(30):
        for i in range(3):
            i1, i2 = (i + 1) % 3, (i + 2) % 3
            for j in range(3):
                j1, j2 = (j + 1) % 3, (j + 2) % 3
                cof[i, j] = a[i1, j1] * a[i2, j2] - a[i1, j2] * a[i2, j1]
        det = a[0, 0] * cof[0, 0] + a[0, 1] * cof[0, 1] + a[0, 2] * cof[0, 2]
        if not det > 0.0:
            return False
        change = 0.0
        for i in range(3):
            for j in range(3):
                new = 0.5 * (a[i, j] + cof[i, j] / det)  # A^-T = cofactor matrix / det
                change = max(change, abs(new - a[i, j]))
                a[i, j] = new
        if change <= 1e-15:  # quadratic convergence: the previous step was already at rounding level
            out[:, :] = a
            return True
    return False


@kernel(**JIT)
def _system(q, u, w, corners, a, b):
    """The stacked 2n x 9 system A x = b of eqs. (9)-(10) into a (zeroed here) and b."""
    a[:, :] = 0.0
    for i in range(corners.shape[0]):
        p0 = corners[i, 0]
        p1 = corners[i, 1]
        a[2 * i, 0] = p0
        a[2 * i, 1] = p1
        a[2 * i, 2] = 1.0
        a[2 * i, 3] = -u[i] * p0
        a[2 * i, 4] = -u[i] * p1
        a[2 * i, 5] = -u[i]
        a[2 * i + 1, 3] = -w[i] * p0
        a[2 * i + 1, 4] = -w[i] * p1
        a[2 * i + 1, 5] = -w[i]
        a[2 * i + 1, 6] = p0
        a[2 * i + 1, 7] = p1
        a[2 * i + 1, 8] = 1.0
        b[2 * i] = q[i, 0]
        b[2 * i + 1] = q[i, 2]


@kernel(**JIT)
def _pose_from_x(x, rot, t):
    """Eqs. (12)-(14): x = rows of M = [r1 r3 t] -> the nearest rotation and the rescaled translation."""
    r_hat = np.empty((3, 3))
    for k in range(3):
        r_hat[k, 0] = x[3 * k]
        r_hat[k, 2] = x[3 * k + 1]
        t[k] = x[3 * k + 2]
    r_hat[0, 1] = r_hat[1, 2] * r_hat[2, 0] - r_hat[2, 2] * r_hat[1, 0]  # r2 = r3 x r1
    r_hat[1, 1] = r_hat[2, 2] * r_hat[0, 0] - r_hat[0, 2] * r_hat[2, 0]
    r_hat[2, 1] = r_hat[0, 2] * r_hat[1, 0] - r_hat[1, 2] * r_hat[0, 0]
    norm_hat = math.sqrt(np.sum(r_hat * r_hat))
    if not math.isfinite(norm_hat) or norm_hat == 0:
        return CF_DEGENERATE
    if not _polar_rotation(r_hat, rot):
        uu, _, vt = np.linalg.svd(r_hat)
        _matmul3(uu, vt, rot)
        if np.linalg.det(rot) < 0:
            for i in range(3):
                uu[i, 2] = -uu[i, 2]
            _matmul3(uu, vt, rot)
    scale = math.sqrt(np.sum(rot * rot)) / norm_hat
    for k in range(3):
        t[k] *= scale
    return OK


@kernel(**JIT)
def _closed_form(q, u, w, corners, info):
    """Paper eqs. (9)-(14), the least squares by Householder QR. Returns (status, R, t)."""
    n = corners.shape[0]
    a = np.empty((2 * n, 9))
    b = np.empty(2 * n)
    _system(q, u, w, corners, a, b)
    x = np.empty(9)
    rank = _householder_lstsq(a, b, x)
    rot = np.empty((3, 3))
    t = np.empty(3)
    if rank < 9:
        info[0] = rank
        return CF_RANK, rot, t
    return _pose_from_x(x, rot, t), rot, t


@kernel(**JIT)
def _weighted_step_chi2(u, w, corners, rot, r, weight):
    """How far (chi-square, step^T H step) one Gauss-Newton step under these weights would move the pose."""
    n2 = r.shape[0]
    jac, jw, hessian, gradient = np.empty((n2, 6)), np.empty((6, n2)), np.empty((6, 6)), np.empty(6)
    low, step = np.empty((6, 6)), np.empty(6)
    _jacobian(u, w, corners, rot, jac)
    _normal_equations(jac, weight, r, jw, hessian, gradient)
    if not _cholesky(hessian, low):
        return np.inf
    _cholesky_solve(low, gradient, step)
    chi2 = 0.0
    for a in range(6):
        chi2 += step[a] * gradient[a]
    return chi2


@kernel(**JIT)
def _descend(q, u, w, corners, rot, t, r, weight, max_iterations, polish):
    """Levenberg-Marquardt, then undamped Gauss-Newton steps (unless polish is False), on the cost r^T W r with
    the weights fixed; rot, t and r are updated in place. Returns (status, iterations)."""
    n2 = 2 * corners.shape[0]
    new_r = np.empty(n2)
    cost = _quadratic(r, weight)
    damping = 1e-6
    iterations = 0
    jac = np.empty((n2, 6))
    jw = np.empty((6, n2))
    hessian = np.empty((6, 6))
    damped = np.empty((6, 6))
    low = np.empty((6, 6))
    gradient = np.empty(6)
    step = np.empty(6)
    rstep = np.empty((3, 3))
    new_rot = np.empty((3, 3))
    new_t = np.empty(3)
    polishing = False
    total = max_iterations + (POLISH_STEPS if max_iterations > 0 and polish else 0)
    it = 0
    while it < total:
        it += 1
        if it > max_iterations:
            polishing = True
        _jacobian(u, w, corners, rot, jac)
        _normal_equations(jac, weight, r, jw, hessian, gradient)
        damped[:, :] = hessian
        if not polishing:
            for k in range(6):
                damped[k, k] += damping * hessian[k, k]
        if not _cholesky(damped, low):
            return SINGULAR, iterations
        for k in range(6):
            gradient[k] = -gradient[k]
        _cholesky_solve(low, gradient, step)
        _so3_exp(step[:3], rstep)
        _matmul3(rot, rstep, new_rot)
        for k in range(3):
            new_t[k] = t[k] + step[3 + k]
        _residuals(q, u, w, corners, new_rot, new_t, new_r)
        new_cost = _quadratic(new_r, weight)
        biggest = 0.0
        for k in range(6):
            biggest = max(biggest, abs(step[k]))
        if polishing:
            if new_cost > cost * (1.0 + POLISH_COST_TOLERANCE):
                break
            rot[:, :] = new_rot
            t[:] = new_t
            cost = new_cost
            r[:] = new_r
            if biggest < POLISH_STEP_TOLERANCE:
                break
            continue
        iterations = it
        if new_cost <= cost:
            converged = cost - new_cost <= POLISH_COST_TOLERANCE * cost
            rot[:, :] = new_rot
            t[:] = new_t
            cost = new_cost
            r[:] = new_r
            damping = max(damping / 10.0, 1e-12)
            if converged or biggest < 1e-13:
                it = max_iterations  # go on with the polish
        else:
            damping *= 10.0
            if damping > 1e8 or new_cost - cost <= POLISH_COST_TOLERANCE * cost:
                it = max_iterations
    return OK, iterations


@kernel(**JIT)
def _refine(q, u, w, corners, rot, t, corner_cov, weighted, max_iterations, polish, cov_out, rounds):
    """Levenberg-Marquardt + Gauss-Newton polish (unless polish is False) on SO(3) x R^3.

    Returns (status, R, t, residuals, iterations, chi2); cov_out gets the (6, 6) covariance over [delta_F, t] (none
    if cov_out is (0, 0)), chi2 is the residuals' squared Mahalanobis length under the covariance the corners
    induce (inf if that is singular).

    The weights (the inverse of the residuals' covariance, which turns with the pose) are formed at the start
    and, up to `rounds` times in all, formed again at the minimum until they no longer move it: a start far
    from the minimum (a virtual ridge of a hidden face that runs nearly along the laser plane) otherwise
    leaves the minimum of a mis-weighted cost, off the maximum-likelihood pose by several of its standard
    deviations in the direction the weights turned (docs/estimator.md). A round that ends at max_iterations
    stopped short of a minimum (a start creeping along a flat valley, as a four-ridge gauge's wrong starts do):
    no weights are formed again there, or each further round would cost max_iterations more. The basin
    search's and the unscented transform's many refinements take one round: they start at or compare minima,
    and more rounds there doubled a poorly determined profile's time.
    """
    n2 = 2 * corners.shape[0]
    rot = rot.copy()  # the current pose, updated in place: the loop allocates nothing
    t = t.copy()
    r = np.empty(n2)
    _residuals(q, u, w, corners, rot, t, r)
    sigma_r = np.empty((n2, n2))
    information = np.empty((n2, n2))
    weight = np.eye(n2)
    if weighted:
        _residual_covariance(u, w, rot, corner_cov, sigma_r)
        if not _spd_inverse(sigma_r, weight):
            return SINGULAR, rot, t, r, 0, np.inf
    iterations = 0
    invertible = False
    chi2 = np.inf
    for round_ in range(rounds if weighted else 1):
        status, done = _descend(q, u, w, corners, rot, t, r, weight, max_iterations, polish)
        iterations += done
        if status != OK:
            return status, rot, t, r, iterations, np.inf
        # the weights at this minimum, which the covariance below needs anyway: would they move it?
        _residual_covariance(u, w, rot, corner_cov, sigma_r)
        invertible = _spd_inverse(sigma_r, information)
        chi2 = _quadratic(r, information) if invertible else np.inf
        if not (weighted and invertible) or round_ == rounds - 1 or done >= max_iterations or \
                chi2 > REWEIGHT_HOPELESS_CHI2 * n2 or \
                _weighted_step_chi2(u, w, corners, rot, r, information) < REWEIGHT_CHI2:
            break
        weight[:, :] = information
    if weighted:
        if not invertible:
            return SINGULAR, rot, t, r, iterations, np.inf
        weight = information
    if cov_out.shape[0] == 0:  # no covariance wanted (the basin search's triage): half the cost of a short run
        return OK, rot, t, r, iterations, chi2
    jac, jw, hessian, gradient = np.empty((n2, 6)), np.empty((6, n2)), np.empty((6, 6)), np.empty(6)
    _jacobian(u, w, corners, rot, jac)
    _normal_equations(jac, weight, r, jw, hessian, gradient)
    bread = np.empty((6, 6))
    if not _spd_inverse(hessian, bread):
        return SINGULAR, rot, t, r, iterations, np.inf
    js = np.empty((6, n2))
    _matmul(jw, sigma_r, js, False)  # J^T W Sigma_r
    meat = np.empty((6, 6))
    _matmul(js, jw, meat, True)  # J^T W Sigma_r W J
    half = np.empty((6, 6))
    _matmul(bread, meat, half, False)
    _matmul(half, bread, cov_out, False)
    for a in range(6):
        for b in range(a + 1, 6):
            mean = 0.5 * (cov_out[a, b] + cov_out[b, a])
            cov_out[a, b] = mean
            cov_out[b, a] = mean
    return OK, rot, t, r, iterations, chi2


# m^2: a pose whose translation variance (trace) exceeds this gets the curvature of its weak mode's valley in
# its covariance (_add_curvature_term); below it the term is far inside the linear one
CURVED_ABOVE = 1e-8
# (chi-square(1)'s 99 % point / the Gaussian's two-sided 99 % point)^2 = (6.635 / 2.576)^2: the variance along
# the valley's curvature whose Gaussian 99 % point is the quadratic error's
CURVE_TAIL = 6.63
# power iterations for the weakest direction, at most: its variance leads the next by 5-100x here, so the
# direction settles to rounding within 5-25 of them, and the iteration stops once a step moves it by less
POWER_STEPS = 60
POWER_SETTLED = 1e-15


@kernel(**JIT)
def _weakest_direction(cov, v):
    """v = the unit eigenvector of cov's largest eigenvalue (power iteration); returns that eigenvalue."""
    w = np.empty(6)
    for a in range(6):
        v[a] = 1.0 / math.sqrt(6.0)
    value = 0.0
    for _ in range(POWER_STEPS):
        for a in range(6):
            w[a] = 0.0
            for b in range(6):
                w[a] += cov[a, b] * v[b]
        value = 0.0
        for a in range(6):
            value += w[a] * w[a]
        value = math.sqrt(value)
        if value == 0.0:
            return 0.0
        moved = 0.0
        for a in range(6):
            w[a] /= value
            moved = max(moved, abs(w[a] - v[a]))
            v[a] = w[a]
        if moved < POWER_SETTLED:
            break
    return value


@kernel(**JIT)
def _moved_pose(rot, t, v, distance, moved, shifted):
    """(moved, shifted) = the pose (rot, t) moved `distance` along v = [delta_F, t] (the refinement's step)."""
    step, turn = np.empty(3), np.empty((3, 3))
    for a in range(3):
        step[a] = distance * v[a]
        shifted[a] = t[a] + distance * v[3 + a]
    _so3_exp(step, turn)
    _matmul3(rot, turn, moved)


@kernel(**JIT)
def _add_curvature_term(cov, hessian, curved, v, variance):
    """cov += the spread the curvature of the weak mode's valley adds (a least-squares pose, either model).

    Where a pose is poorly determined its error e along the weakest direction v (variance s^2) is large, and
    the minimum of the cost for that e lies off the straight line e v by b(e) = -c e^2 with
    c = 1/2 H^-1 J^T W p'' (p'' the model's second derivative along v; `curved` = J^T W p'', `hessian` =
    J^T W J): the linearised covariance sees e v but not b, which lands in directions it calls tight. Along
    c, b / (|c| s^2) is chi-square(1) distributed, heavier-tailed than a Gaussian: its second moment (3 s^4)
    leaves 1 % of the errors beyond 4.5 standard deviations where a Gaussian puts them beyond 2.6. The term
    added covers its 99 % point instead, CURVE_TAIL s^4 c c^T, so that a consumer's 99 % gate on this
    covariance holds (the part of c along v is left out: the linear term owns v)."""
    low, c = np.empty((6, 6)), np.empty(6)
    if not _cholesky(hessian, low):
        return
    _cholesky_solve(low, curved, c)
    hv, hc = 0.0, 0.0
    for a in range(6):
        for b in range(6):
            hv += v[a] * hessian[a, b] * v[b]
            hc += v[a] * hessian[a, b] * c[b]
    for a in range(6):
        c[a] = 0.5 * (c[a] - hc / hv * v[a])
    for a in range(6):
        for b in range(6):
            cov[a, b] += CURVE_TAIL * variance * variance * c[a] * c[b]


@kernel(**JIT)
def _add_corner_valley_curvature(q, u, w, corners, rot, t, corner_cov, cov):
    """_add_curvature_term for the corner model's (weighted) pose: p'' from the corner residuals at +-s v."""
    n2 = 2 * corners.shape[0]
    v = np.empty(6)
    variance = _weakest_direction(cov, v)
    s = math.sqrt(variance)
    r0, moved_r, second = np.empty(n2), np.empty(n2), np.zeros(n2)
    _residuals(q, u, w, corners, rot, t, r0)
    moved, shifted = np.empty((3, 3)), np.empty(3)
    for sign in (1.0, -1.0):
        _moved_pose(rot, t, v, sign * s, moved, shifted)
        _residuals(q, u, w, corners, moved, shifted, moved_r)
        for i in range(n2):
            second[i] += (moved_r[i] - r0[i]) / variance
    sigma_r, weight = np.empty((n2, n2)), np.empty((n2, n2))
    _residual_covariance(u, w, rot, corner_cov, sigma_r)
    if not _spd_inverse(sigma_r, weight):
        return
    jac, jw, hessian, curved = np.empty((n2, 6)), np.empty((6, n2)), np.empty((6, 6)), np.empty(6)
    _jacobian(u, w, corners, rot, jac)
    _normal_equations(jac, weight, second, jw, hessian, curved)
    _add_curvature_term(cov, hessian, curved, v, variance)


@kernel(**JIT)
def _unstack_residuals(r, out):
    """(2n,) -> (n, 2) residuals; returns their mean norm (the reprojection error)."""
    n = out.shape[0]
    total = 0.0
    for i in range(n):
        out[i, 0] = r[2 * i]
        out[i, 1] = r[2 * i + 1]
        total += math.hypot(r[2 * i], r[2 * i + 1])
    return total / n


@kernel(**JIT)
def detect(points, n_corners, opt, corners, jac, line_var, info, lines_out):
    """Corner detection alone (stages.detect_corners: studies, the NEES tools, the wrong-minimum check); on a
    writable copy of opt, as the estimate detects (profile_kernel.estimate: one compiled detection for all)."""
    return _detect(points, n_corners, opt.copy(), corners, jac, line_var, info, lines_out)


@kernel(**JIT)
def refine_pose(q, u, w, corners, rot, t, corner_cov, weighted, max_iterations, polish, rot_out, t_out, r_out,
                cov_out):
    """The refinement from a given start (stages.refine_pose: the wrong-minimum check, tests). Returns
    (status, iterations); the pose, the stacked residuals and the (6, 6) covariance over [delta_F, t] go to the
    *_out arrays."""
    status, rot2, t2, r2, iterations, _ = _refine(q, u, w, corners, rot, t, corner_cov, weighted, max_iterations,
                                                  polish, cov_out, REWEIGHT_ROUNDS)
    rot_out[:, :] = rot2
    t_out[:] = t2
    r_out[:] = r2
    return status, iterations
