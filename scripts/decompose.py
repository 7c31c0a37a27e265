"""Regenerate the shipped convex decompositions used as MuJoCo collision geometry.

MuJoCo collides a mesh geom as its convex hull, which would fill the mug's handle hole and
cavity. This script runs CoACD (PyPI ``coacd``, the optional extra ``decomposition``) once per
object and writes each convex part as a small OBJ to
``src/activetouch/assets/objects/<name>/hulls/hull_NNN.obj`` plus ``hulls.json`` (parameters
and part count). The runtime never imports coacd: it only reads the shipped files.

Usage::

    .venv/bin/python scripts/decompose.py [--objects mug drill ...] [--threshold 0.05]
        [--threshold-for NAME=VALUE ...] [--max-convex-hull N] [--source-dir DIR]

The mesh is taken from ``--source-dir/<name>/<name>.obj`` when ``--source-dir`` is given and that
file exists, otherwise from the package (``src/activetouch/assets/objects/<name>/<name>.obj``, or
``activetouch.objects.load(name).mesh_path``). ``--threshold-for`` overrides the concavity
threshold of single objects (e.g. a mesh on which CoACD runs too long). Existing hulls are only
rewritten for the objects named in ``--objects`` (default: all of ``OBJECTS``), so pass
``--objects`` to add new ones without touching the shipped decompositions.
"""

from __future__ import annotations

import argparse
import json
import logging
import pathlib
import time

import numpy as np
import trimesh

REPO = pathlib.Path(__file__).resolve().parents[1]
ASSETS = REPO / "src" / "activetouch" / "assets" / "objects"
OBJECTS = ("mug", "drill", "cracker_box", "mustard_bottle", "bleach_cleanser", "tomato_soup_can", "sugar_box",
           "potted_meat_can", "foam_brick")
log = logging.getLogger("decompose")


def mesh_path(name: str, source_dir: pathlib.Path | None) -> pathlib.Path:
    """Path of the watertight source mesh of ``name``: ``source_dir`` first, then the package."""
    if source_dir is not None:
        cand = source_dir / name / f"{name}.obj"
        if cand.is_file():
            return cand
        log.warning("%s: %s not found; using the packaged mesh", name, cand)
    cand = ASSETS / name / f"{name}.obj"
    if cand.is_file():
        return cand
    try:
        from activetouch import objects

        return pathlib.Path(objects.load(name).mesh_path)
    except Exception as e:  # noqa: BLE001 - not a packaged object (or package not importable)
        where = f"{source_dir}/{name}/{name}.obj or " if source_dir is not None else ""
        raise FileNotFoundError(f"no mesh found for object {name!r} (looked in {where}{ASSETS / name})") from e


def _threshold_overrides(items: list[str]) -> dict[str, float]:
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"--threshold-for expects NAME=VALUE, got {item!r}")
        out[name] = float(value)
    return out


def decompose(path: pathlib.Path, threshold: float, seed: int, max_convex_hull: int = -1) -> list[trimesh.Trimesh]:
    """Run CoACD on one mesh; returns the convex parts (object frame, metres)."""
    import coacd  # optional extra `decomposition`

    mesh = trimesh.load(path, force="mesh", process=False)
    parts = coacd.run_coacd(coacd.Mesh(mesh.vertices, mesh.faces), threshold=threshold, seed=seed,
                            preprocess_mode="auto", max_ch_vertex=64, max_convex_hull=max_convex_hull)
    hulls = []
    for verts, faces in parts:
        hull = trimesh.Trimesh(np.asarray(verts), np.asarray(faces)).convex_hull
        if hull.volume > 1e-9:
            hulls.append(hull)
    return hulls


def _coacd_version() -> str | None:
    try:
        from importlib.metadata import version

        return version("coacd")
    except Exception:  # noqa: BLE001
        return None


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--objects", nargs="+", default=list(OBJECTS))
    parser.add_argument("--threshold", type=float, default=0.05, help="CoACD concavity threshold")
    parser.add_argument("--threshold-for", nargs="+", default=[], metavar="NAME=VALUE",
                        help="per-object threshold overrides")
    parser.add_argument("--max-convex-hull", type=int, default=-1,
                        help="CoACD max_convex_hull (merge down to at most N parts; -1 = no limit)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--source-dir", type=pathlib.Path, default=None)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    overrides = _threshold_overrides(args.threshold_for)
    for name in args.objects:
        src = mesh_path(name, args.source_dir)
        t0 = time.time()
        thr = overrides.get(name, args.threshold)
        hulls = decompose(src, thr, args.seed, args.max_convex_hull)
        seconds = time.time() - t0
        out = ASSETS / name / "hulls"
        out.mkdir(parents=True, exist_ok=True)
        for old in out.glob("hull_*.obj"):
            old.unlink()
        for i, h in enumerate(hulls):
            h.export(out / f"hull_{i:03d}.obj", digits=6, include_normals=False)
        info = {
            "object": name, "source": src.name, "method": "coacd", "threshold": thr, "seed": args.seed,
            "max_ch_vertex": 64, "num_hulls": len(hulls),
            "total_hull_volume_m3": float(sum(h.volume for h in hulls)),
        }
        if args.max_convex_hull > 0:
            info["max_convex_hull"] = args.max_convex_hull
        info.update(coacd_version=_coacd_version(), seconds=round(seconds, 1))
        (out / "hulls.json").write_text(json.dumps(info, indent=2) + "\n")
        log.info("%s: %d hulls in %.1f s -> %s", name, len(hulls), seconds, out)


if __name__ == "__main__":
    main()
