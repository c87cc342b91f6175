#!/usr/bin/env python3
"""Fusing and meshing a results folder: spinscan against Open3D's ScalableTSDFVolume, one run.

Both sides get the same views and poses: spinscan fuses the views' points (`spinscan mesh`,
timed by its own fuse_ms + extract_ms, PLY reading excluded); Open3D gets one depth and
colour image per view, made by projecting that view's points with the left camera matrix of
the recording's calib.yaml (M1, no distortion: the points are already undistorted), and is
timed over integrate + extract_triangle_mesh only. Same voxel size (mm), same truncation,
same thread count (OMP_NUM_THREADS, set before Open3D loads; `spinscan mesh --threads`).

    bash bench/setup-open3d.sh          # ../.venv-open3d: Open3D 0.19.0 (see below)
    ../.venv-open3d/bin/python bench/tsdf_open3d.py RESULTS_DIR --calib REC/calib.yaml \
        [--voxel-mm 1] [--truncation-voxels 4] [--threads 1] [--spinscan target/release/spinscan] \
        [--save-open3d OPEN3D.ply]

Open3D 0.20.0's pip wheel (the one ../shared/bench/setup.sh installs) returns an empty
ScalableTSDFVolume on the lab's machines; 0.19.0's integrates. Run with 0.20.0, the script
falls back to a dense UniformTSDFVolume over the object and says so in "volume".
"""
import argparse
import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import time


def read_m1(path):
    try:
        text = open(path).read()
    except OSError as e:
        sys.exit(f"{path}: cannot read the calibration ({e.strerror}); expected a recording's calib.yaml")
    m = re.search(r"M1:.*?data:\s*\[([^\]]*)\]", text, re.S)
    if not m:
        sys.exit(f"{path}: no M1 matrix (expected an OpenCV FileStorage calib.yaml)")
    v = [float(x) for x in m.group(1).replace("\n", " ").split(",")]
    # The image size, where the file gives it (OpenCV's stereo calibration does; calibrations
    # written by other tools may not: see `image_size`).
    w, h = (re.search(rf"{k}:\s*(\d+)", text) for k in ("image_width", "image_height"))
    return v, (int(w.group(1)) if w else None), (int(h.group(1)) if h else None)


