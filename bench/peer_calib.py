#!/usr/bin/env python3
"""OpenCV's stereo calibration beside spinscan's, on the same chessboard pairs, in one run.

    ../.venv-peers/bin/python bench/peer_calib.py DIR [--board 9x6] [--square-mm 24]
        [--ours calib.yaml] [--ours-cmd "spinscan calibrate stereo ... -o calib.yaml"]

DIR holds left*.jpg / right*.jpg (paired in sorted order). OpenCV finds the boards
(findChessboardCorners + cornerSubPix with an 11-pixel half-window, as ../shared's corners.json), calibrates each
camera (calibrateCamera, 5 coefficients) and then both jointly (stereoCalibrate with the
intrinsics as a guess and refined), and prints the RMS values, |T| and the corners' row
mismatch after rectification. With --ours-cmd the command runs first (its wall time is
printed beside OpenCV's); with --ours (or the -o of --ours-cmd) the same figures are printed
for spinscan's calib.yaml, whose rectification is computed here by OpenCV from its M D R T,
on OpenCV's corners, so the two rows differ only by the calibration.
"""
import argparse
import glob
import os
import shlex
import subprocess
import sys
import time

import cv2
import numpy as np


def board_points(cols, rows, square):
    obj = np.zeros((cols * rows, 3), np.float32)
    obj[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square
    return obj


def detect(paths, pattern):
    found = []
    for p in paths:
        img = cv2.imread(p, cv2.IMREAD_GRAYSCALE)
        ok, c = cv2.findChessboardCorners(img, pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if ok:
            c = cv2.cornerSubPix(img, c, (11, 11), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01))
        found.append(c if ok else None)
        size = (img.shape[1], img.shape[0])
    return found, size


def read_calib(path):
    fs = cv2.FileStorage(path, cv2.FILE_STORAGE_READ)
    get = lambda k: fs.getNode(k).mat()
    out = {k: get(k) for k in ("M1", "D1", "M2", "D2", "R", "T")}
    for k in ("rms_left", "rms_right", "rms_stereo"):
        n = fs.getNode(k)
        out[k] = None if n.empty() else n.real()
    return out


def row_mismatch(c, size, left, right):
    R1, R2, P1, P2, *_ = cv2.stereoRectify(c["M1"], c["D1"], c["M2"], c["D2"], size, c["R"], c["T"],
                                           flags=cv2.CALIB_ZERO_DISPARITY, alpha=-1)
    per_pair = []
    for l, r in zip(left, right):
        ul = cv2.undistortPoints(l, c["M1"], c["D1"], R=R1, P=P1)
        ur = cv2.undistortPoints(r, c["M2"], c["D2"], R=R2, P=P2)
        per_pair.append(float(np.mean(np.abs(ul[:, 0, 1] - ur[:, 0, 1]))))
    return float(np.mean(per_pair)), float(np.max(per_pair))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dir")
    ap.add_argument("--board", default="9x6")
    ap.add_argument("--square-mm", type=float, default=24.0)
    ap.add_argument("--ours", help="spinscan's calib.yaml")
    ap.add_argument("--ours-cmd", help="a spinscan command to run (and time) first")
    a = ap.parse_args()
    cols, rows = (int(v) for v in a.board.lower().split("x"))
    pattern = (cols, rows)

    ours_s = None
    if a.ours_cmd:
        t0 = time.perf_counter()
        subprocess.run(shlex.split(a.ours_cmd), check=True)
        ours_s = time.perf_counter() - t0
        if not a.ours:
            argv = shlex.split(a.ours_cmd)
            if "-o" in argv:
                a.ours = argv[argv.index("-o") + 1]

    t0 = time.perf_counter()
    lp = sorted(glob.glob(os.path.join(a.dir, "left*.jpg")) + glob.glob(os.path.join(a.dir, "left*.png")))
    rp = sorted(glob.glob(os.path.join(a.dir, "right*.jpg")) + glob.glob(os.path.join(a.dir, "right*.png")))
    lc, size = detect(lp, pattern)
    rc, _ = detect(rp, pattern)
    pairs = [(l, r) for l, r in zip(lc, rc) if l is not None and r is not None]
    print(f"boards found: left {sum(c is not None for c in lc)}/{len(lp)}, right {sum(c is not None for c in rc)}/{len(rp)}, pairs {len(pairs)}")
    left = [p[0] for p in pairs]
    right = [p[1] for p in pairs]
    obj = [board_points(cols, rows, a.square_mm)] * len(pairs)
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-9)
    rms_l, M1, D1, _, _ = cv2.calibrateCamera(obj, left, size, None, None, criteria=crit)
    rms_r, M2, D2, _, _ = cv2.calibrateCamera(obj, right, size, None, None, criteria=crit)
    rms_s, M1, D1, M2, D2, R, T, _, _ = cv2.stereoCalibrate(obj, left, right, M1, D1, M2, D2, size,
                                                           flags=cv2.CALIB_USE_INTRINSIC_GUESS, criteria=crit)
    cv_s = time.perf_counter() - t0
    cv = {"M1": M1, "D1": D1, "M2": M2, "D2": D2, "R": R, "T": T, "rms_left": rms_l, "rms_right": rms_r, "rms_stereo": rms_s}

    rows_out = [("OpenCV " + cv2.__version__, cv, cv_s)]
    if a.ours:
        rows_out.append(("spinscan", read_calib(a.ours), ours_s))
    print(f"{'':16} {'rms L':>7} {'rms R':>7} {'rms st':>7} {'|T| mm':>9} {'fx L':>8} {'fx R':>8} {'rows mean':>9} {'rows max':>8} {'time s':>7}")
    for name, c, secs in rows_out:
        mean, worst = row_mismatch(c, size, left, right)
        f = lambda v: "   -   " if v is None else f"{v:7.4f}"
        t = "   -   " if secs is None else f"{secs:7.2f}"
        print(f"{name:16} {f(c['rms_left'])} {f(c['rms_right'])} {f(c['rms_stereo'])} {np.linalg.norm(c['T']):9.3f} "
              f"{c['M1'][0, 0]:8.2f} {c['M2'][0, 0]:8.2f} {mean:9.4f} {worst:8.4f} {t}")
    if a.ours:
        o = rows_out[1][1]
        dT = np.linalg.norm(o["T"]) / np.linalg.norm(cv["T"]) - 1
        dR = np.degrees(np.linalg.norm(cv2.Rodrigues(o["R"] @ cv["R"].T)[0]))
        print(f"spinscan vs OpenCV: |T| {100 * dT:+.3f} %, R {dR:.4f} deg")
    return 0


if __name__ == "__main__":
    sys.exit(main())
