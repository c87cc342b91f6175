#!/usr/bin/env python3
"""An independent turntable renderer, written from ../shared/spec/recording-format.md alone
and sharing no code with hw-sim: numpy ray casting of a union of two ellipsoids (a body and
a head, so it occludes itself) with a solid texture of sinusoids saturated into two paints
and dark spots, Lambert and Blinn-Phong light with cast shadows, a blue screen lit unevenly
with vignetting, a blue table disc, sRGB gamma, 2 x 2 supersampling, lens distortion through
OpenCV's model, and gain, offset and noise per camera. It writes calib.yaml with
cv2.FileStorage (OpenCV's own YAML 1.2), frames.jsonl (with a key readers do not know),
left/right PNGs, gt/mesh.ply (the union's outer triangles), gt/poses.jsonl, and for the ideal
rig gt/disparity/ from the ray depths at pixel centres.

    ../.venv-peers/bin/python hw-sim/foreign/render.py OUT [--ideal] [--frames 20]
        [--deg 2] [--seed 3] [--texture-gain 0.9] [--specular 0.18] [--size 640x480]
        [--jpeg Q] [--swap] [--no-angles] [--start-deg D] [--drop 7,8] [--turntable-yaml]
        [--distance 410] [--off-axis 6] [--exposure 1] [--baseline 55] [--converge]
        [--right-gain 1.07]

The last options write what other tools may: JPEG images (an MJPEG camera), a rig whose
right camera sits left of the left one (negative disparities, so no gt/disparity), no
table angles (`table_deg` null), a first angle other than 0 (with a negative --deg: a
clockwise turn), dropped pairs (gaps in seq), and a calibrated axis (turntable.yaml); and
a nearer camera, an object further off the axis, a dimmer lab, a wider baseline, a
toed-in rig whose cameras both aim at the object, and cameras whose gains are set apart.

Needs numpy and opencv-python (`bash ../shared/bench/setup.sh` makes ../.venv-peers with
both). About 3 s a pair. What it showed: docs/assisted-matching.md, "Seventeenth pass", and
docs/registration.md, Known limits ("without the table's angles").
"""
import argparse, json, os, math
import numpy as np, cv2

ap = argparse.ArgumentParser()
ap.add_argument("out")
ap.add_argument("--frames", type=int, default=20)
ap.add_argument("--deg", type=float, default=2.0)
ap.add_argument("--ideal", action="store_true")
ap.add_argument("--seed", type=int, default=3)
ap.add_argument("--specular", type=float, default=0.18)
ap.add_argument("--size", default="640x480")
ap.add_argument("--ss", type=int, default=2)
ap.add_argument("--texture-gain", type=float, default=0.9, help="how hard the texture saturates into its two paints")
ap.add_argument("--jpeg", type=int, default=0, help="write JPEG images of this quality (an MJPEG camera) instead of PNG")
ap.add_argument("--swap", action="store_true", help="the right camera sits left of the left one: negative disparities (no gt/disparity)")
ap.add_argument("--no-angles", action="store_true", help="table_deg null in frames.jsonl (a turntable that reports nothing)")
ap.add_argument("--start-deg", type=float, default=0.0, help="the table's angle at the first frame")
ap.add_argument("--turntable-yaml", action="store_true", help="write turntable.yaml with the true axis (a calibrated turntable)")
ap.add_argument("--distance", type=float, default=410.0, help="the left camera's distance from the table's axis, mm (nearer: larger disparities)")
ap.add_argument("--off-axis", type=float, default=6.0, help="how far the object's centre sits from the table's axis, mm")
ap.add_argument("--exposure", type=float, default=1.0, help="scales both cameras' gain (0.4: a dim lab, its noise relatively stronger)")
ap.add_argument("--baseline", type=float, default=55.0, help="distance between the cameras' centres, mm")
ap.add_argument("--converge", action="store_true", help="the right camera turned to look at the object too (a toed-in rig; not with --ideal)")
ap.add_argument("--right-gain", type=float, default=1.07, help="the right camera's gain over the left's (1.07: a pair a little apart; 0.7: set apart)")
ap.add_argument("--drop", default="", help="comma-separated frame indices left out of the recording (dropped pairs: gaps in seq)")
args = ap.parse_args()
W, H = map(int, args.size.split("x"))
rng = np.random.default_rng(args.seed)

