#!/usr/bin/env python3
"""A picture of a mesh without a GPU or a display: its triangles sampled at seven points
each, projected orthographically, z-buffered by painting far to near, shaded by the
interpolated vertex normals and coloured by the vertex colours. Two views side by side: from
slightly above, and from below (where a turntable object's capped base shows).

    ../.venv-peers/bin/python bench/render_mesh.py MESH.ply OUT.png
"""
import sys, numpy as np, open3d as o3d
import cv2
m = o3d.io.read_triangle_mesh(sys.argv[1]); out = sys.argv[2]
v = np.asarray(m.vertices); n = np.asarray(m.vertex_normals); c = np.asarray(m.vertex_colors)
t = np.asarray(m.triangles)
ctr = v.mean(0)
def view(elev, azim, W=520, H=420):
    # Rotation: azimuth about the object's up (-y in camera frame), then elevation.
    a, e = np.radians(azim), np.radians(elev)
    Ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    Rx = np.array([[1, 0, 0], [0, np.cos(e), -np.sin(e)], [0, np.sin(e), np.cos(e)]])
    R = Rx @ Ry
    # Sample each triangle at several barycentric points for a dense, hole-free splat.
    bc = np.array([[1/3,1/3,1/3],[.6,.2,.2],[.2,.6,.2],[.2,.2,.6],[.8,.1,.1],[.1,.8,.1],[.1,.1,.8]])
    P = np.einsum('kj,tjd->tkd', bc, v[t]).reshape(-1, 3)
    N = np.einsum('kj,tjd->tkd', bc, n[t]).reshape(-1, 3)
    C = np.einsum('kj,tjd->tkd', bc, c[t]).reshape(-1, 3)
    q = (P - ctr) @ R.T; nn = N @ R.T
    s = 0.8 * min(W, H) / (np.ptp(q[:, :2], 0).max())
    x = (q[:, 0] * s + W / 2).astype(int); y = (q[:, 1] * s + H / 2).astype(int)
    ok = (x >= 0) & (x < W) & (y >= 0) & (y < H)
    order = np.argsort(-q[ok, 2])  # far to near: nearer overwrite
    img = np.full((H, W, 3), 255.0)
    light = np.array([0.3, -0.5, -0.8]); light /= np.linalg.norm(light)
    shade = np.clip(np.abs(nn[ok] @ light), 0.15, 1.0)[:, None]
    col = np.clip(C[ok] * (0.35 + 0.65 * shade), 0, 1) * 255
    img[y[ok][order], x[ok][order]] = col[order]
    return img
img = np.concatenate([view(15, 0), view(-70, 30)], 1).astype(np.uint8)
cv2.imwrite(out, img[:, :, ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])
print(out, img.shape)
