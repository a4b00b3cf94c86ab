#!/usr/bin/env python3
"""Write a complete pose graph (every pair of N poses joined by an edge) as g2o, to stress
the online estimator with a dense graph (`so2lin stream`).

Usage: python3 benches/complete_graph.py N SEED OUT.g2o

Poses are uniform in a 10 × 10 square with uniform headings; each edge (i, j), i < j, listed
in robot order (all edges into node j right after node j appears), is the true relative pose
plus Gaussian noise (σ_xy = 0.05, σ_θ = 0.02 rad) with the matching diagonal information.
Nothing is shipped: the file is generated where it is used.
"""
import math
import random
import sys


def main():
    n, seed, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
    rng = random.Random(seed)
    poses = [(rng.uniform(0, 10), rng.uniform(0, 10), rng.uniform(-math.pi, math.pi)) for _ in range(n)]
    sxy, sth = 0.05, 0.02
    with open(out, "w") as f:
        for j in range(1, n):
            for i in range(j):
                xi, yi, ti = poses[i]
                xj, yj, tj = poses[j]
                c, s = math.cos(ti), math.sin(ti)
                dx, dy = xj - xi, yj - yi
                zx = c * dx + s * dy + rng.gauss(0, sxy)
                zy = -s * dx + c * dy + rng.gauss(0, sxy)
                zt = math.atan2(math.sin(tj - ti), math.cos(tj - ti)) + rng.gauss(0, sth)
                ixy, ith = 1 / sxy**2, 1 / sth**2
                f.write(f"EDGE_SE2 {i} {j} {zx!r} {zy!r} {zt!r} {ixy!r} 0 0 {ixy!r} 0 {ith!r}\n")


if __name__ == "__main__":
    main()
