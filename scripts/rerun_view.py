#!/usr/bin/env python3
"""Writes the Rerun recording of `datagen view` (see datagen/src/inspect/view.rs).

Usage: rerun_view.py PARTS_DIR OUT.rrd

PARTS_DIR holds what `datagen view` prepared: view.json (per-frame K and world_from_camera, the
novel trajectories with their mask files), frame_NNNNN.png, points_NNNNN.npy (M, 3) float32 world
points and colors_NNNNN.npy (M, 3) uint8. On the timeline `frame` (the sequence's frame index) it
logs:

  world                                   view coordinates (OpenCV: x right, y down, z forward)
  world/points                            the frame's coloured point cloud
  world/source                            the source camera: pose and pinhole
  world/source/image                      its image
  world/source/covisibility/<trajectory>  the co-visibility mask (1 co-visible, 0 hidden)
  world/novel/<trajectory>                each novel camera: pose and pinhole (a frustum)

Poses are world_from_camera (4x4, row-major), K in pixels with pixel centres at integer
coordinates; Rerun puts them at half-integers, so K's principal point is moved by +0.5.
"""

import json
import sys
from pathlib import Path

import numpy as np
import rerun as rr
from PIL import Image

# Pixel centres: integers here, half-integers in Rerun's image space.
PIXEL_CENTRE_OFFSET = 0.5
# RGBA of co-visible pixels in the mask overlay: green, half transparent.
COVISIBLE_TINT = (0, 200, 0, 128)


def pinhole(k_row_major, width, height):
    k = np.asarray(k_row_major, dtype=np.float64).reshape(3, 3).copy()
    k[0, 2] += PIXEL_CENTRE_OFFSET
    k[1, 2] += PIXEL_CENTRE_OFFSET
    return rr.Pinhole(image_from_camera=k, resolution=[width, height], camera_xyz=rr.ViewCoordinates.RDF)


def transform(pose_row_major):
    pose = np.asarray(pose_row_major, dtype=np.float64).reshape(4, 4)
    return rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3])


def main(parts: Path, out: Path) -> None:
    view = json.loads((parts / "view.json").read_text())
    width, height = view["width"], view["height"]
    recording = rr.RecordingStream(f"datagen view {view['source_id']}")
    recording.save(str(out))
    recording.log("world", rr.ViewCoordinates.RDF, static=True)
    # Hidden pixels (0) stay see-through; co-visible ones (1) are tinted over the source image.
    recording.log(
        "world/source/covisibility",
        rr.AnnotationContext([(0, "hidden", (0, 0, 0, 0)), (1, "co-visible", COVISIBLE_TINT)]),
        static=True,
    )
    for i in range(view["frames"]):
        recording.set_time("frame", sequence=i)
        points = np.load(parts / f"points_{i:05d}.npy")
        colors = np.load(parts / f"colors_{i:05d}.npy")
        recording.log("world/points", rr.Points3D(points, colors=colors))
        recording.log("world/source", transform(view["world_from_camera"][i]))
        recording.log("world/source", pinhole(view["intrinsics"][i], width, height))
        image = np.asarray(Image.open(parts / f"frame_{i:05d}.png").convert("RGB"))
        recording.log("world/source/image", rr.Image(image))
    for trajectory in view["trajectories"]:
        name = rr.escape_entity_path_part(trajectory["name"])
        for f, (k, pose, mask_file) in enumerate(
            zip(trajectory["intrinsics"], trajectory["world_from_camera"], trajectory["masks"])
        ):
            recording.set_time("frame", sequence=trajectory["clip_start"] + f)
            recording.log(f"world/novel/{name}", transform(pose))
            recording.log(f"world/novel/{name}", pinhole(k, width, height))
            mask = np.asarray(Image.open(parts / mask_file).convert("L"))
            recording.log(f"world/source/covisibility/{name}", rr.SegmentationImage((mask > 0).astype(np.uint8)))
    recording.flush()


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    main(Path(sys.argv[1]), Path(sys.argv[2]))
