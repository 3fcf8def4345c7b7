#!/usr/bin/env python3
"""Which of the C library's elementary functions round differently by CPU variant.

glibc picks, when a process starts, an implementation of `exp`, `log`, `sin`, ... for the
CPU it finds (on x86-64, variants that use FMA instructions where the CPU has them).
Python's `math` module calls those same functions. This evaluates each function over
200,000 pseudo-random arguments, once as the process finds the CPU and once in a child
with `GLIBC_TUNABLES=glibc.cpu.hwcaps=-AVX2,-FMA` (glibc's baseline variants), and prints
how many arguments give different bits. fleetslam computes with the `libm` crate instead
(crates/fleetslam-core/src/math.rs).

    python3 tools/glibc_variants.py
"""
import math
import os
import random
import struct
import subprocess
import sys

N = 200_000
FUNCTIONS = {
    "exp": (math.exp, -20.0, 20.0),
    "log": (math.log, 1e-6, 50.0),
    "log1p": (math.log1p, 1e-6, 50.0),
    "expm1": (math.expm1, -20.0, 20.0),
    "pow (x^1.7)": (lambda x: math.pow(x, 1.7), 1e-6, 50.0),
    "sin": (math.sin, -20.0, 20.0),
    "cos": (math.cos, -20.0, 20.0),
    "tan": (math.tan, -20.0, 20.0),
    "atan": (math.atan, -20.0, 20.0),
    "atan2 (y, 1.3)": (lambda y: math.atan2(y, 1.3), -20.0, 20.0),
    "asin": (math.asin, -1.0, 1.0),
    "acos": (math.acos, -1.0, 1.0),
    "tanh": (math.tanh, -20.0, 20.0),
    "hypot (x, 0.7)": (lambda x: math.hypot(x, 0.7), -20.0, 20.0),
    "sqrt": (math.sqrt, 1e-6, 50.0),
}


def values():
    rng = random.Random(1)
    out = {}
    for name, (f, lo, hi) in FUNCTIONS.items():
        out[name] = [struct.pack("<d", f(rng.uniform(lo, hi))) for _ in range(N)]
    return out


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        for name, vals in values().items():
            sys.stdout.write(name + "\t" + b"".join(vals).hex() + "\n")
        sys.exit(0)
    env = dict(os.environ, GLIBC_TUNABLES="glibc.cpu.hwcaps=-AVX2,-FMA")
    child = subprocess.run(
        [sys.executable, __file__, "--child"], env=env, capture_output=True, text=True, check=True
    )
    theirs = dict(line.split("\t") for line in child.stdout.splitlines())
    for name, vals in values().items():
        other = bytes.fromhex(theirs[name])
        differ = sum(1 for i, v in enumerate(vals) if other[8 * i : 8 * i + 8] != v)
        print(f"{name:16} {differ:6} of {N} arguments give other bits without FMA")
