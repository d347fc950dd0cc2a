#!/usr/bin/env python3
"""Reads a folder of TensorBoard event files with the `tensorboard` package's own readers and
writes what they hold as JSON, for trainer/tests/integration/tensorboard.rs.

Usage: read_tensorboard.py EVENT_DIR OUT_JSON

Two passes:
1. strict: every record of every event file through tensorboard's TFRecord reader, which checks
   both masked CRC-32Cs and raises DataLossError on a mismatch or a truncated record (the
   accumulator below would only log that and stop reading); the first record must be the
   `file_version` event.
2. `EventAccumulator`, keeping every event: scalar tags with (step, value, wall_time), image
   tags with (step, width, height) and the PNG decoded by Pillow to raw RGB bytes (hex).
"""

import io
import json
import pathlib
import sys

from PIL import Image
from tensorboard.backend.event_processing import event_accumulator
from tensorboard.compat.proto import event_pb2
from tensorboard.compat.tensorflow_stub import errors, pywrap_tensorflow


def strict_records(path):
    """Every record of one event file, CRCs checked; raises on any damage."""
    reader = pywrap_tensorflow.PyRecordReader_New(str(path).encode(), 0, b"", None)
    records = []
    while True:
        try:
            reader.GetNext()
        except errors.OutOfRangeError:
            return records
        records.append(reader.record())


def main():
    event_dir = pathlib.Path(sys.argv[1])
    files = sorted(event_dir.glob("events.out.tfevents.*"))
    if not files:
        sys.exit(f"{event_dir}: no events.out.tfevents.* file")
    result = {"files": [], "scalars": {}, "images": {}}
    for path in files:
        records = strict_records(path)
        first = event_pb2.Event.FromString(records[0])
        result["files"].append(
            {"name": path.name, "records": len(records), "file_version": first.file_version}
        )

    # size_guidance 0 keeps every event (the defaults sample scalars and keep only 4 images).
    acc = event_accumulator.EventAccumulator(
        str(event_dir),
        size_guidance={event_accumulator.SCALARS: 0, event_accumulator.IMAGES: 0},
    )
    acc.Reload()
    tags = acc.Tags()
    for tag in tags[event_accumulator.SCALARS]:
        result["scalars"][tag] = [[e.step, e.value, e.wall_time] for e in acc.Scalars(tag)]
    for tag in tags[event_accumulator.IMAGES]:
        images = []
        for e in acc.Images(tag):
            decoded = Image.open(io.BytesIO(e.encoded_image_string))
            images.append(
                {
                    "step": e.step,
                    "width": e.width,
                    "height": e.height,
                    "format": decoded.format,
                    "mode": decoded.mode,
                    "decoded_size": list(decoded.size),
                    "rgb_hex": decoded.convert("RGB").tobytes().hex(),
                }
            )
        result["images"][tag] = images
    pathlib.Path(sys.argv[2]).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
