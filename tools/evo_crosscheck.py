#!/usr/bin/env python3
"""Cross-check `fleetslam evaluate` against `evo_ape` (PyPI `evo`) on the same TUM files.

Simulates a small scenario with the fleetslam binary (`simulate`, then `run`), and compares
the ATE RMSE (and heading RMSE) that `fleetslam evaluate` writes to `evaluation.json` with
what `evo_ape` computes on the same `trajectory_<robot>.tum` files, per robot and for the
team, without alignment (`--align none` against plain `evo_ape`) and with it (`--align se2`
against `evo_ape -a`, SE(3) Umeyama, which on planar z = 0 data is the SE(2) fit). Exits 1
and prints the table when any difference exceeds `--tol` (default 1e-6, absolute).

Two estimates are checked: the run's own (in the truth's frame, so the fit is nearly the
identity) and a copy the script moves by a known rigid transform, which only the alignment
can undo.

Making both tools see the same pose pairs:

* Association. fleetslam compares each estimate pose with the truth *interpolated* at its
  time; evo pairs poses by *nearest* timestamp (within `--t_max_diff`, 0.01 s). The
  simulator's truth holds every robot's pose at each record time, and `run` writes one
  estimate pose per record, so every estimate time is a truth sample: fleetslam's
  interpolation returns that sample and evo's nearest match is that sample. The script
  checks this (every estimate time within 1e-6 s of a truth time, truth samples at least
  0.02 s apart) and stops otherwise, rather than resampling the truth itself.
* Alignment. fleetslam fits ONE SE(2) transform for the whole team (over all robots' pose
  pairs), while `evo_ape -a` fits one per file pair. So the team is also fed to evo as one
  trajectory: robot k's poses, truth and estimate alike, with k * OFFSET seconds added to
  their timestamps (OFFSET longer than any run, so robots never associate with each other).
  evo's RMSE on that pair is the team ATE; the per-robot ATE under the team alignment is
  the RMS of evo's own per-pose errors (`error_array` of `--save_results`) over that
  robot's time segment. Without alignment, evo also runs on each robot's files directly.
  (evo's per-robot `-a` has no fleetslam counterpart and is not compared.)

Not compared: RPE (evo pairs poses by nearest path distance within a tolerance or
consecutively, fleetslam takes the first pose at least `--rpe-distance` further for every
pose) and landmark errors (evo has none).

    pip install evo
    python3 tools/evo_crosscheck.py [--fleetslam PATH_TO_BINARY] [--keep DIR]
"""
import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
# Seconds between robots' segments in the concatenated team files.
OFFSET = 100000.0


def find_binary(given):
    if given:
        return given
    found = shutil.which("fleetslam")
    if found:
        return found
    dirs = [os.environ.get("CARGO_TARGET_DIR"), REPO / "target"]
    for d in filter(None, dirs):
        for profile in ("release", "debug"):
            p = Path(d) / profile / "fleetslam"
            if p.is_file():
                return str(p)
    sys.exit("fleetslam binary not found: pass --fleetslam PATH (or put it on PATH)")


def run(cmd, **kw):
    r = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, **kw)
    if r.returncode != 0:
        sys.exit(f"failed ({r.returncode}): {' '.join(map(str, cmd))}\n{r.stdout}\n{r.stderr}")
    return r.stdout


def read_tum(path):
    rows = []
    with open(path) as f:
        for line in f:
            line = line.strip()
            if line and not line.startswith("#"):
                rows.append([float(v) for v in line.split()])
    return rows


def write_tum(path, rows):
    with open(path, "w") as f:
        for r in rows:
            f.write(" ".join(f"{v:.9f}" for v in r) + "\n")


def robots_in(d):
    return sorted(p.name[len("trajectory_"):-len(".tum")] for p in Path(d).glob("trajectory_*.tum"))