def image_size(calib, o3d):
    """The size of the first left image of the recording that holds `calib`."""
    folder = os.path.join(os.path.dirname(os.path.abspath(calib)), "left")
    names = sorted(n for n in os.listdir(folder) if n.lower().endswith((".png", ".jpg", ".jpeg"))) if os.path.isdir(folder) else []
    if not names:
        sys.exit(f"{calib}: no image_width/image_height, and no left/ images beside it to take the size from "
                 "(expected a recording's calib.yaml)")
    import numpy as np
    img = o3d.io.read_image(os.path.join(folder, names[0]))
    h, w = np.asarray(img).shape[:2]
    return w, h


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("results")
    ap.add_argument("--calib", required=True)
    ap.add_argument("--voxel-mm", type=float, default=1.0)
    ap.add_argument("--truncation-voxels", type=float, default=4.0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--spinscan", default="target/release/spinscan")
    ap.add_argument("--save-open3d", metavar="PLY", help="write Open3D's mesh here, to compare the two surfaces")
    a = ap.parse_args()
    m1, w, h = read_m1(a.calib)
    fx, cx, fy, cy = m1[0], m1[2], m1[4], m1[5]

    # spinscan, timed by itself.
    with tempfile.TemporaryDirectory() as tmp:
        out = subprocess.run([a.spinscan, "mesh", a.results, "-o", os.path.join(tmp, "m.ply"), "--voxel-mm", str(a.voxel_mm),
                              "--truncation-voxels", str(a.truncation_voxels), "--threads", str(a.threads)],
                             capture_output=True, text=True)
    if out.returncode != 0:
        sys.exit(f"{a.spinscan} mesh {a.results} failed (exit {out.returncode}):\n{out.stderr.strip()}")
    ours = json.loads(out.stdout.strip().splitlines()[-1])
    # (Read after spinscan, which says what is wrong with a folder that is not a scan's results.)
    poses = [json.loads(l) for l in open(os.path.join(a.results, "poses.jsonl")) if l.strip()]
    # The largest resident set of the children so far: `spinscan mesh`'s, reading included
    # (run before NumPy and Open3D load, whose pages a forked child would count as its own).
    ours_rss_mib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    os.environ["OMP_NUM_THREADS"] = str(a.threads)
    import numpy as np
    import open3d as o3d
    if w is None or h is None:
        w, h = image_size(a.calib, o3d)
    ours_s = (ours["fuse_ms"] + ours["extract_ms"]) / 1e3

    # Open3D's images, made outside its timing.
    images = []
    for p in poses:
        pcd = o3d.io.read_point_cloud(os.path.join(a.results, "views", f"{p['seq']:06d}.ply"))
        pts, cols = np.asarray(pcd.points), (np.asarray(pcd.colors) * 255).astype(np.uint8)
        z = pts[:, 2]
        ok = z > 0
        u = np.round(fx * pts[ok, 0] / z[ok] + cx).astype(int)
        v = np.round(fy * pts[ok, 1] / z[ok] + cy).astype(int)
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        depth = np.zeros((h, w), np.float32)
        color = np.zeros((h, w, 3), np.uint8)
        # Nearest point per pixel: write far to near.
        order = np.argsort(-z[ok][inside])
        uu, vv = u[inside][order], v[inside][order]
        depth[vv, uu] = z[ok][inside][order]
        color[vv, uu] = cols[ok][inside][order]
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(o3d.geometry.Image(color), o3d.geometry.Image(depth), depth_scale=1.0,
                                                                  depth_trunc=1e5, convert_rgb_to_intensity=False)
        view_from_first = np.linalg.inv(np.array(p["first_from_view"]))
        images.append((rgbd, view_from_first))
    intr = o3d.camera.PinholeCameraIntrinsic(w, h, fx, fy, cx, cy)
    integration = o3d.pipelines.integration
    trunc = a.voxel_mm * a.truncation_voxels

    def run(vol):
        t0 = time.perf_counter()
        for rgbd, ext in images:
            vol.integrate(rgbd, intr, ext)
        t1 = time.perf_counter()
        mesh = vol.extract_triangle_mesh()
        return t1 - t0, time.perf_counter() - t1, mesh

    volume = "ScalableTSDFVolume"
    integrate_s, extract_s, mesh = run(integration.ScalableTSDFVolume(voxel_length=a.voxel_mm, sdf_trunc=trunc, color_type=integration.TSDFVolumeColorType.RGB8))
    if len(mesh.vertices) == 0:
        # Open3D 0.20.0's pip wheel returns an empty ScalableTSDFVolume (and VoxelBlockGrid)
        # on this lab's machines, even for a synthetic slanted plane (0.19.0's does not:
        # bench/setup-open3d.sh): the dense UniformTSDFVolume over spinscan's mesh's
        # bounding box (plus the band) stands in, and the output says so.
        ours_mesh = o3d.io.read_triangle_mesh(os.path.join(a.results, "mesh.ply"))
        lo, hi = ours_mesh.get_min_bound() - 2 * trunc, ours_mesh.get_max_bound() + 2 * trunc
        length = float((hi - lo).max())
        res = int(round(length / a.voxel_mm))
        volume = f"UniformTSDFVolume {res}^3 (ScalableTSDFVolume gave an empty mesh)"
        integrate_s, extract_s, mesh = run(integration.UniformTSDFVolume(length=res * a.voxel_mm, resolution=res, sdf_trunc=trunc,
                                                                          color_type=integration.TSDFVolumeColorType.RGB8, origin=lo.reshape(3, 1)))
    theirs_s = integrate_s + extract_s
    if a.save_open3d:
        o3d.io.write_triangle_mesh(a.save_open3d, mesh)
    print(json.dumps({
        "views": len(poses), "voxel_mm": a.voxel_mm, "truncation_voxels": a.truncation_voxels, "threads": a.threads,
        "spinscan": {"fuse_s": ours["fuse_ms"] / 1e3, "extract_s": ours["extract_ms"] / 1e3, "total_s": ours_s,
                     "vertices": ours["vertices"], "triangles": ours["triangles"], "boundary_edges": ours["boundary_edges"],
                     "peak_rss_mib": ours_rss_mib},
        "open3d": {"version": o3d.__version__, "volume": volume, "integrate_s": integrate_s, "extract_s": extract_s, "total_s": theirs_s,
                   "vertices": len(mesh.vertices), "triangles": len(mesh.triangles)},
        "ratio_spinscan_to_open3d": ours_s / theirs_s,
    }, indent=1))


if __name__ == "__main__":
    main()