def rot(axis, deg):
    a = np.asarray(axis, float); a /= np.linalg.norm(a)
    t = math.radians(deg); K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(t) * K + (1 - math.cos(t)) * K @ K

# ---- object: union of two ellipsoids, in the object frame (mm) ----
ELL = [  # centre, semi-axes, rotation
    (np.array([0.0, 0.0, 0.0]), np.array([36.0, 48.0, 30.0]), rot([0, 0, 1], 14) @ rot([1, 0, 0], -8)),
    (np.array([14.0, 47.0, 5.0]), np.array([24.0, 20.0, 22.0]), rot([0, 1, 0], 30)),
]
def ell_hit(o, d, c, s, R):
    # ray o + t d (object frame), ellipsoid {q: |R^T (q-c) / s| = 1}
    oo = ((o - c) @ R) / s; dd = (d @ R) / s
    A = (dd * dd).sum(-1); B = 2 * (oo * dd).sum(-1); C = (oo * oo).sum(-1) - 1
    disc = B * B - 4 * A * C
    ok = disc > 0
    sq = np.sqrt(np.where(ok, disc, 0))
    t0 = (-B - sq) / (2 * A); t1 = (-B + sq) / (2 * A)
    t = np.where(t0 > 1e-6, t0, np.where(t1 > 1e-6, t1, np.inf))
    return np.where(ok, t, np.inf)
def ell_inside(q, c, s, R):
    qq = ((q - c) @ R) / s
    return (qq * qq).sum(-1) < 1 - 1e-9
def ell_normal(q, c, s, R):
    qq = ((q - c) @ R) / s
    g = (qq / s) @ R.T
    return g / np.linalg.norm(g, axis=-1, keepdims=True)
def obj_hit(o, d):
    """Nearest hit on the union's outer surface: an ellipsoid's hit point inside the other is
    not on the surface; then look again from there."""
    best = np.full(o.shape[0], np.inf); which = np.full(o.shape[0], -1)
    for i, (c, s, R) in enumerate(ELL):
        oo = o.copy(); base = np.zeros(o.shape[0]); tt = np.full(o.shape[0], np.inf)
        live = np.ones(o.shape[0], bool)
        for _ in range(3):
            t = ell_hit(oo[live], d[live], c, s, R)
            idx = np.nonzero(live)[0]
            hit = np.isfinite(t)
            q = oo[idx] + d[idx] * np.where(hit, t, 0)[:, None]
            inside_other = np.zeros(len(idx), bool)
            for j, (c2, s2, R2) in enumerate(ELL):
                if j != i: inside_other |= ell_inside(q, c2, s2, R2)
            good = hit & ~inside_other
            tt[idx[good]] = base[idx[good]] + t[good]
            again = hit & inside_other
            base[idx[again]] += t[again] + 1e-4
            oo[idx[again]] = q[again] + d[idx[again]] * 1e-4
            live[:] = False; live[idx[again]] = True
            if not live.any(): break
        closer = tt < best
        best[closer] = tt[closer]; which[closer] = i
    return best, which
def obj_normal(q, which):
    n = np.zeros_like(q)
    for i, (c, s, R) in enumerate(ELL):
        m = which == i
        if m.any(): n[m] = ell_normal(q[m], c, s, R)
    return n