def check_association(est_dir, truth_dir, robots):
    """Every estimate time is a truth sample, and truth samples are further apart than
    evo's --t_max_diff: then both tools pair each estimate pose with that sample."""
    for r in robots:
        truth_t = [row[0] for row in read_tum(Path(truth_dir) / f"trajectory_{r}.tum")]
        gaps = [b - a for a, b in zip(truth_t, truth_t[1:])]
        if gaps and min(gaps) <= 0.02:
            sys.exit(f"robot {r}: truth samples {min(gaps)} s apart; evo's nearest match is ambiguous")
        for row in read_tum(Path(est_dir) / f"trajectory_{r}.tum"):
            t = row[0]
            # Nearest truth time (truth is sorted).
            lo, hi = 0, len(truth_t)
            while lo < hi:
                mid = (lo + hi) // 2
                if truth_t[mid] < t:
                    lo = mid + 1
                else:
                    hi = mid
            near = min(
                (abs(truth_t[i] - t) for i in (lo - 1, lo) if 0 <= i < len(truth_t)),
                default=math.inf,
            )
            if near > 1e-6:
                sys.exit(
                    f"robot {r}: estimate time {t} is not a truth sample (nearest {near} s off): "
                    "fleetslam would interpolate and evo take the nearest; not comparable"
                )


def moved_copy(src, dst, robots, tx, ty, phi):
    """The estimate moved rigidly by x -> R(phi) x + t (headings turned by phi); no
    metrics.json, so the copy does not claim the truth's frame."""
    dst.mkdir(parents=True)
    c, s = math.cos(phi), math.sin(phi)
    for r in robots:
        out = []
        for t, x, y, z, qx, qy, qz, qw in read_tum(src / f"trajectory_{r}.tum"):
            yaw = math.atan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz)) + phi
            out.append([t, c * x - s * y + tx, s * x + c * y + ty, z, 0, 0,
                        math.sin(yaw / 2), math.cos(yaw / 2)])
        write_tum(dst / f"trajectory_{r}.tum", out)


def concatenate(src, robots, path):
    """One trajectory of all robots: robot k's times shifted by k * OFFSET."""
    rows = []
    for k, r in enumerate(robots):
        for row in read_tum(Path(src) / f"trajectory_{r}.tum"):
            rows.append([row[0] + k * OFFSET] + row[1:])
    write_tum(path, rows)


def evo_ape(evo, ref, est, zip_path, align, relation):
    """Runs evo_ape and returns (rmse, timestamps, error_array, alignment matrix) from its
    saved results."""
    from evo.tools import file_interface

    cmd = [evo, "tum", ref, est, "-r", relation, "--save_results", zip_path, "--no_warnings"]
    if align:
        cmd.append("-a")
    run(cmd)
    res = file_interface.load_res_file(str(zip_path))
    return (
        float(res.stats["rmse"]),
        res.np_arrays["timestamps"],
        res.np_arrays["error_array"],
        res.np_arrays.get("alignment_transformation_sim3"),
    )


