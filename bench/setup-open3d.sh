#!/usr/bin/env bash
# A Python environment with an Open3D whose ScalableTSDFVolume integrates, for
# bench/tsdf_open3d.py. The peers' environment (../shared/bench/setup.sh) pins Open3D 0.20.0,
# whose pip wheel returns an empty ScalableTSDFVolume (and VoxelBlockGrid) on the lab's x86-64
# machines, even for one flat depth image; 0.19.0's integrates (docs/meshing.md, "Against
# Open3D's sparse volume").
#   bash bench/setup-open3d.sh [VENV_DIR]      (default: ../.venv-open3d, beside the repo)
# Then:  ../.venv-open3d/bin/python bench/tsdf_open3d.py RESULTS --calib REC/calib.yaml
set -euo pipefail
venv="${1:-../.venv-open3d}"
if ! ldconfig -p | grep -q libusb-1.0.so.0; then   # open3d's wheel links it
  if command -v apt-get >/dev/null; then
    (apt-get update -qq && apt-get install -y -qq libusb-1.0-0 libgomp1) >/dev/null
  fi
fi
python3 -m venv "$venv"
"$venv/bin/pip" install -q --disable-pip-version-check numpy==2.4.6 open3d==0.19.0
# The check the 0.20.0 wheel fails: one flat depth image, 0.5 m away, must give a mesh.
"$venv/bin/python" - <<'PY'
import numpy as np, open3d as o3d
w, h = 64, 48
rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
    o3d.geometry.Image(np.full((h, w, 3), 128, np.uint8)), o3d.geometry.Image(np.full((h, w), 0.5, np.float32)),
    depth_scale=1.0, depth_trunc=3.0, convert_rgb_to_intensity=False)
v = o3d.pipelines.integration.ScalableTSDFVolume(voxel_length=0.005, sdf_trunc=0.02,
                                                 color_type=o3d.pipelines.integration.TSDFVolumeColorType.RGB8)
v.integrate(rgbd, o3d.camera.PinholeCameraIntrinsic(w, h, 50, 50, 32, 24), np.eye(4))
n = len(v.extract_triangle_mesh().vertices)
if n == 0:
    raise SystemExit(f"open3d {o3d.__version__}: ScalableTSDFVolume gave an empty mesh for a flat depth image")
print(f"open3d {o3d.__version__} ready: ScalableTSDFVolume meshes a flat depth image ({n} vertices)")
PY