# solid texture: sinusoids over the object frame, blended between two paints, with spots
NK = 28
K = rng.normal(size=(NK, 3)); K /= np.linalg.norm(K, axis=1, keepdims=True)
K *= np.exp(rng.uniform(np.log(0.1), np.log(3.0), size=NK))[:, None]
PH = rng.uniform(0, 2 * np.pi, NK); AMP = 1.0 / np.sqrt(0.3 + np.linalg.norm(K, axis=1))
SPOTS = rng.normal(size=(60, 3)) * np.array([30, 40, 26])
def albedo(q):
    v = (np.sin(q @ K.T + PH) * AMP).sum(-1) / np.sqrt((AMP ** 2).sum() / 2) * args.texture_gain
    v = 0.5 + 0.5 * np.tanh(v)
    a = np.array([0.72, 0.38, 0.22]); b = np.array([0.93, 0.86, 0.70])
    col = a * (1 - v)[:, None] + b * v[:, None]
    # dark spots
    d2 = ((q[:, None, :] - SPOTS[None]) ** 2).sum(-1).min(1)
    col *= (1 - 0.55 * np.exp(-d2 / 9.0))[:, None]
    return col

# ---- the lab: table frame, y up, axis through the origin ----
TABLE_R, TABLE_H = 95.0, 14.0
def ext_y(c, s, R):
    return math.sqrt(((R * s[None, :]) ** 2)[1].sum())
bottom = min(c[1] - ext_y(c, s, R) for c, s, R in ELL)
table_from_obj = np.eye(4); table_from_obj[:3, :3] = rot([0, 1, 0], 20)
table_from_obj[:3, 3] = [args.off_axis, -bottom + 0.5, -4.0]   # off the axis, resting on the table
DIST, TILT = args.distance, 22.0
cam_pos = np.array([0.0, 0.0, -DIST]); cam_pos = rot([1, 0, 0], TILT) @ cam_pos  # raised
target = np.array([0.0, 45.0, 0.0]); cam_pos = cam_pos + np.array([0.0, 45.0, 0.0])
def look(pos, tgt):
    z = tgt - pos; z /= np.linalg.norm(z)
    x = np.cross(z, [0, 1, 0]); x /= np.linalg.norm(x)
    y = np.cross(z, x)
    Rc = np.stack([x, y, z])          # rows: camera axes in table coords
    T = np.eye(4); T[:3, :3] = Rc; T[:3, 3] = -Rc @ pos
    return T                          # cam_from_table
camL_from_table = look(cam_pos, target)
B = args.baseline
SIDE = 1.0 if args.swap else -1.0      # the right camera centre sits at x = -SIDE * B
if args.ideal:
    camR_from_camL = np.eye(4); camR_from_camL[:3, 3] = [SIDE * B, 0, 0]
    M1 = np.array([[700.0, 0, 322.5], [0, 700.0, 238.0], [0, 0, 1]]); M2 = M1.copy()
    D1 = np.zeros(5); D2 = np.zeros(5)
else:
    C = np.array([-SIDE * B, 0.9, -1.5])  # right camera centre in the left camera frame
    if args.converge:   # aimed at the object like the left one, with a little roll
        camL_to_table = np.linalg.inv(camL_from_table)
        aimed = look(camL_to_table[:3, :3] @ C + camL_to_table[:3, 3], target)
        Rr = rot([0, 0, 1], 0.6) @ aimed[:3, :3] @ camL_to_table[:3, :3]
    else:
        Rr = rot([0.1, 1, 0.05], -1.1)     # a little toe-in and roll
    camR_from_camL = np.eye(4); camR_from_camL[:3, :3] = Rr; camR_from_camL[:3, 3] = -Rr @ C
    M1 = np.array([[712.0, 0, 331.0], [0, 709.5, 229.0], [0, 0, 1]])
    M2 = np.array([[705.0, 0, 309.0], [0, 706.0, 247.5], [0, 0, 1]])
    D1 = np.array([-0.085, 0.06, 0.0005, -0.0007, 0.0]); D2 = np.array([-0.07, 0.04, -0.0004, 0.0006, 0.0])
camR_from_table = camR_from_camL @ camL_from_table
light_table = np.array([-250.0, 420.0, -300.0])

