"""Prepare a photographed capture in instant-ngp's layout (its fox) as a nerfstudio-data dataset a CPU can fit.

    python benchmarks/capture_prep.py SOURCE OUTPUT [--downscale 8] [--overwrite]

SOURCE is a clone of https://github.com/NVlabs/instant-ngp (its `data/nerf/fox` is read), or any folder holding an
instant-ngp `transforms.json` and the images it lists. Its licence keeps the fox out of this repository: nothing
here ships it, and SOURCE is only read. OUTPUT gets `images/` (each photo shrunk by --downscale with area
averaging) and a `transforms.json` in nerfstudio-data's layout: one OPENCV camera (focal lengths and principal
point scaled to the new size, k1 k2 p1 p2 kept: they act on normalised coordinates), each frame's
`transform_matrix` as it was (camera-to-world with OpenGL axes in both formats). Images that `transforms.json`
lists but SOURCE lacks (the fox lists 67 and holds 50) are dropped, with one line saying how many.

Train a base on it as docs/captures.md says (`nerfstudio-data --center-method focus`: a capture on an arc is
centred on what its cameras look at, not on the cameras).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Dict, List, Tuple

from sked_ns.errors import SkedFileNotFoundError, SkedUserError

FOX = Path("data") / "nerf" / "fox"
LENS = ("k1", "k2", "k3", "k4", "p1", "p2")
"""Distortion coefficients both formats name alike; nerfstudio-data reads each one given."""


def find_transforms(source: Path) -> Path:
    """SOURCE's transforms.json: in the folder itself, or in an instant-ngp clone's fox."""
    if not source.is_dir():
        raise SkedFileNotFoundError(f"SOURCE {source}: no such folder. Pass a clone of instant-ngp or the folder "
                                    "holding its transforms.json (data/nerf/fox).")
    for candidate in (source / "transforms.json", source / FOX / "transforms.json"):
        if candidate.is_file():
            return candidate
    raise SkedFileNotFoundError(f"SOURCE {source}: neither {source / 'transforms.json'} nor "
                                f"{source / FOX / 'transforms.json'} exists. Pass a clone of instant-ngp or the "
                                "folder holding its transforms.json.")


def read_capture(transforms: Path) -> Tuple[Dict, List[dict], int]:
    """(the camera, the frames whose images exist, how many listed images are missing)."""
    try:
        meta = json.loads(transforms.read_text())
    except json.JSONDecodeError as error:
        raise SkedUserError(f"{transforms}: not JSON ({error.msg}, line {error.lineno}).") from None
    missing_keys = [key for key in ("fl_x", "cx", "cy", "w", "h", "frames") if key not in meta]
    if missing_keys:
        raise SkedUserError(f"{transforms}: lacks {', '.join(missing_keys)}; an instant-ngp capture's transforms.json "
                            "names one camera (fl_x, cx, cy, w, h) and its frames.")
    if any(key in frame for frame in meta["frames"] for key in ("fl_x", "w", "k1")):
        raise SkedUserError(f"{transforms}: frames with their own cameras; this script reads one camera for all.")
    present = [frame for frame in meta["frames"] if (transforms.parent / frame["file_path"]).is_file()]
    if not present:
        raise SkedFileNotFoundError(f"{transforms}: none of the {len(meta['frames'])} images it lists exists "
                                    f"under {transforms.parent}.")
    return meta, present, len(meta["frames"]) - len(present)


def camera_at(meta: Dict, width: int, height: int) -> Dict:
    """nerfstudio-data's camera for the photos shrunk to width x height (pixel units scale with the image)."""
    scale_x, scale_y = width / float(meta["w"]), height / float(meta["h"])
    camera = {"camera_model": "OPENCV", "fl_x": float(meta["fl_x"]) * scale_x,
              "fl_y": float(meta.get("fl_y", meta["fl_x"])) * scale_y, "cx": float(meta["cx"]) * scale_x,
              "cy": float(meta["cy"]) * scale_y, "w": width, "h": height}
    return {**camera, **{key: float(meta[key]) for key in LENS if key in meta}}


def prepare(source: Path, output: Path, downscale: int = 8, overwrite: bool = False) -> Path:
    """Write OUTPUT (images/ and transforms.json) from SOURCE; returns OUTPUT's transforms.json."""
    import cv2

    if downscale < 1:
        raise SkedUserError(f"--downscale {downscale}: a whole number >= 1 (8: 1080x1920 photos become 135x240).")
    transforms = find_transforms(source)
    if output.exists() and any(output.iterdir()) and not overwrite:
        raise SkedUserError(f"OUTPUT {output}: not empty. Pass --overwrite to replace it, or another folder.")
    if output.resolve() == transforms.parent.resolve():
        raise SkedUserError(f"OUTPUT {output}: the capture's own folder; its files are never changed. Pass another.")
    meta, present, missing = read_capture(transforms)
    if missing:
        print(f"{missing} of the {len(meta['frames'])} images {transforms} lists are missing under "
              f"{transforms.parent}: dropped.")
    width, height = round(float(meta["w"]) / downscale), round(float(meta["h"]) / downscale)
    (output / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    for frame in present:
        photo = cv2.imread(str(transforms.parent / frame["file_path"]), cv2.IMREAD_COLOR)
        if photo is None:
            raise SkedUserError(f"{transforms.parent / frame['file_path']}: not an image OpenCV can read.")
        name = f"images/{Path(frame['file_path']).stem}.png"
        cv2.imwrite(str(output / name), cv2.resize(photo, (width, height), interpolation=cv2.INTER_AREA))
        frames.append({"file_path": name, "transform_matrix": frame["transform_matrix"]})
    written = output / "transforms.json"
    written.write_text(json.dumps({**camera_at(meta, width, height), "frames": frames}, indent=2))
    print(f"{len(frames)} photos at {width}x{height} in {output}; train a base with: ns-train nerfacto --data "
          f"{output} nerfstudio-data --center-method focus")
    return written


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", type=Path, help="a clone of instant-ngp, or the folder holding its transforms.json")
    parser.add_argument("output", type=Path, help="the nerfstudio-data dataset to write")
    parser.add_argument("--downscale", type=int, default=8, help="shrink each side this many times (8: 135x240)")
    parser.add_argument("--overwrite", action="store_true", help="write over what OUTPUT holds")
    arguments = parser.parse_args(argv)
    prepare(arguments.source, arguments.output, arguments.downscale, arguments.overwrite)


if __name__ == "__main__":
    main(sys.argv[1:])
