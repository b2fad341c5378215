#!/usr/bin/env python3
"""Computational ghost imaging from Python, end to end, with a simulated single-pixel rig.

    python examples/ghost_imaging.py --server http://127.0.0.1:8080 --token hz_...
    # or: HELMHOLTZ_SERVER=... HELMHOLTZ_TOKEN=... python examples/ghost_imaging.py

The token needs the roles rig and reader (``helmholtz-server token create --lab LAB --role
rig,reader``). The script

1. declares a session: Bernoulli patterns on a SIDE x SIDE projector, one bucket detector;
2. generates the patterns the projector would show (``helmholtz.patterns``);
3. "measures" a bucket value per pattern: here the dot product of the pattern with a synthetic
   scene plus noise, where a real rig shows the pattern and reads its detector;
4. uploads the bucket rows (CRC-32C checked, resumable: run it again with the same
   --session-id and only what is missing is stored);
5. asks for the ``auto`` reconstruction, printing its progress;
6. fetches the dual image as an ndarray, compares it with the scene, and saves it (.npy).
"""

from __future__ import annotations

import argparse
import os
import sys
import uuid

import numpy as np

import helmholtz as hz


def synthetic_scene(side: int) -> np.ndarray:
    """A bright ring on a dim gradient, values in [0, 1]."""
    y, x = (np.mgrid[0:side, 0:side] + 0.5) / side
    r = np.hypot(x - 0.5, y - 0.5)
    return 0.15 + 0.2 * x + 0.65 * ((r > 0.2) & (r < 0.32))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--server", default=os.environ.get("HELMHOLTZ_SERVER", "http://127.0.0.1:8080"))
    ap.add_argument("--token", default=os.environ.get("HELMHOLTZ_TOKEN"))
    ap.add_argument("--session-id", default=f"ghost-{uuid.uuid4().hex[:8]}")
    ap.add_argument("--side", type=int, default=16, help="projector pixels per side")
    ap.add_argument("--count", type=int, default=512, help="patterns (bucket rows)")
    ap.add_argument("--noise", type=float, default=0.01, help="bucket noise, standard deviation")
    ap.add_argument("--out", default="dual.npy", help="where to save the dual image")
    args = ap.parse_args()
    if not args.token:
        ap.error("give --token or set HELMHOLTZ_TOKEN")

    spec = hz.PatternSpec.bernoulli(args.side, args.side, args.count, fill=0.5, seed=7)
    scene = synthetic_scene(args.side)
    with hz.Client(args.server, args.token) as client:
        session = client.create_session(args.session_id, spec, channels=["bucket"], rig="example")
        print(f"session {session.id}: {'created' if session.created else 'already there'}, "
              f"{session.committed_rows} of {session.expected_rows} rows stored")

        frames = hz.patterns(spec)  # (count, side, side) float32, what the projector shows
        rng = np.random.default_rng(1)
        buckets = frames.reshape(args.count, -1) @ scene.reshape(-1)
        buckets = buckets + args.noise * rng.standard_normal(args.count)

        report = client.upload(session, buckets[:, None])
        print(f"uploaded: {report.rows_written} rows written, {report.rows_matched} already stored, "
              f"{report.resumes} resumes, {report.seconds:.2f} s")
        client.finish_session(session)

        def progress(r: hz.Reconstruction) -> None:
            print(f"\r{r.method} reconstruction {r.id}: {r.state:9s} {r.progress:6.1%}", end="", flush=True)

        rec = client.wait(client.reconstruct(session, "auto"), progress=progress)
        print()
        image = client.dual_image(rec)
        report_json = client.report(rec)
        choice = (report_json.get("details", {}).get("auto") or [{}])[0]
        err = np.linalg.norm(image - scene) / np.linalg.norm(scene)
        print(f"auto chose {choice.get('model', '?')}; held-out error "
              f"{(report_json.get('held_out') or {}).get('relative_residual')}; "
              f"relative error against the scene {err:.3f}")
        np.save(args.out, image)
        print(f"dual image {image.shape} {image.dtype} saved to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