# rays of each camera: pixel (u, v) centre at integer coordinates, ss x ss samples
def rays(M, D):
    n = args.ss
    offs = (np.arange(n) + 0.5) / n - 0.5
    us, vs = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    pts = []
    for oy in offs:
        for ox in offs:
            pts.append(np.stack([us + ox, vs + oy], -1).reshape(-1, 2))
    pts = np.concatenate(pts)
    und = cv2.undistortPoints(pts.reshape(-1, 1, 2), M, D, None, None, None,
                                  (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)).reshape(-1, 2)
    d = np.concatenate([und, np.ones((len(und), 1))], 1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)
def centre_rays(M, D):
    us, vs = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    pts = np.stack([us, vs], -1).reshape(-1, 1, 2)
    und = cv2.undistortPoints(pts, M, D, None, None, None, (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)).reshape(-1, 2)
    d = np.concatenate([und, np.ones((len(und), 1))], 1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)
RAYS = {"left": rays(M1, D1), "right": rays(M2, D2)}

def table_hit(o, d):
    """Top disc (y = 0, r < TABLE_R) and side (r = TABLE_R, -TABLE_H < y < 0), table frame."""
    t_top = np.where(np.abs(d[:, 1]) > 1e-12, -o[:, 1] / np.where(np.abs(d[:, 1]) > 1e-12, d[:, 1], 1), np.inf)
    q = o + d * t_top[:, None]
    ok = (t_top > 0) & (q[:, 0] ** 2 + q[:, 2] ** 2 < TABLE_R ** 2)
    t_top = np.where(ok, t_top, np.inf)
    A = d[:, 0] ** 2 + d[:, 2] ** 2; Bq = 2 * (o[:, 0] * d[:, 0] + o[:, 2] * d[:, 2]); Cq = o[:, 0] ** 2 + o[:, 2] ** 2 - TABLE_R ** 2
    disc = Bq * Bq - 4 * A * Cq
    sq = np.sqrt(np.maximum(disc, 0)); ts = (-Bq - sq) / (2 * np.maximum(A, 1e-12))
    qs = o + d * ts[:, None]
    oks = (disc > 0) & (ts > 0) & (qs[:, 1] < 0) & (qs[:, 1] > -TABLE_H)
    ts = np.where(oks, ts, np.inf)
    return t_top, ts

