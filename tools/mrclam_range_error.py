#!/usr/bin/env python3
"""MRCLAM landmark range and bearing errors against Vicon truth, by true range.

For every landmark reading of the five robots (barcodes mapped to subjects, robots and
misreads skipped), the robot's truth pose is the Vicon sample at or just after the reading
(within 0.1 s); readings more than 0.5 m off in range (gross outliers) are left out. Prints,
per metre of true range, the count, the mean range error (measured - true), its standard
deviation and the mean bearing error.

    python3 tools/mrclam_range_error.py [../shared/datasets/mrclam-dataset6]
"""
import bisect
import math
import sys
from collections import defaultdict

D = sys.argv[1] if len(sys.argv) > 1 else "../shared/datasets/mrclam-dataset6"


def rows(name):
    with open(f"{D}/{name}") as f:
        return [list(map(float, l.split())) for l in f if l.strip() and not l.startswith("#")]


def wrap(a):
    return (a + math.pi) % (2 * math.pi) - math.pi


subject = {int(b): int(s) for s, b in rows("Barcodes.dat")}
landmark = {int(s): (x, y) for s, x, y, _, _ in rows("Landmark_Groundtruth.dat")}
bins = defaultdict(list)
for r in range(1, 6):
    truth = rows(f"Robot{r}_Groundtruth.dat")
    times = [g[0] for g in truth]
    for t, barcode, rng, brg in rows(f"Robot{r}_Measurement.dat"):
        s = subject.get(int(barcode))
        if s is None or s < 6:
            continue
        i = bisect.bisect_left(times, t)
        if i <= 0 or i >= len(times) or times[i] - times[i - 1] > 0.1:
            continue
        x, y, th = truth[i][1:]
        lx, ly = landmark[s]
        true_range = math.hypot(lx - x, ly - y)
        true_bearing = wrap(math.atan2(ly - y, lx - x) - th)
        e = rng - true_range
        if abs(e) > 0.5:
            continue
        bins[int(true_range)].append((e, wrap(brg - true_bearing)))

print("true range [m] | readings | mean range error [m] | sd [m] | mean bearing error [rad]")
for k in sorted(bins):
    v = bins[k]
    m = sum(e for e, _ in v) / len(v)
    sd = math.sqrt(sum((e - m) ** 2 for e, _ in v) / len(v))
    mb = sum(b for _, b in v) / len(v)
    print(f"{k}-{k + 1} | {len(v)} | {m:+.4f} | {sd:.4f} | {mb:+.4f}")
