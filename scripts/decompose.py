"""Regenerate the shipped convex decompositions used as MuJoCo collision geometry.

MuJoCo collides a mesh geom as its convex hull, which would fill the mug's handle hole and
cavity. This script runs CoACD (PyPI ``coacd``, the optional extra ``decomposition``) once per
object and writes each convex part as a small OBJ to
``src/activetouch/assets/objects/<name>/hulls/hull_NNN.obj`` plus ``hulls.json`` (parameters
and part count). The runtime never imports coacd: it only reads the shipped files.

Usage::

    .venv/bin/python scripts/decompose.py [--objects mug drill cracker_box] [--threshold 0.05]
        [--source-dir DIR]

The mesh is taken from ``activetouch.objects.load(name).mesh_path`` when that package is
available, otherwise from ``--source-dir/<name>/<name>.obj``.
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
OBJECTS = ("mug", "drill", "cracker_box")
log = logging.getLogger("decompose")


def mesh_path(name: str, source_dir: pathlib.Path | None) -> pathlib.Path:
    """Path of the watertight source mesh of ``name``."""
    if source_dir is not None:
        return source_dir / name / f"{name}.obj"
    try:
        from activetouch import objects

        return pathlib.Path(objects.load(name).mesh_path)
    except Exception:  # noqa: BLE001 - objects package may not exist yet
        for cand in (ASSETS / name / f"{name}.obj", pathlib.Path("/work/shared/data/objects") / name / f"{name}.obj"):
            if cand.exists():
                return cand
        raise FileNotFoundError(f"no mesh found for object {name!r}")


def decompose(path: pathlib.Path, threshold: float, seed: int) -> list[trimesh.Trimesh]:
    """Run CoACD on one mesh; returns the convex parts (object frame, metres)."""
    import coacd  # optional extra `decomposition`

    mesh = trimesh.load(path, force="mesh", process=False)
    parts = coacd.run_coacd(coacd.Mesh(mesh.vertices, mesh.faces), threshold=threshold, seed=seed,
                            preprocess_mode="auto", max_ch_vertex=64)
    hulls = []
    for verts, faces in parts:
        hull = trimesh.Trimesh(np.asarray(verts), np.asarray(faces)).convex_hull
        if hull.volume > 1e-9:
            hulls.append(hull)
    return hulls


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--objects", nargs="+", default=list(OBJECTS))
    parser.add_argument("--threshold", type=float, default=0.05, help="CoACD concavity threshold")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--source-dir", type=pathlib.Path, default=None)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    for name in args.objects:
        src = mesh_path(name, args.source_dir)
        t0 = time.time()
        thr = args.threshold
        hulls = decompose(src, thr, args.seed)
        out = ASSETS / name / "hulls"
        out.mkdir(parents=True, exist_ok=True)
        for old in out.glob("hull_*.obj"):
            old.unlink()
        for i, h in enumerate(hulls):
            h.export(out / f"hull_{i:03d}.obj", digits=6, include_normals=False)
        (out / "hulls.json").write_text(json.dumps({
            "object": name, "source": src.name, "method": "coacd", "threshold": thr, "seed": args.seed,
            "max_ch_vertex": 64, "num_hulls": len(hulls),
            "total_hull_volume_m3": float(sum(h.volume for h in hulls)),
        }, indent=2) + "\n")
        log.info("%s: %d hulls in %.1f s -> %s", name, len(hulls), time.time() - t0, out)


if __name__ == "__main__":
    main()