def shade(cam_from_table, ray_cam, obj_from_table, gain, offset, seed):
    table_from_cam = np.linalg.inv(cam_from_table)
    o_t = np.broadcast_to(table_from_cam[:3, 3], ray_cam.shape).copy()
    d_t = ray_cam @ table_from_cam[:3, :3].T
    o_o = o_t @ obj_from_table[:3, :3].T + obj_from_table[:3, 3]
    d_o = d_t @ obj_from_table[:3, :3].T
    t_obj, which = obj_hit(o_o, d_o)
    t_top, t_side = table_hit(o_t, d_t)
    n_rays = len(ray_cam)
    rad = np.zeros((n_rays, 3))
    # screen: chroma blue, lit unevenly (brighter top-left), vignetting by the ray's angle
    cosang = ray_cam[:, 2]
    screen = np.array([0.03, 0.11, 0.52]) * (0.75 + 0.25 * (0.5 - 0.5 * d_t[:, 1])[:, None]) * (cosang ** 3)[:, None]
    rad[:] = screen
    tmin = np.minimum(np.minimum(t_obj, t_top), t_side)
    # table
    for t_tab, normal in ((t_top, np.array([0, 1.0, 0])), (t_side, None)):
        m = np.isfinite(t_tab) & (t_tab <= tmin)
        if not m.any(): continue
        q = o_t[m] + d_t[m] * t_tab[m][:, None]
        nrm = np.broadcast_to(normal, q.shape) if normal is not None else np.stack([q[:, 0], np.zeros(len(q)), q[:, 2]], 1) / TABLE_R
        L = light_table - q; dist = np.linalg.norm(L, axis=1); L /= dist[:, None]
        lam = np.clip((nrm * L).sum(1), 0, 1)
        # shadow of the object
        qo = (q + nrm * 0.01) @ obj_from_table[:3, :3].T + obj_from_table[:3, 3]
        Lo = L @ obj_from_table[:3, :3].T
        ts, _ = obj_hit(qo, Lo)
        lit = ~np.isfinite(ts)
        col = np.array([0.05, 0.13, 0.55])
        rad[m] = col * (0.35 + 0.65 * lam * lit)[:, None]
    m = np.isfinite(t_obj) & (t_obj <= tmin)
    q = o_o[m] + d_o[m] * t_obj[m][:, None]
    nrm = obj_normal(q, which[m])
    table_from_obj = np.linalg.inv(obj_from_table)
    lt_o = table_from_obj[:3, :3].T @ (light_table - table_from_obj[:3, 3])
    L = lt_o - q; L /= np.linalg.norm(L, axis=1, keepdims=True)
    V = -d_o[m]
    lam = np.clip((nrm * L).sum(1), 0, 1)
    ts, _ = obj_hit(q + nrm * 0.01, L)   # self-shadow (the head on the body)
    lit = (~np.isfinite(ts)).astype(float)
    Hh = L + V; Hh /= np.linalg.norm(Hh, axis=1, keepdims=True)
    spec = np.clip((nrm * Hh).sum(1), 0, 1) ** 40 * args.specular * lit
    alb = albedo(q)
    rad[m] = alb * (0.22 + 0.78 * lam * lit)[:, None] + spec[:, None]
    # average the samples, expose, gamma, gain/offset, noise
    n = args.ss * args.ss
    rad = rad.reshape(n, H * W, 3).mean(0).reshape(H, W, 3)
    img = np.clip(rad * 1.15, 0, 1) ** (1 / 2.2) * 255
    img = img * gain + offset + np.random.default_rng(seed).normal(0, 1.3, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)

def ply(path, V, F):
    with open(path, "wb") as f:
        f.write(("ply\nformat binary_little_endian 1.0\ncomment foreign renderer\nelement vertex %d\nproperty float x\nproperty float y\nproperty float z\nelement face %d\nproperty list uchar int vertex_indices\nend_header\n" % (len(V), len(F))).encode())
        f.write(np.asarray(V, "<f4").tobytes())
        rec = np.zeros(len(F), dtype=[("n", "u1"), ("i", "<i4", 3)]); rec["n"] = 3; rec["i"] = F
        f.write(rec.tobytes())

def mesh():
    Vs, Fs, base = [], [], 0
    nu, nv = 360, 180
    for i, (c, s, R) in enumerate(ELL):
        th = np.linspace(0, np.pi, nv + 1); ph = np.linspace(0, 2 * np.pi, nu, endpoint=False)
        T, P = np.meshgrid(th, ph, indexing="ij")
        u = np.stack([np.sin(T) * np.cos(P), np.cos(T), np.sin(T) * np.sin(P)], -1).reshape(-1, 3)
        V = (u * s) @ R.T + c
        F = []
        for a in range(nv):
            for b in range(nu):
                p00 = a * nu + b; p01 = a * nu + (b + 1) % nu; p10 = (a + 1) * nu + b; p11 = (a + 1) * nu + (b + 1) % nu
                F.append((p00, p10, p11)); F.append((p00, p11, p01))
        F = np.array(F)
        cent = V[F].mean(1)
        keep = np.ones(len(F), bool)
        for j, (c2, s2, R2) in enumerate(ELL):
            if j != i: keep &= ~ell_inside(cent, c2, s2, R2)
        Vs.append(V); Fs.append(F[keep] + base); base += len(V)
    return np.concatenate(Vs), np.concatenate(Fs)

out = args.out
for sub in ("left", "right", "gt"):
    os.makedirs(os.path.join(out, sub), exist_ok=True)
