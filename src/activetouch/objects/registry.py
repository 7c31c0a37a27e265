"""Packaged objects and loading of user meshes: :func:`load`, :func:`available`."""
from __future__ import annotations

import importlib.resources
from pathlib import Path

import trimesh

from .known_object import KnownObject

__all__ = ["load", "available"]

_PACKAGED = ("mug", "drill", "cracker_box", "mustard_bottle", "bleach_cleanser", "tomato_soup_can", "sugar_box",
             "potted_meat_can", "foam_brick")
#: Cached-SDF cell size per packaged object (m): 1 mm for the thin-walled mug (walls ~1.2 mm), coarser for
#: the bulkier drill and box to keep the one-off cache build short (cache size grows as 1/res^3). The
#: clutter objects use 2 mm, except 1.5 mm for the soup can (thin rolled rim, recessed lid).
PACKAGED_SDF_RESOLUTION = {
    "mug": 0.001,
    "drill": 0.0015,
    "cracker_box": 0.002,
    "mustard_bottle": 0.002,
    "bleach_cleanser": 0.002,
    "tomato_soup_can": 0.0015,
    "sugar_box": 0.002,
    "potted_meat_can": 0.002,
    "foam_brick": 0.002,
}


def _assets_root() -> Path:
    return Path(str(importlib.resources.files("activetouch") / "assets" / "objects"))


def available() -> list[str]:
    """Names of the packaged objects: the YCB mug, power drill and cracker box, then the clutter objects
    (mustard bottle, bleach cleanser, tomato soup can, sugar box, potted meat can, foam brick)."""
    return list(_PACKAGED)


def load(name_or_path: str | Path, *, device=None, **kwargs) -> KnownObject:
    """Load a packaged object by name or any watertight mesh file.

    Packaged names (see :func:`available`): ``"mug"``, ``"drill"``, ``"cracker_box"``, ``"mustard_bottle"``,
    ``"bleach_cleanser"``, ``"tomato_soup_can"``, ``"sugar_box"``, ``"potted_meat_can"``, ``"foam_brick"``
    (YCB meshes in ``assets/objects/<name>/``, each with its convex decomposition in ``hulls/``).

    Files are read with trimesh (``.obj``, ``.stl``, ``.ply``, ``.off``, ...) and must be one closed,
    consistently wound surface in metres. Extra keyword arguments go to :class:`KnownObject`
    (``sdf_resolution``, ``sdf_padding``, ``hull_dir``).

    Raises:
        ValueError: unknown name (the message lists the available ones), unreadable or empty file,
            or a mesh that is not watertight.
    """
    s = str(name_or_path)
    if s in _PACKAGED:
        path = _assets_root() / s / f"{s}.obj"
        name = s
        kwargs.setdefault("sdf_resolution", PACKAGED_SDF_RESOLUTION[s])
    else:
        path = Path(s).expanduser()
        if not path.is_file():
            raise ValueError(
                f"unknown object {s!r}: not a packaged object (available: {', '.join(available())}) "
                "and no such mesh file"
            )
        name = path.stem
    try:
        mesh = trimesh.load(path, force="mesh", process=True)
    except Exception as e:  # trimesh raises many types for bad files
        raise ValueError(f"could not read mesh file {path}: {e}") from e
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"mesh file {path} holds no triangles")
    return KnownObject(name, mesh, path, device=device, **kwargs)
