#!/usr/bin/env python3
"""The peer of `so2lin stream --order robot --estimate newest`: GTSAM iSAM2 fed the same edges
in the same (robot) order, one update per edge, with `calculateEstimate` of the newest pose
after every update.

Usage: python3 benches/isam2_peer.py FILE.g2o [--so2lin target/release/so2lin] [--so2lin-arg ARG]...

Reads the g2o file with GTSAM's own reader, sorts the edges stably by the first appearance of
their later node (so2lin's `online::robot_order`), then times the whole loop. With --so2lin it
also runs `so2lin stream FILE --json` (robot order, newest pose after every step) right after,
in the same process tree, and prints both loops' times (so2lin: the sum of its steps, reading and finishing excluded, like the loop timed here) and their ratio.
Each --so2lin-arg passes one more argument to that run (e.g. --so2lin-arg --maintain); with
--maintain the time the estimator spent between steps is added for a second ratio,
`ratio_with_maintenance`, since it runs on the robot's thread too.
"""
import json
import subprocess
import sys
import time

import gtsam


def robot_order(edges):
    first = {}
    for (i, j, _, _) in edges:
        for n in (i, j):
            first.setdefault(n, len(first))
    return sorted(edges, key=lambda e: max(first[e[0]], first[e[1]]))


def main():
    path = sys.argv[1]
    so2lin = None
    if "--so2lin" in sys.argv:
        so2lin = sys.argv[sys.argv.index("--so2lin") + 1]
    extra = [sys.argv[k + 1] for k, a in enumerate(sys.argv[:-1]) if a == "--so2lin-arg"]
    graph, initial = gtsam.readG2o(path, False)
    edges = []
    for k in range(graph.size()):
        f = graph.at(k)
        if isinstance(f, gtsam.BetweenFactorPose2):
            keys = f.keys()
            edges.append((keys[0], keys[1], f.measured(), f.noiseModel()))
    edges = robot_order(edges)
    isam = gtsam.ISAM2(gtsam.ISAM2Params())
    known = set()
    start = time.perf_counter()
    newest = None
    for (i, j, z, noise) in edges:
        g = gtsam.NonlinearFactorGraph()
        v = gtsam.Values()
        if not known:
            g.add(gtsam.PriorFactorPose2(i, gtsam.Pose2(), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
            v.insert(i, gtsam.Pose2())
            known.add(i)
        g.add(gtsam.BetweenFactorPose2(i, j, z, noise))
        for (a, b, rel) in ((i, j, z), (j, i, z.inverse())):
            if b not in known:
                base = isam.calculateEstimatePose2(a) if a not in v.keys() else v.atPose2(a)
                v.insert(b, base.compose(rel))
                known.add(b)
                newest = b
        isam.update(g, v)
        isam.calculateEstimatePose2(newest)
    isam_s = time.perf_counter() - start
    out = {"file": path, "edges": len(edges), "isam2_seconds": isam_s}
    if so2lin:
        r = subprocess.run([so2lin, "stream", path, "--json", *extra], capture_output=True, text=True, check=True)
        s = json.loads(r.stdout)
        out["so2lin_args"] = extra
        out["so2lin_steps_seconds"] = s["steps_seconds"]
        out["ratio"] = isam_s / s["steps_seconds"]
        out["so2lin_latency_us"] = s["latency_us"]["all"]
        if s.get("maintenance"):
            # `--maintain` spends the time between steps on the robot's thread: it is real
            # time, so the ratio that counts it is printed beside the steps' own.
            busy = s["steps_seconds"] + s["maintenance"]["seconds"]
            out["so2lin_steps_and_maintenance_seconds"] = busy
            out["ratio_with_maintenance"] = isam_s / busy
    print(json.dumps(out))


if __name__ == "__main__":
    main()
