#!/usr/bin/env python3
"""Cross-check of `so2lin solve`'s refined cost with GTSAM.

Usage: python3 benches/gtsam_refine_check.py [--so2lin target/release/so2lin] FILE.g2o...

For each file and each of so2lin's two residual charts: runs
`so2lin solve FILE --residual R --json --out TMP.g2o` (R = t2v, then log, the default; every
other setting default). TMP.g2o holds the refined poses and every edge of FILE as so2lin read
it, written back exactly (shortest round-trip floats) in g2o's layout (EDGE_SE2, information
I11 I12 I13 I22 I23 I33 over (x, y, θ)) whatever FILE's own was (M3500a is TORO's EDGE2 with
its information order). The script checks it holds as many edges as FILE has edge lines,
builds a GTSAM NonlinearFactorGraph with a full Gaussian model per edge in the same chart,
leaving out the loop closures so2lin rejected (`rejected_edges`, none on the default
datasets), scores so2lin's poses with it, runs GTSAM's Levenberg–Marquardt from those poses to
convergence (a prior fixes the first pose of the file, as so2lin anchors it), and prints one
table row per file:

- **t2v**: g2o's EdgeSE2 error, as a GTSAM CustomFactor: GTSAM's score of so2lin's poses must
  equal so2lin's χ², and the gap to GTSAM's LM measures how well so2lin's t2v refinement
  converged;
- **Log** (so2lin's default): GTSAM's own BetweenFactorPose2 (the SE(2) logarithm): the
  issue's criterion, with so2lin's defaults.

Each gap is (GTSAM's χ² of so2lin's poses − χ² after GTSAM's LM) / χ² after GTSAM's LM.

χ² = 2 · NonlinearFactorGraph.error (GTSAM's error is half the squared Mahalanobis norm).
The two charts differ at second order in the error, so their minima are not the same point;
on strongly anisotropic information (MIT, CSAIL) the difference is large.
"""
import json
import math
import os
import subprocess
import sys
import tempfile

import gtsam
import numpy as np


def read_edges(path):
    edges = []
    with open(path) as f:
        for line in f:
            t = line.split()
            if not t or t[0] != "EDGE_SE2":
                continue
            i, j = int(t[1]), int(t[2])
            dx, dy, dth = (float(v) for v in t[3:6])
            a11, a12, a13, a22, a23, a33 = (float(v) for v in t[6:12])
            info = np.array([[a11, a12, a13], [a12, a22, a23], [a13, a23, a33]])
            edges.append((i, j, gtsam.Pose2(dx, dy, dth), info))
    return edges


def t2v_factor(i, j, z, model):
    """g2o's EdgeSE2 error t2v(Z⁻¹ X_i⁻¹ X_j) (so2lin's cost) as a GTSAM CustomFactor, with
    analytic Jacobians in GTSAM's local (body-frame) tangent of each pose."""
    zx, zy, zt = z.x(), z.y(), z.theta()
    cz, sz = math.cos(zt), math.sin(zt)

    def error(this, values, H):
        a, b = values.atPose2(i), values.atPose2(j)
        ci, si = math.cos(a.theta()), math.sin(a.theta())
        dx, dy = b.x() - a.x(), b.y() - a.y()
        lx, ly = ci * dx + si * dy, -si * dx + ci * dy
        dlx, dly = -si * dx + ci * dy, -ci * dx - si * dy
        ux, uy = lx - zx, ly - zy
        th = b.theta() - a.theta() - zt
        th = math.atan2(math.sin(th), math.cos(th))
        e = np.array([cz * ux + sz * uy, -sz * ux + cz * uy, th])
        if H is not None:
            m = np.array([[cz * ci - sz * si, cz * si + sz * ci], [-sz * ci - cz * si, -sz * si + cz * ci]])
            dth = [cz * dlx + sz * dly, -sz * dlx + cz * dly]
            ja = np.array([[-m[0, 0], -m[0, 1], dth[0]], [-m[1, 0], -m[1, 1], dth[1]], [0.0, 0.0, -1.0]])
            jb = np.array([[m[0, 0], m[0, 1], 0.0], [m[1, 0], m[1, 1], 0.0], [0.0, 0.0, 1.0]])
            # d(x, y, θ)/dξ of X·Exp(ξ) at ξ = 0: the pose's rotation on the translation.
            def local(p):
                c, s = math.cos(p.theta()), math.sin(p.theta())
                return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            H[0] = ja @ local(a)
            H[1] = jb @ local(b)
        return e

    return gtsam.CustomFactor(model, [i, j], error)