fs = cv2.FileStorage(os.path.join(out, "calib.yaml"), cv2.FILE_STORAGE_WRITE)
for k, v in (("M1", M1), ("D1", D1.reshape(1, 5)), ("M2", M2), ("D2", D2.reshape(1, 5)), ("R", camR_from_camL[:3, :3]), ("T", camR_from_camL[:3, 3].reshape(3, 1))):
    fs.write(k, v)
fs.release()
if args.turntable_yaml:   # the table's y axis (up) through its origin, in the left camera frame
    p = camL_from_table[:3, 3]; u = camL_from_table[:3, :3] @ np.array([0.0, 1.0, 0.0])
    with open(os.path.join(out, "turntable.yaml"), "w") as f:
        f.write("axis_point_mm: [%.6f, %.6f, %.6f]\naxis_dir: [%.9f, %.9f, %.9f]\nsource: \"calibrated\"\n" % (*p, *u))
V, F = mesh(); ply(os.path.join(out, "gt/mesh.ply"), V, F)
frames, poses = [], []
GT_DISP = args.ideal and not args.swap   # the spec's gt/disparity: ideal rig, T = (-B, 0, 0)
if GT_DISP:
    os.makedirs(os.path.join(out, "gt/disparity"), exist_ok=True)
    crays = centre_rays(M1, D1)
drop = {int(x) for x in args.drop.split(",") if x}
ext = "jpg" if args.jpeg else "png"
for k in range(args.frames):
    if k in drop: continue
    deg = args.start_deg + k * args.deg
    turn = np.eye(4); turn[:3, :3] = rot([0, 1, 0], deg)
    table_obj = turn @ table_from_obj
    obj_from_table = np.linalg.inv(table_obj)
    L = shade(camL_from_table, RAYS["left"], obj_from_table, 1.0 * args.exposure, 0.0, 1000 + k)
    Rr = shade(camR_from_table, RAYS["right"], obj_from_table, args.right_gain * args.exposure, -5.0, 2000 + k)
    wp = [cv2.IMWRITE_JPEG_QUALITY, args.jpeg] if args.jpeg else []
    cv2.imwrite(os.path.join(out, "left/%06d.%s" % (k, ext)), L[:, :, ::-1], wp)
    cv2.imwrite(os.path.join(out, "right/%06d.%s" % (k, ext)), Rr[:, :, ::-1], wp)
    t0 = 1_000_000_000 + k * 66_666_667
    frames.append({"seq": k, "left": "left/%06d.%s" % (k, ext), "right": "right/%06d.%s" % (k, ext), "t_left_ns": t0 + 120_000, "t_right_ns": t0 + 310_000, "table_deg": None if args.no_angles else deg, "renderer": "foreign"})
    cam_from_obj = camL_from_table @ table_obj
    poses.append({"seq": k, "cam_from_obj": cam_from_obj.tolist()})
    if GT_DISP:
        tfc = np.linalg.inv(camL_from_table)
        o_t = np.broadcast_to(tfc[:3, 3], crays.shape).copy(); d_t = crays @ tfc[:3, :3].T
        o_o = o_t @ obj_from_table[:3, :3].T + obj_from_table[:3, 3]; d_o = d_t @ obj_from_table[:3, :3].T
        t_obj, _ = obj_hit(o_o, d_o)
        t_top, t_side = table_hit(o_t, d_t)
        vis = np.isfinite(t_obj) & (t_obj < t_top) & (t_obj < t_side)
        z = t_obj * crays[:, 2]
        disp = np.where(vis, M1[0, 0] * B / np.where(vis, z, 1), 0)
        cv2.imwrite(os.path.join(out, "gt/disparity/%06d.png" % k), np.round(disp * 256).astype(np.uint16).reshape(H, W))
    print("frame", k, flush=True)
with open(os.path.join(out, "frames.jsonl"), "w") as f:
    for fr in frames: f.write(json.dumps(fr) + "\n")
with open(os.path.join(out, "gt/poses.jsonl"), "w") as f:
    for p in poses: f.write(json.dumps(p) + "\n")