def fleetslam_eval(binary, est_dir, truth_dir, align):
    run([binary, "evaluate", est_dir, "--truth", truth_dir, "--align", align])
    with open(Path(est_dir) / "evaluation.json") as f:
        ev = json.load(f)
    assert ev["alignment"] == align, ev["alignment"]
    return ev


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fleetslam", help="the fleetslam binary (default: on PATH, else target/)")
    ap.add_argument("--evo-ape", default="evo_ape", help="the evo_ape command")
    ap.add_argument("--robots", type=int, default=3)
    ap.add_argument("--landmarks", type=int, default=20)
    ap.add_argument("--duration", type=float, default=40.0)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--particles", type=int, default=30)
    ap.add_argument("--tol", type=float, default=1e-6, help="largest |difference| allowed")
    ap.add_argument("--keep", help="work in this (new) directory and keep it")
    a = ap.parse_args()

    binary = find_binary(a.fleetslam)
    evo = shutil.which(a.evo_ape) or sys.exit(f"{a.evo_ape} not found: pip install evo")
    try:
        import evo as evo_pkg
        from evo.tools import file_interface  # noqa: F401 (reads evo's result zips)
    except ImportError:
        sys.exit(f"{sys.executable} cannot import evo: pip install evo (for this Python)")

    print(f"fleetslam: {binary} ({run([binary, '--version']).strip()}); evo {evo_pkg.__version__}")
    work = Path(a.keep) if a.keep else Path(tempfile.mkdtemp(prefix="evo_crosscheck_"))
    work.mkdir(parents=True, exist_ok=True)
    sim, est = work / "sim", work / "run"
    run([binary, "simulate", "--robots", a.robots, "--landmarks", a.landmarks,
         "--duration", a.duration, "--seed", a.seed, "--out", sim])
    run([binary, "run", sim / "log.ndjson", "--out", est, "--particles", a.particles,
         "--seed", a.seed, "--threads", 1])
    truth = sim / "truth"
    robots = robots_in(est)
    if robots != robots_in(truth):
        sys.exit(f"estimate robots {robots} != truth robots {robots_in(truth)}")
    moved = work / "run_moved"
    moved_copy(est, moved, robots, 4.0, -2.5, 0.7)

    evo_dir = work / "evo"
    evo_dir.mkdir()
    concatenate(truth, robots, evo_dir / "truth_team.tum")

    rows, worst = [], 0.0
    for name, est_dir in (("run", est), ("moved", moved)):
        check_association(est_dir, truth, robots)
        concatenate(est_dir, robots, evo_dir / f"{name}_team.tum")
        for align in ("none", "se2"):
            ev = fleetslam_eval(binary, est_dir, truth, align)
            shutil.copy(Path(est_dir) / "evaluation.json", evo_dir / f"{name}_{align}.json")
            for metric, relation, key in (("ATE", "trans_part", "ate_rmse"),
                                          ("heading", "angle_rad", "heading_rmse")):
                tag = f"{name}_{align}_{relation}"
                team_rmse, stamps, errors, tf = evo_ape(
                    evo, evo_dir / "truth_team.tum", evo_dir / f"{name}_team.tum",
                    evo_dir / f"{tag}_team.zip", align == "se2", relation)
                if tf is not None and tf[2, 2] < 0:
                    sys.exit(f"{tag}: evo's SE(3) fit mirrors the plane (R[2,2] = {tf[2, 2]}); "
                             "no rotation of the plane matches it")
                checks = [("team", team_rmse, ev["team"][key])]
                segment = ((stamps + OFFSET / 2) // OFFSET).astype(int)
                for k, r in enumerate(robots):
                    seg = errors[segment == k]
                    if len(seg) != ev["robots"][r]["matched_poses"]:
                        sys.exit(f"{tag}: robot {r}: evo paired {len(seg)} poses, fleetslam "
                                 f"{ev['robots'][r]['matched_poses']}")
                    if align == "none":
                        # evo on this robot's own files.
                        rmse, _, _, _ = evo_ape(
                            evo, truth / f"trajectory_{r}.tum", Path(est_dir) / f"trajectory_{r}.tum",
                            evo_dir / f"{tag}_{r}.zip", False, relation)
                        # ... and its segment of the team run.
                        checks.append((f"{r} (team file)", float(math.sqrt((seg ** 2).mean())),
                                       ev["robots"][r][key]))
                    else:
                        rmse = float(math.sqrt((seg ** 2).mean()))
                    checks.append((r, rmse, ev["robots"][r][key]))
                for who, evo_v, fs_v in checks:
                    diff = abs(evo_v - fs_v)
                    worst = max(worst, diff)
                    rows.append((name, align, metric, who, fs_v, evo_v, diff))

    print(f"{'estimate':8} {'align':5} {'metric':7} {'robot':14} {'fleetslam':>14} "
          f"{'evo_ape':>14} {'|diff|':>9}")
    for name, align, metric, who, fs_v, evo_v, diff in rows:
        flag = "  MISMATCH" if not diff <= a.tol else ""
        print(f"{name:8} {align:5} {metric:7} {who:14} {fs_v:14.9f} {evo_v:14.9f} "
              f"{diff:9.2e}{flag}")
    print(f"max |difference| = {worst:.3e} over {len(rows)} comparisons (tolerance {a.tol:g}; "
          "ATE in m, heading in rad)")
    if not a.keep and worst <= a.tol:
        shutil.rmtree(work)
    else:
        print(f"files kept in {work}")
    if not worst <= a.tol:
        print("MISMATCH: fleetslam evaluate and evo_ape disagree", file=sys.stderr)
        sys.exit(1)
    print("OK: fleetslam evaluate agrees with evo_ape")


if __name__ == "__main__":
    main()
