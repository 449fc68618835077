"""``napari-imgreg sample``: write the generated sample outcrop scene (contract §8).

The scene: OBJ+MTL+JPEG, georef.json, dem.tif, and photos with sensor
records and ground truth; ``--size`` and ``--seed`` choose which one;
``--scan`` adds a terrestrial laser scan of it (``scan.laz``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ._common import EXIT_OK, say
from ..validate import check_option, check_writable

__all__ = ["add_parser", "run"]


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register the ``sample`` sub-command; its handler is :func:`run`."""
    p = subparsers.add_parser(
        "sample",
        help="write the generated sample outcrop scene to a folder",
        description="Write a generated outcrop (OBJ+MTL+JPEG, georef.json, dem.tif, photos with "
        "sensor records and ground truth, an example drawing per photo "
        "(IMG_xxxx.lines.geojson) and an orientation example in orient/).",
    )
    p.add_argument("--out", required=True,
                   help="folder to write: new, empty, or an earlier run's of the same size and "
                   "seed")
    p.add_argument("--size", default="small", choices=["small", "large"],
                   help="small: about 128,000 triangles, a 2048² texture and three 1024×768 "
                   "photos (10-20 s); large: about 1.2 million triangles, a 4096² texture and "
                   "five 1632×1224 photos (several times longer). Default small")
    p.add_argument("--seed", type=int, default=0, help="0 to 2**32 - 1 (default 0)")
    p.add_argument("--scan", action="store_true",
                   help="also write scan.laz: a terrestrial laser scan of the same outcrop "
                   "(two stations 55 m out, 2 mrad, intensity only, in the georeference's "
                   "CRS), to try the point-cloud path (a few seconds more)")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Run ``sample``: generate the outcrop into ``--out``."""
    from ..sample import cached_sample_scene, check_outcrop_folder, write_outcrop_folder

    check_writable(args.out, folder=True)
    check_option(args.seed, "--seed", 0, 2**32 - 1)  # NumPy's seed range
    check_outcrop_folder(args.out, args.size, args.seed)  # refused before the progress line
    t0 = time.perf_counter()
    # Said first: the folder appears only when the scene is complete.
    cached = cached_sample_scene(args.size, args.seed)
    say(f"copying the {args.size} sample outcrop (seed {args.seed}) from the cache {cached} to "
        f"{args.out} ..." if cached is not None else
        f"generating the {args.size} sample outcrop (seed {args.seed}) for {args.out} ...")
    out = write_outcrop_folder(Path(args.out), size=args.size, seed=args.seed, cached=cached)
    print(f"sample outcrop ({args.size}, seed {args.seed}) written to {out} "
          f"in {time.perf_counter() - t0:.1f} s")
    if args.scan:
        from ..sample.scan import SAMPLE_SCAN_SPEC, scan_scene_folder

        t0 = time.perf_counter()
        scan = scan_scene_folder(out, SAMPLE_SCAN_SPEC)
        print(f"laser scan of it written to {scan} in {time.perf_counter() - t0:.1f} s: use it "
              f"in place of outcrop.obj")
    return EXIT_OK
