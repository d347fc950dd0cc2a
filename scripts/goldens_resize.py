#!/usr/bin/env python3
"""OpenCV's resizes of random frames, for the tests of `trainer`'s video processor.

Usage: goldens_resize.py OUT_DIR

Writes OUT_DIR/source_<k>.png (random RGB frames of a few sizes) and, for each target size,
OUT_DIR/area_<k>_<W>x<H>.png (`cv2.resize(..., interpolation=cv2.INTER_AREA)`, what the public
CogNVS demo brings its conditioning to 720x480 with) and OUT_DIR/linear_<k>_<W>x<H>.png
(`cv2.resize(...)` with its default INTER_LINEAR, what the demo resizes the result back with), and
OUT_DIR/cases.json listing them. Nothing is committed.
"""

import json
import sys
from pathlib import Path

import cv2
import numpy as np

# (source width, height) -> target sizes: shrinking by integer and fractional factors (1280x720
# and 960x540 to the model's 720x480 among them), growing, and mixed.
# Exact doublings and halvings (DyCheck's 360p <-> 720p) and odd widths whose rows end outside
# OpenCV's SIMD blocks are among them.
CASES = {
    (160, 90): [(72, 48), (80, 45), (40, 30), (200, 120), (96, 60), (160, 48)],
    (96, 54): [(72, 48), (48, 27), (150, 100), (60, 80), (192, 108)],
    (64, 48): [(72, 48), (32, 24), (50, 30), (128, 96), (23, 71)],
    (37, 29): [(74, 58), (11, 13), (101, 5)],
}


def main():
    out = Path(sys.argv[1])
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(20261204)
    cases = []
    for k, ((w, h), targets) in enumerate(CASES.items()):
        # Smooth content plus noise: both flat regions and edges.
        y, x = np.mgrid[0:h, 0:w]
        smooth = np.stack([127 + 100 * np.sin(x / (5 + c) + y / (7 + 2 * c)) for c in range(3)], -1)
        frame = np.clip(smooth + rng.normal(0, 40, (h, w, 3)), 0, 255).astype(np.uint8)
        cv2.imwrite(str(out / f"source_{k}.png"), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
        for tw, th in targets:
            for mode, flag in (("area", cv2.INTER_AREA), ("linear", cv2.INTER_LINEAR)):
                resized = cv2.resize(frame, (tw, th), interpolation=flag)
                name = f"{mode}_{k}_{tw}x{th}.png"
                cv2.imwrite(str(out / name), cv2.cvtColor(resized, cv2.COLOR_RGB2BGR))
                cases.append({"source": f"source_{k}.png", "mode": mode, "width": tw, "height": th, "file": name})
    (out / "cases.json").write_text(json.dumps(cases, indent=1))


if __name__ == "__main__":
    main()