def lm(graph, values, first):
    """GTSAM's Levenberg–Marquardt to convergence, with the first pose held by a prior."""
    anchored = gtsam.NonlinearFactorGraph(graph)
    anchored.add(
        gtsam.PriorFactorPose2(first, values.atPose2(first), gtsam.noiseModel.Isotropic.Sigma(3, 1e-9))
    )
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(1000)
    params.setRelativeErrorTol(1e-14)
    params.setAbsoluteErrorTol(0.0)
    return gtsam.LevenbergMarquardtOptimizer(anchored, values, params).optimize()


def read_poses(path):
    poses = {}
    with open(path) as f:
        for line in f:
            t = line.split()
            if t and t[0] == "VERTEX_SE2":
                poses[int(t[1])] = gtsam.Pose2(float(t[2]), float(t[3]), float(t[4]))
    return poses


def log_factor(i, j, z, model):
    """GTSAM's own BetweenFactorPose2: the SE(2) logarithm of Z⁻¹ X_i⁻¹ X_j."""
    return gtsam.BetweenFactorPose2(i, j, z, model)


def run_so2lin(so2lin, path, residual):
    """`so2lin solve PATH --residual R --json --out TMP.g2o` with otherwise default settings:
    its JSON, the refined poses and the edges it wrote (checked against PATH's edge lines)."""
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "out.g2o")
        r = subprocess.run(
            [so2lin, "solve", path, "--residual", residual, "--json", "--out", out],
            capture_output=True,
            text=True,
            check=True,
        )
        s = json.loads(r.stdout)
        poses = read_poses(out)
        edges = read_edges(out)
    with open(path) as f:
        lines = sum(1 for l in f if l.split()[:1] in (["EDGE_SE2"], ["EDGE2"]))
    if lines != len(edges):
        sys.exit(f"{path}: {lines} edge lines, so2lin wrote {len(edges)} edges")
    return s, poses, edges


def main():
    args = sys.argv[1:]
    so2lin = "target/release/so2lin"
    if "--so2lin" in args:
        k = args.index("--so2lin")
        so2lin = args[k + 1]
        del args[k : k + 2]
    print(
        "| file | t2v: so2lin iterations | stop | so2lin χ² | GTSAM χ² of so2lin's poses | "
        "after GTSAM LM | gap | Log (default): so2lin iterations | stop | so2lin χ² | "
        "GTSAM χ² of so2lin's poses | after GTSAM LM | gap |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for path in args:
        row = [os.path.basename(path)]
        cells = []
        for residual, factor in (("t2v", t2v_factor), ("log", log_factor)):
            s, poses, edges = run_so2lin(so2lin, path, residual)
            best = s["hypotheses"][0]
            rejected = {e["edge"] for e in best["rejected_edges"]}
            graph = gtsam.NonlinearFactorGraph()
            for k, (i, j, z, info) in enumerate(edges):
                if k not in rejected:
                    graph.add(factor(i, j, z, gtsam.noiseModel.Gaussian.Information(info)))
            values = gtsam.Values()
            for n, p in poses.items():
                values.insert(n, p)
            scored = 2.0 * graph.error(values)
            optimum = 2.0 * graph.error(lm(graph, values, min(poses)))
            gap = (scored - optimum) / optimum if optimum > 0 else math.nan
            cells += [str(best["iterations"]), best["refinement"], f"{best['cost_refined']:.6f}",
                      f"{scored:.6f}", f"{optimum:.6f}", f"{gap:.1e}"]
        row += cells
        print("| " + " | ".join(row) + " |", flush=True)


if __name__ == "__main__":
    main()
