"""GenICam driver overhead: frames per second through GenICamCamera.capture() (flush stale buffers, wait for a
fresh frame, check it, unpack/copy it, queue the buffer back) against raw harvesters fetches from the same
producer and camera, in the same process.

    .venv/bin/python benchmarks/bench_genicam.py [--frames 200] [--rate 200]

The producer is genicam's simulated one (viky.cti, 400x400 Mono8) free-running at ``--rate`` frames/s, so
both loops are bounded by the camera's rate; the ratio says what the driver's checks and its
fresh-frame-only policy cost. Prints a ``BENCHMARK {json}`` line.
"""
from __future__ import annotations

import argparse
import json
import sys
import time

from drivers.genicam import GenICamCamera, simulated_producer


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--rate", type=float, default=200.0)
    a = ap.parse_args()
    producer = simulated_producer()
    if producer is None:
        print("bench_genicam: the genicam package (viky.cti) is not installed", file=sys.stderr)
        return 2
    with GenICamCamera("0", producer=producer, num_buffers=4) as cam:
        cam.node_map.AcquisitionFrameRate.value = a.rate
        cam.capture()
        ia = cam._ia
        t0 = time.perf_counter()
        for _ in range(a.frames):  # baseline: what harvesters hands out, as fast as it comes
            with ia.fetch(timeout=2.0) as buf:
                buf.payload.components[0].data.copy()
        raw_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        for _ in range(a.frames):
            cam.capture()
        drv_s = time.perf_counter() - t0
    raw_fps, drv_fps = a.frames / raw_s, a.frames / drv_s
    print(f"camera rate {a.rate:.0f} fps, {a.frames} frames, 400x400 Mono8")
    print(f"harvesters fetch (baseline): {raw_fps:7.1f} fps   {1e3 / raw_fps:6.2f} ms/frame")
    print(f"GenICamCamera.capture():      {drv_fps:7.1f} fps   {1e3 / drv_fps:6.2f} ms/frame  (fresh frame, checked)")
    print("BENCHMARK " + json.dumps({"what": "GenICam capture (fps, simulated producer)", "figure": round(drv_fps, 1),
                                     "baseline": round(raw_fps, 1), "ratio": round(drv_fps / raw_fps, 3)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
