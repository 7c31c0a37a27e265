"""Packaged objects and loading of user meshes: :func:`load`, :func:`available`."""
from __future__ import annotations

import importlib.resources
from pathlib import Path

import trimesh

from .known_object import KnownObject

__all__ = ["load", "available"]

_PACKAGED = ("mug", "drill", "cracker_box")
#: Cached-SDF cell size per packaged object (m): 1 mm for the thin-walled mug (walls ~1.2 mm), coarser for
#: the bulkier drill and box to keep the one-off cache build short (cache size grows as 1/res^3).
PACKAGED_SDF_RESOLUTION = {"mug": 0.001, "drill": 0.0015, "cracker_box": 0.002}


def _assets_root() -> Path:
    return Path(str(importlib.resources.files("activetouch") / "assets" / "objects"))


def available() -> list[str]:
    """Names of the packaged objects (YCB mug, power drill, cracker box)."""
    return list(_PACKAGED)


def load(name_or_path: str | Path, *, device=None, **kwargs) -> KnownObject:
    """Load a packaged object by name (``"mug" | "drill" | "cracker_box"``) or any watertight mesh file.

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
